"""The INS pipeline from validated streams to filtered and smoothed tracks.

``data (streams, flow pairs) -> measurements (GNSS fixes, flow frames) -> filter (EKF, RTS)``.
"""
from __future__ import annotations

import dataclasses
import functools
import logging
from collections.abc import Mapping, Sequence
from dataclasses import KW_ONLY, dataclass, field
from typing import Any

import torch
from torch import Tensor

from flowins.data.streams import GnssStream, ImuStream, PoseStream
from flowins.filter.augmentation import with_window
from flowins.filter.ekf import Gate
from flowins.filter.chain import FilterTrack
from flowins.filter.runner import FilterInput, memory_warning, run_filters
from flowins.filter.smoother import SmoothedTrack, rts_smooth_batch
from flowins.flow.pairs import FlowPairs
from flowins.geometry.geodesy import LocalTangentPlane
from flowins.ins.initialization import InitialUncertainty
from flowins.ins.mechanization import SCHEMES, STANDARD_GRAVITY_MPS2, ProcessNoise
from flowins.measurements.flow_update import FlowUpdate, flow_frames
from flowins.measurements.gnss import GnssRecovery, correlation_inflation, gnss_fixes, gnss_noise
from flowins.measurements.gnss_heading import HeadingAlignment, aligned_prior_covariance, fit_from_record
from flowins.measurements.registry import NavigationContext, measurement_kind
from flowins.measurements.tracks import TrackUpdate, track_frames
from flowins.measurements.vehicle import VehicleConstraint  # noqa: F401  (registers the kind "vehicle")
from flowins.measurements.zero_velocity import ZeroVelocity
from flowins.parallel import can_start_workers, run_in_processes, split_by_load
from flowins.state import STATE_DIM, window_size
from flowins.start import Start, StartSettings, choose_start

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class NavigationConfig:
    """Everything the INS(+GNSS) filter needs besides the data."""

    noise: ProcessNoise = field(default_factory=ProcessNoise)
    initial: InitialUncertainty = field(default_factory=InitialUncertainty)
    #: how the filter starts (:mod:`flowins.start`): still, moving, from the ground truth, or auto
    start: StartSettings = field(default_factory=StartSettings)
    gnss_gate: Gate = field(default_factory=Gate)
    #: what follows a run of rejected fixes (:class:`~flowins.measurements.gnss.GnssRecovery`)
    gnss_recovery: GnssRecovery = field(default_factory=GnssRecovery)
    gnss_noise_scale: float = 1.0
    #: correlation time of the GNSS errors (s): each fix's R is inflated by
    #: :func:`~flowins.measurements.gnss.correlation_inflation`; 0: white, as in the paper
    gnss_correlation_s: float = 0.0
    #: heading from the first fixes while the yaw is unknown (:mod:`flowins.measurements.gnss_heading`)
    gnss_heading: HeadingAlignment = field(default_factory=HeadingAlignment)
    output_every: int = 10
    scheme: str = "midpoint"
    gravity_mps2: float = STANDARD_GRAVITY_MPS2
    #: ``"analytic"`` | ``"autodiff"``: the IMU's and the flow measurements' Jacobians
    jacobians: str = "analytic"
    dtype: torch.dtype = torch.float64
    #: where the filter, the smoother and their events run (``cpu``, ``cuda``, ``cuda:1``);
    #: the start and the measurements are prepared on the CPU and moved there
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    #: worker processes a batch of several recordings is split over on the CPU (:func:`navigate_batch`,
    #: :mod:`flowins.parallel`); 1: the batch in this process
    workers: int = 1
    flow_update: FlowUpdate = field(default_factory=FlowUpdate)
    #: the multi-view update of sparse tracks over a window of cloned poses (``filter.tracks``;
    #: :mod:`flowins.measurements.tracks`); its window 0 (the default) leaves it off
    tracks: TrackUpdate = field(default_factory=TrackUpdate)
    #: the settings of each registered measurement kind by name (``filter.measurements.<name>``,
    #: :func:`~flowins.measurements.registry.measurement_settings`); a kind not named here
    #: uses its settings' defaults
    measurements: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.scheme not in SCHEMES:
            raise ValueError(f"NavigationConfig.scheme={self.scheme!r}: expected one of {', '.join(SCHEMES)}")
        if self.jacobians not in ("analytic", "autodiff"):
            raise ValueError(f"NavigationConfig.jacobians={self.jacobians!r}: expected analytic or autodiff")
        if not (isinstance(self.output_every, int) and self.output_every >= 1):
            raise ValueError(f"NavigationConfig.output_every={self.output_every!r}: expected an integer >= 1")
        for key in ("gravity_mps2", "gnss_noise_scale"):
            if not getattr(self, key) > 0.0:
                raise ValueError(f"NavigationConfig.{key}={getattr(self, key)!r}: expected a number > 0")
        if not self.gnss_correlation_s >= 0.0:
            raise ValueError(f"NavigationConfig.gnss_correlation_s={self.gnss_correlation_s!r}: expected a number >= 0")
        if isinstance(self.workers, bool) or not (isinstance(self.workers, int) and self.workers >= 1):
            raise ValueError(f"NavigationConfig.workers={self.workers!r}: expected an integer >= 1")

    def filter_settings(self) -> dict:
        """The keyword arguments of :func:`~flowins.filter.runner.run_filter` this config sets."""
        return dict(noise=self.noise, output_every=self.output_every, gravity_mps2=self.gravity_mps2,
                    jacobians=self.jacobians, scheme=self.scheme)


@dataclass
class NavigationResult:
    filter: FilterTrack
    #: the smoothed 26-dim layout (with a window of cloned poses, the clones beyond the first are
    #: not smoothed: :func:`~flowins.filter.smoother.rts_smooth` with ``marginal``)
    smoother: SmoothedTrack
    frame: LocalTangentPlane | None
    gnss_t_s: Tensor | None
    gnss_enu_m: Tensor | None
    gnss_h_acc_m: Tensor | None
    #: flow pairs left out because they are not inside the IMU time span
    flow_pairs_outside: int = 0
    start: Start | None = None
    #: GNSS fixes before the filter's start (not used)
    gnss_before_start: int = 0
    #: what the smoother ran on where a second pass was tried (``filter.gnss_heading.second_pass``,
    #: :func:`smoother_tracks`): ``{"pass": "second" | "first", "reason": ...}``; None: the one pass
    smoother_pass: dict[str, Any] | None = None

    @property
    def gnss_accepted(self) -> Tensor | None:
        """Gate decision (1 accepted, 0 rejected) of each GNSS fix, in order."""
        flags = [entry["accepted"] for entry in self.filter.log if entry.get("kind") == "gnss"]
        return torch.tensor(flags) if flags else None

    @property
    def heading_status(self) -> list[dict]:
        """The GNSS heading alignment's log entries (``filter.gnss_heading``), aligned or given
        up; if fixes were still held when the run ended, a last entry ``"never set"`` counts
        them: they never updated the filter (the run was too short for them to set the heading)."""
        entries = [e for e in self.filter.log if e.get("kind") == "heading"]
        held = [e for e in self.filter.log if e.get("status") == "held for heading"]
        if held and not entries:
            entries.append({"t_s": held[-1]["t_s"], "kind": "heading", "status": "never set", "fixes": len(held),
                            "reason": "the run ended before the held fixes could set the heading "
                            "(filter.gnss_heading: baseline_m, max_sigma_rad); they never updated the filter"})
        return entries

    def summary(self) -> dict[str, Any]:
        """What the run did, for ``metrics.json``: GNSS fixes accepted, how it started, its
        GNSS resets, fixes before the start, and the heading alignment (each when present)."""
        out: dict[str, Any] = {}
        if self.gnss_accepted is not None:
            out["gnss_accepted"] = int(self.gnss_accepted.sum())
            out["gnss_fixes"] = int(self.gnss_accepted.numel())
        if self.start is not None:
            out["start"] = self.start.as_dict()
        resets = [{k: v for k, v in e.items() if k != "kind"} for e in self.filter.log if e.get("kind") == "gnss_reset"]
        if resets:
            out["gnss_resets"] = resets
        if self.gnss_before_start:
            out["gnss_before_start"] = self.gnss_before_start
        heading = [{k: v for k, v in e.items() if k not in ("kind", "name", "fit")} for e in self.heading_status]
        if heading:
            out["heading_alignment"] = heading  # filter.gnss_heading: when and how the heading was set (or given up)
        if self.smoother_pass is not None:
            out["smoother_pass"] = self.smoother_pass
        return out

    @property
    def flow_log(self) -> list[dict]:
        """The log entries of the flow frames (points, valid, degenerate, accepted, ...)."""
        return [entry for entry in self.filter.log if entry.get("kind") == "flow"]


@dataclass
class NavigationSetup:
    """What :func:`navigate` hands the filter: the prior at the first IMU sample and all events."""

    mean0: Tensor  # (26,)
    cov0: Tensor  # (26, 26)
    events: list
    frame: LocalTangentPlane | None
    gnss_enu_m: Tensor | None
    #: flow pairs left out because they are not inside the IMU time span
    flow_pairs_outside: int = 0
    start: Start | None = None
    #: GNSS fixes before the filter's start (not used)
    gnss_before_start: int = 0


@dataclass(frozen=True)
class NavigationRun:
    """One recording's inputs to :func:`navigate`, :func:`navigate_batch` and
    :func:`prepare_navigation`."""

    #: the IMU samples (``N``) that drive the filter
    imu: ImuStream
    #: fixes (``G``) that update the filter and set the local ENU frame (origin at the first fix, or ``frame``)
    gnss: GnssStream | None = None
    _: KW_ONLY
    #: the local ENU frame of the GNSS fixes; None: at the first fix
    frame: LocalTangentPlane | None = None
    #: frame pairs (dense or sparse) whose points update the filter as the paper's flow frames (needs ``camera``)
    flow: FlowPairs | None = None
    #: sparse tracks over many frames (:class:`~flowins.data.sequence.Tracks`, undistorted pixels) for the
    #: multi-view update (needs ``camera`` and ``config.tracks.window >= 1``; not with ``flow``)
    tracks: Any = None
    #: the flow's camera (:class:`~flowins.measurements.flow.FlowCamera`: K and the IMU->camera transform)
    camera: Any = None
    #: ground-truth poses (``M``) that may set the start (``filter.init.mode`` groundtruth, or auto)
    truth: PoseStream | None = None
    #: ``(3,)`` the body axis along the motion of a moving start
    forward_b: Tensor | None = None
    #: without ``gnss``: fixes (``G'``) that may set the start (a moving start's velocity and heading)
    #: and nothing else, so that a run without GNSS starts as the run with it does
    start_gnss: GnssStream | None = None
    #: further measurement streams by the name of their kind (:mod:`flowins.measurements.registry`);
    #: each stream is what its kind's ``events`` takes
    streams: Mapping[str, Any] = field(default_factory=dict)


def prepare_navigation(run: NavigationRun, *, config: NavigationConfig = NavigationConfig()) -> NavigationSetup:
    """The prior and the measurement events of :func:`navigate` (see there).

    Every number of ``config`` may be a tensor with a gradient (the training wraps
    this same function), so the events carry the graph into the filter.
    """
    imu, gnss, frame = run.imu, run.gnss, run.frame
    events = []
    enu = fixes = None
    if gnss is not None:
        enu, _, frame = gnss.enu(frame)
        inflation = correlation_inflation(gnss.t_s, config.gnss_correlation_s).to(gnss.h_acc_m.dtype)
        cov = gnss_noise(gnss.h_acc_m, gnss.v_acc_m, config.gnss_noise_scale) * inflation.reshape(-1, 1, 1)
        events = gnss_fixes(gnss.t_s, enu, cov, gate=config.gnss_gate, name=gnss.name, heading=config.gnss_heading,
                            recovery=config.gnss_recovery)
    start_gnss = gnss if gnss is not None else run.start_gnss
    if start_gnss is not None:
        start_enu = enu  # the GNSS updates' fixes, converted once
        if start_gnss is not gnss:
            start_enu, _, frame = start_gnss.enu(frame)
        sigma = torch.stack((start_gnss.h_acc_m, start_gnss.h_acc_m, start_gnss.v_acc_m), -1)
        fixes = (start_gnss.t_s, start_enu, sigma)
    start = choose_start(imu, settings=config.start, fixes=fixes, truth=run.truth, forward_b=run.forward_b,
                         uncertainty=config.initial, gravity_mps2=float(config.gravity_mps2), fused=gnss is not None)
    t_end_s = float(imu.t_s[-1])
    before = [e for e in events if e.time_s < start.t_s]
    events = [e for e in events if e.time_s >= start.t_s]
    events += [ZeroVelocity(t, config.start.still.zupt_sigma_mps, f"zero velocity at {t:.2f} s")
               for t in start.zupt_times_s if t <= t_end_s]
    outside = 0
    if run.flow is not None:
        if run.camera is None:
            raise ValueError("navigate: flow pairs need the camera (a FlowCamera with K and the IMU->camera transform)")
        frames, outside = flow_frames(run.flow, run.camera, config.flow_update, t_min_s=start.t_s, t_max_s=t_end_s,
                                      name=run.flow.kind, jacobians=config.jacobians)
        events = events + frames
    clones = 1
    if run.tracks is not None:
        if run.camera is None:
            raise ValueError("navigate: tracks need the camera (a FlowCamera with K and the IMU->camera transform)")
        if run.flow is not None:
            raise ValueError("navigate: a run takes flow pairs or tracks, not both (each frame of either shifts the "
                             "window of cloned poses)")
        if config.tracks.window < 1:
            raise ValueError("navigate: tracks need filter.tracks.window >= 1 (the cloned poses they are seen from)")
        clones = config.tracks.window
        events = events + track_frames(run.tracks, run.camera, config.tracks, t_min_s=start.t_s, t_max_s=t_end_s,
                                       name=run.tracks.name)
    streams = dict(run.streams)
    for name, settings in config.measurements.items():  # a kind switched on that needs no recorded stream
        kind = measurement_kind(name)
        if name not in streams and kind.default_stream is not None and getattr(settings, "mode", None) == "on":
            streams[name] = kind.default_stream()
    if streams:
        context = NavigationContext(t_start_s=start.t_s, t_end_s=t_end_s, frame=frame, dtype=config.dtype)
        for name, stream in streams.items():
            kind = measurement_kind(name)
            settings = config.measurements.get(name)
            settings = kind.settings() if settings is None else settings
            events += [e for e in kind.events(stream, settings, context) if e.time_s >= start.t_s]
    like = {"dtype": config.dtype, "device": torch.device(config.device)}
    mean0, cov0 = with_window(start.mean.to(**like), start.cov.to(**like), clones,
                              nugget_var=config.initial.augmentation_nugget_var)
    return NavigationSetup(mean0, cov0, events, frame, enu, outside, start, len(before))


def navigate(run: NavigationRun, *, config: NavigationConfig = NavigationConfig(),
             progress: bool = False) -> NavigationResult:
    """Run the EKF and the RTS smoother on one recording (:class:`NavigationRun`).

    The filter starts as ``config.start`` says (:func:`~flowins.start.choose_start`:
    still, moving, from ``run.truth``, or auto); measurements before its start are not
    used (the GNSS fixes left out are counted in the result). With GNSS the local ENU
    frame has its origin at the first fix (or ``run.frame``). Measurements after the
    IMU's last sample raise. Flow pairs are added as the paper's flow frames
    (:func:`~flowins.measurements.flow_update.flow_frames`, settings ``config.flow_update``); each of ``run.streams`` by its
    registered kind (:mod:`flowins.measurements.registry`, settings ``config.measurements``).

    When no input or config tensor needs a gradient (:func:`carries_gradient`) the run is
    made in ``torch.inference_mode`` and the result's tensors are inference tensors:
    read them freely, but ``clone()`` one before changing it in place. With a tensor that
    needs a gradient the result carries the graph back to it.
    """
    return navigate_batch([run], config=config, progress=progress)[0]


def carries_gradient(*objects) -> bool:
    """Whether grad mode is on and any tensor in ``objects`` (searched through dataclasses,
    named tuples, lists, tuples and mappings) requires a gradient."""
    if not torch.is_grad_enabled():
        return False
    seen: set[int] = set()
    stack = list(objects)
    while stack:
        obj = stack.pop()
        if isinstance(obj, Tensor):
            if obj.requires_grad:
                return True
        elif isinstance(obj, (str, bytes, int, float, bool, type(None), torch.dtype, torch.device)) or id(obj) in seen:
            continue
        elif dataclasses.is_dataclass(obj):
            seen.add(id(obj))
            stack.extend(getattr(obj, f.name) for f in dataclasses.fields(obj))
        elif isinstance(obj, Mapping):
            seen.add(id(obj))
            stack.extend(obj.values())
        elif isinstance(obj, (list, tuple)):
            seen.add(id(obj))
            stack.extend(obj)
    return False


def navigate_batch(runs: Sequence[NavigationRun], *, config: NavigationConfig = NavigationConfig(),
                   progress: bool = False) -> list[NavigationResult]:
    """:func:`navigate` on several recordings in one batched filter pass
    (:func:`~flowins.filter.runner.run_filters`); each result equals its recording's
    :func:`navigate` up to rounding. One ``config`` serves every run.

    With ``config.workers > 1`` on the CPU, and nothing carrying a gradient, the runs are
    split into that many parts of about equal work (IMU samples and flow frames), each part
    one batched pass in a worker process of its own (:mod:`flowins.parallel`)."""
    gradient = carries_gradient(runs, config)
    if batch_workers(runs, config, gradient=gradient, here=False) > 1:
        if can_start_workers():
            return _navigate_in_workers(runs, config=config, progress=progress)
        log.info("filter: %d runs in this process: it is a daemonic worker, which may not start the "
                 "filter.workers=%d processes", len(runs), config.workers)
    # without a gradient to carry, inference mode skips autograd's bookkeeping on every
    # one of the filter's many small operations
    with torch.inference_mode(not gradient):
        return _navigate_batch(runs, config=config, progress=progress)


def batch_workers(runs: Sequence[NavigationRun], config: NavigationConfig, *, gradient: bool | None = None,
                  here: bool = True) -> int:
    """The worker processes :func:`navigate_batch` splits ``runs`` over: ``config.workers`` (at most
    one per run) on the CPU where nothing carries a gradient (``gradient``; None: look) and,
    with ``here``, this process may start processes (:func:`~flowins.parallel.can_start_workers`);
    else 1, the batch in this process."""
    if min(config.workers, len(runs)) == 1 or config.device.type != "cpu" or (here and not can_start_workers()):
        return 1
    if carries_gradient(runs, config) if gradient is None else gradient:
        return 1
    return min(config.workers, len(runs))


#: a flow frame's share of the work against an IMU sample's (:func:`run_load`): the 300 s walk's
#: dense frames (10 Hz, 256 points, 100 Hz IMU) take most of its filter pass
FRAME_LOAD = 30.0


def run_load(run: NavigationRun) -> float:
    """About how much filtering ``run`` takes: its IMU samples and :data:`FRAME_LOAD` per flow
    frame pair or track frame (splitting a batch over workers evens it out)."""
    frames = 0 if run.flow is None else len(run.flow)
    if run.tracks is not None:
        frames += len(run.tracks.frame_times)
    return float(run.imu.t_s.shape[0]) + FRAME_LOAD * frames


def _navigate_in_workers(runs: Sequence[NavigationRun], *, config: NavigationConfig,
                         progress: bool) -> list[NavigationResult]:
    parts = split_by_load([run_load(run) for run in runs], config.workers)
    log.info("filter: %d runs in %d worker processes (filter.workers=%d)", len(runs), len(parts), config.workers)
    task = functools.partial(navigate_batch, config=dataclasses.replace(config, workers=1), progress=progress)
    done = run_in_processes(task, [([runs[i] for i in part],) for part in parts])
    results: list[NavigationResult | None] = [None] * len(runs)
    for part, part_results in zip(parts, done):
        for i, result in zip(part, part_results):
            results[i] = result
    return results  # type: ignore[return-value]


def _navigate_batch(runs: Sequence[NavigationRun], *, config: NavigationConfig,
                    progress: bool) -> list[NavigationResult]:
    setups = [prepare_navigation(run, config=config) for run in runs]
    inputs = []
    for run, setup in zip(runs, setups):
        first = setup.start.index
        inputs.append(FilterInput(run.imu.t_s[first:], run.imu.acc_mps2[first:], run.imu.gyro_rps[first:],
                                  setup.mean0, setup.cov0, setup.events))
    warning = memory_warning(inputs, output_every=config.output_every)
    if warning:
        log.warning("warning: %s", warning)
    tracks = run_filters(inputs, progress=progress, **config.filter_settings())
    again, passes = smoother_tracks(inputs, tracks, config, progress=progress)
    smoothed = rts_smooth_batch(again, marginal=STATE_DIM)
    return [
        NavigationResult(
            filter=track,
            smoother=smoother,
            smoother_pass=which,
            frame=setup.frame,
            gnss_t_s=None if run.gnss is None else run.gnss.t_s,
            gnss_enu_m=setup.gnss_enu_m,
            gnss_h_acc_m=None if run.gnss is None else run.gnss.h_acc_m,
            flow_pairs_outside=setup.flow_pairs_outside,
            start=setup.start,
            gnss_before_start=setup.gnss_before_start,
        )
        for run, setup, track, smoother, which in zip(runs, setups, tracks, smoothed, passes)
    ]


def heading_fit_record(track: FilterTrack) -> dict[str, Any] | None:
    """The fit of the GNSS heading alignment that set ``track``'s heading (its log entry's
    ``fit``), or None where no fix set it."""
    for entry in track.log:
        if entry.get("kind") == "heading" and entry.get("status") == "aligned" and "fit" in entry:
            return entry["fit"]
    return None


def smoother_tracks(inputs: Sequence[FilterInput], tracks: Sequence[FilterTrack], config: NavigationConfig, *,
                    progress: bool = False) -> tuple[list[FilterTrack], list[dict[str, Any] | None]]:
    """The filter tracks the RTS smoother runs on, one per run of ``inputs`` (filtered into
    ``tracks``), and for each run what was chosen (None: nothing to choose). A run's track is its
    own, or, for a run whose GNSS fixes set its heading (``filter.gnss_heading.second_pass``),
    a second filter pass from the same start. The first pass holds the fixes back until they set
    the heading, and they never update it; the second knows the heading from its first sample
    and applies every fix, so the smoother uses them all.

    The second pass starts at the first pass's smoothed mean at the start (the smoother carries
    the alignment back through the held stretch, where the filter's yaw moved while it was
    unknown, so the fit's rotation alone does not give the start's heading), with the run's own
    prior covariance aligned by the fit (:func:`~flowins.measurements.gnss_heading.aligned_prior_covariance`):
    it claims no more certainty than the prior and the fit (the smoothed covariance would count
    every measurement twice). A second pass that had to reset to the fixes more
    often than the first (``filter.gnss_recovery``: it drifted off them) is not used: the
    smoother runs on the first. All such runs go as one batch; the start carries no gradient
    through the first pass. ``progress``: report the second pass's progress.
    """
    out, which = list(tracks), [None] * len(tracks)
    if not config.gnss_heading.second_pass:
        return out, which
    again = [(i, record) for i, record in enumerate(heading_fit_record(t) for t in tracks) if record is not None]
    if not again:
        return out, which
    rows = []
    first = rts_smooth_batch([tracks[i] for i, _ in again], marginal=STATE_DIM)
    for (i, record), smoothed in zip(again, first):
        run = inputs[i]
        fit = fit_from_record(record, dtype=run.mean0.dtype, device=run.mean0.device)
        smoothed = smoothed.mean[0].detach()
        mean0 = with_window(smoothed, run.cov0[:STATE_DIM, :STATE_DIM], window_size(run.mean0.shape[-1]))[0]
        cov0 = aligned_prior_covariance(run.mean0, run.cov0, mean0, fit,
                                        condition_sigma_rad=config.gnss_heading.condition_sigma_rad)
        rows.append(dataclasses.replace(run, mean0=mean0, cov0=cov0))
    passes = run_filters(rows, **config.filter_settings(), progress=progress, description="smoother's second pass")
    for (i, _), track in zip(again, passes):
        resets_first, resets_second = _resets(tracks[i]), _resets(track)
        if resets_second > resets_first:
            which[i] = {"pass": "first", "reason": f"the second pass reset to the fixes {_times(resets_second)}, the "
                        f"first {_times(resets_first)} (filter.gnss_recovery)"}
        else:
            out[i] = track
            which[i] = {"pass": "second", "reason": "the held fixes set the heading; the smoother's pass knows it "
                        "from the start and applies every fix"}
    return out, which


def _times(n: int) -> str:
    return {0: "never", 1: "once", 2: "twice"}.get(n, f"{n} times")


def _resets(track: FilterTrack) -> int:
    return sum(1 for e in track.log if e.get("kind") == "gnss_reset")
