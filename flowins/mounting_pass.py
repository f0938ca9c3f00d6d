"""The vehicle constraint's mounting, fitted in a first pass (``filter.measurements.vehicle.mounting=fit``).

A constraint that assumes the IMU's axes are the car's where they are not turns the track
(docs/model.md, "The vehicle constraint"). With ``mounting=fit`` the runs that use the
constraint are navigated first without it; :func:`~flowins.measurements.vehicle.fit_mounting`
finds each run's mounting and lever arm on that pass's smoothed track, and each run's stream
carries its fit into the constraint's events, where the fit explains the track (its residual
falls to ``fit_max_residual`` of its start or less). Elsewhere the settings' mounting stays and
the record says why.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any

import torch

from flowins.measurements.vehicle import VehicleConstraint, VehicleSettings, fit_mounting, gyro_at


def _uses_constraint(run: Any, settings: VehicleSettings) -> bool:
    return settings.mode == "on" or (settings.mode == "auto" and "vehicle" in run.streams)


def fit_mountings(runs: Sequence[Any], config: Any, navigate_runs: Callable[..., list]
                  ) -> tuple[list[Any], list[dict[str, Any] | None]]:
    """``(runs, records)``: the runs (:class:`~flowins.navigation.NavigationRun`) with their fitted
    mounting in their ``vehicle`` stream where it is used, and per run what the fit found
    (``{"used", "reason", "mount_pitch_rad", "mount_yaw_rad", "lever_m", "residual_mps", "samples"}``;
    None where no fit was asked for). ``navigate_runs(runs, config=)`` runs the first pass."""
    settings = config.measurements.get("vehicle")
    records: list[dict[str, Any] | None] = [None] * len(runs)
    if settings is None or settings.mounting != "fit":
        return list(runs), records
    which = [i for i, run in enumerate(runs) if _uses_constraint(run, settings)]
    if not which:
        return list(runs), records
    off = dataclasses.replace(config, measurements={**config.measurements,
                                                    "vehicle": dataclasses.replace(settings, mode="off")})
    with torch.no_grad():
        first = navigate_runs([runs[i] for i in which], config=off)
    out = list(runs)
    for i, result in zip(which, first):
        run, smoothed = runs[i], result.smoother
        t = torch.as_tensor(smoothed.t_s, dtype=torch.float64)
        try:
            fit = fit_mounting(smoothed.node_mean, gyro_at(run.imu.t_s, run.imu.gyro_rps, t),
                               forward_axis=settings.forward_axis, up_axis=settings.up_axis)
        except ValueError as error:
            records[i] = {"used": False, "reason": str(error)}
            continue
        used = fit.explains <= settings.fit_max_residual
        reason = (f"the fit takes the constraint's residual on the first pass's smoothed track from "
                  f"{fit.rms_before_mps:.3f} to {fit.rms_after_mps:.3f} m/s")
        if not used:
            reason += (f", more than filter.measurements.vehicle.fit_max_residual={settings.fit_max_residual:g} "
                       "of it: the track does not show the mounting (its heading is not good enough); "
                       "the configured mounting stays")
        records[i] = {"used": used, "reason": reason, **fit.as_dict()}
        if used:
            out[i] = dataclasses.replace(run, streams={**run.streams, "vehicle": VehicleConstraint(mounting=fit)})
    return out, records
