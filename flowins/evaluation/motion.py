"""What a recording's GNSS fixes say about what carries the sensors.

A recording whose metadata names no platform gets no vehicle constraint
(``filter.measurements.vehicle.mode=auto``), yet on a car drive the constraint is what holds the
filter's heading (docs/model.md, "The vehicle constraint"). :func:`vehicle_like` looks at the
fixes alone: their horizontal speed over stretches of at least ``span_s``, and calls the motion
vehicle-like when the median of those speeds is at least ``min_speed_mps`` over at least
``min_duration_s``: a car or a bicycle, not a walker or a runner. Two fixes with white noise
of ``σ`` per axis are about ``2σ`` apart with no motion at all, so a stretch is also at least
``8 σ / min_speed_mps`` long (``σ`` the fixes' median reported ``h_acc``): the fixes' noise
then adds at most a quarter of ``min_speed_mps``. A drone that flies as fast looks the same,
so the jobs only name the constraint as something to try.
"""
from __future__ import annotations

from typing import NamedTuple

import torch

from flowins.data.streams import GnssStream
from flowins.geometry.geodesy import LocalTangentPlane


class VehicleLike(NamedTuple):
    """The motion that made :func:`vehicle_like` say yes."""

    median_speed_mps: float  # the median horizontal speed over the stretches
    distance_m: float  # the horizontal distance the stretches cover
    duration_s: float  # the time the fixes span


def vehicle_like(gnss: GnssStream, *, span_s: float = 5.0, min_speed_mps: float = 5.0,
                 min_duration_s: float = 60.0) -> VehicleLike | None:
    """:class:`VehicleLike` when the fixes move like a wheeled vehicle (see the module doc), else
    None (also for fewer than three fixes or fixes spanning less than ``min_duration_s``)."""
    t = torch.as_tensor(gnss.t_s, dtype=torch.float64)
    if t.shape[0] < 3 or float(t[-1] - t[0]) < min_duration_s:
        return None
    enu = LocalTangentPlane.at_first(gnss.lat_deg, gnss.lon_deg, gnss.alt_m).to_enu(gnss.lat_deg, gnss.lon_deg,
                                                                                       gnss.alt_m)
    span = max(span_s, 8.0 * float(torch.as_tensor(gnss.h_acc_m, dtype=torch.float64).median()) / min_speed_mps)
    # each fix paired with the first fix at least a span later
    later = torch.searchsorted(t, t + span).clamp_max(t.shape[0] - 1)
    pairs = (t[later] - t) >= span
    if int(pairs.sum()) < 2:
        return None
    start, end = torch.nonzero(pairs).squeeze(-1), later[pairs]
    step = torch.linalg.vector_norm(enu[end, :2] - enu[start, :2], dim=-1)
    speed = step / (t[end] - t[start])
    median = float(speed.median())
    if median < min_speed_mps:
        return None
    # the distance along the fixes, one stretch after another
    path = torch.linalg.vector_norm(torch.diff(enu[:, :2], dim=0), dim=-1)
    return VehicleLike(median, float(path.sum()), float(t[-1] - t[0]))


def describe_vehicle_like(motion: VehicleLike) -> str:
    """One line for a job's output: what the fixes show and what to try."""
    return (f"hint: the GNSS fixes move like a wheeled vehicle's (median {motion.median_speed_mps:.1f} m/s over "
            f"{motion.duration_s:.0f} s, {motion.distance_m / 1000:.1f} km). If the sensors ride one, "
            "platform: vehicle in the recording's metadata.yaml (or filter.measurements.vehicle.mode=on) adds the "
            "vehicle constraint, which holds the heading between fixes (docs/model.md, 'The vehicle constraint').")


def vehicle_hint(gnss: GnssStream | None, *, platform_named: bool, mode: str) -> str | None:
    """The jobs' hint for one recording: when its metadata names no platform, the vehicle
    constraint is left to ``mode=auto`` and its fixes move like a vehicle's; else None."""
    if gnss is None or platform_named or mode != "auto":
        return None
    motion = vehicle_like(gnss)
    return None if motion is None else describe_vehicle_like(motion)
