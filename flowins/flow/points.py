"""Flow points: the sparse form every flow source is reduced to before the filter.

A :class:`FlowPoints` holds, for ``M`` points of one frame pair, the pixel in the
first frame, the flow to the second and its 1-σ. Dense fields become candidates
on a pixel grid (:func:`grid_candidates`); sparse trackers give them directly.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor


class FlowPoints(NamedTuple):
    """Flow points of one frame pair: pixels in the first frame, flow and 1-σ, all ``(M, 2)`` px.

    ``dropout_unit_px`` and ``floor_px`` (optional, ``(M, 2)``): the parts of ``σ`` of a
    provider whose Monte Carlo dropout spread has a closed form
    (:meth:`flowins.flow.spynet.SpyNetProvider.moments`); :meth:`at_dropout_rate`
    recomputes ``σ`` for another rate, differentiably.
    """

    uv1_px: Tensor
    flow_px: Tensor
    sigma_px: Tensor
    dropout_unit_px: Tensor | None = None
    floor_px: Tensor | None = None

    # (``__len__`` is the number of points, so ``NamedTuple._replace`` can't be used here)
    def take(self, index: Tensor) -> FlowPoints:
        return FlowPoints(*(None if x is None else x[index] for x in self))

    def __len__(self) -> int:
        return self.uv1_px.shape[0]

    def to(self, like: Tensor) -> FlowPoints:
        return FlowPoints(*(None if x is None else x.to(like) for x in self))

    def at_dropout_rate(self, p: float | Tensor) -> FlowPoints:
        """The points with ``σ = max(sqrt(p / (1 - p)) dropout_unit, floor)`` for dropout rate ``p``."""
        if self.dropout_unit_px is None or self.floor_px is None:
            raise ValueError(
                "FlowPoints.at_dropout_rate: these points carry no dropout moments; compute them with a provider "
                "in closed-form mode (SpyNetProvider(mc_mode='moments'))"
            )
        p = torch.as_tensor(p, dtype=self.dropout_unit_px.dtype, device=self.dropout_unit_px.device)
        sigma = torch.maximum(torch.sqrt(p / (1 - p)) * self.dropout_unit_px, self.floor_px)
        return FlowPoints(self.uv1_px, self.flow_px, sigma, self.dropout_unit_px, self.floor_px)


def grid_candidates(
    flow_px: Tensor,
    sigma_px: Tensor,
    *,
    stride_px: int = 8,
    border_px: int = 8,
    dropout_unit_px: Tensor | None = None,
    floor_px: Tensor | None = None,
) -> FlowPoints:
    """The dense field sampled every ``stride_px`` pixels, ``border_px`` away from the edges.

    Args:
        flow_px, sigma_px: ``(2, H, W)`` (a :class:`~flowins.flow.base.FlowResult` item);
            ``dropout_unit_px``, ``floor_px``: optional ``(2, H, W)`` parts of σ, sampled alike.
    Raises:
        ValueError: for mismatched shapes, non-positive stride, a border that leaves
            no pixel, or non-finite flow or σ at a candidate (a provider must not
            return those; nothing is dropped silently).
    """
    if flow_px.ndim != 3 or flow_px.shape[0] != 2 or sigma_px.shape != flow_px.shape:
        raise ValueError(
            f"grid_candidates: flow and sigma must both be (2, H, W); got {tuple(flow_px.shape)}, {tuple(sigma_px.shape)}"
        )
    if stride_px < 1 or border_px < 0:
        raise ValueError(f"grid_candidates: stride_px must be >= 1 and border_px >= 0; got {stride_px}, {border_px}")
    H, W = flow_px.shape[-2:]
    if 2 * border_px >= min(H, W):
        raise ValueError(f"grid_candidates: border_px={border_px} leaves no pixel of a {W}x{H} field")
    # grid centred in the usable area
    def axis(n: int) -> Tensor:
        usable = n - 2 * border_px
        count = max(1, (usable - 1) // stride_px + 1)
        offset = border_px + (usable - 1 - (count - 1) * stride_px) // 2
        return offset + stride_px * torch.arange(count, device=flow_px.device)

    v, u = torch.meshgrid(axis(H), axis(W), indexing="ij")
    v, u = v.reshape(-1), u.reshape(-1)
    # (M, 2) rows in memory order: the per-point operations downstream reduce and index along the last dim
    flow = flow_px[:, v, u].T.contiguous()
    sigma = sigma_px[:, v, u].T.contiguous()
    bad = ~(torch.isfinite(flow).all(-1) & torch.isfinite(sigma).all(-1) & (sigma > 0).all(-1))
    if bool(bad.any()):
        i = int(torch.nonzero(bad)[0])
        raise ValueError(
            f"grid_candidates: {int(bad.sum())} candidate pixels have non-finite flow or non-positive σ, "
            f"first at (u, v) = ({int(u[i])}, {int(v[i])}): flow {flow[i].tolist()}, σ {sigma[i].tolist()}"
        )
    uv = torch.stack((u, v), -1).to(flow.dtype)
    extras = [None if x is None else x[:, v, u].T.contiguous() for x in (dropout_unit_px, floor_px)]
    return FlowPoints(uv, flow, sigma, *extras)
