"""Still-interval detection, the moving start's pieces and ``filter.init=auto`` against
simulated IMU data whose attitude, motion and still time are known exactly."""
from __future__ import annotations

import math

import pytest
import torch

from flowins.data.streams import ImuStream
from flowins.geometry import quaternion as quat
from flowins.ins.initialization import (
    StillSettings,
    forward_axis,
    kinematic_fit,
    still_interval,
    two_vector_attitude,
)
from flowins.ins.mechanization import STANDARD_GRAVITY_MPS2 as G
from flowins.start import StartSettings, choose_start
from flowins.state import split

F64 = torch.float64
RATE = 200.0
ROLL, PITCH = math.radians(4.0), math.radians(-7.0)


def still_then_moving(still_s: float = 4.0, total_s: float = 8.0, *, vibration: float = 0.0, seed: int = 0,
                      blip: tuple[float, float] | None = None):
    """Device at (ROLL, PITCH) still for ``still_s``, then accelerating forward (a smooth
    1 m/s² ramp); rotor-like vibration of ``vibration`` m/s² at 60, 97 and 141 Hz (and
    0.04 rad/s on the gyro); ``blip``: a 10° roll out and back inside ``(t0, t1)``."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(int(total_s * RATE), dtype=F64) / RATE
    roll = torch.full_like(t, ROLL)
    roll_rate = torch.zeros_like(t)
    if blip is not None:
        t0, t1 = blip
        inside = (t >= t0) & (t <= t1)
        phase = (t - t0) / (t1 - t0)
        roll = torch.where(inside, roll + math.radians(10) * torch.sin(math.pi * phase) ** 2, roll)
        roll_rate = torch.where(inside, math.radians(10) * math.pi / (t1 - t0) * torch.sin(2 * math.pi * phase),
                                roll_rate)
    q = quat.from_euler(roll, torch.full_like(t, PITCH), torch.zeros_like(t))
    ramp = ((t - still_s) / 1.0).clamp(0, 1)
    a_world = torch.stack((ramp * ramp * (3 - 2 * ramp), torch.zeros_like(t), torch.zeros_like(t)), -1)
    f_world = a_world + torch.tensor([0.0, 0.0, G], dtype=F64)
    acc = (quat.to_matrix(q).transpose(-1, -2) @ f_world.unsqueeze(-1)).squeeze(-1)
    gyro = torch.stack((roll_rate, torch.zeros_like(t), torch.zeros_like(t)), -1) + torch.tensor([0.01, -0.02, 0.005])
    acc = acc + 0.01 * torch.randn(acc.shape, generator=g, dtype=F64)
    gyro = gyro + 1e-3 * torch.randn(gyro.shape, generator=g, dtype=F64)
    if vibration:
        shake = sum(torch.sin(2 * math.pi * f * t + p) for f, p in ((60.0, 0.3), (97.0, 1.1), (141.0, 2.0))) / 3 ** 0.5
        acc = acc + vibration * math.sqrt(2) * torch.stack((shake, shake.roll(7), shake.roll(13)), -1)
        gyro = gyro + 0.04 * math.sqrt(2) * torch.stack((shake.roll(3), shake.roll(5), shake.roll(11)), -1)
    return t, acc, gyro


def test_still_interval_ends_where_the_motion_starts_and_vibration_does_not_end_it():
    t, acc, gyro = still_then_moving(vibration=0.5)
    # a raw standard-deviation test (0.3 m/s²) would refuse this start; the low-passed one does not
    assert float(acc[: int(4 * RATE)].std(dim=0).max()) > 0.3
    still = still_interval(t, acc, gyro)
    # the ramp moves the device by 0.3 mm/s in its first 0.1 s: a ZUPT there is still right
    assert 3.6 <= still.end_s <= 4.1, still
    assert "specific force" in still.reason and "filter.init.still.max_acc_mps2" in still.reason
    start = choose_start(ImuStream(t, acc, gyro))
    assert start.mode == "still" and start.zupt_times_s[-1] <= 4.1
    roll, pitch, _ = quat.to_euler(split(start.mean).q)
    assert abs(float(roll) - ROLL) < math.radians(0.2) and abs(float(pitch) - PITCH) < math.radians(0.2)
    torch.testing.assert_close(split(start.mean).b_w, torch.tensor([0.01, -0.02, 0.005], dtype=F64), atol=2e-3, rtol=0)


def test_a_motion_inside_the_window_ends_the_still_interval_before_it():
    t, acc, gyro = still_then_moving(still_s=6.0, blip=(2.0, 2.6))
    still = still_interval(t, acc, gyro)
    assert 1.5 <= still.end_s <= 2.0, still
    start = choose_start(ImuStream(t, acc, gyro))
    roll, _, _ = quat.to_euler(split(start.mean).q)
    assert abs(float(roll) - ROLL) < math.radians(0.2)  # the 10° blip is not averaged in


def test_auto_without_a_still_start_or_fixes_names_the_three_modes():
    t, acc, gyro = still_then_moving(still_s=0.2)
    with pytest.raises(ValueError) as info:
        choose_start(ImuStream(t, acc, gyro))
    message = str(info.value)
    for mode in ("filter.init.mode=still", "filter.init.mode=moving", "filter.init.mode=groundtruth"):
        assert mode in message
    with pytest.raises(ValueError, match="filter.init.still.min_s"):
        choose_start(ImuStream(t, acc, gyro), settings=StartSettings(mode="still"))


def test_kinematic_fit_recovers_an_exact_quadratic():
    t = torch.arange(0.0, 10.0, 1.0, dtype=F64) + 0.3
    p0, v0, a = torch.tensor([1.0, -2.0, 0.5]), torch.tensor([9.0, 3.0, 0.1]), torch.tensor([-0.7, 0.4, 0.0])
    tau = (t - 0.3).unsqueeze(-1)
    z = (p0 + v0 * tau + 0.5 * a * tau**2).to(F64)
    fit = kinematic_fit(t, z, torch.full_like(z, 1e-3), t0_s=0.3, acceleration_sigma_mps2=1e3)
    torch.testing.assert_close(fit.position_m, p0.to(F64), atol=1e-6, rtol=0)
    torch.testing.assert_close(fit.velocity_mps, v0.to(F64), atol=1e-6, rtol=0)
    torch.testing.assert_close(fit.acceleration_mps2, a.to(F64), atol=1e-6, rtol=0)
    # the closed-form variance of a straight-line fit's slope with 2 fixes: 2 sigma^2 / dt^2
    two = kinematic_fit(t[:2], z[:2], torch.full_like(z[:2], 2.0), t0_s=float(t[0]), acceleration_sigma_mps2=1e-9)
    torch.testing.assert_close(two.velocity_var, torch.full((3,), 8.0, dtype=F64), rtol=1e-6, atol=0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_two_vector_attitude_recovers_a_random_rotation(seed):
    g = torch.Generator().manual_seed(seed)
    q_true = quat.normalize(torch.randn(4, generator=g, dtype=F64))
    R = quat.to_matrix(q_true)
    f_world = torch.tensor([0.3, -0.2, G], dtype=F64)
    d_world = torch.tensor([math.cos(1.0), math.sin(1.0), 0.0], dtype=F64)
    q = two_vector_attitude(R.T @ f_world, f_world, R.T @ d_world, d_world)
    assert float(quat.angle_between(q, q_true)) < 1e-9


def test_two_vector_attitude_refuses_a_vertical_forward_axis():
    with pytest.raises(ValueError, match="vertical"):
        two_vector_attitude(torch.tensor([0.0, 0.0, G], dtype=F64), torch.tensor([0.0, 0.0, G], dtype=F64),
                            torch.tensor([0.0, 0.01, 1.0], dtype=F64), torch.tensor([1.0, 0.0, 0.0], dtype=F64))


def test_forward_axis_names_and_camera():
    torch.testing.assert_close(forward_axis("-y"), torch.tensor([0.0, -1.0, 0.0], dtype=F64))
    R_ci = quat.to_matrix(quat.from_euler(*(torch.tensor(a, dtype=F64) for a in (-math.pi / 2, 0.0, -math.pi / 2))))
    axis = forward_axis("auto", R_ci)
    torch.testing.assert_close(R_ci @ axis, torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    with pytest.raises(ValueError, match="forward_axis"):
        forward_axis("w")


def test_a_car_moving_from_the_first_sample_starts_moving_with_its_heading_and_tilt():
    """A car at 10 m/s heading 30° braking at 0.8 m/s², pitched 3°: the mean specific force
    alone would put 4.7° into the pitch; the fixes' acceleration takes it out."""
    heading, pitch = math.radians(30.0), math.radians(3.0)
    q_true = quat.from_euler(torch.tensor(0.0, dtype=F64), torch.tensor(pitch, dtype=F64), torch.tensor(heading, dtype=F64))
    d = torch.tensor([math.cos(heading), math.sin(heading), 0.0], dtype=F64)
    a_world, v0 = -0.8 * d, 10.0 * d
    t = torch.arange(0, 20 * 100, dtype=F64) / 100
    f_body = quat.to_matrix(q_true).T @ (a_world + torch.tensor([0.0, 0.0, G], dtype=F64))
    imu = ImuStream(t, f_body.expand(len(t), 3), torch.zeros(len(t), 3, dtype=F64))
    fix_t = torch.arange(0.5, 20.0, 1.0, dtype=F64)
    enu = v0 * fix_t.unsqueeze(-1) + 0.5 * a_world * fix_t.unsqueeze(-1) ** 2
    start = choose_start(imu, fixes=(fix_t, enu, torch.full_like(enu, 0.05)))
    assert start.mode == "moving" and "not still" in start.reason
    s = split(start.mean)
    assert float(quat.angle_between(s.q, q_true)) < math.radians(0.3)
    torch.testing.assert_close(s.v, v0, atol=0.05, rtol=0)
    assert abs(start.facts["speed_mps"] - 10.0) < 0.05


def test_gnss_fixes_that_move_overrule_an_imu_that_looks_still():
    """Constant velocity on a straight road looks still to an IMU; the fixes say it is not."""
    t = torch.arange(0, 1000, dtype=F64) / 100
    acc = torch.tensor([0.0, 0.0, G], dtype=F64).expand(1000, 3)
    imu = ImuStream(t, acc, torch.zeros(1000, 3, dtype=F64))
    fix_t = torch.arange(0.0, 10.0, 1.0, dtype=F64)
    enu = torch.stack((9.0 * fix_t, torch.zeros_like(fix_t), torch.zeros_like(fix_t)), -1)
    start = choose_start(imu, fixes=(fix_t, enu, torch.full_like(enu, 1.0)))
    assert start.mode == "moving" and "fixes in it move at 9.0 m/s" in start.reason
    assert abs(math.degrees(float(quat.to_euler(split(start.mean).q)[2]))) < 1.0


def test_still_settings_name_the_bad_key():
    with pytest.raises(ValueError, match=r"StillSettings\.lowpass_hz=0\.0: expected a number > 0"):
        StillSettings(lowpass_hz=0.0)
    with pytest.raises(ValueError, match=r"StillSettings\.zupt_hz=nan: expected a finite number"):
        StillSettings(zupt_hz=float("nan"))
