"""The zero-velocity pseudo-measurement of a still device, as a filter event."""
from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from flowins.constants import scalar_like
from flowins.filter.chain import BatchChain, RowBatchEvent
from flowins.filter.updater import update_rows
from flowins.state import STATE


@dataclass(frozen=True)
class ZeroVelocity(RowBatchEvent):
    """A zero-velocity pseudo-measurement ``0 = v + n``, ``n ~ N(0, σ² I₃)`` (a still device)."""

    time_s: float
    sigma_mps: float | Tensor = 0.01
    name: str = "zero velocity"

    def batch_key(self) -> Hashable:
        """Zero velocities with the same σ (the same tensor, or the same number) act together."""
        s = self.sigma_mps
        return (ZeroVelocity, ("tensor", id(s)) if isinstance(s, Tensor) else float(s))

    @classmethod
    def apply_batch(cls, chain: BatchChain, rows: Sequence[int], events: Sequence[ZeroVelocity]) -> None:
        """The pseudo-measurements ``events[i]`` (one σ) on the rows ``rows[i]``, as one update."""
        mean, _ = chain.newest(rows)
        r, D = mean.shape
        eye = torch.eye(3, dtype=mean.dtype, device=mean.device)
        H = mean.new_zeros(r, 1, 3, D)
        H[..., STATE.v] = eye
        sigma = scalar_like(events[0].sigma_mps, mean)
        update_rows(chain, rows, H=H, residual=-mean[:, STATE.v].unsqueeze(1),
                    noise_cov=(sigma**2 * eye).expand(r, 1, 3, 3), likelihood=False,
                    infos=[{"kind": "zero_velocity", "name": e.name} for e in events])
