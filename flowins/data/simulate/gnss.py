"""Simulated GNSS fixes in a city: urban-canyon accuracy, correlated errors, multipath.

* The reported horizontal 1-σ accuracy ``h_acc`` varies between ``min_acc_m`` and
  ``max_acc_m`` with how enclosed the receiver is: ``canyon`` in [0, 1] (0 open
  sky, 1 a deep street canyon), smoothed over time as a receiver's would be.
  Vertical accuracy is ``vertical_ratio * h_acc``.
* The error is consistent with the report: ``e(t) = σ(t) z(t)`` per axis, with
  ``z`` a unit-variance first-order Gauss-Markov process (correlation time
  ``correlation_s``), so the errors are as large as the radius says but
  correlated between consecutive fixes, as real GNSS errors are.
* Multipath outliers: with a probability that grows with ``canyon``, a fix is
  displaced by ``multipath_m`` (uniform range) in a random horizontal direction
  while its reported accuracy stays unchanged (the receiver does not know).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class GnssErrors:
    rate_hz: float = 1.0
    min_acc_m: float = 3.0
    max_acc_m: float = 25.0
    vertical_ratio: float = 1.5
    correlation_s: float = 10.0
    smoothing_s: float = 5.0
    multipath_probability: float = 0.03  # per fix, at canyon = 1 (a third of it in the open)
    multipath_m: tuple[float, float] = (20.0, 60.0)

    def __post_init__(self) -> None:
        if not 0 < self.min_acc_m <= self.max_acc_m:
            raise ValueError(f"GnssErrors: need 0 < min_acc_m <= max_acc_m, got {self.min_acc_m}, {self.max_acc_m}")
        if not 0.0 <= self.multipath_probability <= 1.0:
            raise ValueError(f"GnssErrors.multipath_probability={self.multipath_probability}; expected in [0, 1]")
        if self.rate_hz <= 0 or self.correlation_s <= 0 or self.smoothing_s < 0:
            raise ValueError("GnssErrors: rate_hz and correlation_s must be > 0, smoothing_s >= 0")


def simulate_fixes(
    true_enu_m: Tensor, canyon: Tensor, errors: GnssErrors, generator: torch.Generator
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Noisy fixes for true antenna positions ``(G, 3)`` at ``errors.rate_hz``.

    Returns ``(measured_enu (G, 3), h_acc (G,), v_acc (G,), multipath (G,) bool)``.
    """
    G = true_enu_m.shape[0]
    dt = 1.0 / errors.rate_hz
    dtype = true_enu_m.dtype
    # receiver-smoothed canyon factor -> accuracy radius
    alpha = 1.0 - math.exp(-dt / errors.smoothing_s) if errors.smoothing_s > 0 else 1.0
    smooth = torch.empty_like(canyon)
    level = canyon[0]
    for k in range(G):
        level = level + alpha * (canyon[k] - level)
        smooth[k] = level
    h_acc = errors.min_acc_m + (errors.max_acc_m - errors.min_acc_m) * smooth.clamp(0.0, 1.0) ** 1.5
    v_acc = errors.vertical_ratio * h_acc
    # unit-variance Gauss-Markov errors, scaled by the current accuracy
    phi = math.exp(-dt / errors.correlation_s)
    white = torch.randn(G, 3, generator=generator, dtype=dtype)
    z = torch.empty_like(white)
    state = white[0]
    for k in range(G):
        state = phi * state + math.sqrt(1.0 - phi * phi) * white[k] if k else state
        z[k] = state
    measured = true_enu_m + z * torch.stack((h_acc, h_acc, v_acc), -1)
    # multipath outliers
    p = errors.multipath_probability * (1.0 + 2.0 * smooth.clamp(0.0, 1.0)) / 3.0
    multipath = torch.rand(G, generator=generator, dtype=dtype) < p
    lo, hi = errors.multipath_m
    size = lo + (hi - lo) * torch.rand(G, generator=generator, dtype=dtype)
    angle = 2 * math.pi * torch.rand(G, generator=generator, dtype=dtype)
    offset = torch.stack((size * torch.cos(angle), size * torch.sin(angle), torch.zeros_like(size)), -1)
    measured = measured + torch.where(multipath.unsqueeze(-1), offset, torch.zeros_like(offset))
    return measured, h_acc, v_acc, multipath
