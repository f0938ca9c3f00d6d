"""The directions of the state no relative measurement observes, and an update's covariance
carried along them.

A camera (and any body-frame measurement) sees the same thing when the whole track is moved
by a translation or turned about the world's vertical (gravity fixes roll and pitch, not the
heading): the four unobservable directions of visual-inertial odometry,
:func:`unobservable_directions`. The mechanisation is invariant under the same moves, so the
propagation's Jacobian at an estimate maps these directions at it onto those at the
propagated estimate, and a track's Jacobian at an estimate is blind to them there. What an
EKF breaks is the step between: an update moves the estimate from ``x⁻`` to ``x⁺`` but leaves
the covariance blind along the directions at ``x⁻``, and the next track update, blind along
those at ``x⁺``, takes the difference for information. That is how a filter of camera
updates makes up a heading it cannot see (Huang, Mourikis and Roumeliotis 2010; Li and
Mourikis 2013, who fix it with first-estimate Jacobians). :func:`transport_heading` fixes it
at the update instead: it carries the covariance's heading direction from ``x⁻`` to ``x⁺``,
so that every Jacobian stays at the current estimate and the information the filter holds
along the unobservable directions comes from its prior and from absolute measurements only.
"""
from __future__ import annotations

import torch
from torch import Tensor

from flowins.state import STATE, pose_slices, symmetrize


def unobservable_directions(x: Tensor) -> Tensor:
    """``(..., D, 4)``: the unobservable directions of the state ``x`` ``(..., 19 + 7 N)``: a
    translation of the whole track (columns 0-2: ``e_i`` on ``p`` and on every clone's
    position) and a turn about the world's vertical (column 3: ``e_z × p`` on every position,
    ``e_z × v`` on ``v``, ``½ L((0, e_z)) q`` on every quaternion: the derivative of
    ``q ↦ (cos θ/2, 0, 0, sin θ/2) ⊙ q`` at ``θ = 0``). The biases and the accelerometer
    scale are body-frame quantities: zero rows."""
    N = x.new_zeros(*x.shape, 4)
    eye3 = torch.eye(3, dtype=x.dtype, device=x.device)
    for p, q in pose_slices(x.shape[-1]):
        N[..., p, :3] = eye3
        N[..., p, 3] = _turn(x[..., p])
        N[..., q, 3] = _turn_quaternion(x[..., q])
    N[..., STATE.v, 3] = _turn(x[..., STATE.v])
    return N


def _turn(w: Tensor) -> Tensor:
    """``e_z × w = (-w_y, w_x, 0)``."""
    return torch.stack((-w[..., 1], w[..., 0], torch.zeros_like(w[..., 0])), -1)


def _turn_quaternion(q: Tensor) -> Tensor:
    """``½ L((0, e_z)) q = ½ (-q_z, -q_y, q_x, q_w)``: the derivative of ``q`` turned about the
    world's vertical."""
    return 0.5 * torch.stack((-q[..., 3], -q[..., 2], q[..., 1], q[..., 0]), -1)


def heading_weights(x: Tensor) -> Tensor:
    """``(..., D)``: ``w`` with ``wᵀ δx`` the turn about the world's vertical of the current
    quaternion's error ``δq`` (the ``q`` rows of :func:`unobservable_directions`'s column 3 over
    their squared norm, zero elsewhere), so that ``wᵀ N_ψ(x) = 1`` and ``wᵀ`` of a translation is 0."""
    n_q = torch.zeros_like(x)
    n_q[..., STATE.q] = _turn_quaternion(x[..., STATE.q])
    return n_q / (n_q * n_q).sum(-1, keepdim=True).clamp_min(torch.finfo(x.dtype).tiny)


def blind_to_heading(H: Tensor, x: Tensor) -> Tensor:
    """The Jacobian ``H`` ``(..., m, D)`` of a measurement whose likelihood a turn of the whole
    state about the world's vertical leaves as it is, made blind to that turn at ``x`` ``(..., D)``:
    ``H - (H N_ψ(x)) wᵀ`` with ``w`` of :func:`heading_weights`, so that ``H' N_ψ(x) = 0`` and
    only the columns of the current quaternion change. A zero-velocity update is one: its
    ``0 = v + n`` with isotropic ``n`` is as likely for ``v`` as for ``v`` turned, but ``H = ∂v/∂x``
    at a small ``v̂ ≠ 0`` sees the turn ``e_z × v̂``, and with the heading free (a still start)
    the filter takes that for heading information it has not got."""
    n = unobservable_directions(x)[..., 3]
    Hn = (H * n.unsqueeze(-2)).sum(-1)
    return H - Hn.unsqueeze(-1) * heading_weights(x).unsqueeze(-2)


def _shear(before: Tensor, after: Tensor) -> tuple[Tensor, Tensor]:
    """``(u, w)`` of the transport's ``T = I + u wᵀ``: ``u = N_ψ(after) - N_ψ(before)`` and ``w``
    of :func:`heading_weights` at ``before``."""
    return (unobservable_directions(after)[..., 3] - unobservable_directions(before)[..., 3],
            heading_weights(before))


def heading_transport_step(before: Tensor, after: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`transport_heading` as a linear step of the chain, ``x ↦ T x + b`` ``(..., D, D)``,
    ``(..., D)``, with ``b = -u (wᵀ after)`` so that ``after`` stays where it is and the covariance
    becomes ``T P Tᵀ``. Recorded as a step (no process noise), the RTS smoother carries it back
    exactly; a covariance replaced in place is a change the smoother takes for information."""
    u, w = _shear(before, after)
    T = torch.eye(after.shape[-1], dtype=after.dtype, device=after.device) + u.unsqueeze(-1) * w.unsqueeze(-2)
    return T, -u * (w * after).sum(-1, keepdim=True)


def transport_heading(cov: Tensor, before: Tensor, after: Tensor) -> Tensor:
    """The covariance ``cov`` ``(..., D, D)`` of an update that moved the state from ``before``
    to ``after`` ``(..., D)``, carried so that its heading direction moves with the estimate:
    ``T P Tᵀ`` with ``T = I + u wᵀ``, ``u = N_ψ(after) - N_ψ(before)`` (column 3 of
    :func:`unobservable_directions`: ``e_z × Δp`` on every position, ``e_z × Δv``,
    ``½ L((0, e_z)) Δq`` on every quaternion) and ``w`` the heading part of the current
    quaternion's error (``N_ψ(before)``'s ``q`` rows over their squared norm, so ``wᵀ N_ψ = 1``;
    ``wᵀ`` of a translation is 0).

    ``T`` maps the directions at ``before`` onto those at ``after`` and is a congruence, so the
    information ``Nᵀ P⁻¹ N`` along them is the same before and after (a test checks it) and
    the result is positive semi-definite where ``cov`` is."""
    u, w = _shear(before, after)
    Pw = (cov @ w.unsqueeze(-1)).squeeze(-1)
    wPw = (w * Pw).sum(-1, keepdim=True)
    shear = u.unsqueeze(-1) * Pw.unsqueeze(-2)
    return symmetrize(cov + shear + shear.transpose(-1, -2) + (u * wPw).unsqueeze(-1) * u.unsqueeze(-2))
