"""The camera mounting check (flowins.flow.mounting) against closed forms and simulated truth:
a walk's exact landmark tracks seen by a camera mounted as the simulator mounts it."""
from __future__ import annotations

import functools
import math

import pytest
import torch

from flowins.data.load import Recording
from flowins.data.sequence import PinholeCamera, Sequence
from flowins.data.simulate.scenario import CameraConfig
from flowins.data.simulate.tracks import tracks_along
from flowins.data.streams import ImuStream
from flowins.data.synthetic import ImuErrors, Walk, WalkConfig, corrupt_imu, increment_imu
from flowins.flow.load import check_camera_mounting
from flowins.flow.mounting import _fit, camera_rotations, check_mounting, gyro_rotations, pure_turns
from flowins.flow.pairs import FlowPairs, track_pairs
from flowins.flow.points import FlowPoints
from flowins.geometry import quaternion as quat
from flowins.geometry.camera import RigidTransform

F64 = torch.float64


def _turn(axis: int, degrees: float) -> torch.Tensor:
    v = torch.zeros(3, dtype=F64)
    v[axis] = math.radians(degrees)
    return quat.to_matrix(quat.from_rotation_vector(v))


@functools.lru_cache(maxsize=None)
def _walk(seed: int = 0, duration_s: float = 30.0):
    """30 s of the simulated walk (5 s still, then walking with sway), an IMU at 100 Hz with a
    0.08 rad/s gyroscope bias on x, 0.3 px tracks at 10 Hz of the simulator's camera."""
    g = torch.Generator().manual_seed(seed)
    walk = Walk(WalkConfig(duration_s=duration_s))
    t = torch.arange(0, int(duration_s * 100) + 1, dtype=F64) / 100
    acc, gyro, _ = corrupt_imu(t, *increment_imu(walk, t), ImuErrors(), g)
    gyro = gyro + torch.tensor([0.08, 0.0, 0.0], dtype=F64)
    config = CameraConfig()
    pin = config.intrinsics()
    t_cam = torch.arange(0, int(duration_s * 10) + 1, dtype=F64) / 10
    tracks = tracks_along(t_cam, walk.quaternion(t_cam), walk.position(t_cam), config.imu_to_camera(), pin.K,
                          (pin.height, pin.width), count=1500, ahead_m=10.0, radius_m=10.0, height_m=(0.0, 8.0),
                          noise_px=0.3, generator=g)
    return t, acc, gyro, tracks, pin, config.imu_to_camera()


def test_gyro_rotations_of_a_constant_rate_between_any_two_times():
    t = torch.linspace(0.0, 2.0, 201, dtype=F64)
    rate = torch.tensor([0.3, -0.2, 0.5], dtype=F64)
    t1 = torch.tensor([0.013, 0.5, 1.234], dtype=F64)
    t2 = torch.tensor([0.101, 0.55, 1.9], dtype=F64)
    phi = gyro_rotations(t, rate.expand(201, 3), t1, t2)
    torch.testing.assert_close(phi, rate * (t2 - t1).unsqueeze(-1), atol=1e-12, rtol=0)


def test_gyro_rotations_point_from_the_later_body_to_the_earlier():
    """About z at 1 rad/s for 0.5 s: ``R_{b1 b2}`` rotates the later body's x axis by +0.5 rad."""
    t = torch.linspace(0.0, 1.0, 101, dtype=F64)
    gyro = torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand(101, 3)
    phi = gyro_rotations(t, gyro, torch.tensor([0.2], dtype=F64), torch.tensor([0.7], dtype=F64))[0]
    x_in_b1 = quat.to_matrix(quat.from_rotation_vector(phi)) @ torch.tensor([1.0, 0.0, 0.0], dtype=F64)
    torch.testing.assert_close(x_in_b1, torch.tensor([math.cos(0.5), math.sin(0.5), 0.0], dtype=F64))


def test_camera_rotations_of_exact_points_are_the_cameras_turn():
    """Points seen from two camera poses: the rotation vector of ``R_{c1 c2}`` comes back, the
    translation whatever it is (also none: a pure turn)."""
    g = torch.Generator().manual_seed(0)
    K = torch.tensor([[300.0, 0.0, 160.0], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]], dtype=F64)
    X1 = torch.rand(200, 3, generator=g, dtype=F64) * torch.tensor([8.0, 6.0, 20.0], dtype=F64)
    X1 = X1 + torch.tensor([-4.0, -3.0, 4.0], dtype=F64)  # camera-1 coordinates, in front
    phis = torch.tensor([[0.02, -0.01, 0.03], [0.0, 0.05, 0.0], [-0.04, 0.0, 0.01]], dtype=F64)
    shifts = torch.tensor([[0.3, 0.0, 0.1], [0.0, 0.0, 0.0], [0.0, 0.2, -0.4]], dtype=F64)
    points = []
    for phi, shift in zip(phis, shifts):
        R_c1c2 = quat.to_matrix(quat.from_rotation_vector(phi))
        X2 = (X1 - shift) @ R_c1c2  # x_c1 = R_c1c2 x_c2 + shift
        uv1 = X1[:, :2] / X1[:, 2:] * 300.0 + K[:2, 2]
        uv2 = X2[:, :2] / X2[:, 2:] * 300.0 + K[:2, 2]
        points.append(FlowPoints(uv1, uv2 - uv1, torch.full_like(uv1, 0.5)))
    pairs = FlowPairs(torch.tensor([0.0, 1.0, 2.0], dtype=F64), torch.tensor([0.1, 1.1, 2.1], dtype=F64), points, "sparse")
    phi_c, ok = camera_rotations(pairs, K)
    assert bool(ok.all())
    torch.testing.assert_close(phi_c, phis, atol=1e-5, rtol=0)  # OpenCV solves in float64 to ~1e-6


def test_a_noisy_pure_turn_is_the_cameras_turn_and_parallax_is_not_taken_for_one():
    """A turn alone with 0.3 px noise (an essential matrix is degenerate there) comes back
    within the noise; a 0.2 m step sideways at 4-24 m leaves parallax well above the noise,
    so the turn-only fit is refused for it (the essential matrix decides)."""
    g = torch.Generator().manual_seed(1)
    X1 = torch.rand(300, 3, generator=g, dtype=F64) * torch.tensor([8.0, 6.0, 20.0], dtype=F64)
    X1 = X1 + torch.tensor([-4.0, -3.0, 4.0], dtype=F64)
    phi = torch.tensor([0.01, -0.03, 0.02], dtype=F64)
    R_c1c2 = quat.to_matrix(quat.from_rotation_vector(phi))
    x1 = X1[:, :2] / X1[:, 2:]
    for shift, turn_alone in ((0.0, True), (0.2, False)):
        X2 = (X1 - torch.tensor([shift, 0.0, 0.0], dtype=F64)) @ R_c1c2
        x2 = X2[:, :2] / X2[:, 2:] + 0.3 / 300.0 * torch.randn(300, 2, generator=g, dtype=F64)
        pad = torch.full((50, 2), float("nan"), dtype=F64)  # a shorter pair's padding is no point
        R, median_px = pure_turns(torch.cat((x1, pad))[None], torch.cat((x2, pad))[None], 300.0)
        assert (float(median_px[0]) <= 0.5) == turn_alone, (shift, median_px)
        if turn_alone:
            angle = quat.angle_between(quat.from_matrix(R[0]), quat.from_matrix(R_c1c2))
            assert float(angle) < 1e-3  # 0.3 px at f = 300 px is 1e-3 rad per point, 300 points


def test_the_true_mounting_passes_despite_a_constant_gyro_bias():
    t, _, gyro, tracks, pin, truth = _walk()
    result = check_mounting(t, gyro, track_pairs(tracks, sigma_px=0.3), pin.K, truth.rotation_wxyz)
    assert not result.warn and result.reason == "", result.describe()
    assert result.pairs >= 250
    assert math.degrees(result.angle_rad) < 1.0


@pytest.mark.parametrize("wrong", ["identity", "x", "y", "z"])
def test_a_wrong_mounting_is_named_with_the_true_one_suggested(wrong):
    """Identity where the truth is a quarter turn, or 90° off about the camera's x, y or z."""
    t, _, gyro, tracks, pin, truth = _walk()
    R_true = quat.to_matrix(truth.rotation_wxyz)
    configured = torch.eye(3, dtype=F64) if wrong == "identity" else _turn("xyz".index(wrong), 90.0) @ R_true
    result = check_mounting(t, gyro, track_pairs(tracks, sigma_px=0.3), pin.K, quat.from_matrix(configured))
    assert result.warn, result.describe()
    off = math.degrees(float(quat.angle_between(torch.tensor(result.suggested_wxyz, dtype=F64), truth.rotation_wxyz)))
    assert off < 1.0
    assert "imu_to_camera" in result.describe()
    assert result.configured_error_rps > 5 * result.suggested_error_rps


def test_an_axis_never_turned_about_is_left_to_the_calibration():
    """Rates about one axis only (a car on a flat road, with a gyroscope bias) say nothing of a
    twist of the camera about that axis: the fit keeps the configured twist and finds the axis."""
    g = torch.Generator().manual_seed(0)
    R_true = _turn(0, -90.0) @ _turn(2, -90.0)
    omega_b = torch.zeros(200, 3, dtype=F64)
    omega_b[:, 2] = 0.6 * torch.sin(0.07 * torch.arange(200, dtype=F64))
    omega_c = (omega_b - torch.tensor([0.0, 0.05, 0.0], dtype=F64)) @ R_true.T
    omega_c = omega_c + 1e-4 * torch.randn(omega_c.shape, generator=g, dtype=F64)
    axis_cam = R_true[:, 2]
    twisted = quat.to_matrix(quat.from_rotation_vector(math.radians(40.0) * axis_cam)) @ R_true
    tilted = _turn(0, 10.0) @ R_true  # about an axis the data see
    for configured, expected in ((twisted, twisted), (tilted, R_true)):
        R, *_ = _fit(omega_b, omega_c, configured, 1.0 / math.radians(20.0) ** 2, 6)
        off = math.degrees(float(quat.angle_between(quat.from_matrix(R), quat.from_matrix(expected))))
        assert off < 0.5, off


def test_a_camera_that_hardly_turns_gets_no_verdict():
    t, _, _, tracks, pin, truth = _walk()
    still = torch.zeros(t.shape[0], 3, dtype=F64)
    result = check_mounting(t, still, track_pairs(tracks, sigma_px=0.3), pin.K, torch.tensor([1.0, 0, 0, 0], dtype=F64))
    assert not result.warn and "hardly turns" in result.reason


def test_the_job_warns_once_naming_the_key_and_keeps_the_line():
    t, acc, gyro, tracks, pin, truth = _walk()
    camera = PinholeCamera(pin.width, pin.height, pin.fx, pin.fy, pin.cx, pin.cy)
    wrong = RigidTransform(quat.from_matrix(_turn(1, 90.0) @ quat.to_matrix(truth.rotation_wxyz)), truth.translation_m)
    for transform, warned in ((truth, False), (wrong, True)):
        rec = Recording(Sequence(ImuStream(t, acc, gyro), name="walk", camera=camera, imu_to_camera=transform,
                                 tracks=tracks))
        result = check_camera_mounting(rec, {"sparse": tracks, "dense": "no frames"})
        assert result is not None and result.warn is warned
        assert len(rec.warnings) == int(warned)
        if warned:
            assert "imu_to_camera" in rec.warnings[0] and "sequence.check_mounting=false" in rec.warnings[0]
    assert check_camera_mounting(rec, {"sparse": "no tracks"}) is None


@pytest.mark.parametrize("mirror", ["swap x y", "negate z"])
def test_mirrored_gyroscope_axes_are_named(mirror):
    t, _, gyro, tracks, pin, truth = _walk()
    mirrored = gyro[:, [1, 0, 2]] if mirror == "swap x y" else gyro * torch.tensor([1.0, 1.0, -1.0], dtype=F64)
    pairs = track_pairs(tracks, sigma_px=0.3)
    result = check_mounting(t, mirrored, pairs, pin.K, truth.rotation_wxyz)
    assert result.mirrored and result.warn
    assert "mirrored" in result.describe()
    assert result.mirrored_error_rps < result.suggested_error_rps
    clean = check_mounting(t, gyro, pairs, pin.K, truth.rotation_wxyz)
    assert not clean.mirrored and clean.mirrored_error_rps > clean.suggested_error_rps
