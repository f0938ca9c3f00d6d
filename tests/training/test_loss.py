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


def drifting_arc(v: float, drift: float, duration_s: float):
    """``(t, truth, arc, est_p, est_q)``: a truth walking straight along x at ``v`` (10 Hz) and
    an estimate whose heading drifts at ``drift`` rad/s, so it walks ``arc`` (radius v/δ), seen
    in another frame (turned by 0.3 rad and moved by (2, 1, 0) m)."""
    t = torch.linspace(0.0, duration_s, int(round(10 * duration_s)) + 1, dtype=F64)
    zero = torch.zeros_like(t)
    truth = PoseStream(t, torch.stack((v * t, zero, zero), -1), quat.from_euler(zero, zero, zero))
    arc = torch.stack((v / drift * torch.sin(drift * t), v / drift * (1 - torch.cos(drift * t)), zero), -1)
    turn = quat.to_matrix(quat.from_euler(*(torch.tensor(a, dtype=F64) for a in (0.0, 0.0, 0.3))))
    return t, truth, arc, arc @ turn.T + torch.tensor([2.0, 1.0, 0.0], dtype=F64), quat.from_euler(zero, zero,
                                                                                                     drift * t + 0.3)


def test_segment_loss_of_a_heading_drift_is_the_arc_against_the_chord():
    """The truth walks straight along x at v; the estimate's heading drifts at δ, so it walks
    an arc of radius v/δ. In its own heading frame each segment of L seconds is displaced by
    (v/δ)(sin δL, 1 - cos δL) against (vL, 0): the loss is the mean over the durations of that
    error's length, plus the weight times δL for the heading change; no alignment enters."""
    v, drift = 1.4, 0.01
    t, truth, arc, est_p, est_q = drifting_arc(v, drift, 20.0)
    est = track_of(t, est_p, est_q)
    lengths = torch.tensor([5.0, 10.0], dtype=F64)
    expected = torch.sqrt((v / drift * torch.sin(drift * lengths) - v * lengths) ** 2
                          + (v / drift * (1 - torch.cos(drift * lengths))) ** 2).mean()
    loss = window_loss(est, truth, loss="segments", segment_s=(5.0, 10.0, 60.0), orientation_weight_m_per_rad=2.0)
    assert float(loss.segment_rmse_m) == pytest.approx(float(expected), rel=1e-6)
    assert float(loss.orientation_rmse_rad) == pytest.approx(drift * 7.5, rel=1e-6)
    assert float(loss.loss) == pytest.approx(float(expected) + 2.0 * drift * 7.5, rel=1e-6)
    # a window shorter than every duration is one segment: the whole window
    short = window_loss(est, truth, loss="segments", segment_s=(60.0,))
    whole = torch.tensor(20.0, dtype=F64)
    assert float(short.segment_rmse_m) == pytest.approx(float(torch.sqrt(
        (v / drift * torch.sin(drift * whole) - v * whole) ** 2 + (v / drift * (1 - torch.cos(drift * whole))) ** 2)),
        rel=1e-6)
    with pytest.raises(ValueError, match="model.loss='foo'"):
        window_loss(est, truth, loss="foo")


def test_start_loss_aligns_once_at_the_start_so_a_heading_drift_costs_in_full():
    """The arc of a drifting heading against the straight truth, the estimate in another frame
    (turned by 0.3 rad and moved): aligned once by the first pose, the error at t is the arc's
    distance from the line, |(v/δ)(sin δt, 1 - cos δt) - (vt, 0)|, for the first window and,
    with that alignment passed on, for a later one. Each window's own yaw alignment hides most of it."""
    v, drift = 1.4, 0.01
    t, truth, arc, est_p, est_q = drifting_arc(v, drift, 40.0)
    gap = (arc - truth.pos_m).norm(dim=-1)
    first, later = slice(0, 201), slice(200, 401)
    one = window_loss(track_of(t[first], est_p[first], est_q[first]), truth, loss="start")
    assert float(one.rmse_m) == pytest.approx(float(gap[first].square().mean().sqrt()), rel=1e-6)
    two = window_loss(track_of(t[later], est_p[later], est_q[later]), truth, loss="start", alignment=one.alignment)
    assert float(two.rmse_m) == pytest.approx(float(gap[later].square().mean().sqrt()), rel=1e-6)
    own = window_loss(track_of(t[later], est_p[later], est_q[later]), truth)
    assert float(own.rmse_m) < 0.2 * float(two.rmse_m)
