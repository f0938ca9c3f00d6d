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


def _drive(folder, slip, pitch):
    folder.mkdir()
    (folder / "metadata.yaml").write_text(
        f"simulation:\n  scenario: drive\n  config:\n    slip_per_lateral_rad: {slip}\n"
        f"    pitch_per_acceleration_rad: {pitch}\n")
    return folder


def test_the_simulator_law_is_read_from_the_drives_and_drives_that_differ_are_refused(repo_module, tmp_path):
    bench = repo_module("benchmarks/bench_adaptive_drift.py")
    a, b = _drive(tmp_path / "a", 0.005, 0.01), _drive(tmp_path / "b", 0.005, 0.01)
    assert bench.simulator_law([a, b]) == (0.005, 0.01)
    with pytest.raises(ValueError, match="the drives' laws differ"):
        bench.simulator_law([a, _drive(tmp_path / "c", 0.004, 0.01)])
    (tmp_path / "walk").mkdir()
    with pytest.raises(ValueError, match="walk/metadata.yaml: no simulation.config.slip_per_lateral_rad"):
        bench.simulator_law([a, tmp_path / "walk"])


@pytest.mark.parametrize("mount_yaw_rad", [0.0, 0.2])
def test_the_law_checkpoint_sets_the_cars_slip_and_pitch_and_the_factors_given(repo_module, tmp_path, mount_yaw_rad):
    """Readings whose specific force along the car's forward, left and up axes is (a_f, a_l, 1) g
    and steady over the window: the law's network sets a yaw of A tanh(slip g a_l / A) and a
    pitch of -A tanh(pitch g a_f / A) (A the angles' bound, g in m/s²), and the σ factors given
    at every update; a car going straight and steady gets no angle. With the IMU turned from the
    car's axes by the checkpoint's mounting, the same car-frame force gives the same angles."""
    from flowins.constants import STANDARD_GRAVITY_MPS2 as G
    from flowins.measurements.adaptive_noise import steady_window
    from flowins.measurements.vehicle import VehicleSettings
    from flowins.training.parameters import FilterParameters

    bench = repo_module("benchmarks/bench_adaptive_drift.py")
    source = _checkpoint(tmp_path / "a.ckpt", vehicle_mount_yaw_rad=mount_yaw_rad)
    law = bench.law_checkpoint(source, 0.005, 0.01, (0.5, 2.0), tmp_path / "law.ckpt")
    network = FilterParameters.from_checkpoint(law).adaptive["vehicle"]
    car_force = torch.tensor([[0.0, 0.0, 1.0], [0.2, -0.3, 1.0], [-0.4, 0.25, 1.0]], dtype=torch.float64)  # g
    C_cb = VehicleSettings(mount_yaw_rad=mount_yaw_rad).vehicle_from_imu(car_force)
    if mount_yaw_rad == 0.0:
        torch.testing.assert_close(C_cb, torch.eye(3, dtype=torch.float64))
    imu_force = car_force @ C_cb  # each row C_cbᵀ f: the car's force in IMU axes
    gyro = torch.zeros_like(imu_force)
    windows = torch.cat((gyro, imu_force), -1).unsqueeze(-1).expand(-1, -1, 100)
    with torch.no_grad():
        factors, angles = network(windows, steady_window(C_cb[2]))
    torch.testing.assert_close(factors, torch.tensor([[0.5, 2.0]] * 3, dtype=torch.float64), rtol=1e-12, atol=0)
    A = 0.05
    yaw = A * torch.tanh(0.005 * G * car_force[:, 1] / A)
    pitch = -A * torch.tanh(0.01 * G * car_force[:, 0] / A)
    torch.testing.assert_close(angles, torch.stack((pitch, yaw), -1), rtol=1e-12, atol=1e-15)
    assert float(angles[0].abs().max()) < 1e-15
    with pytest.raises(ValueError, match=r"--law-factors: \[20.0\]; expected numbers within"):
        bench.law_checkpoint(source, 0.005, 0.01, (20.0, 1.0), tmp_path / "bad.ckpt")


def test_a_law_checkpoint_needs_a_network_that_sets_angles(repo_module, tmp_path):
    from flowins.navigation import NavigationConfig
    from flowins.training.module import FilterLearner
    from flowins.training.parameters import FilterParameters, starting_values

    bench = repo_module("benchmarks/bench_adaptive_drift.py")
    params = FilterParameters(starting_values(NavigationConfig()), learn=["acc_noise"], adaptive=["vehicle"])
    path = tmp_path / "no_angles.ckpt"
    torch.save({"state_dict": FilterLearner(params, NavigationConfig(), methods=["ins"]).state_dict()}, path)
    with pytest.raises(ValueError, match="no_angles.ckpt: its vehicle network sets no angles"):
        bench.law_checkpoint(path, 0.005, 0.01, (1.0, 1.0), tmp_path / "law.ckpt")
