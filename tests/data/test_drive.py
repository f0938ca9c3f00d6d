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


def test_the_slopes_scale_the_roads_grade_and_zero_gives_a_flat_road(tmp_path, capsys):
    """The velocity's climb angle against the closed form ``scale · Σ a sin(2π t / T + φ)``; at
    scale 0 the ground truth stays at its start height and the car's x axis is level where it does
    not accelerate (no pitch law, no bumps); the command line's ``--slopes`` sets it and names a
    bad value."""
    from flowins.data.simulate.__main__ import main
    from flowins.data.simulate.drive import _GRADE

    t = torch.linspace(0.0, 300.0, 3001, dtype=F64)
    grade = sum(a * torch.sin(2 * math.pi * t / T + p) for a, T, p in _GRADE)
    for scale in (0.0, 1.0, 2.5):
        v = Drive(DriveConfig(grade_scale=scale, bump_height_m=0.0)).velocity(t)
        climb = torch.atan2(v[..., 2], v[..., :2].norm(dim=-1))
        torch.testing.assert_close(climb, scale * grade, atol=1e-12, rtol=0)
    flat = Drive(DriveConfig(grade_scale=0.0, bump_height_m=0.0, pitch_per_acceleration_rad=0.0))
    assert float(flat.position(t)[..., 2].abs().max()) < 1e-9
    assert float(flat.rotation(t)[..., 2, 0].abs().max()) < 1e-12  # body x has no up component
    assert main([str(tmp_path / "d"), "--scenario", "drive", "--duration", "40", "--outage", "10", "--slopes", "0",
                 "--bumps", "0"]) == 0
    written = simulate_drive(tmp_path / "d", DriveConfig(duration_s=40.0, outage_s=10.0, grade_scale=0.0,
                                                         bump_height_m=0.0))  # read back: the same simulation
    heights = written.groundtruth.pos_m[:, 2]
    assert float((heights - heights[0]).abs().max()) < 1e-6
    capsys.readouterr()
    assert main([str(tmp_path / "e"), "--scenario", "drive", "--duration", "40", "--outage", "10", "--slopes", "-1"]) == 2
    assert "DriveConfig.grade_scale=-1.0; expected a factor in [0, 10]" in capsys.readouterr().err
