"""The zero-velocity pseudo-measurement of a still device, as a filter event."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from flowins.filter.ekf import ekf_update
from flowins.filter.runner import ChainBuilder
from flowins.state import STATE, normalize_quaternions


@dataclass(frozen=True)
class ZeroVelocity:
    """A zero-velocity pseudo-measurement ``0 = v + n``, ``n ~ N(0, σ² I₃)`` (a still device)."""

    time_s: float
    sigma_mps: float | Tensor = 0.01
    name: str = "zero velocity"

    def apply(self, chain: ChainBuilder) -> None:
        mean, cov = chain.mean, chain.cov
        H = torch.zeros(1, 3, mean.shape[-1], dtype=mean.dtype, device=mean.device)
        H[0, :, STATE.v] = torch.eye(3, dtype=mean.dtype, device=mean.device)
        sigma = torch.as_tensor(self.sigma_mps, dtype=mean.dtype, device=mean.device)
        result = ekf_update(mean, cov, innovation=-mean[STATE.v].reshape(1, 3), H=H,
                            noise_cov=(sigma**2 * torch.eye(3, dtype=mean.dtype, device=mean.device)).reshape(1, 3, 3),
                            normalize=normalize_quaternions)
        chain.update(result, kind="zero_velocity", name=self.name)
