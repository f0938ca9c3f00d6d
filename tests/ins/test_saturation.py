"""Saturation finding against recordings clipped on purpose: the clipping is the truth."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from flowins.data.simulate.drive import DriveConfig, drive_sequence
from flowins.data.synthetic import synthetic_walk_recording
from flowins.ins.saturation import Saturation, find_saturation

F64 = torch.float64


@pytest.fixture(scope="module")
def walk():
    return synthetic_walk_recording(duration_s=60, seed=0).imu


@pytest.fixture(scope="module")
def drive():
    return drive_sequence(DriveConfig(duration_s=60.0, seed=1, outage_s=20.0))[0].imu


def naive_longest_run(flags) -> int:
    """Reference: a plain loop over the samples."""
    best = current = 0
    for flag in flags:
        current = current + 1 if flag else 0
        best = max(best, current)
    return best


def expected(sensor, axis, value, t_s, clean, clipped) -> Saturation:
    """The finding clipping at ``value`` makes, from the readings it changed (plus any that
    already sat at the value) and a plain loop for the run."""
    k = "xyz".index(axis)
    at = (clean[:, k] >= value) if value > 0 else (clean[:, k] <= value)
    rows = np.flatnonzero(at.numpy())
    assert torch.equal(at, clipped[:, k] == value)  # the clip made exactly these readings the value
    return Saturation(sensor=sensor, axis=axis, value=value, count=len(rows),
                      longest_run=naive_longest_run(at.tolist()), first_row=int(rows[0]),
                      first_t_s=float(t_s[rows[0]]), last_t_s=float(t_s[rows[-1]]), readings=len(t_s))


def test_a_walk_clipped_at_12_mps2_names_the_z_axis_from_its_first_clipped_row(walk):
    clipped = walk.acc_mps2.clamp(-12.0, 12.0)
    changed = clipped != walk.acc_mps2
    assert int(changed[:, :2].sum()) == 0 and int(changed[:, 2].sum()) > 100  # only z+ reaches 12 m/s²
    found = find_saturation(walk.t_s, clipped, walk.gyro_rps)
    assert found == [expected("accelerometer", "z", 12.0, walk.t_s, walk.acc_mps2, clipped)]
    assert found[0].count == int(changed.sum())
    assert found[0].first_row == int(changed[:, 2].nonzero()[0, 0])
    assert find_saturation(walk.t_s, walk.acc_mps2, walk.gyro_rps) == []


def test_findings_come_in_a_fixed_order_and_numpy_input_gives_the_same(walk):
    acc, gyro = walk.acc_mps2.clamp(-12.0, 12.0), walk.gyro_rps.clamp(-0.2, 0.2)
    found = find_saturation(walk.t_s, acc, gyro)
    assert [(f.sensor, f.axis, f.value) for f in found] == [
        ("accelerometer", "z", 12.0), ("gyroscope", "x", 0.2), ("gyroscope", "x", -0.2),
        ("gyroscope", "y", 0.2), ("gyroscope", "y", -0.2)]
    assert found[3] == expected("gyroscope", "y", 0.2, walk.t_s, walk.gyro_rps, gyro)
    assert find_saturation(walk.t_s.numpy(), acc.numpy().astype(np.float32).astype(np.float64), gyro.numpy()) == found


def test_a_drive_with_its_yaw_rate_clipped_names_the_gyroscope_z_on_the_sides_clipped(drive):
    clipped = drive.gyro_rps.clone()
    clipped[:, 2] = clipped[:, 2].clamp(-0.05, 0.05)
    sides = [v for v, hit in ((0.05, bool((drive.gyro_rps[:, 2] > 0.05).any())),
                              (-0.05, bool((drive.gyro_rps[:, 2] < -0.05).any()))) if hit]
    assert sides == [0.05, -0.05]  # this drive turns both ways beyond 0.05 rad/s
    found = find_saturation(drive.t_s, drive.acc_mps2, clipped)
    assert found == [expected("gyroscope", "z", v, drive.t_s, drive.gyro_rps, clipped) for v in sides]
    assert find_saturation(drive.t_s, drive.acc_mps2, drive.gyro_rps) == []


def still_quantised(seed: int = 0):
    """30 s at 200 Hz of a still IMU: gravity plus white noise (0.006 m/s², 2.5 LSB) on a
    0.0024 m/s² LSB, and gyroscope noise (0.00015 rad/s, 0.75 LSB) through the sensor's
    8-sample low-pass filter (so its extremes last several samples) on a 0.0002 rad/s LSB."""
    gen = torch.Generator().manual_seed(seed)
    n, smooth = 6000, 8
    t = torch.arange(n, dtype=F64) / 200.0
    acc = torch.tensor([0.0, 0.0, 9.80665], dtype=F64) + 0.006 * torch.randn(n, 3, generator=gen, dtype=F64)
    white = torch.randn(n + smooth - 1, 3, generator=gen, dtype=F64)
    total = torch.cat((torch.zeros(1, 3, dtype=F64), white.cumsum(0)))
    gyro = 0.00015 * (total[smooth:] - total[:-smooth]) / smooth**0.5
    return t, torch.round(acc / 0.0024) * 0.0024, torch.round(gyro / 0.0002) * 0.0002


def test_a_still_quantised_imu_is_not_saturated_although_its_extremes_repeat_in_runs():
    t, acc, gyro = still_quantised()
    repeating = 0  # extremes that pass criteria (a) and (b): only the pile-up test (c) can reject them
    for x in torch.cat((acc, gyro), 1).T:
        for side in (x, -x):
            at = side == side.max()
            repeating += int(at.sum()) >= 3 and naive_longest_run(at.tolist()) >= 2
    assert repeating >= 3
    assert find_saturation(t, acc, gyro) == []


def test_the_same_still_imu_clipped_is_found():
    t, acc, gyro = still_quantised()
    levels = torch.unique(acc[:, 2])
    limit = float(levels[(levels - (acc[:, 2].median() + 0.002)).abs().argmin()])  # the level nearest +σ/3
    clipped = acc.clamp(-limit, limit)
    assert find_saturation(t, clipped, gyro) == [expected("accelerometer", "z", limit, t, acc, clipped)]


def test_a_constant_axis_is_not_saturation_and_does_not_hide_a_clip(walk):
    gyro = walk.gyro_rps.clone()
    gyro[:, 2] = 0.0  # a gyroscope axis that reads exactly 0: dead, not clipped
    acc = walk.acc_mps2.clamp(-12.0, 12.0)
    assert [(f.sensor, f.axis) for f in find_saturation(walk.t_s, acc, gyro)] == [("accelerometer", "z")]
    n = walk.t_s.shape[0]
    still = torch.tensor([0.0, 0.0, 9.81], dtype=F64).expand(n, 3)
    assert find_saturation(walk.t_s, still, torch.zeros(n, 3, dtype=F64)) == []


def test_one_spike_or_too_few_readings_at_the_extreme_are_not_saturation():
    t = torch.arange(1000, dtype=F64) / 100.0
    wave = torch.stack((torch.sin(t), torch.cos(t), torch.sin(2 * t)), -1)
    spikes = wave.clone()
    spikes[[100, 300, 500], 0] = 2.0  # three isolated readings at one value: (b) fails (and (a), at 5 by default)
    assert find_saturation(t, spikes, wave) == []
    assert [(f.axis, f.value, f.longest_run) for f in find_saturation(t, spikes, wave, min_run=1, min_count=3)] == [("x", 2.0, 1)]
    plateau = wave.clone()
    plateau[[100, 101], 1] = 2.0  # a run of two: (b) holds, (a) does not
    assert find_saturation(t, plateau, wave) == []
    assert [(f.axis, f.count) for f in find_saturation(t, plateau, wave, min_count=2)] == [("y", 2)]


def test_short_input_gives_no_finding_and_bad_input_names_the_array_and_row():
    for n in (0, 1, 2):
        assert find_saturation(torch.zeros(n, dtype=F64).cumsum(0), torch.full((n, 3), 5.0), torch.zeros(n, 3)) == []
    t = torch.arange(10, dtype=F64)
    with pytest.raises(ValueError, match=r"acc_mps2 has shape \(10, 2\)"):
        find_saturation(t, torch.zeros(10, 2), torch.zeros(10, 3))
    with pytest.raises(ValueError, match=r"gyro_rps has shape \(9, 3\).*N = 10"):
        find_saturation(t, torch.zeros(10, 3), torch.zeros(9, 3))
    gyro = torch.zeros(10, 3)
    gyro[7, 1] = float("nan")
    with pytest.raises(ValueError, match="gyro_rps row 7 is not finite"):
        find_saturation(t, torch.zeros(10, 3), gyro)
    with pytest.raises(ValueError, match="min_run"):
        find_saturation(t, torch.zeros(10, 3), torch.zeros(10, 3), min_run=0)


def test_describe_says_what_sticks_where_in_one_line():
    found = Saturation(sensor="accelerometer", axis="z", value=12.0, count=2071, longest_run=45, first_row=642,
                       first_t_s=3.21, last_t_s=280.4, readings=11317)
    assert found.describe() == ("accelerometer z sticks at +12 m/s² in 2071 readings (18.3 %), longest run 45, "
                                "from t = 3.21 s to 280.4 s")
    gyro = Saturation("gyroscope", "x", -0.05, 3, 2, 0, 0.0, 1.5, 300)
    assert gyro.describe() == "gyroscope x sticks at -0.05 rad/s in 3 readings (1.0 %), longest run 2, from t = 0 s to 1.5 s"


def test_the_job_refuses_a_saturated_recording_naming_axis_and_key():
    """resolve_imu: a clipped walk stops with the stream, the axis and the key to run anyway."""
    from flowins.data.streams import ImuStream
    from flowins.data.synthetic import synthetic_walk_recording
    from flowins.sensor import resolve_imu

    imu = synthetic_walk_recording(duration_s=60.0, seed=0).imu
    clipped = ImuStream(imu.t_s, imu.acc_mps2.clamp(-12.0, 12.0), imu.gyro_rps, name="walk/imu.csv")

    class Rec:
        sensor = None

        def __init__(self, stream):
            self.imu = stream

    preset = {"name": "phone", "acc_noise": 1e-3, "gyro_noise": 1e-4}
    with pytest.raises(ValueError, match=r"walk/imu\.csv: the IMU saturates: accelerometer z .*imu\.check_saturation=false"):
        resolve_imu(preset, [Rec(clipped)], recorded=True)
    assert resolve_imu(preset | {"check_saturation": False}, [Rec(clipped)], recorded=True).name == "phone"
    assert resolve_imu(preset, [Rec(ImuStream(imu.t_s, imu.acc_mps2, imu.gyro_rps, name="walk/imu.csv"))],
                       recorded=True).name == "phone"
