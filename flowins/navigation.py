"""The INS pipeline from validated streams to filtered and smoothed tracks.

``data (streams, flow pairs) -> measurements (GNSS fixes, flow frames) -> filter (EKF, RTS)``.
"""
from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import KW_ONLY, dataclass, field
from functools import partial
from typing import Any, Literal

import torch
from torch import Tensor

from flowins.batching import carries_gradient, navigate_in_workers
from flowins.config import bounded, check_fields
from flowins.data.streams import GnssStream, ImuStream, PoseStream
from flowins.filter.augmentation import with_window
from flowins.filter.ekf import Gate
from flowins.filter.chain import FilterTrack
from flowins.filter.compiling import compiler_for
from flowins.filter.runner import FilterInput, memory_warning, run_filters
from flowins.filter.smoother import SmoothedTrack, rts_smooth_batch
from flowins.flow.pairs import FlowPairs
from flowins.geometry.geodesy import LocalTangentPlane
from flowins.ins.initialization import InitialUncertainty, start_uncertainty
from flowins.ins.mechanization import SCHEMES, STANDARD_GRAVITY_MPS2, ProcessNoise
from flowins.measurements.flow_update import FlowUpdate, flow_frames
from flowins.measurements.gnss import GnssRecovery, correlation_inflation, gnss_fixes, gnss_noise
from flowins.measurements.gnss_heading import HeadingAlignment
from flowins.measurements.registry import NavigationContext, registered_events
from flowins.measurements.tracks import TrackUpdate, track_frames
from flowins.measurements.vehicle import VehicleConstraint  # noqa: F401  (registers the kind "vehicle")
from flowins.measurements.zero_velocity import ZeroVelocity
from flowins.mounting_pass import fit_mountings
from flowins.second_pass import smoother_tracks
from flowins.state import STATE_DIM
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
    gnss_noise_scale: float = bounded(1.0, above=0.0)
    #: correlation time of the GNSS errors (s): each fix's R is inflated by
    #: :func:`~flowins.measurements.gnss.correlation_inflation`; 0: white, as in the paper
    gnss_correlation_s: float = bounded(0.0, minimum=0.0)
    #: heading from the first fixes while the yaw is unknown (:mod:`flowins.measurements.gnss_heading`)
    gnss_heading: HeadingAlignment = field(default_factory=HeadingAlignment)
    output_every: int = bounded(10, minimum=1)
    scheme: str = "midpoint"
    gravity_mps2: float = bounded(STANDARD_GRAVITY_MPS2, above=0.0)
    #: ``"analytic"`` | ``"autodiff"``: the IMU's and the flow measurements' Jacobians
    jacobians: Literal["analytic", "autodiff"] = "analytic"
    dtype: torch.dtype = torch.float64
    #: where the filter, the smoother and their events run (``cpu``, ``cuda``, ``cuda:1``);
    #: the start and the measurements are prepared on the CPU and moved there
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    #: worker processes a batch of several recordings is split over on the CPU (:func:`navigate_batch`,
    #: :mod:`flowins.parallel`); 1: the batch in this process
    workers: int = bounded(1, minimum=1)
    #: ``"false"`` | ``"true"`` | ``"auto"``: the flow frames' update (on a GPU every step) through
    #: ``torch.compile`` (:mod:`flowins.filter.compiling`: inductor, with a C++ compiler on a CPU, CUDA graphs on a GPU)
    compile: Literal["false", "true", "auto"] = "false"
    flow_update: FlowUpdate = field(default_factory=FlowUpdate)
    #: the multi-view update of sparse tracks over a window of cloned poses (``filter.tracks``;
    #: :mod:`flowins.measurements.tracks`; default 10 poses); window 0 is the paper's two-view update
    tracks: TrackUpdate = field(default_factory=TrackUpdate)
    #: the settings of each registered measurement kind by name (``filter.measurements.<name>``,
    #: :func:`~flowins.measurements.registry.measurement_settings`); a kind not named here
    #: uses its settings' defaults
    measurements: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.scheme not in SCHEMES:
            raise ValueError(f"NavigationConfig.scheme={self.scheme!r}: expected one of {', '.join(SCHEMES)}")
        check_fields(self)

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
    #: :func:`~flowins.second_pass.smoother_tracks`): ``{"pass": "second" | "first", "reason": ...}``; None: the one pass
    smoother_pass: dict[str, Any] | None = None
    #: how the filter's steps ran where ``filter.compile`` compiled some, and what it cost
    #: (:meth:`~flowins.filter.compiling.Compiler.describe`), or why it ran eagerly where it asked
    #: (``auto`` without a compiler); None where nothing was asked or no step ran compiled
    filter_steps: str | None = None
    #: seconds of the filter pass spent compiling its steps (new shapes; 0 when eager or all met before)
    filter_compile_s: float = 0.0
    #: the vehicle constraint's fitted mounting (``filter.measurements.vehicle.mounting=fit``,
    #: :func:`~flowins.mounting_pass.fit_mountings`): what it found and whether it is used; None: not asked
    vehicle_mounting: dict[str, Any] | None = None

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
    # without fixes a yaw the start leaves free (its σ above unknown_yaw_sigma_rad) is only the track's
    # reference direction (InitialUncertainty.reference_yaw_rad)
    reference = gnss is None and float(config.initial.yaw_rad) > config.gnss_heading.unknown_yaw_sigma_rad
    start = choose_start(imu, settings=config.start, fixes=fixes, truth=run.truth, forward_b=run.forward_b,
                         uncertainty=start_uncertainty(config.initial, reference=reference),
                         gravity_mps2=float(config.gravity_mps2), fused=gnss is not None)
    t_end_s = float(imu.t_s[-1])
    before = [e for e in events if e.time_s < start.t_s]
    events = [e for e in events if e.time_s >= start.t_s]
    still = config.start.still
    events += [ZeroVelocity(t, still.zupt_sigma_mps, f"zero velocity at {t:.2f} s", still.zupt_keeps_heading)
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
    context = NavigationContext(t_start_s=start.t_s, t_end_s=t_end_s, frame=frame, dtype=config.dtype, imu=imu,
                                gravity_mps2=float(config.gravity_mps2))
    events += registered_events(run.streams, config.measurements, context)
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

    When no input or config tensor needs a gradient (:func:`~flowins.batching.carries_gradient`) the run is
    made in ``torch.inference_mode`` and the result's tensors are inference tensors:
    read them freely, but ``clone()`` one before changing it in place. With a tensor that
    needs a gradient the result carries the graph back to it.
    """
    return navigate_batch([run], config=config, progress=progress)[0]


def navigate_batch(runs: Sequence[NavigationRun], *, config: NavigationConfig = NavigationConfig(),
                   progress: bool = False) -> list[NavigationResult]:
    """:func:`navigate` on several recordings in one batched filter pass
    (:func:`~flowins.filter.runner.run_filters`); each result equals its recording's
    :func:`navigate` up to rounding. One ``config`` serves every run.

    With ``config.workers > 1`` on the CPU, and nothing carrying a gradient, the runs are
    split into that many parts of about equal work (IMU samples and flow frames), each part
    one batched pass in a worker process of its own (:mod:`flowins.parallel`)."""
    gradient = carries_gradient(runs, config)
    results = navigate_in_workers(navigate_batch, runs, config=config, gradient=gradient, progress=progress)
    if results is not None:
        return results
    # without a gradient to carry, inference mode skips autograd's bookkeeping on every
    # one of the filter's many small operations
    with torch.inference_mode(not gradient):
        return _navigate_batch(runs, config=config, progress=progress)


def _navigate_batch(runs: Sequence[NavigationRun], *, config: NavigationConfig,
                    progress: bool) -> list[NavigationResult]:
    runs, mountings = fit_mountings(runs, config, partial(_navigate_batch, progress=progress))
    setups = [prepare_navigation(run, config=config) for run in runs]
    inputs = []
    for run, setup in zip(runs, setups):
        first = setup.start.index
        inputs.append(FilterInput(run.imu.t_s[first:], run.imu.acc_mps2[first:], run.imu.gyro_rps[first:],
                                  setup.mean0, setup.cov0, setup.events))
    warning = memory_warning(inputs, output_every=config.output_every)
    if warning:
        log.warning("warning: %s", warning)
    compiler = compiler_for(config.compile, config.device)
    tracks = run_filters(inputs, progress=progress, compiler=compiler, **config.filter_settings())
    again, passes = smoother_tracks(inputs, tracks, config, progress=progress, compiler=compiler)
    smoothed = rts_smooth_batch(again, marginal=STATE_DIM)
    return [NavigationResult(filter=track, smoother=smoother, smoother_pass=which, frame=setup.frame,
                             gnss_t_s=None if run.gnss is None else run.gnss.t_s, gnss_enu_m=setup.gnss_enu_m,
                             gnss_h_acc_m=None if run.gnss is None else run.gnss.h_acc_m,
                             flow_pairs_outside=setup.flow_pairs_outside, start=setup.start,
                             gnss_before_start=setup.gnss_before_start, vehicle_mounting=mounting,
                             filter_steps=compiler.describe() if compiler.calls or (
                                 config.compile != "false" and not compiler.enabled) else None,
                             filter_compile_s=compiler.compile_s)
            for run, setup, track, smoother, which, mounting in zip(runs, setups, tracks, smoothed, passes, mountings)]
