"""``benchmarks/bench_adaptive_drift.py``: its inputs checked, and the constant runs given the checkpoints' walks."""
import sys

import pytest
import torch


def test_the_drift_bench_names_a_missing_checkpoint_and_recording(repo_module, tmp_path, monkeypatch, capsys):
    bench = repo_module("benchmarks/bench_adaptive_drift.py")
    monkeypatch.setattr(sys, "argv", ["bench_adaptive_drift.py", "--checkpoint", str(tmp_path / "none.ckpt"),
                                      str(tmp_path), "imu=simulated_drive"])
    with pytest.raises(SystemExit):
        bench.main()
    assert "none.ckpt: no such checkpoint" in capsys.readouterr().err
    ckpt = tmp_path / "a.ckpt"
    ckpt.write_bytes(b"")
    monkeypatch.setattr(sys, "argv", ["bench_adaptive_drift.py", "--checkpoint", str(ckpt), str(tmp_path / "gone"),
                                      "imu=simulated_drive"])
    with pytest.raises(SystemExit):
        bench.main()
    assert "gone: no such recording folder" in capsys.readouterr().err


def _checkpoint(path, **start):
    from flowins.navigation import NavigationConfig
    from flowins.training.module import FilterLearner
    from flowins.training.parameters import FilterParameters, starting_values

    values = {**starting_values(NavigationConfig()), **start}
    params = FilterParameters(values, learn=["acc_noise"], adaptive=["vehicle"], adaptive_angles_rad=0.05)
    torch.save({"state_dict": FilterLearner(params, NavigationConfig(), methods=["ins"]).state_dict()}, path)
    return path


def test_the_constant_runs_take_the_checkpoints_walks_and_checkpoints_that_differ_are_refused(repo_module, tmp_path):
    bench = repo_module("benchmarks/bench_adaptive_drift.py")
    a = _checkpoint(tmp_path / "a.ckpt", acc_bias_walk=2e-4, gyro_bias_walk=3e-6, acc_scale_walk=4e-5)
    b = _checkpoint(tmp_path / "b.ckpt", acc_bias_walk=2e-4, gyro_bias_walk=3e-6, acc_scale_walk=4e-5)
    overrides = bench.checkpoint_walks([a, b])
    assert [o.split("=")[0] for o in overrides] == ["imu.acc_bias_walk", "imu.gyro_bias_walk", "filter.acc_scale_walk"]
    assert [float(o.split("=")[1]) for o in overrides] == pytest.approx([2e-4, 3e-6, 4e-5], rel=1e-12)
    c = _checkpoint(tmp_path / "c.ckpt", acc_bias_walk=1e-4, gyro_bias_walk=3e-6, acc_scale_walk=4e-5)
    with pytest.raises(ValueError, match="c.ckpt: bias walks other than"):
        bench.checkpoint_walks([a, c])
