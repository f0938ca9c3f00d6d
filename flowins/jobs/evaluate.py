"""The evaluation job: run each fusion combination on a sequence and report Table I.

``sequence -> flow pairs (dense provider, sparse tracker; cached) -> navigate per
combination -> metrics, plots``. For every combination: the EKF and the RTS
smoother, their RMSE after Procrustes (rotation + translation) alignment to the
ground truth, a Fig. 5 style PNG, TUM trajectories and one JSON of all metrics;
plus the Fig. 2 flow panel for a few frame pairs.
"""
from __future__ import annotations


import dataclasses
import functools
import json
import logging
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from flowins.jobs.cli import console_logging
from flowins.cache import cache_root
from flowins.config import build, check_target, instantiate, setting
from flowins.data.fingerprint import camera_content_key
from flowins.data.sequence import Sequence, within_imu_span
from flowins.data.streams import GnssStream, ImuStream, PoseStream
from flowins.evaluation import plot_trajectory, trajectory_errors, write_tum
from flowins.evaluation.gnss_floor import gnss_floor
from flowins.filter.ekf import Gate
from flowins.measurements.flow_update import FlowRecovery, FlowUpdate
from flowins.measurements.gnss import GnssRecovery
from flowins.measurements.gnss_heading import HeadingAlignment
from flowins.flow.pairs import (
    FlowPairs,
    cache_key,
    cached,
    dense_pairs,
    read_frame,
    run_provider,
    sparse_pairs,
    track_pairs,
)
from flowins.ins.imu_model import ImuModel, imu_model
from flowins.ins.initialization import InitialUncertainty, StillSettings, forward_axis
from flowins.ins.mechanization import ProcessNoise
from flowins.measurements.flow import FlowCamera
from flowins.navigation import NavigationConfig, NavigationResult, navigate
from flowins.start import GroundtruthSettings, MovingSettings, StartSettings
from flowins.state import STATE

log = logging.getLogger("flowins")

#: the filter's precision: float64 only. In float32 the pose copy's nugget (1e-9) is below
#: the rounding of the position variances and the flow update's covariances lose their
#: definiteness (measured on the 60 s walk: ins_gnss smoother 3.6e6 m, ins_dense NaN)
_DTYPES = {"float64": torch.float64}


def start_settings(cfg: Mapping[str, Any]) -> StartSettings:
    """:class:`~flowins.start.StartSettings` from ``filter.init`` (values checked by key)."""
    return build(StartSettings, cfg, "filter.init")


def navigation_config(cfg: Mapping[str, Any], imu: ImuModel | None = None) -> NavigationConfig:
    """:class:`NavigationConfig` from the ``filter`` config group; its IMU noise keys that are
    null come from ``imu`` (the ``imu`` config group, :func:`flowins.ins.imu_model.imu_model`).
    Every value is checked against the settings it builds; errors name the key."""
    if cfg["dtype"] not in _DTYPES:
        raise ValueError(f"filter.dtype={cfg['dtype']!r}: expected one of {list(_DTYPES)} (float32 is not "
                         "precise enough for the pose augmentation and the flow update)")
    noise = {}
    for key in ("acc_noise", "gyro_noise", "acc_bias_walk", "gyro_bias_walk"):
        noise[key] = cfg[key] if cfg[key] is not None else (None if imu is None else imu.noise()[key])
        if noise[key] is None:
            raise ValueError(f"filter.{key} is null and no imu preset was given; set filter.{key} or choose imu=...")
    noise.update(acc_scale_walk=cfg["acc_scale_walk"], discretization=cfg["discretization"])
    simple = ("gnss_noise_scale", "gnss_correlation_s", "output_every", "scheme", "gravity_mps2", "jacobians")
    groups = ("init", "initial", "gnss_gate", "gnss_recovery", "gnss_heading", "flow", "dtype")
    known = (*noise, *simple, *groups)
    for key in cfg:
        if key not in known:
            raise ValueError(f"filter.{key}: unknown key; filter takes {', '.join(known)}")
    return build(
        NavigationConfig,
        {key: cfg[key] for key in simple},
        "filter",
        noise=build(ProcessNoise, noise, "filter"),
        initial=build(InitialUncertainty, cfg["initial"], "filter.initial"),
        start=start_settings(cfg["init"]),
        gnss_gate=build(Gate, cfg["gnss_gate"], "filter.gnss_gate"),
        gnss_recovery=build(GnssRecovery, cfg["gnss_recovery"], "filter.gnss_recovery"),
        gnss_heading=build(HeadingAlignment, cfg["gnss_heading"], "filter.gnss_heading"),
        dtype=_DTYPES[cfg["dtype"]],
        flow_update=flow_update_config(cfg["flow"]),
    )


def flow_update_config(cfg: Mapping[str, Any]) -> FlowUpdate:
    """:class:`FlowUpdate` from ``filter.flow`` (values checked by key)."""
    return build(FlowUpdate, cfg, "filter.flow")


def learned_settings(checkpoint: str, nav_cfg: NavigationConfig, cfg: Mapping[str, Any]) -> tuple[NavigationConfig, dict]:
    """The filter config and job config with a ``train.py`` checkpoint's learned parameters
    (noise, gates, flow noise; the dropout rate goes to the flow provider when it has one)."""
    from flowins.training.parameters import FilterParameters

    params = FilterParameters.from_checkpoint(checkpoint)
    values = params.values()
    cfg = dict(cfg)
    if "p" in cfg["flow"]:
        cfg["flow"] = {**cfg["flow"], "p": values["dropout_p"]}
    log.info(f"learned parameters from {checkpoint}: " + ", ".join(f"{k}={v:.4g}" for k, v in values.items()))
    return params.apply(nav_cfg, training=False), cfg


@dataclass
class EvalInputs:
    """What the job evaluates: IMU, optional GNSS, camera frames or tracks, ground truth."""

    name: str
    imu: ImuStream
    gnss: GnssStream | None
    truth: PoseStream | None
    sequence: Sequence | None = None
    #: what reading changed (a stream cropped to the IMU span), printed and kept in metrics.json
    warnings: list[str] = dataclasses.field(default_factory=list)

    @functools.cached_property
    def content_key(self) -> str:
        """Content key of the recording's frames, calibration and tracks, the flow cache's
        key for the recording (:func:`flowins.data.fingerprint.camera_content_key`; it
        reads every frame file, so only once and only when flow is asked for)."""
        return "" if self.sequence is None else camera_content_key(self.sequence)

    @property
    def camera(self) -> FlowCamera | None:
        seq = self.sequence
        if seq is None or seq.camera is None or seq.imu_to_camera is None:
            return None
        return FlowCamera.from_calibration(seq.camera, seq.imu_to_camera)


def load_sequence(cfg: Mapping[str, Any], *, quick: bool, progress: bool = False) -> EvalInputs:
    """``sequence.path=DIR`` reads a recording (flowins folder, EuRoC, ADVIO); otherwise
    the simulated city walk (:func:`flowins.data.simulate.simulate`, cached)."""
    if cfg.get("path"):
        from flowins.data.read import read_sequence

        seq = read_sequence(cfg["path"], max_imu_gap_s=cfg["max_imu_gap_s"])
        seq, cropped = within_imu_span(seq, crop=cfg["crop"])
        for line in cropped:
            log.warning("warning: %s", line)
        return EvalInputs(seq.name, seq.imu, seq.gnss, seq.groundtruth, seq, cropped)
    if cfg["kind"] != "simulated_walk":
        raise ValueError(
            f"sequence.kind={cfg['kind']!r} is not supported; use the built-in 'simulated_walk' "
            "or give a recording with sequence.path=DIR"
        )
    from flowins.data.simulate import CameraConfig, SimulationConfig, simulate

    config = SimulationConfig(
        duration_s=float(cfg["quick_duration_s"] if quick else cfg["duration_s"]),
        seed=int(cfg["seed"]),
        imu_rate_hz=float(cfg["imu_rate_hz"]),
        camera=CameraConfig(**dict(cfg["camera"])),
        flow_every=0,
    )
    seq = simulate(config=config, progress=progress)
    return EvalInputs(seq.name, seq.imu, seq.gnss, seq.groundtruth, seq)


def load_flow(kind: str, rec: EvalInputs, cfg: Mapping[str, Any], *, progress: bool) -> FlowPairs | str:
    """The dense or sparse flow pairs of the recording (computed once, then cached),
    or the reason they can't be had."""
    seq = rec.sequence
    if seq is None or seq.camera is None:
        return "the sequence has no camera"
    pairs_cfg = cfg["flow_pairs"]
    step = int(pairs_cfg["step"])
    if kind == "sparse" and cfg["sparse"].get("source") == "tracks":
        if seq.tracks is None:
            return "sparse.source=tracks but the sequence has no tracks.csv"
        return track_pairs(seq.tracks, sigma_px=float(cfg["sparse"]["sigma_px"]), step=step).undistorted(seq.camera)
    if seq.frames is None:
        return "the sequence has no camera frames"
    settings = cfg["flow"] if kind == "dense" else cfg["sparse"]
    target = settings if kind == "dense" else settings["tracker"]  # what instantiate builds
    extra = dict(stride_px=pairs_cfg["stride_px"], border_px=pairs_cfg["border_px"],
                 input_scale=pairs_cfg["input_scale"]) if kind == "dense" else {}
    provider = instantiate(target, "flow" if kind == "dense" else "sparse.tracker")
    weights = provider if isinstance(provider, torch.nn.Module) else None  # keyed by its state dict
    key = cache_key(kind=kind, source=rec.content_key, provider=settings, weights=weights, step=step, **extra)
    path = Path(cfg["cache_dir"] or cache_root()) / "flow" / f"{kind}-{key}.npz"
    label = str(target.get("_target_", "")).rsplit(".", 1)[-1]

    def compute() -> FlowPairs:
        if kind == "dense":
            return dense_pairs(seq.frames, provider, step=step, batch_size=int(pairs_cfg["batch_size"]),
                               progress=progress, description=label, **extra)
        return sparse_pairs(seq.frames, provider, step=step, progress=progress, description=label)

    if path.is_file():
        log.info(f"{kind} flow: {label}, read from the cache {path}")
    pairs = cached(path, compute)
    return pairs.undistorted(seq.camera)


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
    tick = lambda b: "x" if b else " "
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


#: a ground truth that spans less (m, largest distance from its mean) leaves the alignment's rotation undetermined
MIN_TRUTH_EXTENT_M = 0.5


def truth_extent_problem(truth: PoseStream | None) -> str | None:
    """Why ``truth`` can't score a track (it barely moves), or None."""
    if truth is None:
        return None
    extent = float(torch.linalg.vector_norm(truth.pos_m - truth.pos_m.mean(0), dim=-1).max())
    if extent >= MIN_TRUTH_EXTENT_M:
        return None
    return (f"{truth.name}: the ground truth stays within {extent:.3g} m of its mean (< {MIN_TRUTH_EXTENT_M} m), so "
            "the alignment's rotation is undetermined: no RMSE is computed (n/a); the tracks are written as TUM files")


def _export(out: Path, name: str, result: NavigationResult, rec: EvalInputs, plots: bool) -> dict[str, Any]:
    metrics: dict[str, Any] = {}
    tracks = {}
    score = rec.truth is not None and truth_extent_problem(rec.truth) is None
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
    if result.gnss_accepted is not None:
        metrics["gnss_accepted"] = int(result.gnss_accepted.sum())
        metrics["gnss_fixes"] = int(result.gnss_accepted.numel())
    if result.start is not None:
        metrics["start"] = result.start.as_dict()
    resets = [{k: v for k, v in e.items() if k not in ("kind",)} for e in result.filter.log if e.get("kind") == "gnss_reset"]
    if resets:
        metrics["gnss_resets"] = resets
    if result.flow_pairs_outside:
        warnings.append(f"flow: {result.flow_pairs_outside} frame pairs outside the filter's span (its start at "
                        f"{result.start.t_s:.2f} s to the IMU's last sample) are not used")
    if result.gnss_before_start:
        metrics["gnss_before_start"] = result.gnss_before_start
    heading = [{k: v for k, v in e.items() if k not in ("kind", "name")} for e in result.heading_status]
    if heading:
        metrics["heading_alignment"] = heading  # filter.gnss_heading: when and how the heading was set (or given up)
    if plots and score:
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


def flow_panels(rec: EvalInputs, cfg: Mapping[str, Any], out: Path, count: int) -> list[Path]:
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


def _flow_stats(result: NavigationResult, pairs: FlowPairs) -> dict[str, Any]:
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


def run_warnings(result: NavigationResult) -> list[str]:
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
    inflated = [e for e in log if e.get("kind") == "flow_inflate"]
    if inflated:
        warnings.append(f"flow: {len(inflated)} time(s) most points of {inflated[0]['frames']} frames in a row failed "
                        f"the gate (first at {inflated[0]['t_s']:.1f} s); the velocity and gyroscope bias σ were "
                        "inflated to let the flow back in (filter.flow.recovery)")
    sigma = result.filter.node_cov[:, STATE.p, STATE.p].diagonal(dim1=-2, dim2=-1)[:, :2].sum(-1).sqrt()
    if float(sigma.max()) > 100.0:
        k = int(sigma.argmax())
        warnings.append(f"the filter's own horizontal position σ reaches {float(sigma[k]):.0f} m (at "
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


def gnss_floor_metrics(gnss: GnssStream, truth: PoseStream, *, correlation_s: float | None = None) -> dict[str, Any]:
    """:func:`~flowins.evaluation.gnss_floor.gnss_floor` of a sequence's fixes against its truth
    (``correlation_s``: the GNSS errors' τ; estimated from them when None)."""
    from flowins.geometry.geodesy import gnss_to_enu

    enu, cov, _ = gnss_to_enu(gnss)
    floor = gnss_floor(gnss.t_s, enu, cov.diagonal(dim1=-2, dim2=-1).sqrt(), truth.t_s, truth.pos_m,
                       correlation_s=correlation_s)
    return {
        "rmse_m": floor.rmse_m,
        "horizontal_rmse_m": floor.horizontal_rmse_m,
        "correlation_s": floor.correlation_s,
        "fixes_used": floor.fixes_used,
        "fixes": floor.fixes,
        "error_rms_enu_m": list(floor.error_sigma_m),
    }


def describe_gnss_floor(floor: Mapping[str, Any]) -> str:
    e, n, u = floor["error_rms_enu_m"]
    return (
        f"GNSS floor (flowins.evaluation.gnss_floor): a causal filter that knew the motion exactly and weighted\n"
        f"the fixes by their true error model would score {floor['rmse_m']:.2f} m ({floor['horizontal_rmse_m']:.2f} m "
        f"if it also knew the height); the fixes'\nerrors are {e:.1f}/{n:.1f}/{u:.1f} m RMS (E/N/U), correlated over "
        f"{floor['correlation_s']:.1f} s ({floor['fixes_used']} of {floor['fixes']} fixes pass the gate).\n"
        f"A GNSS filter scores below it only by trusting the fixes less than they deserve; the smoother has no such floor."
    )


def check_job_settings(cfg: Mapping[str, Any]) -> None:
    """The job's own keys (``combinations``, ``flow_pairs``, ``sequence``, ...) checked
    before any work: each error names the key and what was expected."""
    combinations, methods = cfg["combinations"], cfg["methods"]
    if isinstance(combinations, str) or not hasattr(combinations, "__len__") or not len(combinations):
        raise ValueError(f"combinations={combinations!r}: expected a list of at least one of {', '.join(methods)} "
                         "(configs/method/)")
    for name in combinations:
        if not isinstance(name, str) or name not in methods:
            raise ValueError(f"combinations: unknown combination {name!r}; expected one of {', '.join(methods)} "
                             "(configs/method/)")
    for key in ("quick", "progress", "plots"):
        setting(cfg, key, bool)
    setting(cfg, "flow_panels", int, minimum=0)
    setting(cfg, "model.checkpoint", str | None)
    check_data_settings(cfg)
    flows = {kind for name in combinations for kind in ("sparse", "dense") if methods[name][kind]}
    if "dense" in flows:
        check_target(cfg["flow"], "flow")
    if "sparse" in flows:
        source = setting(cfg, "sparse.source", str)
        if source not in ("tracker", "tracks"):
            raise ValueError(f"sparse.source={source!r}: expected tracker (run sparse.tracker on the frames) or "
                             "tracks (the recording's tracks.csv)")
        if source == "tracks":
            setting(cfg, "sparse.sigma_px", float, minimum=1e-6)
        else:
            check_target(cfg["sparse"]["tracker"], "sparse.tracker")


def check_data_settings(cfg: Mapping[str, Any]) -> None:
    """The keys both jobs share (``flow_pairs``, ``sequence``, ``cache_dir``), checked by key."""
    setting(cfg, "cache_dir", str | None)
    setting(cfg, "flow_pairs.step", int, minimum=1)
    setting(cfg, "flow_pairs.input_scale", float, minimum=1e-3, maximum=1.0)
    setting(cfg, "flow_pairs.stride_px", int, minimum=1)
    setting(cfg, "flow_pairs.border_px", int, minimum=0)
    setting(cfg, "flow_pairs.batch_size", int, minimum=1)
    setting(cfg, "sequence.path", str | None)
    setting(cfg, "sequence.max_imu_gap_s", float, minimum=1e-6)
    setting(cfg, "sequence.crop", bool)
    if not cfg["sequence"].get("path"):
        setting(cfg, "sequence.duration_s", float, minimum=1.0)
        setting(cfg, "sequence.quick_duration_s", float, minimum=1.0)
        setting(cfg, "sequence.seed", int)
        setting(cfg, "sequence.imu_rate_hz", float, minimum=1.0)


def run(cfg: Mapping[str, Any]) -> list[Row]:
    """Run the job; returns the table rows (also printed and written to ``metrics.json``)."""
    console_logging()
    check_job_settings(cfg)
    out = Path(cfg["output_dir"])
    out.mkdir(parents=True, exist_ok=True)
    quick, progress, plots = cfg["quick"], cfg["progress"], cfg["plots"]
    methods: Mapping[str, Mapping[str, bool]] = cfg["methods"]
    t0 = time.perf_counter()
    rec = load_sequence(cfg["sequence"], quick=quick, progress=progress)
    n_gnss = 0 if rec.gnss is None else len(rec.gnss)
    seq = rec.sequence
    n_frames = 0 if seq is None or seq.frames is None else len(seq.frames)
    log.info(f"sequence: {rec.name}, {rec.imu.duration_s:.0f} s, {len(rec.imu)} IMU samples, {n_frames} camera frames, "
          f"{n_gnss} GNSS fixes, ground truth: {'yes' if rec.truth is not None else 'no'} "
          f"({time.perf_counter() - t0:.1f} s to load)")
    unscored = truth_extent_problem(rec.truth)
    if unscored:
        log.warning("warning: %s", unscored)
    sensor = None if seq is None else seq.metadata.get("imu")
    imu = imu_model(cfg["imu"], recording=bool(cfg["sequence"].get("path")), sensor=sensor)
    imu.check_readings(rec.imu)
    nav_cfg = navigation_config(cfg["filter"], imu)
    checkpoint = (cfg.get("model") or {}).get("checkpoint")
    if checkpoint:
        nav_cfg, cfg = learned_settings(checkpoint, nav_cfg, cfg)
    noise = nav_cfg.noise
    log.info(f"imu: {imu.name} ({imu.source or 'config'}): filter densities acc {float(noise.acc_noise):.3g} m/s²/√Hz, "
          f"gyro {float(noise.gyro_noise):.3g} rad/s/√Hz, walks {float(noise.acc_bias_walk):.3g} m/s³/√Hz, "
          f"{float(noise.gyro_bias_walk):.3g} rad/s²/√Hz")
    calibration = None if seq is None or seq.imu_to_camera is None else seq.imu_to_camera
    forward_b = forward_axis(nav_cfg.start.moving.forward_axis,
                             None if calibration is None else calibration.rotation_matrix)

    flows: dict[str, FlowPairs | str] = {}
    for kind in ("sparse", "dense"):
        if any(methods[name][kind] for name in cfg["combinations"]):
            t1 = time.perf_counter()
            flows[kind] = load_flow(kind, rec, cfg, progress=progress)
            if isinstance(flows[kind], FlowPairs):
                log.info(f"{kind} flow: {len(flows[kind])} frame pairs ({time.perf_counter() - t1:.1f} s)")

    rows, metrics = [], {}
    for name in cfg["combinations"]:
        m_cfg = methods[name]
        sources = (bool(m_cfg["gnss"]), bool(m_cfg["sparse"]), bool(m_cfg["dense"]))
        reason = None
        if sources[0] and rec.gnss is None:
            reason = "the sequence has no GNSS"
        flow = None
        for kind, used in (("sparse", sources[1]), ("dense", sources[2])):
            if used:
                flow = flows[kind]
                if isinstance(flow, str):
                    reason = flow
        if reason is not None:
            rows.append(Row(name, sources, None, None, f"not applicable: {reason}"))
            metrics[name] = {"status": "not applicable", "reason": reason}
            continue
        t1 = time.perf_counter()
        result = navigate(rec.imu, rec.gnss if sources[0] else None, config=nav_cfg, flow=flow,
                          camera=rec.camera if flow is not None else None, truth=rec.truth, forward_b=forward_b,
                          start_gnss=rec.gnss, progress=progress)
        m = _export(out, name, result, rec, plots)
        if flow is not None:
            m.update(_flow_stats(result, flow))
        m["seconds"] = time.perf_counter() - t1
        m["warnings"] = run_warnings(result) + ([unscored] if unscored else [])
        metrics[name] = m
        note = ("no ground truth: TUM tracks only" if rec.truth is None else
                "the ground truth does not move: TUM tracks only" if unscored else "")
        rows.append(Row(name, sources, m["filter_rmse_m"], m["smoother_rmse_m"], note, seconds=m["seconds"]))
        fr = "n/a" if m["filter_rmse_m"] is None else f"{m['filter_rmse_m']:.2f} m"
        log.info(f"  {name:<16} filter RMSE {fr} ({m['seconds']:.1f} s); {result.start.describe()}")
        for entry in m.get("heading_alignment", []):
            if entry["status"] == "never set":
                log.info(f"  {'':<16} GNSS: {entry['fixes']} fixes held for the heading to the end: {entry['reason']}")
    if plots and isinstance(flows.get("dense"), FlowPairs) and int(cfg.get("flow_panels", 0)) > 0:
        flow_panels(rec, cfg, out, int(cfg["flow_panels"]))
    table = format_table(rows)
    log.info("\nRMSE after Procrustes alignment (rotation + translation) to the ground truth\n")
    log.info(table)
    starts = {m["start"]["mode"] for m in metrics.values() if isinstance(m, dict) and "start" in m}
    if starts:
        log.info(f"\nstart: {', '.join(sorted(starts))} (filter.init.mode={nav_cfg.start.mode}; per row in metrics.json)")
    warned = [(n, w) for n, m in metrics.items() if isinstance(m, dict) for w in m.get("warnings", [])]
    if warned:
        log.info("\nwarnings:")
        for n, w in warned:
            log.info(f"  {n}: {w}")
    uses_gnss = any(methods[name]["gnss"] for name in cfg["combinations"])
    if uses_gnss and rec.gnss is not None and rec.truth is not None and not unscored and len(rec.gnss) >= 3:
        try:
            metrics["gnss_floor"] = gnss_floor_metrics(rec.gnss, rec.truth)
            log.info("\n" + describe_gnss_floor(metrics["gnss_floor"]))
        except ValueError as error:  # e.g. too few fixes inside the truth's time span: reported, not fatal
            metrics["gnss_floor"] = {"status": "not computed", "reason": str(error)}
            log.info(f"\nGNSS floor not computed: {error}")
    if rec.warnings:
        metrics["input_warnings"] = rec.warnings
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=float))
    log.info(f"\nwrote {out}/metrics.json, *.tum" + (", *.png" if plots else ""))
    for r in rows:
        if r.filter_rmse_m is not None and not math.isfinite(r.filter_rmse_m):
            raise RuntimeError(f"{r.name}: non-finite RMSE; see {out}")
    return rows
