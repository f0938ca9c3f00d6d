"""GNSS position model h(x) = p + C(q) ℓ against finite differences and closed forms (float64)."""
from __future__ import annotations

import math

import pytest
import torch

from flowins.geometry import quaternion as quat
from flowins.measurements.gnss import gnss_jacobian, gnss_noise, gnss_position
from flowins.state import STATE, STATE_DIM, make_state

F64 = torch.float64
LEVER_ARM_M = torch.tensor([0.12, -0.05, 0.30], dtype=F64)


def random_states(*batch: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)

    def randn(*shape):
        return torch.randn(*batch, *shape, generator=g, dtype=F64)

    return make_state(
        p=10.0 * randn(3),
        v=randn(3),
        q=1.2 * randn(4),  # not unit: h must use the rotation of q/|q|
        b_a=0.1 * randn(3),
        b_w=0.01 * randn(3),
        T_a=1.0 + 0.01 * randn(3),
        p_prev=randn(3),
        q_prev=randn(4),
    )


def central_differences(f, x: torch.Tensor, h: float = 1e-6) -> torch.Tensor:
    cols = []
    for i in range(x.shape[-1]):
        e = torch.zeros_like(x)
        e[i] = h
        cols.append((f(x + e) - f(x - e)) / (2.0 * h))
    return torch.stack(cols, dim=-1)


def test_position_is_antenna_position_for_a_known_rotation():
    """Yaw 90°: the body x axis points north, so a forward lever arm moves the antenna north."""
    q = quat.from_euler(*(torch.tensor(a, dtype=F64) for a in (0.0, 0.0, math.pi / 2)))
    p = torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    x = make_state(p=p, v=torch.zeros(3, dtype=F64), q=q)
    h = gnss_position(x, torch.tensor([0.5, 0.0, 0.2], dtype=F64))
    torch.testing.assert_close(h, torch.tensor([1.0, 2.5, 3.2], dtype=F64), rtol=0, atol=1e-15)


def test_jacobian_matches_finite_differences_with_lever_arm():
    x = random_states(seed=1)
    J = gnss_jacobian(x, LEVER_ARM_M)
    assert J.shape == (3, STATE_DIM)
    fd = central_differences(lambda xx: gnss_position(xx, LEVER_ARM_M), x)
    torch.testing.assert_close(J, fd, rtol=0, atol=1e-8)
    # only p and q enter
    others = torch.ones(STATE_DIM, dtype=torch.bool)
    others[STATE.p] = False
    others[STATE.q] = False
    assert (J[:, others] == 0).all()
    assert J[:, STATE.q].abs().max() > 1e-2


def test_jacobian_with_zero_lever_arm_is_exactly_the_position_selector():
    x = random_states(seed=2)
    J = gnss_jacobian(x, torch.zeros(3, dtype=F64))
    expected = torch.zeros(3, STATE_DIM, dtype=F64)
    expected[:, STATE.p] = torch.eye(3, dtype=F64)
    torch.testing.assert_close(J, expected, rtol=0, atol=0)
    torch.testing.assert_close(gnss_position(x, torch.zeros(3, dtype=F64)), x[STATE.p], rtol=0, atol=0)


@pytest.mark.parametrize("batch", [(1,), (3, 2)])
def test_batched_shapes_agree_with_single_states(batch):
    x = random_states(*batch, seed=3)
    h = gnss_position(x, LEVER_ARM_M)
    J = gnss_jacobian(x, LEVER_ARM_M)
    assert h.shape == (*batch, 3)
    assert J.shape == (*batch, 3, STATE_DIM)
    flat_x, flat_h, flat_J = x.reshape(-1, STATE_DIM), h.reshape(-1, 3), J.reshape(-1, 3, STATE_DIM)
    for i in range(flat_x.shape[0]):
        torch.testing.assert_close(flat_h[i], gnss_position(flat_x[i], LEVER_ARM_M), rtol=0, atol=1e-15)
        fd = central_differences(lambda xx: gnss_position(xx, LEVER_ARM_M), flat_x[i])
        torch.testing.assert_close(flat_J[i], fd, rtol=0, atol=1e-8)


def test_noise_is_diagonal_with_scaled_accuracies():
    h_acc = torch.tensor([3.0, 10.0], dtype=F64)
    v_acc = torch.tensor([4.5, 15.0], dtype=F64)
    R = gnss_noise(h_acc, v_acc)
    assert R.shape == (2, 3, 3)
    torch.testing.assert_close(R[0], torch.diag(torch.tensor([9.0, 9.0, 20.25], dtype=F64)), rtol=0, atol=0)
    torch.testing.assert_close(R[1], torch.diag(torch.tensor([100.0, 100.0, 225.0], dtype=F64)), rtol=0, atol=0)
    R2 = gnss_noise(h_acc, v_acc, scale=2.0)
    torch.testing.assert_close(R2, 4.0 * R, rtol=1e-15, atol=0)
    R0 = gnss_noise(torch.tensor(3.0, dtype=F64), torch.tensor(4.0, dtype=F64))
    torch.testing.assert_close(R0, torch.diag(torch.tensor([9.0, 9.0, 16.0], dtype=F64)), rtol=0, atol=0)
