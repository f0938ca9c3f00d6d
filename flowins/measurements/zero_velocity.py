"""The zero-velocity pseudo-measurement of a still device, as a filter event."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from flowins.filter.chain import ChainBuilder
from flowins.filter.updater import update
from flowins.state import STATE


@dataclass(frozen=True)
class ZeroVelocity:
    """A zero-velocity pseudo-measurement ``0 = v + n``, ``n ~ N(0, σ² I₃)`` (a still device)."""

    time_s: float
    sigma_mps: float | Tensor = 0.01
    name: str = "zero velocity"

    def apply(self, chain: ChainBuilder) -> None:
        mean = chain.mean
        H = torch.zeros(1, 3, mean.shape[-1], dtype=mean.dtype, device=mean.device)
        H[0, :, STATE.v] = torch.eye(3, dtype=mean.dtype, device=mean.device)
        sigma = torch.as_tensor(self.sigma_mps, dtype=mean.dtype, device=mean.device)
        update(chain, H=H, residual=-mean[STATE.v].reshape(1, 3),
               noise_cov=(sigma**2 * torch.eye(3, dtype=mean.dtype, device=mean.device)).reshape(1, 3, 3),
               likelihood=False, kind="zero_velocity", name=self.name)
