"""Which flow points a frame uses: candidates from a dense field, then a ranked, spread pick.

A dense flow field has ``H x W`` points; the filter uses ``N`` of them (a few
hundred). Selection has two stages:

1. :func:`flowins.flow.points.grid_candidates` (state-free, done once per frame pair): the field's
   values on a regular grid of pixels, at least ``border_px`` from the image edge.
2. :func:`select_points` (at the filter's current state, inside the update): a
   score per candidate, and :func:`spread_top_k` keeps the ``N`` best while spreading
   them over image cells, so one textured corner can't take every slot.

Scores (``method``):

* ``"parallax"`` (default): rotation-compensated parallax over flow σ. Only the
  part of a flow vector that the rotation between the frames does not explain
  carries information about the translation; points near the focus of expansion
  or far away have sub-σ parallax, and their triangulation (and so ``h``) is
  strongly nonlinear in the flow. The parallax needs only the two orientations of
  the state, not the depth.
* ``"sigma"``: lowest flow uncertainty first (the paper's Monte Carlo σ).
* ``"grid"``: no ranking; an even spread over the image.
"""
from __future__ import annotations

import torch
from torch import Tensor

from flowins.flow.points import FlowPoints
from flowins.geometry import quaternion as quat
from flowins.measurements.flow import normalise_pixels, ray_angle
from flowins.state import STATE_DIM, split

METHODS = ("parallax", "sigma", "grid")


def spread_top_k(score: Tensor, uv_px: Tensor, k: int, *, cell_px: float) -> Tensor:
    """Indices of ``k`` points: the best of every ``cell_px`` square cell first, then the
    second best of every cell, and so on (ties in rank by score).

    Args:
        score ``(M,)`` (higher is better), uv_px ``(M, 2)``.
    Returns:
        ``(min(k, M),)`` indices in order of selection.
    """
    M = score.shape[0]
    if k >= M:
        return torch.argsort(score, descending=True, stable=True)
    order = torch.argsort(score, descending=True, stable=True)
    cell = torch.floor(uv_px / cell_px).to(torch.int64)
    cell_id = cell[:, 0] * 100_003 + cell[:, 1]
    cell_sorted = cell_id[order]
    # rank of each point within its cell (0 = best): stable sort by cell keeps score order
    by_cell = torch.argsort(cell_sorted, stable=True)
    grouped = cell_sorted[by_cell]
    position = torch.arange(M, device=score.device)
    new_group = torch.ones(M, dtype=torch.bool, device=score.device)
    new_group[1:] = grouped[1:] != grouped[:-1]
    group_start = torch.cummax(torch.where(new_group, position, torch.zeros_like(position)), 0).values
    rank = torch.empty_like(position)
    rank[by_cell] = position - group_start
    key = rank * M + position  # rank first, then overall score order
    return order[torch.argsort(key)[:k]]


def rotation_parallax_px(x: Tensor, points: FlowPoints, K: Tensor, R_ci: Tensor) -> Tensor:
    """Rotation-compensated parallax of each point, px: the angle between the two
    viewing rays in the world frame times the focal length ``(M,)``.

    Args:
        x ``(26,)`` state (uses ``q`` and ``q_prev`` only); K ``(3, 3)``; R_ci ``(3, 3)``.
    """
    if x.shape[-1] != STATE_DIM:
        raise ValueError(f"rotation_parallax_px: x must be (..., {STATE_DIM}), got {tuple(x.shape)}")
    s = split(x)
    R_ic = R_ci.transpose(-1, -2).to(x)
    R_b = quat.to_matrix(torch.stack((s.q_prev, s.q), dim=-2))  # (..., 2, 3, 3) body -> world
    # the angle is rotation invariant: compare in camera 1's frame, ray 2 rotated by R₁ᵀ R₂
    R_rel = R_ci.to(x) @ R_b[..., 0, :, :].transpose(-1, -2) @ R_b[..., 1, :, :] @ R_ic
    K = K.to(x)
    uv1 = points.uv1_px.to(x)
    xy = normalise_pixels(torch.stack((uv1, uv1 + points.flow_px.to(x))), K)  # (2, M, 2)
    rays = torch.cat((xy, torch.ones_like(xy[..., :1])), -1)
    r1, r2 = rays[0], rays[1] @ R_rel.transpose(-1, -2)
    return 0.5 * (K[0, 0] + K[1, 1]) * ray_angle(r1, r2)


def select_points(
    x: Tensor,
    points: FlowPoints,
    K: Tensor,
    R_ci: Tensor,
    *,
    n_points: int,
    method: str = "parallax",
    cell_px: float = 32.0,
) -> Tensor:
    """Indices of the ``n_points`` candidates a frame's update uses (see the module doc)."""
    if method not in METHODS:
        raise ValueError(f"point selection method must be one of {METHODS}, got {method!r}")
    if n_points < 1:
        raise ValueError(f"n_points must be >= 1, got {n_points}")
    sigma = torch.linalg.vector_norm(points.sigma_px.to(x), dim=-1) / 2**0.5
    if method == "parallax":
        score = rotation_parallax_px(x, points, K, R_ci) / sigma
    elif method == "sigma":
        score = -sigma
    else:
        score = torch.zeros_like(sigma)
    return spread_top_k(score, points.uv1_px, n_points, cell_px=cell_px)
