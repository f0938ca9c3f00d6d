"""The evaluation job: run each fusion combination on a recording and report Table I.

``recording -> flow pairs (cached) -> navigate per combination -> metrics, plots``. For
every combination: the EKF and the RTS smoother, their RMSE after Procrustes (rotation +
translation) alignment to the ground truth, a Fig. 5 style PNG, TUM trajectories and one
JSON of all metrics; plus the Fig. 2 flow panel for a few frame pairs. The steps live in
the package (:mod:`flowins.settings`, :mod:`flowins.data.load`, :mod:`flowins.flow.load`,
:mod:`flowins.navigation`, :mod:`flowins.evaluation`); this module strings them together
and writes what they return.
"""
from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from flowins.config import instantiate
from flowins.data.load import Recording, load_recording
from flowins.evaluation import plot_trajectory, trajectory_errors, write_tum
from flowins.evaluation.gnss_floor import describe_gnss_floor, gnss_floor_metrics
from flowins.evaluation.metrics import truth_extent_problem
from flowins.evaluation.report import Row, format_table
from flowins.flow.load import load_flow
from flowins.flow.pairs import FlowPairs, read_frame, run_provider
from flowins.ins.imu_model import imu_model
from flowins.ins.initialization import forward_axis
from flowins.jobs.cli import console_logging
from flowins.measurements.flow import FlowCamera
from flowins.navigation import NavigationConfig, NavigationResult, flow_statistics, navigate, run_warnings
from flowins.settings import check_job_settings, navigation_config
from flowins.state import STATE

log = logging.getLogger("flowins")


def run(cfg: Mapping[str, Any]) -> list[Row]:
    """Run the job; returns the table rows (also printed and written to ``metrics.json``)."""
    console_logging()
    check_job_settings(cfg)
    out = Path(cfg["output_dir"])
    out.mkdir(parents=True, exist_ok=True)
    rec = _load(cfg)
    nav_cfg, cfg = _filter_config(cfg, rec)
    flows = _flows(cfg, rec)
    unscored = truth_extent_problem(rec.truth)  # a ground truth that can't score a track, or None
    if unscored:
        log.warning("warning: %s", unscored)
    rows, metrics = [], {}
    for name in cfg["combinations"]:
        row, metrics[name] = _combination(name, cfg, rec, nav_cfg, flows, out, unscored)
        rows.append(row)
    if cfg["plots"] and isinstance(flows.get("dense"), FlowPairs) and cfg["flow_panels"] > 0:
        flow_panels(rec, cfg, out, cfg["flow_panels"])
    _report(rows, metrics, cfg, rec, nav_cfg, unscored)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=float))
    log.info(f"\nwrote {out}/metrics.json, *.tum" + (", *.png" if cfg["plots"] else ""))
    for r in rows:
        if r.filter_rmse_m is not None and not math.isfinite(r.filter_rmse_m):
            raise RuntimeError(f"{r.name}: non-finite RMSE; see {out}")
    return rows


def _load(cfg: Mapping[str, Any]) -> Recording:
    t0 = time.perf_counter()
    rec = load_recording(cfg["sequence"], quick=cfg["quick"], progress=cfg["progress"])
    seq = rec.sequence
    n_gnss = 0 if rec.gnss is None else len(rec.gnss)
    n_frames = 0 if seq.frames is None else len(seq.frames)
    log.info(f"sequence: {rec.name}, {rec.imu.duration_s:.0f} s, {len(rec.imu)} IMU samples, {n_frames} camera frames, "
             f"{n_gnss} GNSS fixes, ground truth: {'yes' if rec.truth is not None else 'no'} "
             f"({time.perf_counter() - t0:.1f} s to load)")
    return rec


def _filter_config(cfg: Mapping[str, Any], rec: Recording) -> tuple[NavigationConfig, Mapping[str, Any]]:
    """The filter's settings: the IMU preset (its range checked against the readings), the
    ``filter`` group, and a ``train.py`` checkpoint's learned values when one is given."""
    imu = imu_model(cfg["imu"], recording=bool(cfg["sequence"].get("path")), sensor=rec.sequence.metadata.get("imu"))
    imu.check_readings(rec.imu)
    nav_cfg = navigation_config(cfg["filter"], imu)
    if cfg["model"].get("checkpoint"):
        from flowins.training.parameters import learned_settings

        nav_cfg, cfg = learned_settings(cfg["model"]["checkpoint"], nav_cfg, cfg)
    noise = nav_cfg.noise
    log.info(f"imu: {imu.name} ({imu.source or 'config'}): filter densities acc {float(noise.acc_noise):.3g} m/s²/√Hz, "
             f"gyro {float(noise.gyro_noise):.3g} rad/s/√Hz, walks {float(noise.acc_bias_walk):.3g} m/s³/√Hz, "
             f"{float(noise.gyro_bias_walk):.3g} rad/s²/√Hz")
    return nav_cfg, cfg


def _flows(cfg: Mapping[str, Any], rec: Recording) -> dict[str, FlowPairs | str]:
    """The sparse and dense flow pairs the combinations use (or why they can't be had)."""
    flows: dict[str, FlowPairs | str] = {}
    for kind in ("sparse", "dense"):
        if any(cfg["methods"][name][kind] for name in cfg["combinations"]):
            t1 = time.perf_counter()
            flows[kind] = load_flow(kind, rec, cfg, progress=cfg["progress"])
            if isinstance(flows[kind], FlowPairs):
                log.info(f"{kind} flow: {len(flows[kind])} frame pairs ({time.perf_counter() - t1:.1f} s)")
    return flows


def _combination(name: str, cfg: Mapping[str, Any], rec: Recording, nav_cfg: NavigationConfig,
                 flows: dict[str, FlowPairs | str], out: Path, unscored: str | None) -> tuple[Row, dict[str, Any]]:
    """One row of the table: navigate with the combination's sources, export, score."""
    m_cfg = cfg["methods"][name]
    sources = (bool(m_cfg["gnss"]), bool(m_cfg["sparse"]), bool(m_cfg["dense"]))
    reason = "the sequence has no GNSS" if sources[0] and rec.gnss is None else None
    flow = None
    for kind, used in (("sparse", sources[1]), ("dense", sources[2])):
        if used:
            flow = flows[kind]
            if isinstance(flow, str):
                reason = flow
    if reason is not None:
        return Row(name, sources, None, None, f"not applicable: {reason}"), {"status": "not applicable", "reason": reason}
    t1 = time.perf_counter()
    seq = rec.sequence
    calibration = seq.imu_to_camera
    forward_b = forward_axis(nav_cfg.start.moving.forward_axis, None if calibration is None else calibration.rotation_matrix)
    result = navigate(rec.imu, rec.gnss if sources[0] else None, config=nav_cfg, flow=flow,
                      camera=FlowCamera.from_sequence(seq) if flow is not None else None, truth=rec.truth,
                      forward_b=forward_b, start_gnss=rec.gnss, progress=cfg["progress"])
    m = _export(out, name, result, rec, plots=cfg["plots"], score=rec.truth is not None and unscored is None)
    if flow is not None:
        m.update(flow_statistics(result, flow))
    m["seconds"] = time.perf_counter() - t1
    m["warnings"] = run_warnings(result) + ([unscored] if unscored else [])
    note = ("no ground truth: TUM tracks only" if rec.truth is None else
            "the ground truth does not move: TUM tracks only" if unscored else "")
    fr = "n/a" if m["filter_rmse_m"] is None else f"{m['filter_rmse_m']:.2f} m"
    log.info(f"  {name:<16} filter RMSE {fr} ({m['seconds']:.1f} s); {result.start.describe()}")
    for entry in m.get("heading_alignment", []):
        if entry["status"] == "never set":
            log.info(f"  {'':<16} GNSS: {entry['fixes']} fixes held for the heading to the end: {entry['reason']}")
    return Row(name, sources, m["filter_rmse_m"], m["smoother_rmse_m"], note, seconds=m["seconds"]), m


def _export(out: Path, name: str, result: NavigationResult, rec: Recording, *, plots: bool, score: bool
            ) -> dict[str, Any]:
    """Write the TUM tracks (and, with ``plots`` and a ground truth that can ``score`` them, the
    figure); the row's metrics."""
    metrics: dict[str, Any] = {}
    tracks = {}
    # the filter's nodes before a heading alignment are re-expressed in the aligned frame
    # (FilterTrack.in_final_frame): one frame per track, as the smoother's
    for kind, track in (("filter", result.filter.in_final_frame()), ("smoother", result.smoother)):
        pos, q = track.mean[:, STATE.p], track.mean[:, STATE.q]
        write_tum(out / f"{name}_{kind}.tum", track.t, pos, q)
        if not score:
            metrics[f"{kind}_rmse_m"] = None
            continue
        err = trajectory_errors(track.t, pos, rec.truth.t_s, rec.truth.pos_m, align="se3")
        metrics[f"{kind}_rmse_m"] = err.rmse_m
        metrics[f"{kind}_num_associated"] = err.num_associated
        tracks[kind] = (err.t_s, err.aligned_est)
    metrics.update(result.summary())
    if plots and score:
        # GNSS is plotted in the frame the aligned tracks live in (the truth's)
        plot_trajectory(
            out / f"{name}.png",
            ground_truth_m=rec.truth.pos_m,
            tracks=tracks,
            gnss_m=result.gnss_enu_m,
            gnss_radius_m=None if result.gnss_enu_m is None else result.gnss_h_acc_m,
            title=f"{name}: filter {metrics['filter_rmse_m']:.2f} m, smoother {metrics['smoother_rmse_m']:.2f} m RMSE",
        )
    return metrics


def flow_panels(rec: Recording, cfg: Mapping[str, Any], out: Path, count: int) -> list[Path]:
    """The paper's Fig. 2 (frames, Δu, Δv, σ) for ``count`` frame pairs spread over the recording."""
    from flowins.flow.visualize import flow_panel

    frames = rec.sequence.frames
    step = int(cfg["flow_pairs"]["step"])
    provider = instantiate(cfg["flow"], "flow")
    paths = []
    n = len(frames) - step
    for i in torch.linspace(0.2 * n, 0.8 * n, count).round().long().tolist():
        a, b = read_frame(frames, i), read_frame(frames, i + step)
        result = run_provider(provider, a[None], b[None], float(cfg["flow_pairs"]["input_scale"]))
        t = float(frames.t_s[i])
        paths.append(flow_panel(a, b, result.flow[0], result.sigma[0], out / f"flow_panel_{i:06d}.png",
                                title=f"{rec.name}: frames {i} -> {i + step} (t = {t:.1f} s)"))
    return paths


def _report(rows: list[Row], metrics: dict[str, Any], cfg: Mapping[str, Any], rec: Recording,
            nav_cfg: NavigationConfig, unscored: str | None) -> None:
    """Print the table, how the filter started, the warnings and the GNSS floor (into ``metrics``)."""
    log.info("\nRMSE after Procrustes alignment (rotation + translation) to the ground truth\n")
    log.info(format_table(rows))
    starts = {m["start"]["mode"] for m in metrics.values() if isinstance(m, dict) and "start" in m}
    if starts:
        log.info(f"\nstart: {', '.join(sorted(starts))} (filter.init.mode={nav_cfg.start.mode}; per row in metrics.json)")
    warned = [(n, w) for n, m in metrics.items() if isinstance(m, dict) for w in m.get("warnings", [])]
    if warned:
        log.info("\nwarnings:")
        for n, w in warned:
            log.info(f"  {n}: {w}")
    uses_gnss = any(cfg["methods"][name]["gnss"] for name in cfg["combinations"])
    if uses_gnss and rec.gnss is not None and rec.truth is not None and not unscored and len(rec.gnss) >= 3:
        try:
            metrics["gnss_floor"] = gnss_floor_metrics(rec.gnss, rec.truth)
            log.info("\n" + describe_gnss_floor(metrics["gnss_floor"]))
        except ValueError as error:  # e.g. too few fixes inside the truth's time span: reported, not fatal
            metrics["gnss_floor"] = {"status": "not computed", "reason": str(error)}
            log.info(f"\nGNSS floor not computed: {error}")
    if rec.warnings:
        metrics["input_warnings"] = rec.warnings
