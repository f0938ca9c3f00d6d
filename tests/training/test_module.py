"""The learner's selection of the best validation: the start competes with every epoch, on
the held-out (``val``) score or, with ``data.select``, on the long sequences' mean."""
import math

import pytest

from flowins.navigation import NavigationConfig
from flowins.training.module import FilterLearner, heldout_table, selection_table
from flowins.training.parameters import NAMES, SIGNED, FilterParameters


def _entry(label, score, raw):
    return {"label": label, "step": 0, "rmse_m": {"ins_gnss": score}, "score": score, "raw": raw}


def test_select_best_loads_the_lowest_validation_and_prefers_the_earliest_on_a_tie():
    params = FilterParameters({n: 0.3 if n == "dropout_p" else 0.01 * i if n in SIGNED else 0.5 + i for i, n in enumerate(NAMES)})
    learner = FilterLearner(params, NavigationConfig(), methods=["ins_gnss"])
    with pytest.raises(ValueError, match="no validation"):
        learner.select_best()
    start = {n: float(params.raw[n].detach()) for n in NAMES}
    moved = {n: v + 0.5 for n, v in start.items()}
    other = {n: v - 0.25 for n, v in start.items()}
    learner.history = [_entry("start", 1.0, start), _entry("epoch 1", math.inf, moved),
                       _entry("epoch 2", 0.5, other), _entry("epoch 3", 0.5, moved)]
    chosen = learner.select_best()
    assert chosen["label"] == "epoch 2"
    assert {n: float(params.raw[n].detach()) for n in NAMES} == other
    # an epoch no better than the start leaves the start
    learner.history = [_entry("start", 0.7, start), _entry("epoch 1", 0.7, moved), _entry("epoch 2", 0.9, other)]
    assert learner.select_best()["label"] == "start"
    assert {n: float(params.raw[n].detach()) for n in NAMES} == start


def _long(entry, rmse):
    """``entry`` with the RMSE of two ``data.select`` sequences and their mean, as a validation records them."""
    return {**entry, "select_rmse_m": {"ins_gnss": rmse}, "select_score": sum(rmse) / len(rmse)}


def test_select_best_chooses_on_the_select_sequences_not_on_the_val_score():
    params = FilterParameters({n: 0.3 if n == "dropout_p" else 0.01 * i if n in SIGNED else 0.5 + i for i, n in enumerate(NAMES)})
    learner = FilterLearner(params, NavigationConfig(), methods=["ins_gnss"])
    start = {n: float(params.raw[n].detach()) for n in NAMES}
    moved = {n: v + 0.5 for n, v in start.items()}
    other = {n: v - 0.25 for n, v in start.items()}
    # val ranks epoch 1 first; the long sequences rank epoch 2 first (epoch 3 ties it, later)
    learner.history = [_long(_entry("start", 1.0, start), [2.0, 4.0]), _long(_entry("epoch 1", 0.5, moved), [3.0, 5.0]),
                       _long(_entry("epoch 2", 0.9, other), [1.0, 3.0]), _long(_entry("epoch 3", 0.8, moved), [2.5, 1.5])]
    chosen = learner.select_best()
    assert chosen["label"] == "epoch 2"
    assert {n: float(params.raw[n].detach()) for n in NAMES} == other
    table = selection_table(learner.history, chosen)
    assert "lowest select mean" in table
    row = next(line for line in table.splitlines() if line.startswith("epoch 2"))
    assert row.split()[2:] == ["0.900", "0.900", "2.00", "±", "1.00", "m", "2.000", "<-", "chosen"]
    assert "chosen" not in next(line for line in table.splitlines() if line.startswith("epoch 1"))
    # the start competes and wins a tie with a later epoch, however much better that epoch's val score is
    learner.history = [_long(_entry("start", 2.0, start), [1.0, 1.0]), _long(_entry("epoch 1", 0.1, moved), [0.5, 1.5]),
                       _long(_entry("epoch 2", 0.1, other), [math.inf, 0.5])]
    learner.history[2]["select_score"] = math.inf  # a filter diverged on one long sequence
    assert learner.select_best()["label"] == "start"
    assert {n: float(params.raw[n].detach()) for n in NAMES} == start


def test_the_heldout_table_puts_the_select_mean_and_std_beside_the_val_mean():
    val = {"learned": {"ins_gnss": [1.0, 2.0]}, "start": {"ins_gnss": [2.0, 4.0]}}
    select = {"learned": {"ins_gnss": [3.0, 5.0, 7.0]}, "start": {"ins_gnss": [5.0, 5.0, 5.0]}}
    lines = heldout_table(val, ["ins_gnss"], select).splitlines()
    assert lines[0].split() == ["parameters", "ins_gnss", "select", "ins_gnss"]
    # population std of 3, 5, 7: sqrt(8 / 3) = 1.633
    assert lines[1].split() == ["learned", "1.50", "m", "5.00", "±", "1.63", "m"]
    assert lines[2].split() == ["start", "3.00", "m", "5.00", "±", "0.00", "m"]
    assert lines[3].split() == ["reduction", "50.0", "%", "0.0", "%"]
    # without select sequences the table has the val columns only
    assert heldout_table(val, ["ins_gnss"], {}) == heldout_table(val, ["ins_gnss"])
    assert "select" not in heldout_table(val, ["ins_gnss"])
    # with the smoother's RMSE the select cell is filter / smoother, and so is its reduction
    smoother = {"learned": {"ins_gnss": [2.0, 2.0, 2.0]}, "start": {"ins_gnss": [4.0, 5.0, 6.0]}}
    lines = heldout_table(val, ["ins_gnss"], select, smoother).splitlines()
    assert lines[0].split() == ["parameters", "ins_gnss", "select", "ins_gnss", "filter", "/", "smoother"]
    assert lines[1].split() == ["learned", "1.50", "m", "5.00", "±", "1.63", "/", "2.00", "±", "0.00", "m"]
    assert lines[2].split() == ["start", "3.00", "m", "5.00", "±", "0.00", "/", "5.00", "±", "0.82", "m"]
    assert lines[3].split() == ["reduction", "50.0", "%", "0.0", "/", "60.0", "%"]


def _one_epoch(tmp_path, *overrides):
    """``python train.py`` for one epoch of ``ins_gnss`` on a 12 s walk (GNSS heading alignment
    off, no warm-up, rate 0.05) with ``overrides``; returns the sequence, the filter
    configuration, the learned names, the start parameters and the parameters after the epoch."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf
    from pathlib import Path

    from flowins.ins.imu_model import imu_model
    from flowins.jobs.train import run
    from flowins.settings import flow_config, navigation_config
    from flowins.training.data import load_training_sequence

    configs = str(Path(__file__).resolve().parents[2] / "configs")
    with initialize_config_dir(config_dir=configs, version_base="1.3"):
        cfg = OmegaConf.to_container(compose("train", overrides=[
            f"output_dir={tmp_path / 'out'}", f"cache_dir={tmp_path / 'cache'}", "progress=false", "logger=csv",
            "methods=[ins_gnss]", "filter.gnss_heading.enabled=false", "data.train=[{seed: 1, duration_s: 12.0}]",
            "data.val=[{seed: 1, duration_s: 12.0}]", "curriculum_window_s=[]", "trainer.max_epochs=1",
            "model.warmup_steps=0", "model.lr=0.05", *overrides]), resolve=True)
    result = run(cfg)
    seq = load_training_sequence({"seed": 1, "duration_s": 12.0}, {**cfg, "flow": flow_config(cfg, moments=True)},
                                 methods=["ins_gnss"])
    base = navigation_config(cfg["filter"], imu_model(cfg["imu"], recording=False))
    learn = [n for n in NAMES if n not in ("initial_position_m", "initial_yaw_rad")]
    last = FilterParameters.from_checkpoint(tmp_path / "out" / "checkpoints" / "last.ckpt")
    return seq, base, learn, FilterParameters(result["start"], learn=learn), last


def _assert_first_adam_step(params, last, reached, lr=0.05):
    """``last`` is one Adam step of rate ``lr`` from ``params`` on the gradient ``reached`` (by
    name), clipped to norm 1: each coordinate moves ``lr`` against its gradient's sign."""
    import torch

    norm = torch.linalg.vector_norm(torch.stack([torch.as_tensor(g) for g in reached.values()]))
    clip = min(1.0, 1.0 / (float(norm) + 1e-6))
    for name in NAMES:
        expected = float(params.raw[name].detach())
        if name in reached:
            g = float(reached[name]) * clip
            expected -= lr * g / (abs(g) + 1e-8)
        assert float(last.raw[name]) == pytest.approx(expected, rel=1e-9, abs=1e-12), name


def test_accumulated_windows_take_one_adam_step_on_their_mean_gradient(tmp_path):
    """``model.accumulate_windows=2`` over a sequence of two windows: one step, on the mean of
    both windows' gradients (computed here window by window), as Adam's first step takes it."""
    import torch

    from flowins.training.unroll import run_window, window_bounds, window_loss

    seq, base, learn, params, last = _one_epoch(tmp_path, "window_s=6.0", "model.accumulate_windows=2")
    # the reference: both windows' losses from the start values, their mean's gradient, Adam's first step
    config = params.apply(base, training=True)
    first, second = window_bounds(seq.imu.t_s, 6.0)
    a = run_window(seq, "ins_gnss", config, first)
    b = run_window(seq, "ins_gnss", config, second, start=(a.mean.detach(), a.cov.detach()))
    loss = 0.5 * (window_loss(a.track, seq.truth).loss + window_loss(b.track, seq.truth).loss)
    grads = torch.autograd.grad(loss, [params.raw[n] for n in learn], allow_unused=True)
    reached = {n: g for n, g in zip(learn, grads) if g is not None}
    _assert_first_adam_step(params, last, reached)
    assert len(reached) >= 5 and {"acc_noise", "gnss_noise_scale"} <= set(reached)


def _window_gradients(seq, base, learn, params):
    """The window loss's gradient by learned name (None where it does not reach) and the
    innovation likelihood per scalar measurement (with its graph) of ``ins_gnss`` over the
    sequence's one 12 s window at ``params``' values."""
    import torch

    from flowins.training.unroll import run_window, window_bounds, window_loss

    (window,) = window_bounds(seq.imu.t_s, 12.0)
    out = run_window(seq, "ins_gnss", params.apply(base, training=True), window, likelihood=True)
    loss = window_loss(out.track, seq.truth).loss
    grads = torch.autograd.grad(loss, [params.raw[n] for n in learn], allow_unused=True, retain_graph=True)
    return dict(zip(learn, grads)), out.nll / out.nll_count


def test_innovation_learns_takes_those_parameters_from_the_likelihood(tmp_path):
    """``model.innovation_learns=[gnss_noise_scale]`` over one 12 s window: Adam's first step
    moves ``gnss_noise_scale`` along the gradient of the window's innovation negative
    log-likelihood per scalar measurement and every other parameter along the window loss's
    (both computed here from the start values); the two gradients of ``gnss_noise_scale``
    have opposite signs here, so a step on the wrong one fails."""
    import torch

    seq, base, learn, params, last = _one_epoch(tmp_path, "window_s=12.0", "model.innovation_learns=[gnss_noise_scale]")
    by_loss, likelihood = _window_gradients(seq, base, learn, params)
    by_likelihood = float(torch.autograd.grad(likelihood, params.raw["gnss_noise_scale"])[0])
    assert by_likelihood * float(by_loss["gnss_noise_scale"]) < 0
    reached = {n: g for n, g in by_loss.items() if g is not None and n != "gnss_noise_scale"}
    reached["gnss_noise_scale"] = torch.tensor(by_likelihood)
    _assert_first_adam_step(params, last, reached)


def test_noise_level_likelihood_steps_on_the_level_gradient(tmp_path):
    """``model.noise_level=likelihood`` over one 12 s window: Adam's first step moves every
    learned noise parameter along :func:`level_gradient` of the window loss's and the innovation
    likelihood's gradients (both computed here from the start values), and the gates and other
    parameters along the loss's alone."""
    import torch

    from flowins.training.parameters import LEVEL_NAMES
    from flowins.training.unroll import level_gradient

    seq, base, learn, params, last = _one_epoch(tmp_path, "window_s=12.0", "model.noise_level=likelihood")
    by_loss, likelihood = _window_gradients(seq, base, learn, params)
    group = [n for n in learn if n in LEVEL_NAMES]
    by_likelihood = torch.autograd.grad(likelihood, [params.raw[n] for n in group], allow_unused=True)
    reached = {n: g for n, g in by_loss.items() if g is not None and n not in group}
    reached.update(zip(group, level_gradient([by_loss[n] for n in group], by_likelihood)))
    _assert_first_adam_step(params, last, reached)
    assert {"acc_noise", "gnss_noise_scale", "gnss_gate_threshold"} <= set(reached)


def test_noise_level_needs_two_learned_noise_parameters():
    from flowins.training.parameters import ModelSettings, starting_values

    params = FilterParameters(starting_values(NavigationConfig()), learn=["acc_noise", "flow_gate_threshold"])
    with pytest.raises(ValueError, match="model.noise_level=likelihood: needs at least two learned noise"):
        FilterLearner(params, NavigationConfig(), methods=["ins_gnss"], model=ModelSettings(noise_level="likelihood"))



def test_the_average_is_the_mean_of_every_step_of_the_last_epochs_and_its_label():
    """``model.average_epochs=2`` of 3 epochs: ``use_average`` loads the plain mean, over the
    steps of epochs 2 and 3 only, of every learned coordinate and of the adaptive network's
    weights (a naive mean of the recorded iterates); frozen parameters stay; the next
    validation outside a fit is recorded under ``mean 2-3``."""
    from types import SimpleNamespace

    import torch

    from flowins.training.parameters import ModelSettings

    start = {n: 0.3 if n == "dropout_p" else 0.01 * i if n in SIGNED else 0.5 + i for i, n in enumerate(NAMES)}
    params = FilterParameters(start, learn=["acc_noise", "gyro_noise"], adaptive=["vehicle"])
    learner = FilterLearner(params, NavigationConfig(), methods=["ins_gnss"], model=ModelSettings(average_epochs=2))
    assert learner.use_average() is None  # nothing averaged yet
    frozen = float(params.raw["gnss_noise_scale"].detach())
    learned = {n: q for n, q in params.raw.items() if q.requires_grad}
    learned.update({f"net.{n}": q for n, q in params.adaptive.named_parameters()})
    generator = torch.Generator().manual_seed(0)
    kept = []
    for epoch in range(3):
        learner._trainer = SimpleNamespace(max_epochs=3, current_epoch=epoch)
        for _ in range(2 + epoch):  # steps per epoch differ: every step counts once
            with torch.no_grad():
                for q in learned.values():
                    q.copy_(torch.randn(q.shape, generator=generator, dtype=q.dtype))
            learner._add_to_average()
            if epoch >= 1:
                kept.append({n: q.detach().clone() for n, q in learned.items()})
    with torch.no_grad():
        for q in learned.values():
            q.zero_()
    assert learner.use_average() == "mean 2-3"
    for name, q in learned.items():
        naive = sum(k[name] for k in kept) / len(kept)
        assert torch.allclose(q.detach(), naive, rtol=1e-12, atol=1e-15), name
    assert float(params.raw["gnss_noise_scale"].detach()) == frozen
    # the next validation outside a fit takes that label, and only the next
    learner._trainer = SimpleNamespace(max_epochs=3, current_epoch=2, sanity_checking=False,
                                       state=SimpleNamespace(fn=None), is_global_zero=False,
                                       datamodule=None)
    learner.log = lambda *args, **kwargs: None
    learner._val = {"ins_gnss": [1.0]}
    learner.on_validation_epoch_end()
    learner._val = {"ins_gnss": [2.0]}
    learner.on_validation_epoch_end()
    assert [e["label"] for e in learner.history] == ["mean 2-3", "start"]
    assert learner.history[0]["raw"]["acc_noise"] == pytest.approx(float(sum(k["acc_noise"] for k in kept) / len(kept)))
    # without model.average_epochs nothing is averaged
    off = FilterLearner(params, NavigationConfig(), methods=["ins_gnss"])
    off._trainer = SimpleNamespace(max_epochs=3, current_epoch=2)
    off._add_to_average()
    assert off.use_average() is None


def test_the_recheck_is_off_in_the_training_steps_only_where_the_model_says():
    """``model.recheck_while_training=false``: a training step's flow update has no recheck,
    every validation the configured one (hard, at its probability); by default the training
    step's recheck is soft, with the flow gate's softness."""
    from flowins.training.parameters import ModelSettings, starting_values

    params = FilterParameters(starting_values(NavigationConfig()), learn=["flow_gate_softness"])
    softness = float(params.value("flow_gate_softness"))
    configured = NavigationConfig().flow_update.recheck
    assert configured.mode == "hard"
    for flag in (True, False):
        learner = FilterLearner(params, NavigationConfig(), methods=["ins_dense"],
                                model=ModelSettings(recheck_while_training=flag))
        step = learner.filter_config(params, training=True).flow_update.recheck
        held_out = learner.filter_config(params, training=False).flow_update.recheck
        assert (held_out.mode, held_out.probability) == ("hard", configured.probability)
        if flag:
            assert (step.mode, step.probability) == ("soft", configured.probability)
            assert float(step.softness) == pytest.approx(softness)
        else:
            assert step.mode == "off"


def test_the_adaptive_network_steps_at_its_own_rate_and_the_constant_parameters_at_lr(tmp_path):
    """``model.adaptive_lr``: Adam's first step moves a weight by its group's rate against its
    gradient's sign (``|Δ| = rate`` wherever the gradient is not tiny), so after one window the
    network's zero-started head and linear path sit within ``adaptive_lr`` of 0, reaching it, and
    the learned σs' coordinates within ``lr``, reaching it."""
    import torch
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf
    from pathlib import Path

    from flowins.data.simulate.drive import DriveConfig, simulate_drive
    from flowins.jobs.train import run

    folder = tmp_path / "drive"
    simulate_drive(folder, DriveConfig(duration_s=24.0, outage_s=0.0))
    configs = str(Path(__file__).resolve().parents[2] / "configs")
    with initialize_config_dir(config_dir=configs, version_base="1.3"):
        cfg = OmegaConf.to_container(compose("train", overrides=[
            "experiment=real_vehicle", "imu=simulated_drive", f"output_dir={tmp_path / 'out'}",
            f"cache_dir={tmp_path / 'cache'}", "progress=false", "logger=csv", f"data.train=[{{path: {folder}}}]",
            f"data.val=[{{path: {folder}}}]", "window_s=30.0", "trainer.max_epochs=1", "model.warmup_steps=0",
            "model.lr=0.05", "model.adaptive_lr=0.002", "model.adaptive=[vehicle]", "model.adaptive_angles_rad=0.05",
            "filter.measurements.vehicle.lateral_sigma_mps=0.1", "filter.measurements.vehicle.vertical_sigma_mps=0.1",
            "model.learn=[vehicle_lateral_sigma_mps,vehicle_vertical_sigma_mps]"]), resolve=True)
    run(cfg)
    state = torch.load(tmp_path / "out" / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]
    for name in ("head.weight", "head.bias", "recent.weight"):
        moved = state[f"params.adaptive.vehicle.{name}"].abs()
        assert float(moved.max()) == pytest.approx(0.002, rel=1e-6) and bool((moved <= 0.002 * (1 + 1e-9)).all()), name
    for name in ("vehicle_lateral_sigma_mps", "vehicle_vertical_sigma_mps"):
        assert abs(float(state[f"params.raw.{name}"])) == pytest.approx(0.05, rel=1e-6), name
