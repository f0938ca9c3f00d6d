"""Telling a vehicle's fixes from a walker's, on tracks of known speed."""
import pytest
import torch

from flowins.data.streams import GnssStream
from flowins.evaluation.motion import describe_vehicle_like, vehicle_like
from flowins.geometry.geodesy import LocalTangentPlane

F64 = torch.float64


def _fixes(speed_mps: float, duration_s: float, *, noise_m: float = 2.0, every_s: float = 1.0, seed: int = 0,
           turn_rad_s: float = 0.0) -> GnssStream:
    """Fixes of a track at a constant speed (turning at ``turn_rad_s``), with white noise per axis."""
    gen = torch.Generator().manual_seed(seed)
    t = torch.arange(0.0, duration_s + 1e-9, every_s, dtype=F64)
    heading = turn_rad_s * t
    dt = torch.full_like(t, every_s)
    east = torch.cumsum(speed_mps * torch.cos(heading) * dt, 0)
    north = torch.cumsum(speed_mps * torch.sin(heading) * dt, 0)
    enu = torch.stack((east, north, torch.zeros_like(t)), -1) + noise_m * torch.randn(t.shape[0], 3, generator=gen, dtype=F64)
    lat, lon, alt = LocalTangentPlane(49.0, 8.4, 110.0).to_geodetic(enu)
    acc = torch.full_like(t, noise_m)
    return GnssStream(t + 1000.0, lat, lon, alt, acc, acc)


@pytest.mark.parametrize("speed", [8.0, 15.0])
def test_a_car_s_fixes_are_vehicle_like_with_its_speed(speed):
    motion = vehicle_like(_fixes(speed, 120.0, turn_rad_s=0.02))
    assert motion is not None
    assert abs(motion.median_speed_mps - speed) < 0.1 * speed  # a turn shortens the chords a little
    assert motion.duration_s == pytest.approx(120.0)
    assert motion.distance_m > 0.9 * speed * 120.0
    assert "platform: vehicle" in describe_vehicle_like(motion)


@pytest.mark.parametrize("speed, duration", [(1.4, 300.0), (3.5, 300.0), (0.0, 300.0), (10.0, 30.0)])
def test_a_walker_a_runner_a_still_receiver_and_a_short_drive_are_not(speed, duration):
    assert vehicle_like(_fixes(speed, duration, noise_m=3.0, seed=1)) is None


def test_a_fix_s_noise_does_not_make_a_vehicle_of_a_walker_with_sparse_fixes():
    # fixes every 2 s with 5 m of noise: over single intervals a walker would seem to move ~4 m/s
    assert vehicle_like(_fixes(1.4, 600.0, noise_m=5.0, every_s=2.0, seed=2)) is None


def test_fixes_with_tens_of_metres_of_noise_stretch_the_span_so_a_walker_stays_a_walker():
    # 20 m per axis over 5 s would be 8 m/s of apparent speed; their reported accuracy lengthens the stretches
    walker = _fixes(1.4, 300.0, noise_m=20.0, seed=3)
    assert vehicle_like(walker) is None  # over 5 s stretches the noise alone would pass for a vehicle
    car = vehicle_like(_fixes(10.0, 300.0, noise_m=20.0, seed=3))
    assert car is not None and abs(car.median_speed_mps - 10.0) < 1.5


def test_the_hint_goes_only_to_a_recording_that_leaves_the_constraint_to_auto_and_names_no_platform():
    from flowins.evaluation.motion import vehicle_hint
    car = _fixes(10.0, 120.0)
    assert "wheeled vehicle" in vehicle_hint(car, platform_named=False, mode="auto")
    assert vehicle_hint(car, platform_named=True, mode="auto") is None  # platform: vehicle already applies it
    assert vehicle_hint(car, platform_named=False, mode="on") is None
    assert vehicle_hint(car, platform_named=False, mode="off") is None  # the user said no
    assert vehicle_hint(None, platform_named=False, mode="auto") is None
    assert vehicle_hint(_fixes(1.4, 120.0), platform_named=False, mode="auto") is None
