"""The evaluation job on a recording read from disk (``sequence.path=DIR``)."""
import json
import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from flowins.data.folder import write_folder
from flowins.data.sequence import Sequence
from flowins.data.synthetic import synthetic_walk_recording
from flowins.evaluation import trajectory_errors
from flowins.jobs.evaluate import run

CONFIGS = str(Path(__file__).resolve().parents[2] / "configs")


def _compose(overrides):
    with initialize_config_dir(config_dir=CONFIGS, version_base=None):
        return compose("evaluate", overrides=overrides)


def test_a_recording_without_gnss_reports_the_gnss_rows_as_not_applicable(tmp_path):
    rec = synthetic_walk_recording(duration_s=20.0, seed=2)
    folder = write_folder(Sequence(rec.imu, name="walk", groundtruth=rec.truth), tmp_path / "walk")
    out = tmp_path / "out"
    cfg = _compose([f"sequence.path={folder}", f"output_dir={out}", "plots=false", "progress=false",
                    "combinations=[ins,ins_gnss,ins_dense]"])
    rows = {r.name: r for r in run(cfg)}
    assert rows["ins_gnss"].filter_rmse_m is None and "no GNSS" in rows["ins_gnss"].note
    assert rows["ins_dense"].filter_rmse_m is None
    ins = rows["ins"]
    assert ins.filter_rmse_m is not None and 0.0 < ins.filter_rmse_m < 1e4
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["ins_gnss"]["status"] == "not applicable"
    # the job's RMSE is the one an independent evaluation of the written TUM track gives
    tum = torch.tensor([[float(v) for v in line.split()] for line in (out / "ins_filter.tum").read_text().splitlines()
                        if line and not line.startswith("#")], dtype=torch.float64)
    err = trajectory_errors(tum[:, 0], tum[:, 1:4], rec.truth.t_s, rec.truth.pos_m, align="se3")
    assert abs(err.rmse_m - ins.filter_rmse_m) < 1e-6 * max(1.0, ins.filter_rmse_m)


@pytest.mark.slow
def test_the_default_configuration_composes_and_runs_quick(tmp_path):
    cfg = _compose([f"output_dir={tmp_path}", "quick=true", "plots=false", "progress=false", "combinations=[ins_gnss]"])
    (row,) = run(cfg)
    assert row.name == "ins_gnss" and row.filter_rmse_m is not None and row.filter_rmse_m < 30.0
    # the GNSS floor is recorded, and the ins_gnss filter (its motion not known exactly) is not below it
    floor = json.loads((tmp_path / "metrics.json").read_text())["gnss_floor"]
    assert 0.0 < floor["rmse_m"] <= row.filter_rmse_m and floor["fixes_used"] <= floor["fixes"]


@pytest.fixture(scope="module")
def small_walk(tmp_path_factory):
    """A 60 s simulated walk at 320 x 240 (camera, GNSS, ground truth), written once."""
    from flowins.data.simulate import SimulationConfig, simulate

    folder = tmp_path_factory.mktemp("walk")
    config = SimulationConfig(duration_s=60.0, seed=0, flow_every=0)
    simulate(folder, config, progress=False)
    return folder


@pytest.mark.slow
def test_every_combination_runs_on_a_simulated_walk_and_flow_bounds_the_drift(small_walk, tmp_path):
    out = tmp_path / "out"
    cfg = _compose([f"sequence.path={small_walk}", f"output_dir={out}", f"cache_dir={tmp_path / 'cache'}",
                    "flow=dis", "flow_pairs.input_scale=1.0", "flow_panels=1", "progress=false"])
    rows = {r.name: r for r in run(cfg)}
    assert list(rows) == ["ins", "ins_gnss", "ins_sparse", "ins_dense", "ins_gnss_sparse", "ins_gnss_dense"]
    for row in rows.values():
        assert row.filter_rmse_m is not None and math.isfinite(row.filter_rmse_m) and math.isfinite(row.smoother_rmse_m)
    # the inertial drift is real, and flow (dense or sparse) bounds it
    assert rows["ins"].filter_rmse_m > 10.0
    assert rows["ins_dense"].filter_rmse_m < rows["ins"].filter_rmse_m / 10
    assert rows["ins_sparse"].filter_rmse_m < rows["ins"].filter_rmse_m / 10
    metrics = json.loads((out / "metrics.json").read_text())
    dense = metrics["ins_dense"]
    assert dense["flow_frames"] == dense["flow_pairs"] == 600 and dense["mean_points"] == 256
    assert 0 < dense["mean_accepted"] <= dense["mean_valid"] <= dense["mean_points"]
    assert (out / "ins_gnss_dense.png").is_file() and len(list(out.glob("flow_panel_*.png"))) == 1
    # the flow pairs were cached: a second run reads them back and gives the same track
    cfg2 = _compose([f"sequence.path={small_walk}", f"output_dir={tmp_path / 'again'}", f"cache_dir={tmp_path / 'cache'}",
                     "flow=dis", "flow_pairs.input_scale=1.0", "plots=false", "progress=false",
                     "combinations=[ins_dense]"])
    (again,) = run(cfg2)
    # (alone, not batched with the other flow rows: equal up to rounding)
    assert again.filter_rmse_m == pytest.approx(rows["ins_dense"].filter_rmse_m, abs=1e-8)
    assert len(list((tmp_path / "cache" / "flow").glob("dense-*.npz"))) == 1


@pytest.mark.slow
def test_sparse_rows_on_whole_tracks_run_cache_their_tracks_and_bound_the_drift(small_walk, tmp_path):
    """``filter.tracks.window=5``: Lucas-Kanade with ids kept over the frames, the multi-view update."""
    from flowins.flow.load import read_tracks

    out, cache = tmp_path / "out", tmp_path / "cache"
    cfg = _compose([f"sequence.path={small_walk}", f"output_dir={out}", f"cache_dir={cache}", "plots=false",
                    "progress=false", "combinations=[ins_sparse]", "filter.tracks.window=5"])
    (row,) = run(cfg)
    assert row.filter_rmse_m is not None and row.filter_rmse_m < 10.0  # INS alone: > 10 m (the test above)
    m = json.loads((out / "metrics.json").read_text())["ins_sparse"]
    assert m["track_frames"] > 500 and 0 < m["mean_accepted"] <= m["mean_valid"] <= m["mean_tracks"] <= 128
    (path,) = (cache / "flow").glob("tracks-*.npz")
    tracks = read_tracks(path)
    # ids kept across frames: tracks seen in many frames, at most one row per id and frame
    _, counts = torch.unique(tracks.track_id, return_counts=True)
    assert float(counts.double().mean()) > 3.0 and int(counts.max()) <= 601


def test_a_float32_filter_is_refused_with_the_reason():
    """float32 filtering gave a 3.6e6 m smoother (ins_gnss) and NaN (ins_dense) on the 60 s
    walk: the config says so instead of producing them."""
    from omegaconf import OmegaConf

    from flowins.ins.imu_model import imu_model
    from flowins.settings import navigation_config

    with initialize_config_dir(config_dir=CONFIGS, version_base=None):
        cfg = OmegaConf.to_container(compose("evaluate", overrides=["filter.dtype=float32"]), resolve=False)
    with pytest.raises(ValueError, match="filter.dtype.*float32 is not precise enough"):
        navigation_config(cfg["filter"], imu_model(cfg["imu"], recording=False))
    with initialize_config_dir(config_dir=CONFIGS, version_base=None):
        cfg = OmegaConf.to_container(compose("evaluate"), resolve=False)
    assert navigation_config(cfg["filter"], imu_model(cfg["imu"], recording=False)).dtype == torch.float64


def test_a_car_recording_that_starts_moving_runs_with_no_overrides_and_says_why_ins_alone_drifts(tmp_path):
    """The drive: moving from the first sample; the INS row starts as the GNSS row does (from
    the first fixes, used for nothing else) and its kilometres come with the filter's own σ."""
    from flowins.data.simulate.drive import Drive, DriveConfig, simulate_drive

    config = DriveConfig(duration_s=90.0, outage_s=0.0)
    folder = tmp_path / "drive"
    simulate_drive(folder, config)
    out = tmp_path / "out"
    cfg = _compose([f"sequence.path={folder}", f"output_dir={out}", "plots=false", "progress=false"])
    rows = {r.name: r for r in run(cfg)}
    metrics = json.loads((out / "metrics.json").read_text())
    for name in ("ins", "ins_gnss"):
        assert metrics[name]["start"]["mode"] == "moving"
    assert "for the start only" in metrics["ins"]["start"]["source"]
    assert rows["ins_gnss"].filter_rmse_m < 3.0
    assert rows["ins_sparse"].filter_rmse_m is None and "no camera" in rows["ins_sparse"].note
    drift = [w for w in metrics["ins"]["warnings"] if "inertial drift" in w]
    assert drift and not [w for w in metrics["ins_gnss"]["warnings"] if "inertial drift" in w]
    # the σ the warning quotes is the filter's: the INS row's error is of that order, not hidden in it
    sigma_m = float(drift[0].split("σ reaches ")[1].split(" m")[0])
    assert 100.0 < sigma_m and rows["ins"].filter_rmse_m < 3 * sigma_m
    assert Drive(config).velocity(torch.zeros(1, dtype=torch.float64)).norm() > 8.0


def test_a_ground_truth_that_does_not_move_is_named_and_the_tracks_are_still_written(tmp_path, capsys):
    from flowins.data.streams import PoseStream

    rec = synthetic_walk_recording(duration_s=20.0, seed=2)
    still = PoseStream(rec.truth.t_s, 1e-3 * torch.randn(len(rec.truth.t_s), 3, dtype=torch.float64),
                       name="groundtruth")
    folder = write_folder(Sequence(rec.imu, name="walk", groundtruth=still), tmp_path / "walk")
    out = tmp_path / "out"
    (row,) = run(_compose([f"sequence.path={folder}", f"output_dir={out}", "progress=false", "combinations=[ins]"]))
    assert row.filter_rmse_m is None and "does not move" in row.note
    assert "groundtruth.csv: the ground truth stays within" in capsys.readouterr().out
    assert (out / "ins_filter.tum").is_file() and (out / "ins_smoother.tum").is_file()
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["ins"]["filter_rmse_m"] is None and any("does not move" in w or "stays within" in w
                                                            for w in metrics["ins"]["warnings"])


def test_a_fix_before_the_imu_is_an_error_and_crop_runs_and_records_the_crop(tmp_path):
    from flowins.data.streams import GnssStream

    rec = synthetic_walk_recording(duration_s=20.0, seed=2)
    g = rec.gnss
    early = GnssStream(torch.cat([g.t_s[:1] * 0 + float(rec.imu.t_s[0]) - 0.006, g.t_s]),
                       *(torch.cat([getattr(g, k)[:1], getattr(g, k)]) for k in
                         ("lat_deg", "lon_deg", "alt_m", "h_acc_m", "v_acc_m")), name="gnss")
    folder = write_folder(Sequence(rec.imu, name="walk", gnss=early, groundtruth=rec.truth), tmp_path / "walk")
    base = [f"sequence.path={folder}", "plots=false", "progress=false", "combinations=[ins_gnss]"]
    with pytest.raises(ValueError, match=r"gnss\.csv: row 0 \(0-based\) at t = .* is outside the IMU's time span"):
        run(_compose([*base, f"output_dir={tmp_path / 'a'}"]))
    (row,) = run(_compose([*base, f"output_dir={tmp_path / 'b'}", "sequence.crop=true"]))
    assert row.filter_rmse_m is not None
    metrics = json.loads((tmp_path / "b" / "metrics.json").read_text())
    (note,) = metrics["input_warnings"]
    assert "gnss.csv: cropped 1 rows before and 0 after the IMU span" in note
    assert metrics["ins_gnss"]["gnss_fixes"] == len(g)  # the cropped fix is not among them


def test_a_bad_filter_value_stops_the_job_before_the_recording_is_read(tmp_path):
    cfg = _compose([f"sequence.path={tmp_path / 'not_read'}", f"output_dir={tmp_path / 'out'}", "filter.acc_noise=abc"])
    with pytest.raises(ValueError, match=r"^filter\.acc_noise='abc': expected a number"):
        run(cfg)  # the missing folder would be the error if the recording were read first


@pytest.mark.slow
def test_seeds_run_as_one_batch_and_report_the_mean_and_std_of_the_single_runs(tmp_path, monkeypatch):
    """``sequence.seeds=[a,b]``: each seed's metrics are its single run's (to rounding), the
    table's the mean ± sample std over them."""
    import statistics

    monkeypatch.setenv("FLOWINS_CACHE", str(tmp_path / "cache"))
    common = ["quick=true", "sequence.quick_duration_s=20", "plots=false", "progress=false",
              "combinations=[ins,ins_gnss]"]
    rows = {r.name: r for r in run(_compose(common + ["sequence.seeds=[5,6]", f"output_dir={tmp_path / 'both'}"]))}
    metrics = json.loads((tmp_path / "both" / "metrics.json").read_text())
    for name in ("ins", "ins_gnss"):
        alone = []
        for seed in (5, 6):
            (row,) = [r for r in run(_compose(common + [f"sequence.seed={seed}", f"output_dir={tmp_path / str(seed)}"]))
                      if r.name == name]
            batched = metrics[name]["per_seed"][str(seed)]
            for kind in ("filter", "smoother"):
                single = getattr(row, f"{kind}_rmse_m")
                assert abs(batched[f"{kind}_rmse_m"] - single) <= 1e-8 * max(1.0, single)
            assert (tmp_path / "both" / f"seed_{seed}" / f"{name}_filter.tum").is_file()
            alone.append(row)
        r = rows[name]
        for kind in ("filter", "smoother"):
            values = [getattr(a, f"{kind}_rmse_m") for a in alone]
            assert abs(getattr(r, f"{kind}_rmse_m") - statistics.mean(values)) <= 1e-8 * max(values)
            assert abs(getattr(r, f"{kind}_std_m") - statistics.stdev(values)) <= 1e-8 * max(values)


@pytest.mark.parametrize(("seeds", "message"), [("[]", "expected a list of integers"), ("[1,1]", "appears twice"),
                                                ("[a]", r"sequence.seeds\[0\]")])
def test_bad_seeds_are_refused_naming_the_key(tmp_path, seeds, message):
    cfg = _compose([f"output_dir={tmp_path}", "quick=true", "progress=false", f"sequence.seeds={seeds}"])
    with pytest.raises(ValueError, match=message):
        run(cfg)


@pytest.mark.slow
def test_the_job_scores_plots_and_writes_a_filter_run_on_another_device(tmp_path, monkeypatch, fake_device):
    """``filter.device`` other than the CPU: the job's scoring, TUM export, plots, warnings and
    metrics read the tracks where they are (the fake device of ``conftest.FakeDevice``), with
    no op meeting a CPU tensor there, and report what the CPU run reports."""
    import dataclasses

    import flowins.settings

    rec = synthetic_walk_recording(duration_s=20.0, seed=2)
    folder = write_folder(Sequence(rec.imu, gnss=rec.gnss, name="walk", groundtruth=rec.truth), tmp_path / "walk")
    build = flowins.settings.navigation_config
    metrics = {}
    for device in ("cpu", "meta"):
        monkeypatch.setattr(flowins.settings, "navigation_config",
                            lambda *a, _device=device, **k: dataclasses.replace(build(*a, **k), device=_device))
        out = tmp_path / device
        with fake_device() as mode:
            run(_compose([f"sequence.path={folder}", f"output_dir={out}", "progress=false", "combinations=[ins,ins_gnss]",
                          f"plots={str(device == 'meta').lower()}"]))  # the plots of the tracks on the device
        assert mode.slips == {}, mode.slips
        assert (out / "ins_gnss.png").is_file() == (device == "meta")
        metrics[device] = json.loads((out / "metrics.json").read_text())
        for name in ("ins", "ins_gnss"):
            metrics[device][name].pop("seconds")
    assert metrics["meta"]["ins_gnss"] == metrics["cpu"]["ins_gnss"] and metrics["meta"]["ins"] == metrics["cpu"]["ins"]
    assert (tmp_path / "meta" / "ins_gnss_filter.tum").read_text() == (tmp_path / "cpu" / "ins_gnss_filter.tum").read_text()


def test_the_drift_block_prints_each_rows_filter_and_smoother_drift_mean_over_seeds(caplog):
    """Two seeds of one row average; a row without a ground truth's orientation has no line;
    a length the path never reached reads n/a."""
    import logging

    from flowins.jobs.evaluate import _report_drift

    def run(rpe_f, rpe_s, kitti, scale=(1.0, -0.5)):
        drift = lambda rpe, pct: {"rpe_delta_s": 10.0, "rpe_translation_rmse_m": rpe,  # noqa: E731
                                  "kitti_translation_pct": kitti, "scale_pct": pct}
        return {"filter_drift": drift(rpe_f, scale[0]), "smoother_drift": drift(rpe_s, scale[1])}

    per_run = {"ins_dense": [run(2.0, 1.0, 1.5), run(4.0, 3.0, 2.5, (2.0, -1.5))], "ins_gnss": [run(5.0, 1.0, None)],
               "ins": [{"filter_rmse_m": 3.0}]}
    with caplog.at_level(logging.INFO, logger="flowins"):
        _report_drift(per_run)
    text = caplog.text
    assert "RPE over 10 s" in text
    assert "ins_dense" in text and "3.00 / 2.00 m" in text and "2.00 / 2.00 %" in text
    assert "scale" in text and "+1.50 / -1.00 %" in text and "+1.00 / -0.50 %" in text
    assert "5.00 / 1.00 m" in text and "n/a" in text
    assert "  ins " not in text
