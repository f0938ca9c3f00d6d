"""The evaluation job on a recording read from disk (``sequence.path=DIR``)."""
import json
from pathlib import Path

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


def test_the_default_configuration_composes_and_runs_quick(tmp_path):
    cfg = _compose([f"output_dir={tmp_path}", "quick=true", "plots=false", "progress=false", "combinations=[ins_gnss]"])
    (row,) = run(cfg)
    assert row.name == "ins_gnss" and row.filter_rmse_m is not None and row.filter_rmse_m < 30.0
