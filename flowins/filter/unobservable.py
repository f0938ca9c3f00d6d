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
        qs = x[..., q]  # ½ L((0, 0, 0, 1)) q = ½ (-q_z, -q_y, q_x, q_w)
        N[..., q, 3] = 0.5 * torch.stack((-qs[..., 3], -qs[..., 2], qs[..., 1], qs[..., 0]), -1)
    N[..., STATE.v, 3] = _turn(x[..., STATE.v])
    return N


def _turn(w: Tensor) -> Tensor:
    """``e_z × w = (-w_y, w_x, 0)``."""
    return torch.stack((-w[..., 1], w[..., 0], torch.zeros_like(w[..., 0])), -1)


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
    n_before = unobservable_directions(before)[..., 3]
    u = unobservable_directions(after)[..., 3] - n_before
    at_q = torch.zeros(cov.shape[-1], dtype=torch.bool, device=cov.device)
    at_q[STATE.q] = True
    n_q = torch.where(at_q, n_before, 0.0)
    w = n_q / (n_q * n_q).sum(-1, keepdim=True).clamp_min(torch.finfo(cov.dtype).tiny)
    Pw = (cov @ w.unsqueeze(-1)).squeeze(-1)
    wPw = (w * Pw).sum(-1, keepdim=True)
    shear = u.unsqueeze(-1) * Pw.unsqueeze(-2)
    return symmetrize(cov + shear + shear.transpose(-1, -2) + (u * wPw).unsqueeze(-1) * u.unsqueeze(-2))
