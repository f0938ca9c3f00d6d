"""The still prior (still_prior) against simulated still data with a known attitude and gyro bias."""
from __future__ import annotations

import math

import pytest
import torch
from torch.func import jacrev

from flowins.geometry import quaternion as quat
from flowins.ins.initialization import InitialUncertainty, still_prior
from flowins.ins.mechanization import STANDARD_GRAVITY_MPS2
from flowins.state import CORE_DIM, STATE, STATE_DIM, split

F64 = torch.float64
ROLL, PITCH, YAW = math.radians(10.0), math.radians(-20.0), 0.7
GYRO_BIAS = torch.tensor([0.01, -0.02, 0.005], dtype=F64)
ACC_STD, GYRO_STD = 0.01, 1e-3
RATE_HZ = 100.0


def still_imu(n: int = 700, seed: int = 0, roll: float = ROLL, pitch: float = PITCH, acc_std: float = ACC_STD):
    """``n`` samples at 100 Hz of a device held still at (roll, pitch), any yaw, plus white noise."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(n, dtype=F64) / RATE_HZ
    q_true = quat.from_euler(*(torch.tensor(a, dtype=F64) for a in (roll, pitch, -2.0)))  # yaw is not seen
    f_body = quat.to_matrix(q_true).T @ torch.tensor([0.0, 0.0, STANDARD_GRAVITY_MPS2], dtype=F64)
    acc = f_body + acc_std * torch.randn(n, 3, generator=g, dtype=F64)
    gyro = GYRO_BIAS + GYRO_STD * torch.randn(n, 3, generator=g, dtype=F64)
    return t, acc, gyro


def first_seconds(t, acc, gyro, seconds: float = 5.0):
    """The samples of the first ``seconds`` (what a still start of that length hands the prior)."""
    keep = t <= t[0] + seconds
    return acc[keep], gyro[keep]


def test_attitude_and_gyro_bias_are_recovered():
    t, acc, gyro = still_imu()
    # after the 5 s window the device moves: those rows must not be used
    acc[t > 5.0] += torch.tensor([3.0, -2.0, 1.0], dtype=F64)
    gyro[t > 5.0] += 0.5
    p0 = torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    mean, _ = still_prior(*first_seconds(t, acc, gyro), yaw_rad=YAW, position_m=p0)
    assert mean.shape == (STATE_DIM,) and mean.dtype == F64
    s = split(mean)
    roll, pitch, yaw = quat.to_euler(s.q)
    assert abs(float(roll) - ROLL) < 1e-3
    assert abs(float(pitch) - PITCH) < 1e-3
    assert abs(float(yaw) - YAW) < 1e-12
    torch.testing.assert_close(s.q.norm(), torch.tensor(1.0, dtype=F64), rtol=0, atol=1e-14)
    n = int((t <= 5.0).sum())
    assert (s.b_w - GYRO_BIAS).abs().max() < 5.0 * GYRO_STD / math.sqrt(n)
    torch.testing.assert_close(s.p, p0, rtol=0, atol=0)
    torch.testing.assert_close(s.v, torch.zeros(3, dtype=F64), rtol=0, atol=0)
    torch.testing.assert_close(s.b_a, torch.zeros(3, dtype=F64), rtol=0, atol=0)
    torch.testing.assert_close(s.T_a, torch.ones(3, dtype=F64), rtol=0, atol=0)
    torch.testing.assert_close(s.p_prev, s.p, rtol=0, atol=0)
    torch.testing.assert_close(s.q_prev, s.q, rtol=0, atol=0)


@pytest.mark.parametrize("roll_deg, pitch_deg", [(0.0, 0.0), (-35.0, 60.0), (170.0, 5.0)])
def test_noise_free_attitude_is_exact(roll_deg, pitch_deg):
    t, acc, gyro = still_imu(n=50, roll=math.radians(roll_deg), pitch=math.radians(pitch_deg), acc_std=0.0)
    mean, _ = still_prior(*first_seconds(t, acc, gyro), yaw_rad=0.0)
    roll, pitch, _ = quat.to_euler(split(mean).q)
    torch.testing.assert_close(
        torch.stack((roll, pitch)), torch.tensor([math.radians(roll_deg), math.radians(pitch_deg)], dtype=F64),
        rtol=0, atol=1e-12,
    )


def test_covariance_is_spd_with_an_exact_augmented_copy():
    t, acc, gyro = still_imu()
    u = InitialUncertainty()
    mean, cov = still_prior(*first_seconds(t, acc, gyro), yaw_rad=YAW, uncertainty=u)
    assert cov.shape == (STATE_DIM, STATE_DIM)
    torch.testing.assert_close(cov, cov.T, rtol=0, atol=0)
    assert float(torch.linalg.eigvalsh(cov).min()) > 0.0
    torch.linalg.cholesky(cov)  # raises if not positive definite

    core = slice(0, CORE_DIM)
    nugget = u.augmentation_nugget_var * torch.eye(3, dtype=F64)
    # cross-covariances of the copy with the core are those of the original
    torch.testing.assert_close(cov[STATE.p_prev, core], cov[STATE.p, core], rtol=0, atol=1e-18)
    torch.testing.assert_close(cov[STATE.q_prev, core], cov[STATE.q, core], rtol=0, atol=1e-18)
    torch.testing.assert_close(cov[STATE.p_prev, STATE.p_prev], cov[STATE.p, STATE.p] + nugget, rtol=0, atol=1e-18)
    torch.testing.assert_close(
        cov[STATE.q_prev, STATE.q_prev], cov[STATE.q, STATE.q] + u.augmentation_nugget_var * torch.eye(4, dtype=F64),
        rtol=0, atol=1e-18,
    )
    torch.testing.assert_close(cov[STATE.p_prev, STATE.q_prev], cov[STATE.p, STATE.q], rtol=0, atol=1e-18)

    # the stated 1-σ on the plain blocks
    for name, std in (
        ("p", u.position_m), ("v", u.velocity_mps), ("b_a", u.acc_bias_mps2),
        ("b_w", u.gyro_bias_rps), ("T_a", u.acc_scale),
    ):
        sl = getattr(STATE, name)
        torch.testing.assert_close(cov[sl, sl], std**2 * torch.eye(3, dtype=F64), rtol=1e-14, atol=0)


def test_orientation_covariance_is_the_stated_world_frame_rotation_uncertainty():
    """``δ = log(q' ⊙ q*)`` linearised at ``q`` maps the 4x4 block to ``diag(σ_r², σ_p², σ_y²)``."""
    t, acc, gyro = still_imu()
    u = InitialUncertainty()
    mean, cov = still_prior(*first_seconds(t, acc, gyro), yaw_rad=YAW, uncertainty=u)
    q = split(mean).q
    J = jacrev(lambda qq: quat.to_rotation_vector(quat.multiply(qq, quat.conjugate(q))))(q)  # (3, 4)
    expected = torch.diag(torch.tensor([u.roll_pitch_rad, u.roll_pitch_rad, u.yaw_rad], dtype=F64) ** 2)
    torch.testing.assert_close(J @ cov[STATE.q, STATE.q] @ J.T, expected, rtol=1e-10, atol=1e-14)
    # and the length of q carries the radial variance only
    torch.testing.assert_close(q @ cov[STATE.q, STATE.q] @ q, torch.tensor(u.quaternion_radial**2, dtype=F64))
