"""A wheeled vehicle's motion constraint: no sideways and no vertical velocity in its own frame.

A car does not slip sideways or leave the road, so between GNSS fixes its velocity in the
vehicle frame is ``(v_forward, 0, 0)`` (the non-holonomic constraint of wheeled-vehicle
navigation, as ai-imu-dr uses). With the IMU's axes along the vehicle's (``forward_axis``,
``up_axis``; KITTI's OXTS: x forward, z up) the pseudo-measurement is

    0 = e_lateralᵀ C(q)ᵀ v + n_lat,   0 = e_upᵀ C(q)ᵀ v + n_up,

``n ~ N(0, diag(σ_lat², σ_up²))``, applied every ``1 / rate_hz`` seconds from the start.
Its Jacobian has blocks on the velocity (``e_kᵀ C(q)ᵀ``) and on the quaternion
(:func:`~flowins.geometry.quaternion.rotate_jacobian` of the conjugate). The kind registers
itself as ``vehicle``: a run uses it when its streams hold ``vehicle`` (a
:class:`VehicleConstraint`: ``filter.measurements.vehicle.mode=on``, or ``auto`` on a
recording whose metadata names ``platform: vehicle``).
"""
from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from flowins.config import bounded, check_fields
from flowins.constants import cached_constant, scalar_like
from flowins.filter.chain import BatchChain, RowBatchEvent
from flowins.filter.updater import update_rows
from flowins.geometry import quaternion as quat
from flowins.measurements.registry import MeasurementKind, NavigationContext, register
from flowins.state import STATE

AXES = {"x": (0, 1.0), "-x": (0, -1.0), "y": (1, 1.0), "-y": (1, -1.0), "z": (2, 1.0), "-z": (2, -1.0)}
MODES = ("auto", "on", "off")


@dataclass(frozen=True)
class VehicleSettings:
    """``filter.measurements.vehicle``."""

    #: auto: on when the recording's metadata names ``platform: vehicle``; on; off
    mode: Literal["auto", "on", "off"] = "auto"
    #: σ of the sideways and of the vertical velocity in the vehicle frame (m/s)
    lateral_sigma_mps: float | Tensor = bounded(1.0, above=0.0)
    vertical_sigma_mps: float | Tensor = bounded(1.0, above=0.0)
    #: pseudo-measurements per second
    rate_hz: float = bounded(5.0, above=0.0)
    #: the IMU axes along the vehicle's forward and up directions
    forward_axis: Literal["x", "-x", "y", "-y", "z", "-z"] = "x"
    up_axis: Literal["x", "-x", "y", "-y", "z", "-z"] = "z"

    def __post_init__(self) -> None:
        check_fields(self)
        if AXES[self.forward_axis][0] == AXES[self.up_axis][0]:
            raise ValueError(f"VehicleSettings.forward_axis={self.forward_axis!r} and up_axis={self.up_axis!r} "
                             "are the same axis")

    def rows(self) -> tuple[Tensor, Tensor]:
        """``E (2, 3)``: the body's lateral and up unit axes as rows (the up axis with its sign)."""
        up_i, up_s = AXES[self.up_axis]
        fwd_i, _ = AXES[self.forward_axis]
        lateral_i = 3 - up_i - fwd_i
        E = torch.zeros(2, 3, dtype=torch.float64)
        E[0, lateral_i] = 1.0
        E[1, up_i] = up_s
        return E


@dataclass(frozen=True)
class VehicleConstraint:
    """The stream that switches the constraint on for a run (it carries no data)."""


def platform_streams(platform: str | None) -> dict[str, VehicleConstraint]:
    """The streams a recording's ``platform`` (its metadata) brings: the vehicle constraint for
    ``vehicle`` (used unless ``filter.measurements.vehicle.mode=off``), none otherwise."""
    return {"vehicle": VehicleConstraint()} if platform == "vehicle" else {}


def body_velocity_jacobians(q: Tensor, v: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(v_b, ∂v_b/∂v (3, 3), ∂v_b/∂q (3, 4))`` of the body-frame velocity ``v_b = C(q)ᵀ v``."""
    q_conj = quat.conjugate(q)
    v_b = quat.rotate(q_conj, v)
    d_v = quat.to_matrix(q).transpose(-1, -2)
    d_q = quat.rotate_jacobian(q_conj, v) * _flip(q.dtype, q.device)  # ∂conj(q)/∂q = diag(1, -1, -1, -1)
    return v_b, d_v, d_q


@dataclass(frozen=True)
class VehicleUpdate(RowBatchEvent):
    """One non-holonomic pseudo-measurement at ``time_s`` (module docstring)."""

    time_s: float
    settings: VehicleSettings
    name: str = "vehicle constraint"

    def batch_key(self) -> Hashable:
        """Updates with the same settings (one run's, or one config's for a batch) act together."""
        return (VehicleUpdate, id(self.settings))

    @classmethod
    def apply_batch(cls, chain: BatchChain, rows: Sequence[int], events: Sequence[VehicleUpdate]) -> None:
        """The pseudo-measurements ``events[i]`` (one settings) on the rows ``rows[i]``, as one update."""
        settings = events[0].settings
        mean, _ = chain.newest(rows)
        r, D = mean.shape
        E = _rows(settings.forward_axis, settings.up_axis, mean.dtype, mean.device)
        v_b, d_v, d_q = body_velocity_jacobians(mean[:, STATE.q], mean[:, STATE.v])
        H = mean.new_zeros(r, 1, 2, D)
        H[:, 0, :, STATE.v] = E @ d_v
        H[:, 0, :, STATE.q] = E @ d_q
        sigma = torch.stack([scalar_like(s, mean) for s in (settings.lateral_sigma_mps, settings.vertical_sigma_mps)])
        update_rows(chain, rows, H=H, residual=-(v_b @ E.T).unsqueeze(1),
                    noise_cov=torch.diag_embed(sigma**2).expand(r, 1, 2, 2), likelihood=False,
                    infos=[{"kind": "vehicle", "name": e.name} for e in events])


@cached_constant
def _rows(forward_axis: str, up_axis: str, dtype: torch.dtype, device: torch.device) -> Tensor:
    """:meth:`VehicleSettings.rows` of these axes in ``dtype`` on ``device``, built once."""
    return VehicleSettings(forward_axis=forward_axis, up_axis=up_axis).rows().to(dtype=dtype, device=device)


@cached_constant
def _flip(dtype: torch.dtype, device: torch.device) -> Tensor:
    return torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=dtype, device=device)


def vehicle_events(stream: VehicleConstraint, settings: VehicleSettings, context: NavigationContext) -> list:
    """A :class:`VehicleUpdate` every ``1 / rate_hz`` s after the start (none with ``mode=off``)."""
    if settings.mode == "off":
        return []
    step = 1.0 / settings.rate_hz
    times = torch.arange(context.t_start_s + step, context.t_end_s + 1e-9, step, dtype=torch.float64).tolist()
    return [VehicleUpdate(t, settings) for t in times]


register(MeasurementKind("vehicle", VehicleSettings, vehicle_events, default_stream=VehicleConstraint))
