"""The unobservable directions and the heading transport (flowins.filter.unobservable) against
finite differences of the moves they stand for and against the mechanisation's own Jacobian."""
from __future__ import annotations

import math

import pytest
import torch

from flowins.filter.propagation import propagate_batched
from flowins.filter.unobservable import (blind_to_heading, heading_transport_step, heading_weights, transport_heading,
                                         unobservable_directions)
from flowins.geometry import quaternion as quat
from flowins.ins.mechanization import STANDARD_GRAVITY_MPS2, ProcessNoise
from flowins.state import STATE, pose_slices, state_dim

F64 = torch.float64


def _state(clones: int, batch: tuple[int, ...], generator: torch.Generator) -> torch.Tensor:
    x = torch.randn(*batch, state_dim(clones), generator=generator, dtype=F64)
    for _, q in pose_slices(x.shape[-1]):
        x[..., q] = torch.nn.functional.normalize(x[..., q], dim=-1)
    return x


def _moved(x: torch.Tensor, shift: torch.Tensor, yaw: float) -> torch.Tensor:
    """The whole track turned by ``yaw`` about the world's vertical, then shifted (naively, pose by pose)."""
    c, s = math.cos(yaw), math.sin(yaw)
    Rz = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    qz = torch.tensor([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)], dtype=F64)
    out = x.clone()
    for p, q in pose_slices(x.shape[-1]):
        out[..., p] = x[..., p] @ Rz.T + shift
        out[..., q] = quat.multiply(qz.expand_as(x[..., q]), x[..., q])
    out[..., STATE.v] = x[..., STATE.v] @ Rz.T
    return out


@pytest.mark.parametrize("batch", [(), (1,), (3, 2)])
@pytest.mark.parametrize("clones", [1, 3])
def test_directions_are_the_derivatives_of_a_shift_and_a_turn(batch, clones):
    g = torch.Generator().manual_seed(clones + len(batch))
    x = _state(clones, batch, g)
    N = unobservable_directions(x)
    assert N.shape == (*batch, x.shape[-1], 4)
    h = 1e-6
    zero = torch.zeros(3, dtype=F64)
    for i in range(3):
        e = torch.zeros(3, dtype=F64)
        e[i] = h
        numeric = (_moved(x, e, 0.0) - _moved(x, -e, 0.0)) / (2 * h)
        torch.testing.assert_close(N[..., i], numeric, atol=1e-8, rtol=0)
    numeric = (_moved(x, zero, h) - _moved(x, zero, -h)) / (2 * h)
    torch.testing.assert_close(N[..., 3], numeric, atol=1e-8, rtol=0)
    # the body-frame entries (biases, scale) do not move
    assert float(N[..., STATE.b_a.start:STATE.T_a.stop, :].abs().max()) == 0.0


def test_the_propagation_maps_the_directions_onto_those_of_the_propagated_state():
    """The mechanisation is invariant under the shift and the turn, so its Jacobian at x maps
    N(x) onto N(f(x)): the property the heading transport relies on."""
    g = torch.Generator().manual_seed(4)
    x0 = _state(3, (), g)
    x0[STATE.b_a.start:STATE.T_a.stop] = 0.01 * x0[STATE.b_a.start:STATE.T_a.stop]
    x0[STATE.T_a] = 1.0
    D = x0.shape[-1]
    K = 20
    acc = 0.5 * torch.randn(K, 3, generator=g, dtype=F64) + torch.tensor([0.0, 0.0, STANDARD_GRAVITY_MPS2], dtype=F64)
    gyro = 0.3 * torch.randn(K, 3, generator=g, dtype=F64)
    dt = torch.full((K,), 0.01, dtype=F64)
    out = propagate_batched(x0, torch.eye(D, dtype=F64), acc, gyro, dt, torch.tensor([K - 1]),
                            noise=ProcessNoise(), gravity_mps2=STANDARD_GRAVITY_MPS2)
    Phi, x1 = out.transition[-1], out.mean[-1]
    torch.testing.assert_close(Phi @ unobservable_directions(x0), unobservable_directions(x1), atol=1e-9, rtol=0)


def _psd(D: int, g: torch.Generator) -> torch.Tensor:
    A = torch.randn(D, D, generator=g, dtype=F64)
    return A @ A.T / D + 0.05 * torch.eye(D, dtype=F64)


def _information(cov: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    N = unobservable_directions(x)
    return N.transpose(-1, -2) @ torch.linalg.solve(cov, N)


@pytest.mark.parametrize("clones", [1, 4])
def test_transport_keeps_the_information_along_the_directions_and_moves_nothing_else(clones):
    g = torch.Generator().manual_seed(10 + clones)
    before = _state(clones, (2,), g)
    after = before + 0.05 * torch.randn(before.shape, generator=g, dtype=F64)
    P = torch.stack([_psd(before.shape[-1], g) for _ in range(2)])
    moved = transport_heading(P, before, after)
    torch.testing.assert_close(_information(moved, after), _information(P, before), atol=1e-9, rtol=1e-9)
    # the plain covariance holds other information at the new estimate: the test can tell
    assert float((_information(P, after) - _information(P, before)).abs().max()) > 1e-3
    # a congruence: symmetric, positive definite, and the identity where the estimate stays
    torch.testing.assert_close(moved, moved.transpose(-1, -2), atol=0, rtol=0)
    assert float(torch.linalg.eigvalsh(moved).min()) > 0.0
    torch.testing.assert_close(transport_heading(P, before, before), P, atol=1e-15, rtol=0)
    # entries off the positions, velocity and quaternions keep their variances and covariances
    body = torch.arange(STATE.b_a.start, STATE.T_a.stop)
    torch.testing.assert_close(moved[:, body][:, :, body], P[:, body][:, :, body], atol=1e-15, rtol=0)


def test_transport_is_differentiable_and_keeps_a_singular_covariance_positive_semidefinite():
    g = torch.Generator().manual_seed(3)
    before = _state(2, (), g)
    after = before + 0.1 * torch.randn(before.shape, generator=g, dtype=F64)
    A = torch.randn(before.shape[-1], 5, generator=g, dtype=F64)
    P = A @ A.T  # rank 5
    moved = transport_heading(P, before, after)
    assert float(torch.linalg.eigvalsh(moved).min()) > -1e-12
    assert torch.autograd.gradcheck(lambda c, a: transport_heading(c, before, a),
                                     (P.clone().requires_grad_(), after.clone().requires_grad_()))


def test_heading_weights_pick_the_turn_and_ignore_a_translation():
    """``wᵀ N_ψ = 1`` and ``wᵀ`` of each translation 0, with clones in the state; ``w`` lives on
    the current quaternion alone."""
    for clones in (1, 3):
        x = _state(clones, (), torch.Generator().manual_seed(4))
        N = unobservable_directions(x)
        w = heading_weights(x)
        torch.testing.assert_close(w @ N, torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=F64), atol=1e-12, rtol=0)
        off_q = torch.ones(x.shape[-1], dtype=torch.bool)
        off_q[STATE.q] = False
        assert torch.all(w[off_q] == 0)


def test_blind_to_heading_sees_no_turn_and_changes_only_the_quaternion_columns():
    """``H' N_ψ(x) = 0``; ``H'`` differs from ``H`` in the current quaternion's columns only, and
    agrees with it on every direction ``w`` does not see (``wᵀ d = 0``); blind twice is blind
    once. Batched ``(3, 2)`` Jacobians of 5 rows each."""
    gen = torch.Generator().manual_seed(5)
    x = _state(1, (3, 2), gen)
    H = torch.randn(3, 2, 5, x.shape[-1], generator=gen, dtype=F64)
    blind = blind_to_heading(H, x)
    N = unobservable_directions(x)
    assert float((blind @ N[..., 3:]).abs().max()) < 1e-12
    assert float((H @ N[..., 3:]).abs().min()) > 1e-6  # a Jacobian that did see it
    off_q = torch.ones(x.shape[-1], dtype=torch.bool)
    off_q[STATE.q] = False
    assert torch.equal(blind[..., off_q], H[..., off_q])
    d = torch.randn(3, 2, x.shape[-1], 1, generator=gen, dtype=F64)
    w = heading_weights(x).unsqueeze(-1)
    d = d - w * (w.transpose(-1, -2) @ d) / (w.transpose(-1, -2) @ w)  # wᵀ d = 0
    torch.testing.assert_close(blind @ d, H @ d, atol=1e-12, rtol=0)
    torch.testing.assert_close(blind_to_heading(blind, x), blind, atol=1e-12, rtol=0)


def test_the_transport_as_a_step_keeps_the_estimate_and_gives_the_transported_covariance():
    """``T after + b = after`` and ``T P Tᵀ`` is :func:`transport_heading`'s covariance."""
    gen = torch.Generator().manual_seed(6)
    before = _state(2, (3,), gen)
    after = before + 0.05 * torch.randn(before.shape, generator=gen, dtype=F64)
    cov = torch.stack([_psd(before.shape[-1], gen) for _ in range(3)])
    T, b = heading_transport_step(before, after)
    torch.testing.assert_close((T @ after.unsqueeze(-1)).squeeze(-1) + b, after, atol=1e-12, rtol=0)
    torch.testing.assert_close(T @ cov @ T.transpose(-1, -2), transport_heading(cov, before, after), atol=1e-12, rtol=0)
