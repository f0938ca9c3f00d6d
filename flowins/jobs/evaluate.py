"""The evaluation job: run each fusion combination on a sequence and report Table I.

For every combination: the EKF and the RTS smoother, their RMSE after
Procrustes (rotation + translation) alignment to the ground truth, a Fig. 5
style PNG, TUM trajectories and one JSON of all metrics.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import torch

from flowins.data.streams import GnssStream, ImuStream, PoseStream
from flowins.data.synthetic import Recording, synthetic_walk_recording
from flowins.evaluation import plot_trajectory, trajectory_errors, write_tum
from flowins.filter.ekf import Gate
from flowins.ins.initialization import InitialUncertainty
from flowins.ins.mechanization import ProcessNoise
from flowins.navigation import NavigationConfig, NavigationResult, navigate
from flowins.state import STATE

#: Table I rows: name -> (uses GNSS, uses sparse flow, uses dense flow)
COMBINATIONS: dict[str, tuple[bool, bool, bool]] = {
    "ins": (False, False, False),
    "ins_gnss": (True, False, False),
    "ins_sparse": (False, True, False),
    "ins_dense": (False, False, True),
    "ins_gnss_sparse": (True, True, False),
    "ins_gnss_dense": (True, False, True),
}

_DTYPES = {"float64": torch.float64, "float32": torch.float32}


def navigation_config(cfg: Mapping[str, Any]) -> NavigationConfig:
    """:class:`NavigationConfig` from the ``filter`` config group."""
    if cfg["dtype"] not in _DTYPES:
        raise ValueError(f"filter.dtype must be one of {list(_DTYPES)}, got {cfg['dtype']!r}")
    return NavigationConfig(
        noise=ProcessNoise(
            acc_noise=cfg["acc_noise"],
            gyro_noise=cfg["gyro_noise"],
            acc_bias_walk=cfg["acc_bias_walk"],
            gyro_bias_walk=cfg["gyro_bias_walk"],
            acc_scale_walk=cfg["acc_scale_walk"],
            discretization=cfg["discretization"],
        ),
        initial=InitialUncertainty(**dict(cfg["initial"])),
        stationary_s=cfg["stationary_s"],
        initial_yaw_rad=cfg["initial_yaw_rad"],
        gnss_gate=Gate(mode=cfg["gnss_gate"]["mode"], probability=cfg["gnss_gate"]["probability"]),
        gnss_noise_scale=cfg["gnss_noise_scale"],
        output_every=cfg["output_every"],
        scheme=cfg["scheme"],
        gravity_mps2=cfg["gravity_mps2"],
        jacobians=cfg["jacobians"],
        dtype=_DTYPES[cfg["dtype"]],
    )


@dataclass
class EvalInputs:
    """What the job evaluates: IMU, optional GNSS and optional ground truth."""

    name: str
    imu: ImuStream
    gnss: GnssStream | None
    truth: PoseStream | None


def load_sequence(cfg: Mapping[str, Any], *, quick: bool) -> EvalInputs:
    """``sequence.path=DIR`` reads a recording (flowins folder, EuRoC, ADVIO); otherwise
    the built-in simulated walk of ``sequence.kind``."""
    if cfg.get("path"):
        from flowins.data.read import read_sequence

        seq = read_sequence(cfg["path"])
        return EvalInputs(seq.name, seq.imu, seq.gnss, seq.groundtruth)
    if cfg["kind"] != "synthetic_walk":
        raise ValueError(
            f"sequence.kind={cfg['kind']!r} is not supported; use the built-in 'synthetic_walk' "
            "or give a recording with sequence.path=DIR"
        )
    rec: Recording = synthetic_walk_recording(
        duration_s=60.0 if quick else float(cfg["duration_s"]),
        seed=int(cfg["seed"]),
        imu_rate_hz=float(cfg["imu_rate_hz"]),
        gnss_rate_hz=float(cfg["gnss_rate_hz"]),
    )
    return EvalInputs(rec.imu.name, rec.imu, rec.gnss, rec.truth)


@dataclass
class Row:
    name: str
    sources: tuple[bool, bool, bool]
    filter_rmse_m: float | None
    smoother_rmse_m: float | None
    note: str = ""
    seconds: float = 0.0


def format_table(rows: list[Row]) -> str:
    """The Table I analogue as fixed-width text."""
    tick = lambda b: "x" if b else " "  # noqa: E731
    lines = [
        f"{'#':>2}  {'combination':<16} {'INS':^4} {'GNSS':^5} {'sparse':^7} {'dense':^6} {'filter RMSE':>12} {'smoother RMSE':>14}",
        "-" * 74,
    ]
    for i, r in enumerate(rows, 1):
        f = "n/a" if r.filter_rmse_m is None else f"{r.filter_rmse_m:.2f} m"
        s = "n/a" if r.smoother_rmse_m is None else f"{r.smoother_rmse_m:.2f} m"
        g, sp, d = r.sources
        lines.append(
            f"{i:>2}  {r.name:<16} {tick(True):^4} {tick(g):^5} {tick(sp):^7} {tick(d):^6} {f:>12} {s:>14}"
            + (f"   ({r.note})" if r.note else "")
        )
    return "\n".join(lines)


def _export(out: Path, name: str, result: NavigationResult, rec: EvalInputs, plots: bool) -> dict[str, Any]:
    metrics: dict[str, Any] = {}
    tracks = {}
    for kind, track in (("filter", result.filter), ("smoother", result.smoother)):
        pos, q = track.mean[:, STATE.p], track.mean[:, STATE.q]
        write_tum(out / f"{name}_{kind}.tum", track.t, pos, q)
        if rec.truth is None:
            metrics[f"{kind}_rmse_m"] = None
            continue
        err = trajectory_errors(track.t, pos, rec.truth.t_s, rec.truth.pos_m, align="se3")
        metrics[f"{kind}_rmse_m"] = err.rmse_m
        metrics[f"{kind}_num_associated"] = err.num_associated
        tracks[kind] = (err.t_s, err.aligned_est)
    if result.gnss_accepted is not None:
        metrics["gnss_accepted"] = int(result.gnss_accepted.sum())
        metrics["gnss_fixes"] = int(result.gnss_accepted.numel())
    if plots and rec.truth is not None:
        gnss = radius = None
        if result.gnss_enu_m is not None:
            # GNSS is plotted in the frame the aligned tracks live in (the truth's)
            gnss, radius = result.gnss_enu_m, result.gnss_h_acc_m
        plot_trajectory(
            out / f"{name}.png",
            ground_truth_m=rec.truth.pos_m,
            tracks=tracks,
            gnss_m=gnss,
            gnss_radius_m=radius,
            title=f"{name}: filter {metrics['filter_rmse_m']:.2f} m, smoother {metrics['smoother_rmse_m']:.2f} m RMSE",
        )
    return metrics


def run(cfg: Mapping[str, Any]) -> list[Row]:
    """Run the job; returns the table rows (also printed and written to ``metrics.json``)."""
    out = Path(cfg["output_dir"])
    out.mkdir(parents=True, exist_ok=True)
    nav_cfg = navigation_config(cfg["filter"])
    quick = bool(cfg.get("quick", False))
    t0 = time.perf_counter()
    rec = load_sequence(cfg["sequence"], quick=quick)
    n_gnss = 0 if rec.gnss is None else len(rec.gnss)
    print(f"sequence: {rec.name}, {rec.imu.duration_s:.0f} s, {len(rec.imu)} IMU samples, "
          f"{n_gnss} GNSS fixes, ground truth: {'yes' if rec.truth is not None else 'no'} "
          f"({time.perf_counter() - t0:.1f} s to load)")
    rows, metrics = [], {}
    for name in cfg["combinations"]:
        if name not in COMBINATIONS:
            raise ValueError(f"unknown combination {name!r}; expected one of {list(COMBINATIONS)}")
        sources = COMBINATIONS[name]
        if sources[1] or sources[2]:
            rows.append(Row(name, sources, None, None, "optical flow: not in this release"))
            metrics[name] = {"status": "not available"}
            continue
        if sources[0] and rec.gnss is None:
            rows.append(Row(name, sources, None, None, "not applicable: the sequence has no GNSS"))
            metrics[name] = {"status": "not applicable", "reason": "no GNSS"}
            continue
        t1 = time.perf_counter()
        result = navigate(rec.imu, rec.gnss if sources[0] else None, config=nav_cfg, progress=bool(cfg.get("progress")))
        m = _export(out, name, result, rec, bool(cfg.get("plots", True)))
        m["seconds"] = time.perf_counter() - t1
        metrics[name] = m
        note = "" if rec.truth is not None else "no ground truth: TUM tracks only"
        rows.append(Row(name, sources, m["filter_rmse_m"], m["smoother_rmse_m"], note, seconds=m["seconds"]))
    table = format_table(rows)
    print("\nRMSE after Procrustes alignment (rotation + translation) to the ground truth\n")
    print(table)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=float))
    print(f"\nwrote {out}/metrics.json, *.tum" + (", *.png" if cfg.get("plots", True) else ""))
    for r in rows:
        if r.filter_rmse_m is not None and not math.isfinite(r.filter_rmse_m):
            raise RuntimeError(f"{r.name}: non-finite RMSE; see {out}")
    return rows
