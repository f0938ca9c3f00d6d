"""The training unroll on another device: windows, their losses and gradients, and the
held-out RMSE, on the fake device of ``conftest.FakeDevice`` (a GPU's stand-in)."""
import math
import pytest
import torch

from flowins.data.synthetic import synthetic_walk_recording
from flowins.measurements.gnss_heading import HeadingAlignment
from flowins.navigation import NavigationConfig
from flowins.training.parameters import NAMES, FilterParameters, starting_values
from flowins.training.unroll import (LOSSES, TrainingSequence, run_windows, sequences_rmse, split_gradient, level_gradient, window_bounds,
                                     window_loss)


@pytest.mark.slow
def test_the_unroll_on_another_device_gives_the_cpu_losses_gradients_and_rmse(fake_device):
    """Parameters placed on the fake device (``module.to(cuda)``): every window loss, its gradient
    and the held-out RMSE equal the CPU run's, and no op meets a CPU tensor on the device."""
    rec = synthetic_walk_recording(duration_s=12.0, seed=1)
    seq = TrainingSequence("walk", rec.imu, rec.gnss, rec.truth)
    base = NavigationConfig(gnss_heading=HeadingAlignment(enabled=False))
    start = starting_values(base)
    learn = [n for n in NAMES if start[n] > 0 and n not in ("initial_position_m", "initial_yaw_rad", "dropout_p")]
    outputs = {}
    for device in ("cpu", "meta"):
        params = FilterParameters(start, learn=learn)
        if device == "meta":
            fake_device.place(params)
        with fake_device() as mode:
            config = params.apply(base, training=True, device=device)
            first, second = window_bounds(seq.imu.t_s, 6.0)
            (a,) = run_windows([seq], "ins_gnss", config, [first])
            (b,) = run_windows([seq], "ins_gnss", config, [second], starts=[(a.mean.detach(), a.cov.detach())])
            assert b.track.mean.device.type == device
            values = []
            for loss in LOSSES:
                total = sum(window_loss(w.track, seq.truth, loss=loss, nll_weight=0.1, orientation_weight_m_per_rad=0.1).loss
                            for w in (a, b))
                grads = torch.autograd.grad(total, [params.raw[n] for n in learn], allow_unused=True, retain_graph=True)
                values.append(torch.stack([total.detach()] + [torch.zeros(()) if g is None else g.cpu() for g in grads]))
            rmse = sequences_rmse([seq], "ins_gnss", params.apply(base, training=False, device=device))
        assert mode.slips == {}, mode.slips
        outputs[device] = (torch.stack(values).cpu(), rmse)
    assert torch.equal(outputs["meta"][0], outputs["cpu"][0]) and outputs["meta"][1] == outputs["cpu"][1]
    assert int((outputs["cpu"][0][:, 1:] != 0).sum()) >= 3 * 5  # the gradients reach the parameters


def test_the_heldout_filter_and_smoother_rmse_are_those_of_navigate():
    """:func:`sequences_errors` (the long held-out walks' filter and smoother RMSE) on two walks
    in one batch: each pair equals :func:`flowins.navigation.navigate` on its walk alone, scored
    with Table I's SE(3) alignment, and the smoother differs from the filter."""
    from flowins.evaluation.metrics import trajectory_errors
    from flowins.navigation import NavigationRun, navigate
    from flowins.state import STATE
    from flowins.training.unroll import sequences_errors

    recs = [synthetic_walk_recording(duration_s=d, seed=s) for d, s in ((12.0, 1), (10.0, 2))]
    seqs = [TrainingSequence(f"walk {k}", r.imu, r.gnss, r.truth) for k, r in enumerate(recs)]
    config = FilterParameters(starting_values(base := NavigationConfig(gnss_heading=HeadingAlignment(enabled=False))),
                              learn=()).apply(base, training=False)
    errors = sequences_errors(seqs, "ins_gnss", config)
    for seq, (filtered, smoothed) in zip(seqs, errors):
        result = navigate(NavigationRun(seq.imu, seq.gnss), config=config)
        expected = [float(trajectory_errors(track.t, track.mean[:, STATE.p], seq.truth.t_s, seq.truth.pos_m,
                                            align="se3").rmse_m)
                    for track in (result.filter.in_final_frame(), result.smoother)]
        assert (filtered, smoothed) == pytest.approx(expected, rel=1e-9)
        assert abs(smoothed - filtered) > 1e-3 * filtered
    assert [f for f, _ in errors] == sequences_rmse(seqs, "ins_gnss", config)


@pytest.mark.parametrize("start", ["fork", "spawn"])
def test_the_heldout_rmse_split_over_worker_processes_is_the_batch_here_in_order(start, caplog, monkeypatch):
    """filter.workers=2 (train.py's validations on the CPU): three walks of different seeds and
    lengths under one method each (so a result in the wrong place shows), with learned
    parameters, give each walk the filter and smoother RMSE of the batch in this process, up to
    rounding (another batch, one thread); also where the workers are started by spawn and every
    input crosses pickled."""
    import dataclasses

    import flowins.parallel as parallel
    from flowins.training.unroll import sequences_errors

    recs = [synthetic_walk_recording(duration_s=d, seed=s) for d, s in ((8.0, 1), (10.0, 2), (6.0, 3))]
    seqs = [TrainingSequence(f"walk {k}", r.imu, r.gnss, r.truth) for k, r in enumerate(recs)]
    base = NavigationConfig(gnss_heading=HeadingAlignment(enabled=False))
    params = FilterParameters(starting_values(base), learn=["acc_noise", "gnss_noise_scale"])
    with torch.no_grad():
        config = params.apply(base, training=False)
    methods = ["ins_gnss", "ins_gnss", "ins"]
    here = sequences_errors(seqs, methods, config)
    assert len({round(f, 6) for f, _ in here}) == 3
    monkeypatch.setattr(parallel, "start_method", lambda: start)
    with caplog.at_level("DEBUG", logger="flowins"):
        there = sequences_errors(seqs, methods, dataclasses.replace(config, workers=2))
    assert any("3 runs in 2 worker processes" in r.getMessage() for r in caplog.records)
    for (f_there, s_there), (f_here, s_here) in zip(there, here, strict=True):
        assert f_there == pytest.approx(f_here, rel=1e-9) and s_there == pytest.approx(s_here, rel=1e-7)


def test_one_sequence_under_two_methods_in_one_batch_equals_each_method_alone():
    """run_windows with one method per row (the training step's rows: each sequence under each
    method): the batched windows' end states, losses and the gradient of their summed loss equal
    those of each method run alone (1e-9), and the two methods' tracks differ."""
    rec = synthetic_walk_recording(duration_s=12.0, seed=1)
    seq = TrainingSequence("walk", rec.imu, rec.gnss, rec.truth)
    base = NavigationConfig(gnss_heading=HeadingAlignment(enabled=False))
    start = starting_values(base)
    learn = ["acc_noise", "gyro_noise", "gnss_noise_scale", "initial_velocity_mps"]
    params = FilterParameters(start, learn=learn)
    config = params.apply(base, training=True)
    window = window_bounds(seq.imu.t_s, 6.0)[0]
    learned = [params.raw[n] for n in learn]

    def grads(results):
        total = sum(window_loss(r.track, seq.truth).loss for r in results)
        return total.detach(), torch.stack(torch.autograd.grad(total, learned))

    batched = run_windows([seq, seq], ["ins", "ins_gnss"], config, [window, window])
    alone = [run_windows([seq], method, params.apply(base, training=True), [window])[0] for method in ("ins", "ins_gnss")]
    for b, a in zip(batched, alone):
        torch.testing.assert_close(b.mean, a.mean, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(b.cov, a.cov, rtol=1e-9, atol=1e-12)
    assert float((batched[0].mean - batched[1].mean).detach().abs().max()) > 1e-3
    loss_b, grad_b = grads(batched)
    loss_a, grad_a = grads(alone)
    torch.testing.assert_close(loss_b, loss_a, rtol=1e-9, atol=0.0)
    torch.testing.assert_close(grad_b, grad_a, rtol=1e-7, atol=1e-12)
    assert bool((grad_a != 0).all())
    with pytest.raises(ValueError, match="one per sequence"):
        run_windows([seq], ["ins", "ins_gnss"], config, [window])


def test_split_gradient_takes_each_parameter_from_its_own_loss():
    """Closed forms: loss = a² + 3ab, likelihood = b³ + ab; a learns from the loss (2a + 3b),
    b from the likelihood (3b² + a); c reaches neither the loss nor (it is not asked there)."""
    a, b, c = (torch.tensor(v, dtype=torch.float64, requires_grad=True) for v in (1.5, -0.7, 2.0))
    loss = a * a + 3 * a * b
    likelihood = b**3 + a * b + c
    ga, gb, gc = split_gradient(loss, likelihood, [a, b, c], [False, True, False])
    assert float(ga) == pytest.approx(2 * 1.5 + 3 * -0.7, rel=1e-15)
    assert float(gb) == pytest.approx(3 * 0.49 + 1.5, rel=1e-15)
    assert gc is None  # c is in the likelihood only, and learns from the loss
    loss = a * a + 3 * a * b
    assert [float(g) for g in split_gradient(loss, None, [a, b], [False, False])] == pytest.approx([2 * 1.5 - 2.1, 4.5])
    loss = a * a + 3 * a * b
    assert split_gradient(loss, None, [a, b], [False, True])[1] is None  # no likelihood: nothing for b
    with pytest.raises(ValueError, match="2 flags for 3 parameters"):
        split_gradient(loss, None, [a, b, c], [False, True])


def test_level_gradient_moves_the_common_level_by_the_likelihood_and_the_ratios_by_the_loss():
    """Closed forms for a group of three: loss = (a − b)² + c·a (the ratios, and a common part),
    likelihood = (a + b + c − 3)² (the level alone). Each gradient is the loss's minus its mean
    over the group plus the likelihood's mean; a fourth parameter outside the group takes the
    loss's, a fifth in ``from_likelihood`` the likelihood's alone."""
    a, b, c, d, e = (torch.tensor(v, dtype=torch.float64, requires_grad=True) for v in (0.4, -0.2, 1.1, 0.7, 0.3))
    loss = (a - b) ** 2 + c * a + d * d * a + e
    likelihood = (a + b + c - 3) ** 2 + e * e
    ga, gb, gc, gd, ge = split_gradient(loss, likelihood, [a, b, c, d, e], [False, False, False, False, True],
                                        level=[True, True, True, False, True])
    by_loss = [2 * 0.6 + 1.1 + 0.49, -2 * 0.6, 0.4]  # ∂/∂a, ∂/∂b, ∂/∂c of the loss
    by_likelihood = 2 * (0.4 - 0.2 + 1.1 - 3)  # the same for a, b and c
    mean = sum(by_loss) / 3
    assert [float(g) for g in (ga, gb, gc)] == pytest.approx([x - mean + by_likelihood for x in by_loss], rel=1e-14)
    assert float(ga + gb + gc) == pytest.approx(3 * by_likelihood, rel=1e-14)  # the level: the likelihood's alone
    assert float(gd) == pytest.approx(2 * 0.7 * 0.4, rel=1e-14)
    assert float(ge) == pytest.approx(2 * 0.3, rel=1e-14)
    # the likelihood reaching none of them (None): the ratios' part alone
    assert [float(g) for g in level_gradient([torch.tensor(1.0), torch.tensor(3.0)], [None, None])] == [-1.0, 1.0]
    # one the loss does not reach (None) takes the others' mean loss gradient, negated, and the level
    got = level_gradient([torch.tensor(1.0), None, torch.tensor(5.0)], [torch.tensor(2.0), torch.tensor(-4.0), None])
    assert [float(g) for g in got] == pytest.approx([-1.0 - 2 / 3, -2.0 - 2 / 3, 3.0 - 2 / 3], rel=1e-6)
    assert level_gradient([None, None], [None, None]) == [None, None]
    with pytest.raises(ValueError, match="1 level flags for 2 parameters"):
        split_gradient(a * b, None, [a, b], [False, False], level=[True])


def test_one_factor_on_every_noise_level_leaves_the_estimates_unchanged():
    """The premise of ``model.noise_level=likelihood`` (:func:`level_gradient`): every noise
    density, walk, initial 1-σ and measurement σ of ``ins_gnss`` times ``e^0.4`` (the start's
    covariance times ``e^0.8``, the GNSS gate and the still start's zero-velocity updates off) leaves the filter's means and so the window
    loss unchanged, and scales every covariance by ``e^0.8``; one of them alone changes the loss."""
    from dataclasses import replace

    from flowins.filter.ekf import Gate
    from flowins.navigation import NavigationRun, prepare_navigation
    from flowins.training.parameters import LEVEL_NAMES

    rec = synthetic_walk_recording(duration_s=12.0, seed=1)
    seq = TrainingSequence("walk", rec.imu, rec.gnss, rec.truth)
    base = NavigationConfig(gnss_heading=HeadingAlignment(enabled=False), gnss_gate=Gate(mode="off"))
    # no zero-velocity updates at the still start: their σ is no learned parameter
    base = replace(base, start=replace(base.start, still=replace(base.start.still, zupt_hz=0.0)))
    start = starting_values(base)
    window = (0, seq.imu.t_s.shape[0] - 1)

    def run(shift: dict[str, float], factor: float):  # unbounded: a shift of the coordinate is one of ln θ
        params = FilterParameters(start, learn=(), bounds={n: None for n in NAMES}, ceilings={})
        with torch.no_grad():
            for name, x in shift.items():
                params.raw[name].fill_(x)
        config = params.apply(base, training=False)
        setup = prepare_navigation(NavigationRun(seq.imu, seq.gnss), config=base)
        (out,) = run_windows([seq], "ins_gnss", config, [window], starts=[(setup.mean0, setup.cov0 * factor)])
        return out, float(window_loss(out.track, seq.truth).loss)

    group = [n for n in (*LEVEL_NAMES, "initial_position_m", "initial_yaw_rad") if start[n] > 0]
    (a, loss_a), (b, loss_b) = run({}, 1.0), run({n: 0.4 for n in group}, math.exp(0.8))
    torch.testing.assert_close(b.track.mean, a.track.mean, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(b.track.cov, a.track.cov * math.exp(0.8), rtol=1e-7, atol=1e-15)
    assert loss_b == pytest.approx(loss_a, rel=1e-9)
    _, loss_c = run({"gnss_noise_scale": 0.4}, 1.0)
    assert abs(loss_c - loss_a) > 1e-3 * loss_a


def test_a_window_can_start_from_the_ground_truth():
    """``filter.init.mode=groundtruth`` in training: the first window starts at the truth's
    position and velocity (the sequence's truth reaches the start)."""
    import dataclasses

    from flowins.state import STATE

    rec = synthetic_walk_recording(duration_s=12.0, seed=2)
    seq = TrainingSequence("walk", rec.imu, rec.gnss, rec.truth)
    base = NavigationConfig(gnss_heading=HeadingAlignment(enabled=False))
    base = dataclasses.replace(base, start=dataclasses.replace(base.start, mode="groundtruth"))
    config = FilterParameters(starting_values(base), learn=["acc_noise"]).apply(base, training=True, device="cpu")
    (result,) = run_windows([seq], "ins", config, [window_bounds(seq.imu.t_s, 6.0)[0]])
    p0 = result.track.node_mean[0, STATE.p].detach()
    k = int(torch.argmin((rec.truth.t_s - float(rec.imu.t_s[0])).abs()))
    assert float((p0 - rec.truth.pos_m[k]).norm()) < 0.05
