"""The training loss of a window against a hand-made truth: position, NLL-free, orientation."""
import math
from types import SimpleNamespace

import pytest
import torch

from flowins.data.streams import PoseStream
from flowins.geometry import quaternion as quat
from flowins.state import STATE, STATE_DIM
from flowins.training.unroll import orientation_rmse, window_loss

F64 = torch.float64


def circle(n: int = 200):
    """A 20 s walk on a 10 m circle with the body's x axis along the velocity."""
    t = torch.linspace(0.0, 20.0, n, dtype=F64)
    angle = 0.2 * t
    pos = torch.stack((10 * torch.cos(angle), 10 * torch.sin(angle), 0.1 * torch.sin(t)), -1)
    yaw = angle + math.pi / 2
    q = quat.from_euler(torch.zeros_like(yaw), torch.zeros_like(yaw), yaw)
    return t, pos, q


def track_of(t, pos, q):
    mean = torch.zeros(t.shape[0], STATE_DIM, dtype=F64)
    mean[:, STATE.p], mean[:, STATE.q] = pos, q
    cov = torch.eye(STATE_DIM, dtype=F64).expand(t.shape[0], -1, -1).clone()
    return SimpleNamespace(t=t, mean=mean, cov=cov)


def test_orientation_term_is_the_attitude_error_left_after_the_yaw_alignment():
    """The estimate is the truth in another heading and origin (which the alignment removes)
    with a constant 0.02 rad roll error on top (which it can't)."""
    t, pos, q = circle()
    yaw = quat.from_euler(torch.tensor(0.0, dtype=F64), torch.tensor(0.0, dtype=F64), torch.tensor(0.7, dtype=F64))
    R = quat.to_matrix(yaw)
    roll = quat.from_rotation_vector(torch.tensor([0.02, 0.0, 0.0], dtype=F64))
    q_est = quat.multiply(yaw.expand_as(q), quat.multiply(q, roll.expand_as(q)))
    est = track_of(t, pos @ R.T + torch.tensor([5.0, -3.0, 1.0], dtype=F64), q_est)
    truth = PoseStream(t, pos, q)
    plain = window_loss(est, truth)
    assert float(plain.rmse_m) < 2e-6 and float(plain.orientation_rmse_rad) == 0.0
    loss = window_loss(est, truth, orientation_weight_m_per_rad=10.0)
    assert float(loss.orientation_rmse_rad) == pytest.approx(2 * math.sin(0.01), rel=1e-9)
    assert float(loss.loss) == pytest.approx(float(loss.rmse_m) + 10.0 * 2 * math.sin(0.01), rel=1e-9)


def test_orientation_rmse_is_sign_free_and_has_a_finite_gradient_at_zero():
    _, _, q = circle(20)
    assert float(orientation_rmse(q, -q)) < 1e-7
    q_est = q.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(orientation_rmse(q_est, q), q_est)
    assert torch.isfinite(grad).all()
    angles = torch.linspace(0.0, 0.1, 20, dtype=F64)
    tilted = quat.multiply(q, quat.from_rotation_vector(torch.stack((angles, 0 * angles, 0 * angles), -1)))
    assert float(orientation_rmse(tilted, q)) == pytest.approx(float(angles.square().mean().sqrt()), rel=1e-3)


def test_orientation_term_needs_a_truth_with_orientations():
    t, pos, q = circle()
    with pytest.raises(ValueError, match="orientations"):
        window_loss(track_of(t, pos, q), PoseStream(t, pos, name="positions only"), orientation_weight_m_per_rad=1.0)
