"""The zero-velocity pseudo-measurement of a still device, as a filter event.

Its likelihood, ``0 = v + n`` with isotropic ``n``, is the same for a velocity and that velocity
turned about the vertical, so a still device says nothing about its heading. ``∂v/∂x`` at the
small ``v̂`` an update starts from does see the turn (``e_z × v̂``), and a still start with a free
yaw (σ π) would take that for heading information: the 53 updates of the default walk's
5.26 s still start bring the heading σ of its IMU-only run to 31° (docs/initialization.md). By default the update is
blind to the turn (:func:`~flowins.filter.unobservable.blind_to_heading`) and its covariance
carried to the updated estimate by a linear step of the chain
(:func:`~flowins.filter.unobservable.heading_transport_step`), so the heading keeps what the
start gave it.
"""
from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from flowins.constants import scalar_like
from flowins.filter.chain import BatchChain, RowBatchEvent
from flowins.filter.unobservable import blind_to_heading, heading_transport_step
from flowins.filter.updater import update_rows
from flowins.state import STATE


@dataclass(frozen=True)
class ZeroVelocity(RowBatchEvent):
    """A zero-velocity pseudo-measurement ``0 = v + n``, ``n ~ N(0, σ² I₃)`` (a still device).
    ``keeps_heading``: the update is blind to a turn of the state about the vertical and carries
    its covariance along it (the module doc); False: the plain EKF update with ``H = ∂v/∂x``."""

    time_s: float
    sigma_mps: float | Tensor = 0.01
    name: str = "zero velocity"
    keeps_heading: bool = True

    def batch_key(self) -> Hashable:
        """Zero velocities with the same σ (the same tensor, or the same number) and the same
        ``keeps_heading`` act together."""
        s = self.sigma_mps
        return (ZeroVelocity, ("tensor", id(s)) if isinstance(s, Tensor) else float(s), bool(self.keeps_heading))

    @classmethod
    def apply_batch(cls, chain: BatchChain, rows: Sequence[int], events: Sequence[ZeroVelocity]) -> None:
        """The pseudo-measurements ``events[i]`` (one σ) on the rows ``rows[i]``, as one update."""
        mean, _ = chain.newest(rows)
        r, D = mean.shape
        eye = torch.eye(3, dtype=mean.dtype, device=mean.device)
        H = mean.new_zeros(r, 1, 3, D)
        H[..., STATE.v] = eye
        keeps = events[0].keeps_heading
        if keeps:
            H = blind_to_heading(H, mean.unsqueeze(1))
        sigma = scalar_like(events[0].sigma_mps, mean)
        update_rows(chain, rows, H=H, residual=-mean[:, STATE.v].unsqueeze(1),
                    noise_cov=(sigma**2 * eye).expand(r, 1, 3, 3), likelihood=False,
                    infos=[{"kind": "zero_velocity", "name": e.name} for e in events])
        if keeps:  # as a step of the chain, which the smoother carries back exactly
            after, _ = chain.newest(rows)
            T, b = heading_transport_step(mean, after)
            chain.linear_predict_rows(rows, T, T.new_zeros(()).expand(T.shape), b)
