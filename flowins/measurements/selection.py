"""Which flow points a frame uses: candidates from a dense field, then a ranked, spread pick.

A dense flow field has ``H x W`` points; the filter uses ``N`` of them (a few
hundred). Selection has two stages:

1. :func:`flowins.flow.points.grid_candidates` (state-free, done once per frame pair): the field's
   values on a regular grid of pixels, at least ``border_px`` from the image edge.
2. :func:`select_points` (at the filter's current state, inside the update): a
   score per candidate, and :func:`spread_top_k` keeps the ``N`` best while spreading
   them over image cells, so one textured corner can't take every slot.

Both take leading batch dimensions (one frame per sequence) and a mask of the real
candidates (sequences with fewer candidates are padded); padding is picked last.

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

from flowins.constants import cached_constant
from flowins.flow.points import FlowPoints
from flowins.measurements.flow import cast_like, normalise_pixels, ray_angle, scaled_rotations, state_size
from flowins.state import STATE

METHODS = ("parallax", "sigma", "grid")


def spread_top_k(score: Tensor, uv_px: Tensor, k: int, *, cell_px: float, mask: Tensor | None = None) -> Tensor:
    """Indices of ``k`` points per row: the best of every ``cell_px`` square cell first, then the
    second best of every cell, and so on (within a round by score; ties by index).

    The order is one fixed order of all points, so a smaller ``k`` picks a prefix.

    Args:
        score ``(..., M)`` (higher is better), uv_px ``(..., M, 2)``.
        mask: ``(..., M)`` bool, False for padding: padded points come after every real point
            of their row (gather ``mask`` at the result to tell which picks are real), and the
            real ones are picked as the row alone, without its padding, would pick them.
    Returns:
        ``(..., min(k, M))`` indices in order of selection.
    """
    M = score.shape[-1]
    uv = uv_px if uv_px.dtype == torch.float64 else uv_px.to(torch.float64)
    cell = torch.div(uv, cell_px, rounding_mode="floor") @ _cell_weights(uv.device)  # an exact integer id per cell
    if mask is not None:  # padding in a cell of its own (whatever its pixels hold), ranked last below
        cell = torch.where(mask, cell, float("inf"))
    order = torch.argsort(score, dim=-1, descending=True, stable=True)
    # group by cell, by score within a cell (stable): each point's rank in its cell is its
    # distance from the first of its group
    grouped, by_cell = torch.sort(torch.take_along_dim(cell, order, -1), dim=-1, stable=True)
    rank = _positions(M, score.device) - torch.searchsorted(grouped, grouped)
    members = torch.take_along_dim(order, by_cell, -1)  # grouped position -> point
    if mask is not None:
        rank = torch.where(torch.take_along_dim(mask, members, -1), rank, M)
    # round first, then score order (by_cell is the position in score order): the keys are
    # distinct, so the k smallest in order are a full argsort's first k
    pick = torch.topk(torch.add(by_cell, rank, alpha=M), min(k, M), dim=-1, largest=False).indices
    return torch.take_along_dim(members, pick, -1)


@cached_constant
def _cell_weights(device: torch.device) -> Tensor:
    return torch.tensor([100_003.0, 1.0], dtype=torch.float64, device=device)


@cached_constant
def _positions(M: int, device: torch.device) -> Tensor:
    return torch.arange(M, device=device)


def _rotation_parallax_angle(x: Tensor, points: FlowPoints, K: Tensor, R_ci: Tensor) -> Tensor:
    """The angle (rad) ``(..., M)`` between each point's two viewing rays with the rotation of the
    state compensated (see :func:`rotation_parallax_px`)."""
    state_size(x, "rotation_parallax_px")  # q and q_prev (clone 0) sit where they do in the 26-dim state
    # R(q) |q|² of both orientations: the angle does not depend on the scale
    R_b = scaled_rotations(x[..., _orientations(x.device)].view(*x.shape[:-1], 2, 4))
    R_ci = cast_like(R_ci, x)
    R_ic = R_ci.transpose(-1, -2)
    # the angle is rotation invariant: compare in camera 1's frame, ray 2 rotated by R₁ᵀ R₂
    R_rel = R_ci @ (R_b[..., 0, :, :].transpose(-1, -2) @ R_b[..., 1, :, :]) @ R_ic
    uv1 = cast_like(points.uv1_px, x)
    uv = torch.stack((uv1, uv1 + cast_like(points.flow_px, x)), -2)  # (..., M, 2, 2)
    K = cast_like(K, x)
    xy = normalise_pixels(uv, K if K.ndim == 2 else K[..., None, None, :, :])
    rays = torch.cat((xy, _ones(x.dtype, x.device).expand(*xy.shape[:-1], 1)), -1)
    turned = rays[..., 1, :] @ R_rel.transpose(-1, -2)  # (..., M, 3) rows times (..., 3, 3)
    return ray_angle(rays[..., 0, :], turned)


@cached_constant
def _orientations(device: torch.device) -> Tensor:
    return STATE.indices("q_prev", "q").to(device)


@cached_constant
def _ones(dtype: torch.dtype, device: torch.device) -> Tensor:
    return torch.ones(1, dtype=dtype, device=device)


def rotation_parallax_px(x: Tensor, points: FlowPoints, K: Tensor, R_ci: Tensor) -> Tensor:
    """Rotation-compensated parallax of each point, px: the angle between the two
    viewing rays in the world frame times the focal length ``(..., M)``.

    Args:
        x ``(..., 26)`` state, or ``(..., 19 + 7 N)`` with a window of cloned poses (uses ``q`` and
        ``q_prev`` only); points with tensors ``(..., M, 2)``;
        K ``(3, 3)``, R_ci ``(3, 3)``, shared or with the batch dims.
    """
    K = cast_like(K, x)
    focal = 0.5 * (K[..., 0, 0] + K[..., 1, 1])
    return _rotation_parallax_angle(x, points, K, R_ci) * (focal if K.ndim == 2 else focal.unsqueeze(-1))


def select_points(
    x: Tensor,
    points: FlowPoints,
    K: Tensor,
    R_ci: Tensor,
    *,
    n_points: int,
    method: str = "parallax",
    cell_px: float = 32.0,
    mask: Tensor | None = None,
) -> Tensor:
    """Indices ``(..., min(n_points, M))`` of the candidates a frame's update uses (see the module
    doc), for states ``x`` ``(..., 26)`` (or ``(..., 19 + 7 N)``) and points with tensors
    ``(..., M, 2)``; ``K``, ``R_ci`` shared or with the batch dims; ``mask`` ``(..., M)`` False for padding, which is picked
    after every real candidate of its row (:func:`spread_top_k`).

    Scores are compared within a row only, so they leave out factors common to a row (the
    focal length, the ``√2`` of the mean σ).
    """
    if method not in METHODS:
        raise ValueError(f"point selection method must be one of {METHODS}, got {method!r}")
    if n_points < 1:
        raise ValueError(f"n_points must be >= 1, got {n_points}")
    if method == "grid":
        score = x.new_zeros(points.uv1_px.shape[:-1])
    else:
        sigma = torch.linalg.vector_norm(cast_like(points.sigma_px, x), dim=-1)
        score = _rotation_parallax_angle(x, points, K, R_ci) / sigma if method == "parallax" else -sigma
    return spread_top_k(score, points.uv1_px, n_points, cell_px=cell_px, mask=mask)
