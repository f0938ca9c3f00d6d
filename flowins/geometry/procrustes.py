"""Rotations that best map one set of points or vectors onto another (Procrustes, Wahba).

For centred points ``x̃ᵢ``, ``ỹᵢ`` and weights ``wᵢ`` the angle maximising
``Σ wᵢ ỹᵢᵀ R(θ) x̃ᵢ`` is ``θ = atan2(Σ wᵢ (x̃ᵢ × ỹᵢ), Σ wᵢ x̃ᵢ · ỹᵢ)`` (planar Procrustes),
with the weighted centres ``c = Σ wᵢ xᵢ / Σ wᵢ``. Used by the evaluation's 4-DoF alignment
and by the GNSS heading alignment. :func:`wahba_rotation` is the 3-D rotation between two
sets of vectors (the camera mounting check, :mod:`flowins.flow.mounting`).
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor


class PlanarFit(NamedTuple):
    theta_rad: Tensor  # (...) the rotation angle, counter-clockwise
    centre_source: Tensor  # (..., 2)
    centre_target: Tensor  # (..., 2)
    spread: Tensor  # (...) Σ wᵢ |x̃ᵢ|², the information on θ per unit residual variance
    weight_sum: Tensor  # (...) Σ wᵢ (N without weights)


def planar_rotation(source_xy: Tensor, target_xy: Tensor, weights: Tensor | None = None) -> PlanarFit:
    """The planar Procrustes fit of ``target ≈ R(θ)(source - c_s) + c_t`` for points
    ``(..., N, 2)`` (extra columns are ignored) and optional weights ``(..., N)``."""
    xs, xt = source_xy[..., :2], target_xy[..., :2]
    if weights is None:
        c_s, c_t = xs.mean(dim=-2), xt.mean(dim=-2)
        total = torch.full(xs.shape[:-2], float(xs.shape[-2]), dtype=xs.dtype, device=xs.device)
        ds, dt = xs - c_s.unsqueeze(-2), xt - c_t.unsqueeze(-2)
        cross = (ds[..., 0] * dt[..., 1] - ds[..., 1] * dt[..., 0]).sum(-1)
        dot = (ds * dt).sum(-1).sum(-1)
        spread = (ds * ds).sum(-1).sum(-1)
    else:
        total = weights.sum(-1)
        c_s = (weights.unsqueeze(-1) * xs).sum(-2) / total.unsqueeze(-1)
        c_t = (weights.unsqueeze(-1) * xt).sum(-2) / total.unsqueeze(-1)
        ds, dt = xs - c_s.unsqueeze(-2), xt - c_t.unsqueeze(-2)
        cross = (weights * (ds[..., 0] * dt[..., 1] - ds[..., 1] * dt[..., 0])).sum(-1)
        dot = (weights * (ds * dt).sum(-1)).sum(-1)
        spread = (weights * (ds * ds).sum(-1)).sum(-1)
    return PlanarFit(torch.atan2(cross, dot), c_s, c_t, spread, total)


def rotation_2d(theta_rad: Tensor) -> Tensor:
    """``R(θ)`` ``(..., 2, 2)``, counter-clockwise about the vertical."""
    c, s = torch.cos(theta_rad), torch.sin(theta_rad)
    return torch.stack((torch.stack((c, -s), -1), torch.stack((s, c), -1)), -2)


def wahba_rotation(source: Tensor, target: Tensor, weights: Tensor | None = None, *,
                   prior: Tensor | None = None, prior_weight: float = 0.0) -> Tensor:
    """The rotation ``R`` ``(..., 3, 3)`` minimising ``Σ wᵢ |tᵢ - R sᵢ|² + prior_weight · θ²(R, prior)``
    for vectors ``source``, ``target`` ``(..., N, 3)`` and weights ``(..., N)`` (Wahba's problem,
    one per leading index; no centring).

    With ``B = Σ wᵢ tᵢ sᵢᵀ + prior_weight · prior / 2`` (``θ² ≈ 3 - tr(priorᵀ R)`` near the
    prior) the optimum over SO(3) is ``U diag(1, 1, det(U Vᵀ)) Vᵀ`` for ``B = U S Vᵀ``: the
    data decide the directions they excite and the prior the rest."""
    w = torch.ones_like(source[..., 0]) if weights is None else weights
    B = (w.unsqueeze(-1) * target).transpose(-1, -2) @ source
    if prior is not None and prior_weight > 0:
        B = B + 0.5 * prior_weight * prior
    U, _, Vh = torch.linalg.svd(B)
    d = torch.linalg.det(U @ Vh)
    D = torch.diag_embed(torch.stack((torch.ones_like(d), torch.ones_like(d), d), -1))
    return U @ D @ Vh
