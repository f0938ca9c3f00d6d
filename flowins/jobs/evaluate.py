"""The evaluation job: run each fusion combination on a recording and report Table I.

``recording -> flow pairs (cached) -> navigate each combination (the flow rows as one
batch) -> metrics, plots``. For every combination: the EKF and the RTS smoother, their RMSE
after Procrustes (rotation + translation) alignment to the ground truth, a Fig. 5 style
PNG, TUM trajectories and one JSON of all metrics; plus the Fig. 2 flow panel for a few
frame pairs. The steps live in the package (:mod:`flowins.settings`,
:mod:`flowins.data.load`, :mod:`flowins.flow.load`, :mod:`flowins.navigation`,
:mod:`flowins.evaluation`); this module strings them together and writes what they return.
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
from flowins.evaluation.drift import drift_metrics
from flowins.evaluation.gnss_floor import describe_gnss_floor, gnss_floor_metrics
from flowins.evaluation.metrics import truth_extent_problem
from flowins.evaluation.motion import vehicle_hint
from flowins.evaluation.report import Row, format_table
from flowins.data.sequence import Tracks
from flowins.flow.load import check_camera_mounting, load_flow, load_tracks, uses_tracks
from flowins.flow.pairs import FlowPairs, read_frame, run_provider
from flowins.ins.initialization import forward_axis
from flowins.jobs.cli import console_logging
from flowins.measurements.flow import FlowCamera
from flowins.measurements.vehicle import VehicleSettings, platform_streams
from flowins.batching import batch_workers
from flowins.evaluation.run_report import (flow_statistics, mounting_line, run_summary, run_warnings,
                                           track_statistics)
from flowins.navigation import NavigationConfig, NavigationResult, NavigationRun, navigate_batch
from flowins.settings import evaluate_settings, filter_setup
from flowins.state import STATE, STATE_DIM

log = logging.getLogger("flowins")


def run(cfg: Mapping[str, Any]) -> list[Row]:
    """Run the job; returns the table rows (also printed and written to ``metrics.json``).

    With ``sequence.seeds=[...]`` every combination runs on the simulated walk of each seed,
    all seeds in one batched filter pass, and the table gives the mean ± standard deviation
    over the seeds (each seed's tracks and metrics under ``seed_<n>/``)."""
    console_logging()
    settings = evaluate_settings(cfg)
    out = Path(cfg["output_dir"])
    out.mkdir(parents=True, exist_ok=True)
    seeds = settings.sequence.seeds
    if seeds is None:
        recs, outs = [_load(cfg)], [out]
    else:
        recs = [_load({**cfg, "sequence": {**cfg["sequence"], "seed": int(seed)}}) for seed in seeds]
        outs = [out / f"seed_{int(seed)}" for seed in seeds]
        for path in outs:
            path.mkdir(exist_ok=True)
    setup = filter_setup(cfg, recs, recorded=bool(settings.sequence.path), checkpoint=settings.model.checkpoint)
    log.info(setup.describe())
    if settings.uses("dense"):
        log.info(setup.describe_flow(cfg["flow"]))
    configured_flow, cfg = cfg["flow"], {**cfg, "flow": setup.flow}
    nav_cfg = setup.navigation
    flows = [_flows(cfg, rec) for rec in recs]
    if settings.sequence.check_mounting:
        for rec, rec_flows in zip(recs, flows):
            check_camera_mounting(rec, rec_flows)
    unscored = [truth_extent_problem(rec.truth) for rec in recs]  # a ground truth that can't score a track, or None
    for problem in dict.fromkeys(u for u in unscored if u):
        log.warning("warning: %s", problem)
    rows, metrics = _combinations(cfg, recs, nav_cfg, flows, outs, unscored, seeds)
    if cfg["plots"] and isinstance(flows[0].get("dense"), FlowPairs) and cfg["flow_panels"] > 0:
        flow_panels(recs[0], cfg, outs[0], cfg["flow_panels"])
    _report(rows, metrics, cfg, recs, nav_cfg, unscored, seeds)
    if setup.imu.name == "measured":  # noise measured from the recording itself: said under the table too
        log.info("\n" + setup.describe())
    metrics["imu"] = {"name": setup.imu.name, "source": setup.imu.source,
                      **{k: float(getattr(nav_cfg.noise, k)) for k in ("acc_noise", "gyro_noise", "acc_bias_walk",
                                                                       "gyro_bias_walk")}}
    if settings.uses("dense"):  # which flow the dense rows used, and whether it is the configured one
        metrics["dense_flow"] = {"provider": setup.flow, "as_configured": setup.flow == configured_flow}
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


def _flows(cfg: Mapping[str, Any], rec: Recording) -> dict[str, FlowPairs | Tracks | str]:
    """The sparse and dense flow pairs the combinations use (or why they can't be had); with
    ``filter.tracks.window >= 1`` the sparse rows get tracks over many frames instead."""
    flows: dict[str, FlowPairs | Tracks | str] = {}
    for kind in ("sparse", "dense"):
        if any(cfg["methods"][name][kind] for name in cfg["combinations"]):
            t1 = time.perf_counter()
            if kind == "sparse" and uses_tracks(cfg):
                flows[kind] = load_tracks(rec, cfg, progress=cfg["progress"])
                if isinstance(flows[kind], Tracks):
                    log.info(f"sparse tracks: {int(torch.unique(flows[kind].track_id).numel())} tracks over "
                             f"{len(flows[kind].frame_times)} frames for the multi-view update "
                             f"(window {cfg['filter']['tracks']['window']}; {time.perf_counter() - t1:.1f} s)")
                continue
            flows[kind] = load_flow(kind, rec, cfg, progress=cfg["progress"])
            if isinstance(flows[kind], FlowPairs):
                log.info(f"{kind} flow: {len(flows[kind])} frame pairs ({time.perf_counter() - t1:.1f} s)")
    return flows


def _combinations(cfg: Mapping[str, Any], recs: list[Recording], nav_cfg: NavigationConfig,
                  flows: list[dict[str, FlowPairs | str]], outs: list[Path], unscored: list[str | None],
                  seeds: list[int] | None) -> tuple[list[Row], dict[str, Any]]:
    """The table's rows: every combination on every recording, the flow rows in one batched
    filter pass (:func:`~flowins.navigation.navigate_batch`: each run as it runs alone, up to
    rounding; on a GPU one batch instead of one launch-bound run per row), then each row
    exported and scored; several recordings give the mean ± std over them."""
    planned = {name: _runs(name, cfg, recs, nav_cfg, flows) for name in cfg["combinations"]}
    # the batch steps its runs together from event to event, so runs whose events differ in
    # kind and rate would pad each other: the flow rows (one event per frame) form one batch,
    # every other row its own (its recordings together)
    batches: dict[str, list[str]] = {}
    for name, plan in planned.items():
        if isinstance(plan, list):
            batches.setdefault("flow" if plan[0].flow is not None else "tracks" if plan[0].tracks is not None
                               else name, []).append(name)
    results: dict[str, list[NavigationResult]] = {}
    seconds: dict[str, float] = {}
    for names in batches.values():
        runs = [run for name in names for run in planned[name]]
        t1 = time.perf_counter()
        done = iter(navigate_batch(runs, config=nav_cfg, progress=cfg["progress"]))
        wall = time.perf_counter() - t1
        for name in names:
            results[name], seconds[name] = [next(done) for _ in planned[name]], wall / len(runs)
        for line in dict.fromkeys(r.filter_steps for name in names for r in results[name] if r.filter_steps):
            log.info(f"  {', '.join(names)}: {line}")
        if len(names) > 1:
            workers = batch_workers(runs, nav_cfg)
            where = "one batched filter pass" if workers == 1 else f"batched filter passes in {workers} worker processes"
            log.info(f"  {', '.join(names)}: {len(runs)} runs in {where} on {nav_cfg.device}, {wall:.1f} s")
    rows, metrics = [], {}
    for name, plan in planned.items():
        if isinstance(plan, str):
            row, metrics[name] = (Row(name, _sources(cfg, name), None, None, f"not applicable: {plan}"),
                                  {"status": "not applicable", "reason": plan})
        else:
            row, metrics[name] = _score(name, cfg, recs, results[name], flows, outs, unscored, seeds, seconds[name])
        rows.append(row)
    return rows, metrics


def _sources(cfg: Mapping[str, Any], name: str) -> frozenset[str]:
    return frozenset(key for key, used in cfg["methods"][name].items() if used)


def _pairs(name: str, cfg: Mapping[str, Any], flows: list[dict[str, FlowPairs | str]]) -> list[FlowPairs | str | None]:
    """The flow pairs (or why there are none) of combination ``name`` on each recording."""
    sources = _sources(cfg, name)
    pairs: list[FlowPairs | str | None] = [None] * len(flows)
    for kind in ("sparse", "dense"):
        if kind in sources:
            pairs = [rec_flows[kind] for rec_flows in flows]
    return pairs


def _runs(name: str, cfg: Mapping[str, Any], recs: list[Recording], nav_cfg: NavigationConfig,
          flows: list[dict[str, FlowPairs | str]]) -> list[NavigationRun] | str:
    """The combination's :class:`NavigationRun` on each recording, or why it is not applicable."""
    sources = _sources(cfg, name)
    reason = "the sequence has no GNSS" if "gnss" in sources and any(rec.gnss is None for rec in recs) else None
    pairs = _pairs(name, cfg, flows)
    reason = next((p for p in pairs if isinstance(p, str)), reason)
    if reason is not None:
        return reason
    runs = []
    for rec, flow in zip(recs, pairs):
        calibration = rec.sequence.imu_to_camera
        forward_b = forward_axis(nav_cfg.start.moving.forward_axis,
                                 None if calibration is None else calibration.rotation_matrix)
        tracks = flow if isinstance(flow, Tracks) else None
        runs.append(NavigationRun(rec.imu, rec.gnss if "gnss" in sources else None,
                                  flow=None if tracks is not None else flow, tracks=tracks,
                                  camera=FlowCamera.from_sequence(rec.sequence) if flow is not None else None,
                                  truth=rec.truth, forward_b=forward_b, start_gnss=rec.gnss,
                                  streams=platform_streams(rec.platform)))
    return runs


def _score(name: str, cfg: Mapping[str, Any], recs: list[Recording], results: list[NavigationResult],
           flows: list[dict[str, FlowPairs | str]], outs: list[Path], unscored: list[str | None],
           seeds: list[int] | None, seconds_per_run: float) -> tuple[Row, dict[str, Any]]:
    """One row of the table from its results on every recording: export, score, log."""
    sources = _sources(cfg, name)
    per_run = []
    for rec, flow, result, out, problem in zip(recs, _pairs(name, cfg, flows), results, outs, unscored):
        m = _export(out, name, result, rec, plots=cfg["plots"], score=rec.truth is not None and problem is None)
        if isinstance(flow, Tracks):
            m.update(track_statistics(result))
        elif flow is not None:
            m.update(flow_statistics(result, flow))
        m["seconds"] = seconds_per_run
        m["warnings"] = run_warnings(result) + ([problem] if problem else [])
        per_run.append(m)
    rec, result = recs[0], results[0]
    note = ("no ground truth: TUM tracks only" if rec.truth is None else
            "the ground truth does not move: TUM tracks only" if unscored[0] else "")
    if seeds is None:
        m = per_run[0]
        fr = "n/a" if m["filter_rmse_m"] is None else f"{m['filter_rmse_m']:.2f} m"
        log.info(f"  {name:<16} filter RMSE {fr} ({m['seconds']:.1f} s)")
        for entry in m.get("heading_alignment", []):
            if entry["status"] == "never set":
                log.info(f"  {'':<16} GNSS: {entry['fixes']} fixes held for the heading to the end: {entry['reason']}")
        if mounting := m.get("vehicle_mounting"):
            log.info(f"  {'':<16} {mounting_line(mounting)}")
        return Row(name, sources, m["filter_rmse_m"], m["smoother_rmse_m"], note, seconds=m["seconds"],
                   start=result.start.describe() if result.start is not None else ""), m
    seconds = seconds_per_run * len(recs)
    summary: dict[str, Any] = {"seeds": [int(s) for s in seeds], "seconds": seconds}
    for kind in ("filter", "smoother"):
        values = [m[f"{kind}_rmse_m"] for m in per_run]
        mean, std = _mean_std(values)
        summary[f"{kind}_rmse_m"], summary[f"{kind}_rmse_std_m"] = mean, std
    summary["per_seed"] = {str(int(s)): m for s, m in zip(seeds, per_run)}
    fr = "n/a" if summary["filter_rmse_m"] is None else \
        f"{summary['filter_rmse_m']:.2f} ± {summary['filter_rmse_std_m']:.2f} m"
    log.info(f"  {name:<16} filter RMSE {fr} over {len(seeds)} seeds ({seconds:.1f} s for all)")
    return Row(name, sources, summary["filter_rmse_m"], summary["smoother_rmse_m"], note, seconds=seconds,
               filter_std_m=summary["filter_rmse_std_m"], smoother_std_m=summary["smoother_rmse_std_m"]), summary


def _mean_std(values: list[float | None]) -> tuple[float | None, float | None]:
    """Mean and sample standard deviation (n - 1) of the values; None if any is None."""
    if any(v is None for v in values):
        return None, None
    x = torch.tensor(values, dtype=torch.float64)
    return float(x.mean()), float(x.std()) if len(values) > 1 else 0.0


def _export(out: Path, name: str, result: NavigationResult, rec: Recording, *, plots: bool, score: bool
            ) -> dict[str, Any]:
    """Write the TUM tracks (and, with ``plots`` and a ground truth that can ``score`` them, the
    figure); the row's metrics."""
    metrics: dict[str, Any] = {}
    tracks = {}
    # the filter's nodes before a heading alignment are re-expressed in the aligned frame
    # (FilterTrack.in_final_frame): one frame per track, as the smoother's
    for kind, track in (("filter", result.filter.in_final_frame(marginal=STATE_DIM)), ("smoother", result.smoother)):
        pos, q = track.mean[:, STATE.p], track.mean[:, STATE.q]
        write_tum(out / f"{name}_{kind}.tum", track.t, pos, q)
        if not score:
            metrics[f"{kind}_rmse_m"] = None
            continue
        err = trajectory_errors(track.t, pos, rec.truth.t_s, rec.truth.pos_m, align="se3")
        metrics[f"{kind}_rmse_m"] = err.rmse_m
        metrics[f"{kind}_num_associated"] = err.num_associated
        if rec.truth.quat_wxyz is not None:  # drift as odometry papers report it (RPE, KITTI's %)
            metrics[f"{kind}_drift"] = drift_metrics(track.t, pos, q, rec.truth.t_s, rec.truth.pos_m,
                                                     rec.truth.quat_wxyz)
        tracks[kind] = (err.t_s, err.aligned_est)
    metrics.update(run_summary(result))
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


def _report_starts(rows: list[Row], per_run: dict[str, list[dict[str, Any]]], mode: str) -> None:
    """How the filter started, once under the table: one line when every row started the
    same way, else one line per way with the rows that started so (over several seeds: the
    modes; each seed's start is in metrics.json)."""
    groups: dict[str, list[str]] = {}
    for row in rows:
        if row.start:
            groups.setdefault(row.start, []).append(row.name)
    if len(groups) == 1:
        log.info(f"\n{next(iter(groups))} (every row; filter.init.mode={mode})")
    elif groups:
        log.info(f"\nstart (filter.init.mode={mode}):")
        for line, names in groups.items():
            log.info(f"  {', '.join(names)}: {line.removeprefix('start: ')}")
    else:
        modes = {m["start"]["mode"] for ms in per_run.values() for m in ms if "start" in m}
        if modes:
            log.info(f"\nstart: {', '.join(sorted(modes))} (filter.init.mode={mode}; per row in metrics.json)")


def _report_drift(per_run: dict[str, list[dict[str, Any]]]) -> None:
    """Each row's drift (``filter_drift``, ``smoother_drift``: :func:`~flowins.evaluation.drift.drift_metrics`)
    under the table, filter / smoother, the mean over seeds; nothing where no row has one."""
    def mean(ms: list[dict[str, Any]], kind: str, key: str) -> float | None:
        values = [m.get(f"{kind}_drift", {}).get(key) for m in ms]
        return None if not values or any(v is None for v in values) else sum(values) / len(values)

    def pair(ms: list[dict[str, Any]], key: str, unit: str, sign: str = "") -> str:
        f, s = mean(ms, "filter", key), mean(ms, "smoother", key)
        return "n/a" if f is None or s is None else f"{f:{sign}.2f} / {s:{sign}.2f} {unit}"

    lines = [f"  {name:<16} {pair(ms, 'rpe_translation_rmse_m', 'm'):>20}   {pair(ms, 'kitti_translation_pct', '%'):>18}"
             f"   {pair(ms, 'scale_pct', '%', '+'):>18}"
             for name, ms in per_run.items() if any("filter_drift" in m for m in ms)]
    if lines:
        delta = next(m["filter_drift"]["rpe_delta_s"] for ms in per_run.values() for m in ms if "filter_drift" in m)
        log.info("\ndrift, filter / smoother (flowins.evaluation.drift: RPE and KITTI's % with no alignment, the scale "
                 "from a Sim(3) one; metrics.json *_drift):\n"
                 f"  {'':<16} {f'RPE over {delta:g} s':>20}   {'KITTI 100-800 m':>18}   {'scale':>18}\n" + "\n".join(lines))


def _vehicle_hints(recs: list[Recording], labels: list[str], nav_cfg: NavigationConfig) -> list[str]:
    """:func:`flowins.evaluation.motion.vehicle_hint` of each recording, labelled."""
    mode = (nav_cfg.measurements.get("vehicle") or VehicleSettings()).mode
    hints = [vehicle_hint(rec.gnss, platform_named=rec.platform is not None, mode=mode) for rec in recs]
    return [label + hint for label, hint in zip(labels, hints) if hint]


def _report(rows: list[Row], metrics: dict[str, Any], cfg: Mapping[str, Any], recs: list[Recording],
            nav_cfg: NavigationConfig, unscored: list[str | None], seeds: list[int] | None) -> None:
    """Print the table, how the filter started, the warnings and the GNSS floor (into ``metrics``)."""
    over = "" if seeds is None else f", mean ± std over seeds {', '.join(str(int(s)) for s in seeds)}"
    log.info(f"\nRMSE after Procrustes alignment (rotation + translation) to the ground truth{over}\n")
    log.info(format_table(rows))
    per_run = {n: ([m] if seeds is None else list(m["per_seed"].values())) for n, m in metrics.items()
               if isinstance(m, dict) and m.get("status") != "not applicable"}
    _report_starts(rows, per_run, nav_cfg.start.mode)
    _report_drift(per_run)
    labels = [""] if seeds is None else [f"seed {int(s)}: " for s in seeds]
    hints = _vehicle_hints(recs, labels, nav_cfg)
    if hints:
        metrics["hints"] = hints
        log.info("\n" + "\n".join(hints))
    warned = [(n, label + w) for n, ms in per_run.items() for label, m in zip(labels, ms) for w in m.get("warnings", [])]
    if warned:
        log.info("\nwarnings:")
        for n, w in warned:
            log.info(f"  {n}: {w}")
    uses_gnss = any(cfg["methods"][name]["gnss"] for name in cfg["combinations"])
    floors = {}
    for label, rec, problem in zip(labels, recs, unscored):
        if uses_gnss and rec.gnss is not None and rec.truth is not None and not problem and len(rec.gnss) >= 3:
            try:
                floors[label] = gnss_floor_metrics(rec.gnss, rec.truth)
            except ValueError as error:  # e.g. too few fixes inside the truth's time span: reported, not fatal
                floors[label] = {"status": "not computed", "reason": str(error)}
    if seeds is None and floors:
        metrics["gnss_floor"] = floor = floors[""]
        log.info(f"\nGNSS floor not computed: {floor['reason']}" if floor.get("status") == "not computed" else
                 "\n" + describe_gnss_floor(floor))
    elif floors:
        metrics["gnss_floor"] = {label.removeprefix("seed ").rstrip(": "): f for label, f in floors.items()}
        values = [f["rmse_m"] for f in floors.values() if "rmse_m" in f]
        if values:
            mean, std = _mean_std(values)
            log.info(f"\nGNSS floor (flowins.evaluation.gnss_floor): {mean:.2f} ± {std:.2f} m over {len(values)} seeds")
    warnings = [w for rec in recs for w in rec.warnings]
    if warnings:
        metrics["input_warnings"] = warnings
