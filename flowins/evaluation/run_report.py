"""What a filter run did, for the evaluate job's table and ``metrics.json``: its flow and track
statistics and the warnings a reader of the table must know (read from the run's log)."""
from __future__ import annotations

import math
from collections.abc import Sized
from typing import Any, Protocol

import torch

from flowins.state import STATE


class RunLog(Protocol):
    """What the report reads of a run (a :class:`~flowins.navigation.NavigationResult`)."""

    filter: Any  # FilterTrack: log, node_cov, t_s
    flow_pairs_outside: int
    gnss_before_start: int
    start: Any  # Start: t_s, as_dict()
    smoother_pass: dict[str, Any] | None
    vehicle_mounting: dict[str, Any] | None

    @property
    def flow_log(self) -> list[dict]: ...

    @property
    def gnss_accepted(self) -> Any: ...  # (G,) tensor of 0/1, or None

    @property
    def heading_status(self) -> list[dict]: ...


def run_summary(result: RunLog) -> dict[str, Any]:
    """What the run did, for ``metrics.json``: GNSS fixes accepted, how it started, its
    GNSS resets, fixes before the start, the heading alignment, which pass the smoother
    ran on and the vehicle constraint's fitted mounting (each when present)."""
    out: dict[str, Any] = {}
    if result.gnss_accepted is not None:
        out["gnss_accepted"] = int(result.gnss_accepted.sum())
        out["gnss_fixes"] = int(result.gnss_accepted.numel())
    if result.start is not None:
        out["start"] = result.start.as_dict()
    resets = [{k: v for k, v in e.items() if k != "kind"} for e in result.filter.log if e.get("kind") == "gnss_reset"]
    if resets:
        out["gnss_resets"] = resets
    if result.gnss_before_start:
        out["gnss_before_start"] = result.gnss_before_start
    heading = [{k: v for k, v in e.items() if k not in ("kind", "name", "fit")} for e in result.heading_status]
    if heading:
        out["heading_alignment"] = heading  # filter.gnss_heading: when and how the heading was set (or given up)
    if result.smoother_pass is not None:
        out["smoother_pass"] = result.smoother_pass
    if result.vehicle_mounting is not None:
        out["vehicle_mounting"] = result.vehicle_mounting  # filter.measurements.vehicle.mounting=fit
    return out


def mounting_line(record: dict[str, Any]) -> str:
    """One line on the vehicle constraint's fitted mounting (``filter.measurements.vehicle.mounting=fit``)."""
    if "mount_yaw_rad" not in record:
        return f"vehicle mounting not fitted: {record['reason']}"
    lever = ", ".join(f"{x:.2f}" for x in record["lever_m"])
    return (f"vehicle mounting {'fitted' if record['used'] else 'fitted, not used'}: pitch "
            f"{math.degrees(record['mount_pitch_rad']):.2f}°, yaw {math.degrees(record['mount_yaw_rad']):.2f}°, "
            f"lever arm ({lever}) m; {record['reason']}")


def flow_statistics(result: RunLog, pairs: Sized) -> dict[str, Any]:
    """How the flow fared in a run: frames, points per frame, accepted, left out."""
    log = result.flow_log
    frames = [e for e in log if e["points"]]
    n = max(1, len(frames))
    return {
        "flow_frames": len(frames),
        "flow_pairs": len(pairs),
        "flow_pairs_outside_imu": result.flow_pairs_outside,
        "mean_candidates": sum(e["candidates"] for e in frames) / n,
        "mean_points": sum(e["points"] for e in frames) / n,
        "mean_valid": sum(e["valid"] for e in frames) / n,
        "mean_accepted": sum(e["accepted"] for e in frames) / n,
        "mean_low_parallax": sum(e["low_parallax"] for e in frames) / n,
        "mean_degenerate": sum(e["degenerate"] + e["behind"] for e in frames) / n,
    }


def track_statistics(result: RunLog) -> dict[str, Any]:
    """How the multi-view track update fared in a run: frames, tracks used per frame (of those
    complete there), valid, accepted, left out."""
    log = [entry for entry in result.filter.log if entry.get("kind") == "tracks"]
    n = max(1, len(log))
    return {
        "track_frames": len(log),
        "mean_tracks": sum(e["tracks"] for e in log) / n,
        "mean_candidates": sum(e["candidates"] for e in log) / n,
        "mean_valid": sum(e["valid"] for e in log) / n,
        "mean_accepted": sum(e.get("accepted", 0.0) for e in log) / n,
        "mean_low_parallax": sum(e["low_parallax"] for e in log) / n,
        "mean_degenerate": sum(e["degenerate"] + e["behind"] for e in log) / n,
    }


def run_warnings(result: RunLog) -> list[str]:
    """What a reader of the table must know about a run: GNSS resets, flow inflations, an
    unbounded position σ (inertial drift), most fixes rejected, a filter that ends rejecting
    the fixes (inconsistent), fixes before the start."""
    warnings = []
    log = result.filter.log
    resets = [e for e in log if e.get("kind") == "gnss_reset"]
    if resets:
        worst = max(resets, key=lambda e: e["offset_m"])
        rejected = sum(e["why"] == "rejected" for e in resets)
        why = ", ".join(part for part in (f"{rejected} after rejected fixes" if rejected else "",
                                          f"{len(resets) - rejected} after inconsistent innovations"
                                          if len(resets) > rejected else "") if part)
        warnings.append(f"GNSS: the filter drifted from the fixes and was reset {len(resets)} time(s) ({why}; largest "
                        f"jump {worst['offset_m']:.1f} m at {worst['t_s']:.1f} s; filter.gnss_recovery)")
    inflated = [e for e in log if e.get("kind") == "flow" and e.get("inflated")]
    if inflated:
        warnings.append(f"flow: {len(inflated)} time(s) most points of {inflated[0]['gated_frames']} frames in a row failed "
                        f"the gate (first at {inflated[0]['t_s']:.1f} s); the velocity and gyroscope bias σ were "
                        "inflated to let the flow back in (filter.flow.recovery)")
    sigma = result.filter.node_cov[:, STATE.p, STATE.p].diagonal(dim1=-2, dim2=-1)[:, :2].sum(-1).sqrt()
    heading = [e for e in log if e.get("kind") == "heading" and e.get("status") in ("aligned", "given up")]
    first = 0
    if heading:  # until the fixes set a free heading (or are applied as they come), its σ of π
        first = int(torch.searchsorted(result.filter.t_s, heading[0]["t_s"]))  # spreads the position: no drift
        if heading[0]["status"] == "given up":
            warnings.append(f"GNSS heading: the held fixes did not set the free heading; given up at "
                            f"{heading[0]['t_s']:.1f} s ({heading[0].get('reason', 'no reason logged')}; "
                            "filter.gnss_heading)")
    sigma = sigma[first:]
    if sigma.numel() and float(sigma.max()) > 100.0:
        worst = int(sigma.argmax())
        k = first + worst
        warnings.append(f"the filter's own horizontal position σ reaches {float(sigma[worst]):.0f} m (at "
                        f"{float(result.filter.t_s[k]):.0f} s): nothing bounds the position there, the error is "
                        "inertial drift")
    fixes = [e for e in log if e.get("kind") == "gnss" and "nis" in e]
    if fixes:
        rejected = sum(e["accepted"] < 0.5 for e in fixes)
        if rejected > len(fixes) / 2:
            warnings.append(f"GNSS: {rejected} of {len(fixes)} fixes failed the gate: the filter disagrees with them "
                            "(filter.gnss_gate, imu noise)")
        tail = fixes[-10:]
        if len(tail) >= 3 and sum(e["accepted"] < 0.5 for e in tail) > len(tail) / 2:
            warnings.append(f"GNSS: the run ends inconsistent: {sum(e['accepted'] < 0.5 for e in tail)} of the last "
                            f"{len(tail)} fixes failed the gate")
    if result.flow_pairs_outside:
        warnings.append(f"flow: {result.flow_pairs_outside} frame pairs outside the filter's span (its start at "
                        f"{result.start.t_s:.2f} s to the IMU's last sample) are not used")
    if result.gnss_before_start:
        warnings.append(f"GNSS: {result.gnss_before_start} fixes before the filter's start "
                        f"({result.start.t_s:.2f} s) are not used")
    return warnings
