"""The simulated drive: its IMU, its position and its GNSS against the closed-form trajectory."""
from __future__ import annotations

import math

import pytest
import torch

from flowins.data.simulate.drive import Drive, DriveConfig, drive_sequence, simulate_drive
from flowins.data.synthetic import increment_imu, sample_times
from flowins.geometry import quaternion as quat
from flowins.geometry.geodesy import LocalTangentPlane
from flowins.ins.mechanization import STANDARD_GRAVITY_MPS2 as G
from flowins.filter.propagation import propagate_mean
from flowins.state import make_state, split

F64 = torch.float64


def test_the_position_is_the_integral_of_the_velocity():
    """Central differences of the quadrature position against the closed-form velocity (on a
    road without bumps, whose heights are in closed form: tests/measurements/test_vehicle.py)."""
    drive = Drive(DriveConfig(bump_height_m=0.0))
    t = torch.linspace(0.3, 299.7, 2001, dtype=F64)
    h = 1e-3
    fd = (drive.position(t + h) - drive.position(t - h)) / (2 * h)
    torch.testing.assert_close(fd, drive.velocity(t), atol=1e-6, rtol=0)
    torch.testing.assert_close(drive.position(torch.zeros((), dtype=F64)), torch.zeros(3, dtype=F64))


def test_the_car_drives_from_the_first_sample_at_8_to_15_mps_along_its_x_axis():
    drive = Drive()
    t = torch.linspace(0.0, 300.0, 30001, dtype=F64)
    speed = drive.velocity(t).norm(dim=-1)
    assert 8.0 <= float(speed.min()) and float(speed.max()) <= 15.0 and float(speed[0]) > 8.0
    x_world = drive.rotation(t)[..., :, 0]
    cosine = (x_world * drive.velocity(t)).sum(-1) / speed
    # within 2.5° of the velocity: the car slips, pitches and rides over bumps (their climb turns the velocity most)
    assert 1 - 1e-12 > float(cosine.min()) > math.cos(math.radians(2.5))
    smooth = Drive(DriveConfig(slip_per_lateral_rad=0.0, pitch_per_acceleration_rad=0.0, bump_height_m=0.0))
    cosine = (smooth.rotation(t)[..., :, 0] * smooth.velocity(t)).sum(-1) / smooth.velocity(t).norm(dim=-1)
    assert float(cosine.min()) > 1 - 1e-12  # without them body x is along the velocity


def test_its_exact_imu_integrates_back_to_the_drive():
    """The noise-free delta-velocity/angle IMU, mechanised from the true start, stays on the
    quadrature position within 2 cm over 60 s (only the trapezoidal position step approximates)."""
    drive = Drive()
    t = sample_times(60.0, 100.0, 0.05, torch.Generator().manual_seed(3))
    acc, gyro = increment_imu(drive, t)
    x0 = make_state(p=drive.position(t[:1])[0], v=drive.velocity(t[:1])[0], q=drive.quaternion(t[:1])[0])
    xs = propagate_mean(x0, acc[1:], gyro[1:], torch.diff(t), G, "midpoint")
    err = (split(xs).p - drive.position(t[1:])).norm(dim=-1)
    assert float(err.max()) < 0.02, f"max error {float(err.max()):.3g} m"
    q_err = quat.angle_between(split(xs).q[-1], drive.quaternion(t[-1:])[0])
    assert float(q_err) < 1e-6


def test_the_fixes_have_their_accuracy_and_an_outage_in_the_middle():
    config = DriveConfig(duration_s=200.0, outage_s=60.0, seed=2)
    seq, _ = drive_sequence(config)
    t = seq.gnss.t_s
    assert not bool(((t >= 70.0) & (t < 130.0)).any())
    assert bool((t < 70.0).any()) and bool((t >= 130.0).any())
    enu = LocalTangentPlane(*config.origin).to_enu(seq.gnss.lat_deg, seq.gnss.lon_deg, seq.gnss.alt_m)
    err = enu - Drive(config).position(t)
    assert float(seq.gnss.h_acc_m.min()) == pytest.approx(config.gnss_sigma_m)
    rms = err.pow(2).mean(0).sqrt()
    assert 0.5 * config.gnss_sigma_m < float(rms[:2].mean()) < 1.6 * config.gnss_sigma_m


def test_simulate_drive_writes_a_folder_that_reads_back(tmp_path):
    config = DriveConfig(duration_s=30.0, outage_s=0.0)
    written = simulate_drive(tmp_path / "drive", config)
    again = simulate_drive(tmp_path / "drive", config)  # read back, not simulated again
    assert written.metadata["imu"] == "simulated_drive" and written.camera is None
    torch.testing.assert_close(again.imu.acc_mps2, written.imu.acc_mps2, rtol=0, atol=0)
    assert math.isclose(float(written.groundtruth.t_s[-1]), 29.9, abs_tol=0.11)


def test_the_command_line_writes_the_drive_it_describes(tmp_path, capsys):
    from flowins.data.simulate.__main__ import main

    assert main([str(tmp_path / "d"), "--scenario", "drive", "--duration", "40", "--outage", "10", "--seed", "3"]) == 0
    written = simulate_drive(tmp_path / "d", DriveConfig(duration_s=40.0, outage_s=10.0, seed=3))  # read back
    expected, _ = drive_sequence(DriveConfig(duration_s=40.0, outage_s=10.0, seed=3))
    torch.testing.assert_close(written.imu.gyro_rps, expected.imu.gyro_rps, rtol=0, atol=0)
    assert len(written.gnss) == len(expected.gnss) and "written to" in capsys.readouterr().out
