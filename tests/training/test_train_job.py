"""The training job end to end on tiny simulated walks, and learning from a mis-tuned start.

The flow is OpenCV's DIS (fast on a CPU) so that the simulated sequences and their
flow are made in seconds; the SpyNet moments path is covered in tests/flow.
"""
import json
import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from flowins.ins.imu_model import imu_model
from flowins.settings import navigation_config
from flowins.jobs.train import GPU_ROWS, few_rows_note, run
from flowins.settings import flow_config, parameter_sets
from flowins.training.data import load_training_sequence
from flowins.training.parameters import NOISE_NAMES, FilterParameters
from flowins.training.unroll import run_window, window_bounds, window_loss

CONFIGS = str(Path(__file__).resolve().parents[2] / "configs")


def _cfg(tmp_path, *overrides):
    with initialize_config_dir(config_dir=CONFIGS, version_base="1.3"):
        cfg = compose("train", overrides=[f"output_dir={tmp_path / 'out'}", f"cache_dir={tmp_path / 'cache'}", "flow=dis",
                                          "progress=false", "logger=csv", *overrides])
    return OmegaConf.to_container(cfg, resolve=True)


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return tmp_path_factory.mktemp("train")


TINY = ["data.train=[{seed: 1, duration_s: 20.0}]", "data.val=[{seed: 3, duration_s: 20.0}]", "data.select=[]",
        "window_s=10.0", "filter.flow.n_points=32", "trainer.max_epochs=1"]


#: what Lightning printed on every run before the job dealt with it (the cause fixed, or the
#: message dropped precisely: flowins.jobs.train._without_lightning_noise)
NOISE = ("LeafSpec", "litlogger", "transfer_batch_to_device", "requires_grad=True to a scalar")


@pytest.mark.slow
def test_train_job_writes_a_checkpoint_that_evaluate_reads(workdir, recwarn, capfd, caplog):
    from flowins.jobs.evaluate import run as evaluate

    cfg = _cfg(workdir, "experiment=mistuned", *TINY)
    result = run(cfg)
    printed = "".join(capfd.readouterr()) + caplog.text + "".join(str(w.message) for w in recwarn)
    assert not [n for n in NOISE if n in printed], printed
    out = Path(cfg["output_dir"])
    held = json.loads((out / "heldout.json").read_text())
    assert set(held["rmse_m"]) == {"learned", "start", "hand-tuned"}
    for per_method in held["rmse_m"].values():
        assert set(per_method) == {"ins_dense", "ins_gnss_dense"}
        assert all(math.isfinite(v) for v in sum(per_method.values(), []))
    assert result["skipped_windows"] == 0
    # the start is the hand-tuned values times 10 for every noise parameter
    for name in NOISE_NAMES:
        if result["hand-tuned"][name] > 0:
            assert result["start"][name] == pytest.approx(10 * result["hand-tuned"][name])
    # the start was validated before the first step, and the checkpoint is the best of it, the epoch
    # and the better of the two with experiment=mistuned's flow gates
    history = result["history"]
    first = min(history[:2], key=lambda entry: entry["score"])
    assert [entry["label"] for entry in history] == ["start", "epoch 1", *(f"{first['label']}, gate {p}"
                                                                           for p in ("0.95", "0.99", "0.999"))]
    # each validation said so as it ended, with its score
    assert f"start: held out {history[0]['score']:.3f} m (ins_dense {history[0]['rmse_m']['ins_dense']:.3f}" in caplog.text
    assert f"epoch 1 of 1: held out {history[1]['score']:.3f} m" in caplog.text
    chosen = min(history, key=lambda entry: entry["score"])
    assert result["chosen"] == chosen["label"]
    assert json.loads((out / "selection.json").read_text())["chosen"] == chosen["label"]
    # the held-out test of the selected parameters scores what their validation scored
    for method in ("ins_dense", "ins_gnss_dense"):
        assert held["rmse_m"]["learned"][method][0] == pytest.approx(chosen["rmse_m"][method], rel=1e-9)
    assert held["rmse_m"]["start"]["ins_dense"][0] == pytest.approx(history[0]["rmse_m"]["ins_dense"], rel=1e-9)
    # the epoch's learning moved the learned parameters and kept the frozen ones
    last = FilterParameters.from_checkpoint(out / "checkpoints" / "last.ckpt").values()
    assert last["flow_sigma_scale"] != pytest.approx(result["start"]["flow_sigma_scale"], rel=1e-6)
    assert last["initial_yaw_rad"] == pytest.approx(result["start"]["initial_yaw_rad"], rel=1e-12)
    learned = result["learned"]
    ckpt = Path(result["checkpoint"])
    assert ckpt.is_file()
    assert FilterParameters.from_checkpoint(ckpt).values() == pytest.approx(learned, rel=1e-9)

    # evaluate.py model.checkpoint=PATH runs with those values: same RMSE as the job's held-out test
    with initialize_config_dir(config_dir=CONFIGS, version_base="1.3"):
        ecfg = compose("evaluate", overrides=[
            f"output_dir={workdir / 'eval'}", f"cache_dir={workdir / 'cache'}", "flow=dis", "plots=false",
            "progress=false", "quick=true", "sequence.seed=3", "sequence.quick_duration_s=20.0",
            "filter.flow.n_points=32", f"model.checkpoint={ckpt}", "combinations=[ins_dense]"])
    (row,) = evaluate(ecfg)
    assert row.filter_rmse_m == pytest.approx(held["rmse_m"]["learned"]["ins_dense"][0], rel=1e-6)


@pytest.mark.slow
def test_a_few_steps_from_a_mistuned_start_reduce_the_loss(workdir):
    cfg = _cfg(workdir, "experiment=mistuned", *TINY)
    seq = load_training_sequence({"seed": 1, "duration_s": 20.0}, {**cfg, "flow": flow_config(cfg, moments=True)},
                                 methods=["ins_dense"])
    base = navigation_config(cfg["filter"], imu_model(cfg["imu"], recording=False))
    _, start, learn = parameter_sets(cfg, base)
    params = FilterParameters(start, learn)
    opt = torch.optim.Adam([p for p in params.parameters() if p.requires_grad], lr=0.1)
    window = window_bounds(seq.imu.t_s, 20.0)[0]

    def loss() -> torch.Tensor:
        result = run_window(seq, "ins_dense", params.apply(base, training=True), window)
        return window_loss(result.track, seq.truth).loss

    losses = []
    for _ in range(6):
        opt.zero_grad()
        value = loss()
        value.backward()
        opt.step()
        losses.append(float(value.detach()))
    final = float(loss().detach())
    # the window's aligned position RMSE (m) at least halves (measured: 1.94 m -> 0.34 m)
    assert final < 0.5 * losses[0], losses + [final]
    values = params.values()
    # what ins_dense depends on moved (GNSS and, with DIS flow, the dropout rate get no gradient)
    moved = [n for n in params.learned if params.raw[n].grad is not None]
    assert {"acc_noise", "gyro_noise", "flow_sigma_scale", "flow_sigma_floor_px"} <= set(moved)
    assert all(values[n] != pytest.approx(start[n], rel=1e-9) for n in moved), {n: (values[n], start[n]) for n in moved}
    assert all(values[n] == pytest.approx(start[n], rel=1e-12) for n in set(start) - set(params.learned))


def test_a_training_recording_with_an_impossible_reading_is_refused(tmp_path):
    from flowins.data.folder import write_folder
    from flowins.data.sequence import Sequence
    from flowins.data.streams import ImuStream
    from flowins.data.synthetic import synthetic_walk_recording

    rec = synthetic_walk_recording(duration_s=10.0, seed=1)
    acc = rec.imu.acc_mps2.clone()
    acc[321, 2] = 1e6
    imu = ImuStream(rec.imu.t_s, acc, rec.imu.gyro_rps)
    folder = write_folder(Sequence(imu, name="spiked", groundtruth=rec.truth), tmp_path / "spiked")
    cfg = _cfg(tmp_path, "methods=[ins]", f"data.train=[{{path: {folder}}}]", f"data.val=[{{path: {folder}}}]")
    with pytest.raises(ValueError, match=r"imu\.csv: sample 321 .*accelerometer reading 1e\+06 m/s².*imu\.acc_range_mps2"):
        run(cfg)  # the recordings are read, then checked against the preset the job resolves



def test_a_mounting_fit_is_refused_by_training_naming_what_it_takes_instead(tmp_path):
    """``mounting=fit`` runs a first pass per run in ``evaluate.py``; training's windows have none,
    so the job stops before it reads anything rather than train with the mounting as configured."""
    cfg = _cfg(tmp_path, *TINY, "methods=[ins_gnss]", "filter.measurements.vehicle.mode=on",
               "filter.measurements.vehicle.mounting=fit")
    with pytest.raises(ValueError, match=r"mounting=fit: .*\(model\.learn: vehicle_mount_\*_rad"):
        run(cfg)


#: INS + GNSS with every fix applied as it comes: no flow to compute, a run in seconds
GNSS = ["methods=[ins_gnss]", "filter.gnss_heading.enabled=false", "data.train=[{seed: 1, duration_s: 20.0}]",
        "data.val=[{seed: 3, duration_s: 20.0}]", "window_s=10.0", "curriculum_window_s=[]", "trainer.max_epochs=1"]
#: two long held-out walks of different lengths (their batched filter pass pads the shorter one)
SELECT = [{"seed": 6, "duration_s": 20.0}, {"seed": 7, "duration_s": 24.0}]


@pytest.mark.slow
def test_select_sequences_choose_the_checkpoint_on_their_rmse_each_computed_as_alone(workdir):
    import numpy as np
    from flowins.training.unroll import sequence_rmse

    cfg = _cfg(workdir / "select", *GNSS, "data.select=[{seed: 6, duration_s: 20.0},{seed: 7, duration_s: 24.0}]")
    result = run(cfg)
    out = Path(cfg["output_dir"])
    history = result["history"]
    assert [entry["label"] for entry in history] == ["start", "epoch 1"]
    # each validation's RMSE of each select sequence: the filter alone on it, with the parameters validated
    seqs = [load_training_sequence(s, {**cfg, "flow": flow_config(cfg, moments=True)}, methods=["ins_gnss"])
            for s in SELECT]
    base = navigation_config(cfg["filter"], imu_model(cfg["imu"], recording=False))
    validated = {"start": FilterParameters(result["start"], learn=()),
                 "epoch 1": FilterParameters.from_checkpoint(out / "checkpoints" / "last.ckpt")}
    for entry in history:
        config = validated[entry["label"]].apply(base, training=False)
        alone = [sequence_rmse(seq, "ins_gnss", config) for seq in seqs]
        assert entry["select_rmse_m"]["ins_gnss"] == pytest.approx(alone, rel=1e-9), entry["label"]
        assert entry["select_score"] == pytest.approx(sum(alone) / 2, rel=1e-9)
    assert history[0]["select_score"] != pytest.approx(history[1]["select_score"], rel=1e-6)  # the epoch moved them
    # the checkpoint is the lower select score, and its held-out test scores what its validation scored
    chosen = min(history, key=lambda entry: entry["select_score"])
    assert result["chosen"] == chosen["label"]
    assert json.loads((out / "selection.json").read_text())["chosen"] == chosen["label"]
    held = json.loads((out / "heldout.json").read_text())
    assert set(held["select_rmse_m"]) == {"learned", "start", "hand-tuned"}
    assert held["select_rmse_m"]["learned"]["ins_gnss"] == pytest.approx(chosen["select_rmse_m"]["ins_gnss"], rel=1e-9)
    assert held["select_rmse_m"]["start"]["ins_gnss"] == pytest.approx(history[0]["select_rmse_m"]["ins_gnss"],
                                                                       rel=1e-9)
    learned = np.array(chosen["select_rmse_m"]["ins_gnss"])
    # the smoother over the select sequences, with the chosen parameters, beside the filter
    from flowins.training.unroll import sequences_errors

    config = FilterParameters.from_checkpoint(out / "checkpoints" / "best.ckpt").apply(base, training=False)
    smoothed = np.array([e[1] for e in sequences_errors(seqs, "ins_gnss", config)])
    assert held["select_smoother_rmse_m"]["learned"]["ins_gnss"] == pytest.approx(smoothed.tolist(), rel=1e-9)
    row = next(line for line in (out / "heldout.txt").read_text().splitlines() if line.startswith("learned"))
    assert row.split()[-8:] == [f"{learned.mean():.2f}", "±", f"{learned.std():.2f}", "/",
                                f"{smoothed.mean():.2f}", "±", f"{smoothed.std():.2f}", "m"]
    metrics = (out / "csv" / "version_0" / "metrics.csv").read_text().splitlines()[0].split(",")
    assert {"select/ins_gnss/filter_rmse_m", "select/rmse_mean_m", "test/learned/select/ins_gnss/filter_rmse_m",
            "test/learned/select/ins_gnss/smoother_rmse_m"} <= set(metrics)

    # the training itself does not see the select sequences: its validations are those of a run without them
    plain = run(_cfg(workdir / "plain", *GNSS, "data.select=[]"))
    keys = ("label", "step", "rmse_m", "score", "raw")
    assert [{k: e[k] for k in keys} for e in plain["history"]] == [{k: e[k] for k in keys} for e in history]


@pytest.mark.slow
def test_the_last_epochs_mean_competes_for_the_checkpoint(workdir):
    """``model.average_epochs=2`` over three epochs of one step each: after the last epoch the
    mean of epochs 2 and 3 (their steps' parameters, here each epoch's last) is validated as
    one more candidate, ``best.ckpt`` is the lowest of all, and ``last.ckpt`` keeps the last
    step's parameters."""
    cfg = _cfg(workdir / "average", *GNSS, "window_s=20.0", "trainer.max_epochs=3", "model.average_epochs=2",
               "model.learn=[acc_noise, gyro_noise, gnss_noise_scale]")
    result = run(cfg)
    history = result["history"]
    assert [e["label"] for e in history] == ["start", "epoch 1", "epoch 2", "epoch 3", "mean 2-3"]
    assert [e["step"] for e in history] == [0, 1, 2, 3, 3]
    for name in ("acc_noise", "gyro_noise", "gnss_noise_scale"):
        assert history[4]["raw"][name] == pytest.approx(0.5 * (history[2]["raw"][name] + history[3]["raw"][name]),
                                                        rel=1e-12), name
    assert history[4]["raw"]["acc_bias_walk"] == history[3]["raw"]["acc_bias_walk"]  # not learned: as it was
    assert history[4]["score"] != pytest.approx(history[3]["score"], rel=1e-6)  # the mean is another filter
    chosen = min(history, key=lambda entry: entry["score"])
    assert result["chosen"] == chosen["label"]
    out = Path(cfg["output_dir"]) / "checkpoints"
    best, last = FilterParameters.from_checkpoint(out / "best.ckpt"), FilterParameters.from_checkpoint(out / "last.ckpt")
    for name in ("acc_noise", "gyro_noise", "gnss_noise_scale"):
        assert float(best.raw[name]) == pytest.approx(chosen["raw"][name], rel=1e-12)
        assert float(last.raw[name]) == pytest.approx(history[3]["raw"][name], rel=1e-12)


@pytest.mark.slow
def test_the_chosen_parameters_with_other_flow_gates_compete_for_the_checkpoint(workdir):
    """``model.select_flow_gate=[0.95, 0.99]``: after training, the chosen validation's
    parameters with the flow gate at χ²₁(0.95) and χ²₁(0.99) are validated as two more
    candidates, everything else as chosen; each scores what those parameters score run alone,
    ``best.ckpt`` is the lowest of all."""
    from flowins.filter.ekf import chi2_quantile
    from flowins.training.unroll import sequence_rmse

    cfg = _cfg(workdir / "gates", *TINY, "methods=[ins_dense]", "model.select_flow_gate=[0.95, 0.99]")
    result = run(cfg)
    history = result["history"]
    first = min(history[:2], key=lambda entry: entry["score"])
    assert [e["label"] for e in history] == ["start", "epoch 1", f"{first['label']}, gate 0.95",
                                             f"{first['label']}, gate 0.99"]
    seq = load_training_sequence({"seed": 3, "duration_s": 20.0}, {**cfg, "flow": flow_config(cfg, moments=True)},
                                 methods=["ins_dense"])
    base = navigation_config(cfg["filter"], imu_model(cfg["imu"], recording=False))
    for entry, p in zip(history[2:], (0.95, 0.99)):
        assert entry["values"]["flow_gate_threshold"] == pytest.approx(chi2_quantile(p, 1), rel=1e-12)
        assert {n: v for n, v in entry["raw"].items() if n != "flow_gate_threshold"} == \
            {n: v for n, v in first["raw"].items() if n != "flow_gate_threshold"}
        config = FilterParameters(entry["values"], learn=()).apply(base, training=False)
        assert entry["score"] == pytest.approx(sequence_rmse(seq, "ins_dense", config), rel=1e-9), entry["label"]
    assert any(e["score"] != pytest.approx(first["score"], rel=1e-6) for e in history[2:])  # the gate matters here
    chosen = min(history, key=lambda entry: entry["score"])
    assert result["chosen"] == chosen["label"]
    best = FilterParameters.from_checkpoint(Path(cfg["output_dir"]) / "checkpoints" / "best.ckpt")
    assert float(best.value("flow_gate_threshold")) == pytest.approx(chosen["values"]["flow_gate_threshold"], rel=1e-12)


def test_choosing_a_flow_gate_needs_a_method_with_dense_flow():
    from flowins.navigation import NavigationConfig
    from flowins.training.module import FilterLearner
    from flowins.training.parameters import ModelSettings, starting_values

    params = FilterParameters(starting_values(NavigationConfig()), learn=["acc_noise"])
    with pytest.raises(ValueError, match=r"model\.select_flow_gate: no method of \['ins_gnss'\] uses dense flow"):
        FilterLearner(params, NavigationConfig(), methods=["ins_gnss"], model=ModelSettings(select_flow_gate=(0.95,)))


@pytest.mark.slow
def test_an_empty_select_list_is_a_run_without_the_key(workdir):
    without = run(_cfg(workdir / "without", *GNSS, "~data.select"))
    empty = run(_cfg(workdir / "empty", *GNSS, "data.select=[]"))
    assert empty["history"] == without["history"]
    assert all("select_score" not in entry for entry in empty["history"])
    assert empty["chosen"] == without["chosen"] == min(empty["history"], key=lambda entry: entry["score"])["label"]
    for name in ("selection.json", "heldout.json", "heldout.txt"):
        assert (workdir / "empty" / "out" / name).read_text() == (workdir / "without" / "out" / name).read_text(), name


def test_a_bad_select_source_is_refused_naming_its_key(tmp_path):
    from flowins.training.data import SequenceDataModule

    with pytest.raises(ValueError, match=r"data\.select\[0\]\.foo: unknown key"):
        run(_cfg(tmp_path, "data.select=[{foo: 1}]"))
    with pytest.raises(ValueError, match=r"data\.select\[0\] \{'foo': 1\}"):
        SequenceDataModule(train=[{"seed": 1}], val=[{"seed": 3}], select=[{"foo": 1}], config={}, methods=["ins"])


@pytest.mark.slow
def test_a_batch_of_windows_has_the_mean_loss_and_gradient_of_its_sequences_windows(workdir):
    """run_windows: the windows of two sequences in one batched filter; the mean of their
    losses has the mean of the gradients each window gives alone (run_window)."""
    from flowins.training.unroll import run_windows

    cfg = _cfg(workdir, "experiment=mistuned", *TINY)
    seqs = [load_training_sequence({"seed": seed, "duration_s": 20.0}, {**cfg, "flow": flow_config(cfg, moments=True)},
                                   methods=["ins_gnss"]) for seed in (1, 2)]
    base = navigation_config(cfg["filter"], imu_model(cfg["imu"], recording=False))
    _, start, learn = parameter_sets(cfg, base)
    params = FilterParameters(start, learn)
    learned = [(name, p) for name, p in params.raw.items() if p.requires_grad]
    windows = [window_bounds(seq.imu.t_s, 10.0)[0] for seq in seqs]
    losses, grads = [], []
    for seq, window in zip(seqs, windows):
        params.zero_grad()
        result = run_window(seq, "ins_gnss", params.apply(base, training=True), window)
        loss = window_loss(result.track, seq.truth).loss
        loss.backward()
        losses.append(float(loss.detach()))
        grads.append({name: p.grad.clone() for name, p in learned if p.grad is not None})
    params.zero_grad()
    results = run_windows(seqs, "ins_gnss", params.apply(base, training=True), windows)
    batch = [window_loss(r.track, seq.truth).loss for r, seq in zip(results, seqs)]
    total = torch.stack(batch).mean()
    total.backward()
    assert [float(b.detach()) for b in batch] == pytest.approx(losses, rel=1e-9)
    assert grads[0], "the GNSS window's loss has a gradient"
    for name, p in learned:
        if name in grads[0]:
            expected = 0.5 * (grads[0][name] + grads[1][name])
            torch.testing.assert_close(p.grad, expected, rtol=1e-7, atol=1e-12)


def test_a_gpu_run_with_few_rows_per_step_is_told_and_others_are_not():
    note = few_rows_note("cuda", 1, 2)
    assert note is not None and "2 filter rows per step" in note and "data.batch_size=1 x 2 methods" in note
    assert few_rows_note("cuda", GPU_ROWS, 1) is None  # enough rows
    assert few_rows_note("cuda", GPU_ROWS // 2, 2) is None  # batch_size times methods
    assert few_rows_note("cpu", 1, 1) is None  # a CPU run is not told
    assert "1 filter row per step" in few_rows_note("cuda", 1, 1)


@pytest.mark.slow
def test_training_moves_the_adaptive_noise_network_and_its_checkpoint_keeps_it(workdir):
    """``model.adaptive=[vehicle]``: the optimiser steps the network's weights with the other
    parameters (its head starts at zero: the constant σs), and the checkpoint holds them."""
    cfg = _cfg(workdir / "adaptive", *GNSS, "filter.measurements.vehicle.mode=on", "model.adaptive=[vehicle]",
               "model.learn=[acc_noise, vehicle_lateral_sigma_mps]")
    run(cfg)
    params = FilterParameters.from_checkpoint(Path(cfg["output_dir"]) / "checkpoints" / "last.ckpt")
    head = params.adaptive["vehicle"].head
    assert head.bias.abs().max() > 1e-3 and head.weight.abs().max() > 1e-3


def test_a_start_that_waits_for_fixes_is_refused_naming_why_and_what_to_set():
    """A moving drive whose fixes come every 30 s: the moving start waits for its second fix, so
    the filter would begin seconds in, where training starts it at the first sample. The error
    names the recording, the row, the wait and the settings that fix it; with the reference start
    (``filter.init.mode=groundtruth``) the same window runs."""
    from flowins.data.simulate.drive import DriveConfig, drive_sequence
    from flowins.data.streams import GnssStream, PoseStream
    from flowins.navigation import NavigationConfig
    from flowins.start import StartSettings
    from flowins.training.unroll import TrainingSequence

    seq = drive_sequence(DriveConfig(duration_s=95.0, outage_s=0.0))[0]
    g = seq.gnss
    keep = torch.arange(len(g.t_s)) % 30 == 0  # 4 fixes: the reference start ties its frame to 3 or more
    sparse = GnssStream(g.t_s[keep], g.lat_deg[keep], g.lon_deg[keep], g.alt_m[keep], g.h_acc_m[keep], g.v_acc_m[keep],
                        name=g.name)
    train = TrainingSequence("sparse-fixes drive", seq.imu, sparse, seq.groundtruth)
    window = (0, 2000)
    with pytest.raises(ValueError) as raised:
        run_window(train, "ins_gnss", NavigationConfig(), window)
    message = str(raised.value)
    assert message.startswith("sparse-fixes drive: training starts the filter at the recording's first IMU sample")
    assert "filter.init.mode=auto: moving" in message and "waited" in message
    assert "filter.init.mode=groundtruth" in message and "start_s, " in message
    result = run_window(train, "ins_gnss", NavigationConfig(start=StartSettings(mode="groundtruth")), window)
    assert torch.isfinite(result.track.node_mean).all()
    # a reference that begins late: the crop is the only advice
    gt = seq.groundtruth
    after = gt.t_s >= 1.0
    late = TrainingSequence("late reference", seq.imu, sparse,
                            PoseStream(gt.t_s[after], gt.pos_m[after], gt.quat_wxyz[after], name=gt.name))
    with pytest.raises(ValueError) as raised:
        run_window(late, "ins_gnss", NavigationConfig(start=StartSettings(mode="groundtruth")), window)
    message = str(raised.value)
    assert "(filter.init.mode=groundtruth: groundtruth) begins at row" in message and "start_s, 1.0" in message
    assert "or start from the reference" not in message
