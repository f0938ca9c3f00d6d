"""Unrolling the filter over windows of a sequence, and the loss against ground truth.

``sequence -> (events with the current parameters) -> filter over a window -> loss``.
A sequence is cut into windows at IMU sample times; the filter runs through one
window from the (detached) state at its start, so the gradient of a window's loss
reaches back to that window's start only (truncated backpropagation through time).
The events are rebuilt from the parameters for every window
(:func:`flowins.navigation.prepare_navigation`, the same function ``evaluate.py``
uses), so each window sees the current values.
"""
from __future__ import annotations

import dataclasses
import functools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import torch
from torch import Tensor

from flowins.batching import batch_workers, run_load
from flowins.data.sequence import Tracks
from flowins.data.streams import GnssStream, ImuStream, PoseStream
from flowins.evaluation.alignment import (
    Alignment,
    align_start,
    align_yaw,
    apply_alignment,
    apply_alignment_to_quaternions,
)
from flowins.evaluation.metrics import (
    associate,
    interpolate_positions,
    interpolate_quaternions,
    segment_errors,
    trajectory_errors,
)
from flowins.filter.chain import NodeTrack
from flowins.filter.compiling import compiler_for
from flowins.filter.runner import FilterInput, run_filters
from flowins.filter.smoother import rts_smooth_batch
from flowins.flow.pairs import FlowPairs
from flowins.measurements.flow import FlowCamera
from flowins.navigation import NavigationConfig, NavigationRun, prepare_navigation
from flowins.parallel import in_distributed_run, run_parts, split_by_load
from flowins.second_pass import smoother_tracks
from flowins.state import STATE, STATE_DIM

log = logging.getLogger(__name__)

#: the rows of Table I as (GNSS, sparse, dense) sources
METHODS: dict[str, tuple[bool, bool, bool]] = {
    "ins": (False, False, False),
    "ins_gnss": (True, False, False),
    "ins_sparse": (False, True, False),
    "ins_dense": (False, False, True),
    "ins_gnss_sparse": (True, True, False),
    "ins_gnss_dense": (True, False, True),
}


@dataclass
class TrainingSequence:
    """One recording with ground truth, and its flow pairs (with dropout moments for learning ``p``)."""

    name: str
    imu: ImuStream
    gnss: GnssStream | None
    truth: PoseStream
    camera: FlowCamera | None = None
    dense: FlowPairs | None = None
    sparse: FlowPairs | None = None
    #: sparse tracks over many frames (:class:`~flowins.data.sequence.Tracks`) for the sparse methods'
    #: multi-view update (``filter.tracks.window >= 1``), in place of ``sparse``
    tracks: Any = None
    #: the IMU preset the recording names (its metadata's ``imu``), or None
    sensor: str | None = None
    #: further measurement streams by kind (:attr:`flowins.navigation.NavigationRun.streams`),
    #: e.g. the vehicle constraint of a recording whose metadata names ``platform: vehicle``
    streams: dict = field(default_factory=dict)

    def sources(self, method: str) -> tuple[GnssStream | None, FlowPairs | Tracks | None]:
        """The GNSS stream and flow pairs (the tracks, for a sparse method of a sequence that has
        them) ``method`` uses; a clear error when one is missing."""
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; expected one of {list(METHODS)}")
        gnss, sparse, dense = METHODS[method]
        if gnss and self.gnss is None:
            raise ValueError(f"{self.name}: method {method} needs GNSS, the sequence has none")
        flow = self.dense if dense else (self.tracks if self.tracks is not None else self.sparse) if sparse else None
        if (dense or sparse) and flow is None:
            raise ValueError(f"{self.name}: method {method} needs {'dense' if dense else 'sparse'} flow pairs")
        return (self.gnss if gnss else None), flow


def has_moments(flow: FlowPairs | None) -> bool:
    """Whether the flow pairs carry dropout moments (their σ can be recomputed at another rate)."""
    return isinstance(flow, FlowPairs) and bool(flow.points) and flow.points[0].dropout_unit_px is not None


def window_bounds(t_s: Tensor, window_s: float) -> list[tuple[int, int]]:
    """``[(i_a, i_b)]`` IMU sample index ranges of consecutive windows of about ``window_s``;
    consecutive windows share their boundary sample, the last one takes the remainder."""
    if window_s <= 0:
        raise ValueError(f"window_s must be > 0, got {window_s}")
    t = torch.as_tensor(t_s, dtype=torch.float64)
    edges = torch.arange(float(t[0]), float(t[-1]), window_s, dtype=torch.float64)
    index = torch.unique(torch.searchsorted(t, edges).clamp_max(t.shape[0] - 1)).tolist()
    if index[-1] != t.shape[0] - 1:
        if t[-1] - t[index[-1]] < 0.5 * window_s and len(index) > 1:
            index[-1] = t.shape[0] - 1  # a short tail joins the last window
        else:
            index.append(t.shape[0] - 1)
    return list(zip(index[:-1], index[1:]))


class WindowResult(NamedTuple):
    #: the filtered nodes, all in the window's final frame (a heading alignment re-expresses
    #: the nodes before it, :meth:`~flowins.filter.chain.FilterTrack.in_final_frame`)
    track: NodeTrack
    mean: Tensor  # (26,) the state at the window's end (with the graph)
    cov: Tensor  # (26, 26)
    #: the window's summed innovation negative log-likelihood and its number of scalar
    #: measurements (:attr:`~flowins.filter.chain.FilterTrack.nll`); None unless asked for
    nll: Tensor | None = None
    nll_count: float = 0.0
    #: the RTS smoother's nodes over the window (in its final frame); None unless asked for
    smoothed: NodeTrack | None = None


def run_window(
    seq: TrainingSequence,
    method: str,
    config: NavigationConfig,
    bounds: tuple[int, int],
    *,
    dropout_p: Tensor | float | None = None,
    start: tuple[Tensor, Tensor] | None = None,
    likelihood: bool = False,
) -> WindowResult:
    """The filter of ``method`` from IMU sample ``bounds[0]`` to ``bounds[1]``.

    ``start``: the state ``(mean, cov)`` at the window's first sample (carried over from
    the previous window); None: the sequence's own prior (then ``bounds[0]`` must be 0).
    Events at the first sample belong to the previous window unless this is the first.
    ``dropout_p``: recompute the flow σ at this dropout rate (the pairs need moments).
    ``likelihood``: also sum the updates' innovation negative log-likelihood (:attr:`WindowResult.nll`).
    """
    return run_windows([seq], method, config, [bounds], dropout_p=dropout_p, starts=[start], likelihood=likelihood)[0]


def run_windows(
    seqs: Sequence[TrainingSequence],
    method: str | Sequence[str],
    config: NavigationConfig,
    bounds: Sequence[tuple[int, int]],
    *,
    dropout_p: Tensor | float | None = None,
    starts: Sequence[tuple[Tensor, Tensor] | None] | None = None,
    likelihood: bool = False,
    smooth: bool = False,
) -> list[WindowResult]:
    """:func:`run_window` of one window of each sequence, ``seqs[i]`` from ``bounds[i][0]`` to
    ``bounds[i][1]`` starting at ``starts[i]``, all in one batched filter pass
    (:func:`~flowins.filter.runner.run_filters`); ``smooth``: each with its RTS smoother
    (:attr:`WindowResult.smoothed`; on a second filter pass where the GNSS heading alignment
    calls for one, :func:`~flowins.second_pass.smoother_tracks`). ``method``: one for every row, or one per row (a
    sequence may appear once per method). ``dropout_p`` applies to the rows whose flow
    pairs carry dropout moments."""
    starts = [None] * len(seqs) if starts is None else starts
    methods = [method] * len(seqs) if isinstance(method, str) else list(method)
    if len(methods) != len(seqs):
        raise ValueError(f"run_windows: {len(methods)} methods for {len(seqs)} sequences; expected one per sequence")
    inputs = []
    for seq, row_method, (i_a, i_b), start in zip(seqs, methods, bounds, starts):
        if start is None and i_a != 0:
            raise ValueError(f"run_window: a window starting at IMU sample {i_a} needs the state there (start=...)")
        gnss, flow = seq.sources(row_method)
        imu = seq.imu
        t_a, t_b = float(imu.t_s[i_a]), float(imu.t_s[i_b])
        tracks = flow if isinstance(flow, Tracks) else None
        if tracks is not None:
            flow = None  # the whole recording's schedule: the clones carry over from window to window
        if flow is not None:
            # only the pairs this window uses (and the one before, whose end frame augments)
            flow = flow.select((flow.t2_s > t_a - 1.0) & (flow.t2_s <= t_b))
            if dropout_p is not None and has_moments(flow):
                flow = flow.at_dropout_rate(dropout_p)
        has_camera = flow is not None or tracks is not None
        setup = prepare_navigation(NavigationRun(imu, gnss, flow=flow, tracks=tracks,
                                                 camera=seq.camera if has_camera else None, streams=seq.streams,
                                                 truth=seq.truth),  # for filter.init.mode=groundtruth
                                   config=config)
        if setup.start.index != 0:
            late_s = float(imu.t_s[setup.start.index] - imu.t_s[0])
            reference = "" if config.start.mode == "groundtruth" else ", or start from the reference (filter.init.mode=groundtruth)"
            raise ValueError(
                f"{seq.name}: training starts the filter at the recording's first IMU sample, but its start "
                f"(filter.init.mode={config.start.mode}: {setup.start.mode}) begins at row {setup.start.index}, "
                f"{late_s:.2f} s in ({setup.start.reason}); crop the recording to begin there (its data.train or "
                f"data.val entry's start_s, {math.ceil(late_s * 100) / 100:.2f} s later){reference}")
        first = start is None
        events = [e for e in setup.events if (t_a < e.time_s or (first and e.time_s == t_a)) and e.time_s <= t_b]
        mean0, cov0 = (setup.mean0, setup.cov0) if first else start
        inputs.append(FilterInput(imu.t_s[i_a : i_b + 1], imu.acc_mps2[i_a : i_b + 1], imu.gyro_rps[i_a : i_b + 1],
                                  mean0, cov0, events))
    tracks = run_filters(inputs, **config.filter_settings(), likelihood=likelihood,
                         compiler=compiler_for(config.compile, config.device))
    smoothed = rts_smooth_batch(smoother_tracks(inputs, tracks, config)[0], marginal=STATE_DIM) if smooth else None
    return [WindowResult(track.in_final_frame(marginal=STATE_DIM), track.node_mean[-1], track.node_cov[-1], track.nll, track.nll_count,
                         None if smoothed is None else smoothed[i])
            for i, track in enumerate(tracks)]


class WindowLoss(NamedTuple):
    loss: Tensor  # scalar, what is minimised
    rmse_m: Tensor  # position RMSE after the yaw + translation alignment (no gradient through it)
    nll: Tensor  # mean Gaussian negative log-likelihood of the aligned position errors (0 if unused)
    orientation_rmse_rad: Tensor = torch.zeros(())  # chordal orientation RMSE after the same alignment (0 if unused)
    innovation_nll: Tensor = torch.zeros(())  # innovation NLL per scalar measurement (0 if unused)
    segment_rmse_m: Tensor = torch.zeros(())  # mean over durations of the segment RMSE (0 unless loss="segments")
    #: the alignment the errors were taken after (no gradient): with loss="start", the one to
    #: pass to the sequence's later windows
    alignment: Alignment | None = None


#: the window losses :func:`window_loss` knows (``model.loss``)
LOSSES = ("window", "segments", "start")


def orientation_rmse(q_est: Tensor, q_ref: Tensor) -> Tensor:
    """Chordal RMS orientation error (rad) of unit quaternions ``(K, 4)``: ``2 sqrt(mean(sin²(θ/2)))``
    with ``sin²(θ/2) = 1 - (q_est · q_ref)²`` (sign-free, smooth at ``θ = 0``; equal to the RMS of
    ``θ`` to third order)."""
    dot = (q_est * q_ref).sum(-1) / (q_est.norm(dim=-1) * q_ref.norm(dim=-1))
    return 2.0 * torch.sqrt((1.0 - dot * dot).clamp_min(0.0).mean() + 1e-16)


def window_loss(
    track: NodeTrack,
    truth: PoseStream,
    *,
    nll_weight: float = 0.0,
    orientation_weight_m_per_rad: float = 0.0,
    innovation_weight: float = 0.0,
    innovation: tuple[Tensor, float] | None = None,
    max_dt_s: float = 0.1,
    loss: str = "window",
    segment_s: Sequence[float] = (10.0, 20.0, 40.0),
    alignment: Alignment | None = None,
) -> WindowLoss:
    """Position (and optionally orientation) error of a window's filter track against the ground truth.

    The estimate is interpolated at the truth's times inside the window and aligned to
    them by a yaw rotation and a translation (:func:`~flowins.evaluation.alignment.align_yaw`;
    the heading and origin of an INS without GNSS are arbitrary). The alignment is
    computed without a gradient: it minimises the squared error, so its own derivative
    contributes nothing to the gradient (envelope theorem). The loss is the aligned
    position RMSE (m), plus ``nll_weight`` times the mean negative log-likelihood
    ``½ (eᵀ P⁻¹ e + log det 2πP)`` of the aligned errors under the filter's position
    covariance, so the covariances learn to be honest, plus
    ``orientation_weight_m_per_rad`` times the orientation RMSE (rad,
    :func:`orientation_rmse`) of the yaw-aligned attitude (needs a truth with orientations),
    plus ``innovation_weight`` times the innovation negative log-likelihood per scalar
    measurement, ``innovation = (nll, count)`` of the window
    (:attr:`WindowResult.nll`, :attr:`WindowResult.nll_count`): the likelihood of the
    measurements under the filter's own predictions, which fixes the absolute noise levels
    that the RMSE sees only as ratios, and needs no ground truth.

    ``loss="segments"`` replaces the aligned RMSE by the relative errors over segments of
    the durations ``segment_s`` inside the window (:func:`~flowins.evaluation.metrics.segment_errors`,
    the mean over durations of each one's RMS displacement error), and the orientation term by
    the RMS heading-change error over the same segments. With a truth that has orientations the
    displacements are compared in their own heading frames, so no alignment enters and heading
    and scale drift inside a segment cost in full (the per-window yaw alignment absorbs most
    of a drift). Without orientations the displacements are compared after the window's yaw
    alignment. Durations longer than the window are left out; a window shorter than all of
    them is one segment, the whole window.

    ``loss="start"`` aligns once per sequence instead of once per window: ``alignment`` (the
    one :attr:`WindowLoss.alignment` returned for the sequence's first window), or, for the
    first window, the heading and position of the window's first node against the truth's
    (:func:`~flowins.evaluation.alignment.align_start`; the window's own yaw alignment when
    the truth has no orientations). Heading drift since the start then costs in full.
    """
    if loss not in LOSSES:
        raise ValueError(f"model.loss={loss!r}: expected one of {', '.join(LOSSES)}")
    if orientation_weight_m_per_rad > 0 and truth.quat_wxyz is None:
        raise ValueError(f"{truth.name}: the orientation loss (orientation_weight_m_per_rad > 0) needs a ground "
                         "truth with orientations (quat_wxyz); this one has positions only")
    if innovation_weight > 0 and (innovation is None or innovation[0] is None):
        raise ValueError("window_loss: innovation_weight > 0 needs the window's innovation likelihood "
                         "(run_windows(..., likelihood=True))")
    t, pos, cov = track.t, track.mean[:, STATE.p], track.cov[:, STATE.p, STATE.p]
    inside = (truth.t_s >= t[0]) & (truth.t_s <= t[-1])
    t_ref, p_ref = truth.t_s[inside], truth.pos_m[inside].to(pos)
    if t_ref.shape[0] < 3:
        raise ValueError(f"window [{float(t[0]):.2f}, {float(t[-1]):.2f}] s has {t_ref.shape[0]} ground-truth samples; need >= 3")
    assoc = associate(t, t_ref, max_dt_s=max_dt_s)
    est = interpolate_positions(pos, assoc)
    ref = p_ref[assoc.ref_index]
    q_ref = None if truth.quat_wxyz is None else truth.quat_wxyz[inside].to(pos)[assoc.ref_index]
    with torch.no_grad():
        if loss != "start" or alignment is None:
            alignment = _start_alignment(track, assoc, est, ref, q_ref) if loss == "start" else align_yaw(est.detach(), ref)
        alignment = Alignment(*(x.detach() for x in alignment))
    err = apply_alignment(alignment, est) - ref
    rmse = torch.sqrt((err * err).sum(-1).mean() + 1e-12)
    if loss == "segments":
        position, heading = _segment_terms(track, assoc, t_ref, est, ref, q_ref, alignment, segment_s)
        attitude = heading if orientation_weight_m_per_rad > 0 else pos.new_zeros(())
    else:
        position = rmse
        attitude = (_aligned_orientation_rmse(track, assoc, q_ref, alignment) if orientation_weight_m_per_rad > 0
                    else pos.new_zeros(()))
    nll = _position_nll(cov, assoc, err, alignment) if nll_weight > 0 else pos.new_zeros(())
    innovation_nll = innovation[0] / max(innovation[1], 1.0) if innovation_weight > 0 else pos.new_zeros(())
    total = position + nll_weight * nll + orientation_weight_m_per_rad * attitude + innovation_weight * innovation_nll
    return WindowLoss(total, rmse.detach(), nll.detach(), attitude.detach(), innovation_nll.detach(),
                      position.detach() if loss == "segments" else pos.new_zeros(()), alignment)


def _start_alignment(track: NodeTrack, assoc, est: Tensor, ref: Tensor, q_ref: Tensor | None) -> Alignment:
    """``loss="start"``'s alignment of a sequence's first window: the heading and position of its
    first node against the truth's, or the window's yaw alignment without orientations."""
    if q_ref is None:
        return align_yaw(est.detach(), ref)
    q_first = interpolate_quaternions(track.mean[:, STATE.q], assoc)[0]
    return align_start(est[0], q_first, ref[0], q_ref[0])


def _segment_terms(track: NodeTrack, assoc, t_ref: Tensor, est: Tensor, ref: Tensor, q_ref: Tensor | None,
                   alignment: Alignment, segment_s: Sequence[float]) -> tuple[Tensor, Tensor]:
    """``loss="segments"``: the mean over durations of the RMS displacement error, and the RMS
    heading-change error (0 without orientations; see :func:`window_loss`)."""
    t_k = t_ref[assoc.ref_index]
    span = float(t_k[-1] - t_k[0])
    lengths = [float(x) for x in segment_s if float(x) <= span] or [span]
    if q_ref is None:
        segments = segment_errors(t_k, apply_alignment(alignment, est), ref, lengths)
        return segments.rmse_m.mean(), est.new_zeros(())
    q_est = interpolate_quaternions(track.mean[:, STATE.q], assoc)
    segments = segment_errors(t_k, est, ref, lengths, q_est=q_est, q_ref=q_ref)
    return segments.rmse_m.mean(), segments.heading_rmse_rad.mean()


def _aligned_orientation_rmse(track: NodeTrack, assoc, q_ref: Tensor, alignment: Alignment) -> Tensor:
    """The orientation RMSE (rad) of the yaw-aligned attitude (:func:`orientation_rmse`)."""
    q_est = apply_alignment_to_quaternions(alignment, interpolate_quaternions(track.mean[:, STATE.q], assoc))
    return orientation_rmse(q_est, q_ref)


def _position_nll(cov: Tensor, assoc, err: Tensor, alignment: Alignment) -> Tensor:
    """The mean ``½ (eᵀ P⁻¹ e + log det 2πP)`` of the aligned errors under the filter's
    position covariance (interpolated, rotated by the alignment)."""
    w = assoc.weight.to(cov).view(-1, 1, 1)
    left = assoc.est_left
    P = (1 - w) * cov[left] + w * cov[left + 1]
    R = alignment.rotation
    P = R @ P @ R.T + 1e-9 * torch.eye(3, dtype=cov.dtype, device=cov.device)
    maha = (err.unsqueeze(-2) @ torch.linalg.solve(P, err.unsqueeze(-1))).reshape(-1)
    return 0.5 * (maha + torch.logdet(2 * torch.pi * P)).mean()


def split_gradient(loss: Tensor, likelihood: Tensor | None, params: Sequence[Tensor],
                   from_likelihood: Sequence[bool], level: Sequence[bool] | None = None) -> list[Tensor | None]:
    """The gradient of each of ``params``: of ``likelihood`` where ``from_likelihood`` says so,
    of ``loss`` elsewhere (None where the chosen one does not reach it or is None). Two backward passes
    through one graph (``model.innovation_learns``: the flow noise's absolute level from the
    innovation likelihood, the rest from the window loss).

    ``level`` marks a group of noise parameters (``model.noise_level=likelihood``) whose common
    level comes from ``likelihood`` and whose ratios come from ``loss``: each one's gradient is
    :func:`level_gradient` of both (a parameter both in ``level`` and ``from_likelihood`` takes
    the likelihood's alone)."""
    if len(from_likelihood) != len(params):
        raise ValueError(f"split_gradient: {len(from_likelihood)} flags for {len(params)} parameters")
    if level is not None and len(level) != len(params):
        raise ValueError(f"split_gradient: {len(level)} level flags for {len(params)} parameters")
    grouped = [bool(g) and not f for g, f in zip(level or [False] * len(params), from_likelihood)]
    by_loss = [i for i, f in enumerate(from_likelihood) if not f]
    by_likelihood = [i for i, f in enumerate(from_likelihood) if f or grouped[i]]
    found_loss: dict[int, Tensor | None] = {}
    found_likelihood: dict[int, Tensor | None] = {}
    for indices, target, keep, out in ((by_loss, loss, bool(by_likelihood), found_loss),
                                       (by_likelihood, likelihood, False, found_likelihood)):
        if indices and target is not None and target.requires_grad:
            out.update(zip(indices, torch.autograd.grad(target, [params[i] for i in indices], allow_unused=True,
                                                         retain_graph=keep)))
    grads: list[Tensor | None] = [found_likelihood.get(i) if f else found_loss.get(i)
                                  for i, f in enumerate(from_likelihood)]
    members = [i for i, g in enumerate(grouped) if g]
    if members:
        mixed = level_gradient([found_loss.get(i) for i in members], [found_likelihood.get(i) for i in members])
        for i, g in zip(members, mixed):
            grads[i] = g
    return grads


def level_gradient(by_loss: Sequence[Tensor | None], by_likelihood: Sequence[Tensor | None]) -> list[Tensor | None]:
    """The gradients of a group of noise parameters' coordinates (each ``≈ ln θ`` near its
    start) that move their common level along the likelihood and their ratios along the loss:
    ``g_i − mean(g) + mean(ℓ)``, with ``g`` the loss's gradients and ``ℓ`` the likelihood's
    (None counts as 0; all None: None for each). The loss's part is its gradient projected
    onto the directions that keep the group's mean coordinate, so a parameter the loss does not
    reach (a GNSS noise scale while every fix is held) moves against the others' mean: its
    ratio to them is what the loss changes.

    Scaling every noise density, walk, initial 1-σ and measurement σ of a linear-Gaussian
    filter by one factor leaves its gains and so its estimates unchanged: a position loss
    sees the ratios between them only, while the innovation likelihood fixes their level
    (``model.noise_level=likelihood``). The mean over the group is the loss's derivative
    along that common direction, taken out; the likelihood's enters in its place."""
    if len(by_loss) != len(by_likelihood) or not by_loss:
        raise ValueError(f"level_gradient: {len(by_loss)} loss and {len(by_likelihood)} likelihood gradients; "
                         "expected one of each per parameter of the group, at least one")
    ref = next((g for g in (*by_loss, *by_likelihood) if g is not None), None)
    if ref is None:
        return [None] * len(by_loss)
    g = torch.stack([torch.zeros_like(ref) if x is None else x for x in by_loss])
    ell = torch.stack([torch.zeros_like(ref) if x is None else x for x in by_likelihood])
    return list(g - g.mean(dim=0) + ell.mean(dim=0))


def sequence_rmse(seq: TrainingSequence, method: str, config: NavigationConfig, *, dropout_p: float | None = None) -> float:
    """Filter RMSE (m) of ``method`` over the whole sequence after the SE(3) Procrustes
    alignment of Table I (:func:`~flowins.evaluation.metrics.trajectory_errors`), no gradient."""
    return sequences_rmse([seq], method, config, dropout_p=dropout_p)[0]


def sequences_rmse(seqs: Sequence[TrainingSequence], method: str, config: NavigationConfig, *,
                   dropout_p: float | None = None) -> list[float]:
    """:func:`sequence_rmse` of each of ``seqs``, their filters run as one batch (:func:`run_windows`)."""
    return [filtered for filtered, _ in sequences_errors(seqs, method, config, dropout_p=dropout_p, smoother=False)]


def sequences_errors(seqs: Sequence[TrainingSequence], method: str | Sequence[str], config: NavigationConfig, *,
                     dropout_p: float | None = None, smoother: bool = True) -> list[tuple[float, float]]:
    """The filter and the RTS smoother RMSE (m) of ``method`` (one, or one per sequence) over each
    whole sequence of ``seqs`` after the SE(3) alignment of Table I, their filters run as one batch
    (:func:`run_windows`), no gradient; ``smoother=False``: the filter alone (the smoother's RMSE is NaN).

    With ``config.workers > 1`` on the CPU the sequences are split into that many parts of about
    equal work, each part one batch in a worker process of its own with one thread
    (:mod:`flowins.parallel`; as :func:`~flowins.navigation.navigate_batch` splits a batch): the
    held-out validations of ``train.py`` use every core. A part is another batch, so its RMSE
    differs from the one-process batch's by rounding. The workers run eagerly whatever
    ``filter.compile`` says (each validation's workers are new processes, which would compile
    every shape again); in this process the steps run as it says."""
    methods = [method] * len(seqs) if isinstance(method, str) else list(method)
    if len(methods) != len(seqs):
        raise ValueError(f"sequences_errors: {len(methods)} methods for {len(seqs)} sequences; expected one per sequence")
    loads = [sequence_load(seq, m) for seq, m in zip(seqs, methods)]
    if batch_workers(loads, config, gradient=False) > 1 and not in_distributed_run():
        parts = split_by_load([run_load(load) for load in loads], config.workers)
        # a line per validation would crowd train.py's story: debug level
        log.debug("held-out RMSE: %d runs in %d worker processes (filter.workers=%d)", len(seqs), len(parts),
                  config.workers)
        # eagerly there: the workers start afresh at every validation, and would compile its shapes
        # again each time (filter.compile; minutes a validation, where the pass takes seconds)
        task = functools.partial(_sequences_errors_here, config=dataclasses.replace(config, workers=1, compile="false"),
                                 dropout_p=dropout_p, smoother=smoother)
        return run_parts(task, parts, seqs, methods)
    return _sequences_errors_here(seqs, methods, config, dropout_p=dropout_p, smoother=smoother)


def _sequences_errors_here(seqs: Sequence[TrainingSequence], methods: Sequence[str], config: NavigationConfig, *,
                           dropout_p: float | None, smoother: bool) -> list[tuple[float, float]]:
    """:func:`sequences_errors` as one batch in this process, in inference mode (its cached
    tensors are made outside it: :mod:`flowins.constants`)."""
    with torch.inference_mode():
        results = run_windows(list(seqs), list(methods), config, [(0, seq.imu.t_s.shape[0] - 1) for seq in seqs],
                              dropout_p=dropout_p, smooth=smoother)
        return [(track_rmse(result.track, seq.truth), track_rmse(result.smoothed, seq.truth) if smoother
                 else float("nan")) for seq, result in zip(seqs, results)]


class SequenceLoad(NamedTuple):
    """What :func:`~flowins.batching.run_load` reads of a run: a sequence under one method."""

    imu: ImuStream
    flow: FlowPairs | None
    tracks: Tracks | None


def sequence_load(seq: TrainingSequence, method: str) -> SequenceLoad:
    """``seq`` under ``method`` as :func:`~flowins.batching.run_load` weighs a run (splitting
    held-out runs over processes evens them out)."""
    _, flow = seq.sources(method)
    tracks = flow if isinstance(flow, Tracks) else None
    return SequenceLoad(seq.imu, None if tracks is not None else flow, tracks)


def track_rmse(track: NodeTrack, truth: PoseStream) -> float:
    """Position RMSE (m) of a whole track against the truth after Table I's SE(3) alignment."""
    return float(trajectory_errors(track.t, track.mean[:, STATE.p], truth.t_s, truth.pos_m, align="se3").rmse_m)
