"""The flow updater: a camera frame's flow points as a filter event (the paper's per-frame
order: flow update against the augmented previous pose, then pose forgetting and
augmentation), with the point selection, noise, gate and recovery settings."""
from __future__ import annotations

import dataclasses
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import NamedTuple

import torch
from torch import Tensor

from flowins.config import bounded, check_fields
from flowins.constants import cached_constant, scalar_like
from flowins.filter.augmentation import augment_pose_rows
from flowins.filter.chain import BatchChain, RowBatchEvent
from flowins.filter.compiling import bucket, map_tensors
from flowins.filter.ekf import Gate, UpdateResult, left_out_nis
from flowins.filter.updater import gated_update, likelihood_sums
from flowins.flow.points import FlowPoints
from flowins.measurements.flow import EpipolarUpdate, FlowCamera, FlowMeasurements, epipolar_update, flow_measurements
from flowins.measurements.selection import select_points
from flowins.state import STATE


@dataclass(frozen=True)
class FlowRecovery:
    """What follows frames whose flow the filter rejects (config ``filter.flow.recovery``).

    A filter whose velocity or attitude has gone wrong finds most flow points
    outside its gate, and the gate keeps out the very measurements that would correct
    it. After ``after_frames`` consecutive frames with at least ``min_valid`` valid
    points of which at most ``max_accepted`` (a fraction) pass the gate, the velocity's
    σ is raised by ``velocity_sigma_mps`` and the gyroscope bias's by
    ``gyro_bias_sigma_rps``, so that the next frames can pull the filter back. 0 frames
    switches it off. A frame's log entry says how many gated frames in a row it ends
    (``gated_frames``) and whether it inflated (``inflated``).
    """

    after_frames: int = bounded(5, minimum=0)
    max_accepted: float = bounded(0.5, minimum=0.0, below=1.0)
    min_valid: int = bounded(8, minimum=0)
    velocity_sigma_mps: float = bounded(0.5, minimum=0.0)
    gyro_bias_sigma_rps: float = bounded(2e-3, minimum=0.0)

    def __post_init__(self) -> None:
        check_fields(self)

    def step(self, gated: Tensor, mean: Tensor, cov: Tensor, *, valid: Tensor, accepted: Tensor
             ) -> tuple[Tensor, Tensor, Tensor]:
        """One frame of the recovery on ``r`` rows, read by no one in the pass: the frame counts as
        gated with at least ``max(min_valid, 1)`` valid points of which at most ``max_accepted``
        (a fraction) passed. From the rows' gated frames in a row before it ``gated`` ``(r,)``,
        their updated Gaussians ``mean`` ``(r, D)``, ``cov`` ``(r, D, D)`` and the frame's counts
        ``valid``, ``accepted`` ``(r,)``, returns the covariances with the inflation
        (:meth:`inflation`) added where a row reaches ``after_frames`` gated frames, the gated
        frames in a row with this one, and where it inflated (to start counting again).

        The inflation belongs to the updated node, as a process noise ``Q`` with ``Φ = I`` at the
        frame's time: the smoother's recursion through it is the one through a node of its own."""
        now = (valid >= max(self.min_valid, 1)) & (accepted <= self.max_accepted * valid.to(accepted.dtype))
        gated = torch.where(now, gated + 1, 0)
        inflated = gated >= self.after_frames
        return cov + inflated[:, None, None] * self.inflation(mean), gated, inflated

    def inflation(self, mean: Tensor) -> Tensor:
        """``Q (D, D)``: the covariance added to the state ``mean`` ``(..., D)`` (built once per
        setting, size, dtype and device)."""
        return _inflation(float(self.velocity_sigma_mps), float(self.gyro_bias_sigma_rps), mean.shape[-1], mean.dtype,
                          mean.device)


@cached_constant
def _inflation(velocity_sigma_mps: float, gyro_bias_sigma_rps: float, dim: int, dtype: torch.dtype,
               device: torch.device) -> Tensor:
    Q = torch.zeros(dim, dim, dtype=dtype, device=device)
    Q[STATE.v, STATE.v] = velocity_sigma_mps**2 * torch.eye(3, dtype=dtype, device=device)
    Q[STATE.b_w, STATE.b_w] = gyro_bias_sigma_rps**2 * torch.eye(3, dtype=dtype, device=device)
    return Q


@dataclass(frozen=True)
class FlowUpdate:
    """How a frame's flow points update the filter (every field has a config entry).

    Attributes:
        n_points: points used per frame, chosen at the current state by ``selection``
            (:func:`flowins.measurements.selection.select_points`); None: all.
        selection: ``"parallax"`` | ``"sigma"`` | ``"grid"``; ``cell_px``: spreading cell.
        sigma_scale, sigma_floor_px: the flow noise used is
            ``σ = sqrt((sigma_scale σ_flow)² + sigma_floor_px²)`` per component.
        min_parallax_sigma: leave out points whose rotation-compensated parallax is
            below this many σ (0: keep all).
        parallax_inflation: inflate each point's noise by ``p² / (p² - σ²)`` (``p`` the
            measured parallax): the depth, and with it ``H_x``, is estimated from the same
            noisy flow, and without the correction a low-parallax point claims
            ``(p² + σ²) / p²`` times the information it has (errors in variables).
        gate: χ² gate on each point's scalar innovation (moving objects, bad flow).
        recheck: after the gated update, each point is tested again against the posterior
            of the others (:func:`~flowins.filter.ekf.left_out_nis`, χ²₁ at this gate) and
            the update is made again from the prior without the points that fail (a moving
            object's points agree with one another and pass the prior's wide gate; the
            static scene's posterior is narrow enough to see them); mode ``off``: one update.
        sequential: the paper's point-by-point update instead of one stacked update.
        iterations: relinearisations of the measurement (1: EKF, > 1: iterated EKF).
        augmentation: the pose forgetting + augmentation after the update.
        recovery: what follows frames whose flow is nearly all gated (:class:`FlowRecovery`).
    """

    n_points: int | None = bounded(256, minimum=1)
    selection: str = "parallax"
    cell_px: float = 80.0
    sigma_scale: float | Tensor = 1.0
    sigma_floor_px: float | Tensor = 0.25
    min_parallax_sigma: float = bounded(1.0, minimum=0.0)
    parallax_inflation: bool = True
    gate: Gate = field(default_factory=Gate)
    recheck: Gate = field(default_factory=lambda: Gate(probability=0.99))
    sequential: bool = False
    iterations: int = bounded(1, minimum=1)
    augmentation_mode: str = "limit"
    sigma_p0: float | Tensor = 1e3
    sigma_q0: float | Tensor = 1e2
    recovery: FlowRecovery = field(default_factory=FlowRecovery)

    def __post_init__(self) -> None:
        check_fields(self)


#: every point used, no inflation, no parallax limit, no gate: the paper's update as written
PAPER_FLOW_UPDATE = FlowUpdate(n_points=None, min_parallax_sigma=0.0, parallax_inflation=False,
                               sigma_floor_px=0.0, gate=Gate(mode="off"), recheck=Gate(mode="off"))


@dataclass(frozen=True)
class FlowFrame(RowBatchEvent):
    """A camera frame: flow updates against the augmented previous frame's pose, then
    pose forgetting and augmentation (the paper's per-frame order).

    ``points``: the flow points from the previous frame used by the filter to this
    one (:class:`~flowins.flow.points.FlowPoints`, ``M`` of them; ``M = 0`` for the
    first frame, which only augments). The update uses the epipolar component of each
    point (:func:`flowins.measurements.flow.epipolar_update`); degenerate points are
    skipped and counted in the log.
    """

    time_s: float
    points: FlowPoints
    camera: FlowCamera
    update: FlowUpdate = field(default_factory=FlowUpdate)
    name: str = "flow frame"
    #: ``"analytic"`` | ``"autodiff"``: how ``H_x``, ``H_r`` are computed
    #: (:func:`flowins.measurements.flow.flow_measurements`)
    jacobians: str = "analytic"
    #: ``len(points)`` as a 0-dim int64 tensor on the filter's device (:meth:`place`; None: made
    #: when needed)
    count_t: Tensor | None = None

    def noise_sigma(self, sigma_px: Tensor) -> Tensor:
        """``σ = sqrt((sigma_scale σ_flow)² + sigma_floor_px²)`` per component."""
        u = self.update
        return torch.hypot(u.sigma_scale * sigma_px, scalar_like(u.sigma_floor_px, sigma_px))

    def batch_key(self) -> tuple:
        """Frames with the same update settings and Jacobians act together in a batch."""
        return (FlowFrame, id(self.update), self.jacobians)

    @classmethod
    def place(cls, frames: list[FlowFrame], like: Tensor) -> list[FlowFrame]:
        """The frames with their points in ``like``'s dtype and device, all moved in one copy
        (each frame's points a view of it), and their counts of points there (:attr:`count_t`)."""
        points = [frame.points for frame in frames]
        if all(f.count_t is not None and f.points.uv1_px.dtype == like.dtype and f.points.uv1_px.device == like.device
               for f in frames):
            return list(frames)
        counts = [len(p) for p in points]
        moved = torch.cat([torch.cat(p[:3], -1) for p in points]).to(like).split(counts)
        count_t = torch.tensor(counts, dtype=torch.long).to(like.device)
        return [dataclasses.replace(frame, points=FlowPoints(m[:, 0:2], m[:, 2:4], m[:, 4:6]), count_t=count_t[i])
                for i, (frame, m) in enumerate(zip(frames, moved))]

    @classmethod
    def apply_batch(cls, chain: BatchChain, rows: list[int], frames: list[FlowFrame]) -> None:
        """The frames ``frames[i]`` (all with the same :attr:`update`) on the rows ``rows[i]`` of
        ``chain``: the rows' points (padded to one count, with a mask) are selected,
        linearised and update together, then every row's pose is forgotten and augmented."""
        with_points = [i for i, frame in enumerate(frames) if len(frame.points)]
        if with_points:
            _flow_update(chain, [rows[i] for i in with_points], [frames[i] for i in with_points])
        u = frames[0].update
        augment_pose_rows(chain, rows, sigma_p0=u.sigma_p0, sigma_q0=u.sigma_q0, mode=u.augmentation_mode)


def _flow_update(chain: BatchChain, rows: list[int], frames: list[FlowFrame]) -> None:
    """The flow update of frames with points on the rows ``rows``, their logs and recovery."""
    first = frames[0]
    u = first.update
    candidates = [len(frame.points) for frame in frames]
    # compiled: a few fixed shapes. Every row of the chain takes part (a row without a frame here
    # as a copy of the first row's Gaussian with no valid point, its result dropped) and the
    # points are padded to a bucket, with a mask
    compiled = chain.compiler.enabled
    r = len(rows)
    pad = chain.rows - r if compiled else 0
    step_rows = list(rows) + [rows[0]] * pad
    mean, cov = chain.newest(step_rows)
    if compiled and cov.requires_grad and not mean.requires_grad and torch.is_grad_enabled():
        # a training window's first frames: its mean (detached at the window's start, no update yet)
        # carries no gradient where its covariance does, and a compiled step guards on that, so it
        # would compile a second shape; a leaf of the same values gives the parameters the same gradients
        mean = mean.detach().requires_grad_()
    lengths = [frame.count_t for frame in frames]
    frame_points = [frame.points for frame in frames]
    if pad:
        frame_points += [FlowPoints(*(first.points.uv1_px[:0] for _ in range(3)))] * pad
        if all(n is not None for n in lengths):
            lengths += [lengths[0].new_zeros(())] * pad
    points, mask = stack_points(frame_points, like=mean,
                                lengths=None if any(n is None for n in lengths) else lengths,
                                pad_to=bucket(max(candidates)) if compiled else None)
    points = FlowPoints(points.uv1_px, points.flow_px, first.noise_sigma(points.sigma_px))
    camera = stack_cameras([frame.camera for frame in frames] + [first.camera] * pad).to(mean)  # a copy kept by the camera
    step = chain.compiler(flow_frame_step, mean, cov, points, camera, mask, update=u,
                          select=u.n_points is not None and max(candidates) > u.n_points,
                          gated=chain.row_state("flow_gated", step_rows) if u.recovery.after_frames else None,
                          jacobians=first.jacobians, likelihood=chain.likelihood)
    if pad:  # the rows' own results
        step = map_tensors(lambda t: t[:r], step)
    chain.check_failed(step.failed, "flow update", rows)
    if chain.likelihood:
        chain.add_likelihood(rows, step.nll, step.nll_count)
    if step.gated is not None:
        chain.set_row_state("flow_gated", rows, step.gated)
    logs = [dict(kind="flow", name=frame.name, candidates=n, points=n if u.n_points is None else min(u.n_points, n))
            for frame, n in zip(frames, candidates)]
    chain.update_rows(rows, step.mean, step.cov, logs, values=step.values)


class FlowFrameStep(NamedTuple):
    """A flow frame's update of ``r`` rows (:func:`flow_frame_step`)."""

    mean: Tensor  # (r, D) the rows' new Gaussians: the prior where no point was valid,
    cov: Tensor  # (r, D, D) with the recovery's inflation where it acted
    values: dict[str, Tensor]  # (r,) each: the log's facts (counts, accepted, gated frames, inflated)
    gated: Tensor | None  # (r,) the gated frames in a row to carry to the next frame (None: no recovery)
    failed: Tensor | None  # (r,) bool: a factorisation failed in some iteration
    nll: Tensor | None  # (r,) the prior's innovation likelihood and its count of scalars (with ``likelihood``)
    nll_count: Tensor | None


def flow_frame_step(mean: Tensor, cov: Tensor, points: FlowPoints, camera: FlowCamera, mask: Tensor | None, *,
                    update: FlowUpdate, select: bool, gated: Tensor | None = None, jacobians: str = "analytic",
                    likelihood: bool = False) -> FlowFrameStep:
    """A flow frame's whole update of the priors ``(mean, cov)`` ``(r, D)``, ``(r, D, D)`` from its
    points ``(r, M, 2)`` (``σ`` the noise used; ``mask`` ``(r, M)`` the real ones): with ``select``
    the ``update.n_points`` the selection keeps (:func:`~flowins.measurements.selection.select_points`),
    the iterated update (:func:`flow_iteration`, ``update.iterations`` times; a row whose points
    are all invalid at an iteration stops there, keeping its previous result and that iteration's
    counts), the prior kept where no point was valid, and the recovery (:meth:`FlowRecovery.step`)
    from the rows' gated frames in a row ``gated`` ``(r,)``. A pure function of tensors that reads
    nothing back: without a gradient, ``torch.compile(fullgraph=True)`` takes it whole (a test
    holds it)."""
    u = update
    if select:
        keep = select_points(mean, points, camera.K, camera.R_ci, n_points=u.n_points, method=u.selection,
                             cell_px=u.cell_px, mask=mask)  # (r, n)
        packed = torch.cat(points[:3], -1).gather(-2, keep.unsqueeze(-1).expand(*keep.shape, 6))  # one gather
        points = FlowPoints(packed[..., 0:2], packed[..., 2:4], packed[..., 4:6])
        mask = None if mask is None else mask.gather(-1, keep)
    min_parallax = torch.linalg.vector_norm(points.sigma_px, dim=-1) * (u.min_parallax_sigma / 2**0.5)
    x_i, failed, nll = mean, None, (None, None)
    for iteration in range(u.iterations):  # linearised at x_i, applied to the prior
        it = flow_iteration(x_i, mean, cov, points, camera, mask, min_parallax, update=u, jacobians=jacobians,
                            first=iteration == 0, likelihood=iteration == 0 and likelihood)
        if it.result.failed is not None:
            failed = it.result.failed if failed is None else failed | it.result.failed
        if iteration == 0 and likelihood:  # the likelihood of the prior's prediction: the first iteration's only
            nll = likelihood_sums(it.result, 1)
        m, step = it.measurements, it.result
        counts_now = torch.stack((m.valid.sum(-1), m.n_degenerate, m.n_behind, m.n_low_parallax), -1)
        accepted = step.weight.sum(-1)
        if iteration == 0:
            new_mean, new_cov, counts, weight = step.mean, step.cov, counts_now, accepted
            updated = going = None if u.iterations == 1 else m.valid.any(-1)
        else:
            go = going & m.valid.any(-1)
            new_mean = torch.where(go.unsqueeze(-1), step.mean, new_mean)
            new_cov = torch.where(go[:, None, None], step.cov, new_cov)
            counts = torch.where(going.unsqueeze(-1), counts_now, counts)
            weight = torch.where(go, accepted, weight)
            going = go
        x_i = new_mean
    # a row updated iff its first iteration had a valid point; the others keep their node
    has = counts[:, 0] > 0 if updated is None else updated
    new_mean = torch.where(has[:, None], new_mean, mean)
    new_cov = torch.where(has[:, None, None], new_cov, cov)
    values = dict(zip(("valid", "degenerate", "behind", "low_parallax"), counts.unbind(-1)))
    values["accepted"] = torch.where(has, weight, 0.0)
    carried = None
    if gated is not None:
        new_cov, gated, inflated = u.recovery.step(gated, new_mean, new_cov, valid=counts[:, 0],
                                                   accepted=values["accepted"])
        values.update(gated_frames=gated, inflated=inflated)
        carried = torch.where(inflated, 0, gated)
    return FlowFrameStep(new_mean, new_cov, values, carried, failed, *nll)


def flow_frames(pairs, camera, update: FlowUpdate, *, t_min_s: float, t_max_s: float, name: str = "flow",
                jacobians: str = "analytic") -> tuple[list[FlowFrame], int]:
    """One :class:`FlowFrame` per frame time of ``pairs`` (a :class:`~flowins.flow.pairs.FlowPairs`).

    A pair's points update the filter at its end time; its start time must be the
    previous frame event (where the pose was augmented), otherwise an augmentation-only
    frame is inserted there first. Pairs not inside ``[t_min_s, t_max_s]`` are left out
    and counted (second return value).
    """
    empty = torch.zeros(0, 2, dtype=torch.float64)
    events: list[FlowFrame] = []
    outside = 0
    last = None
    for k, (t1, t2) in enumerate(zip(pairs.t1_s.tolist(), pairs.t2_s.tolist())):
        if t1 < t_min_s or t2 > t_max_s:
            outside += 1
            continue
        if last is None or last != t1:
            events.append(FlowFrame(t1, FlowPoints(empty, empty, empty), camera, update, f"{name} frame at {t1:.3f} s", jacobians))
        events.append(FlowFrame(t2, pairs.points[k], camera, update, f"{name} pair {k} ({t1:.3f} -> {t2:.3f} s)", jacobians))
        last = t2
    return events, outside


class FlowIteration(NamedTuple):
    """One step of a flow frame's (iterated) update (:func:`flow_iteration`)."""

    measurements: FlowMeasurements  # linearised at the step's point
    result: UpdateResult  # the gated update of the prior


def flow_iteration(x_i: Tensor, mean: Tensor, cov: Tensor, points: FlowPoints, camera: FlowCamera,
                   mask: Tensor | None, min_parallax_px: Tensor, *, update: FlowUpdate, jacobians: str = "analytic",
                   first: bool = True, likelihood: bool = False) -> FlowIteration:
    """A frame's flow points ``(r, M, 2)`` (``σ`` the noise used) linearised at ``x_i`` ``(r, D)``
    and applied to the prior ``(mean, cov)`` as scalar epipolar measurements, gated
    (:func:`~flowins.filter.updater.gated_update`); ``first``: ``x_i`` is the prior's mean (the
    innovation needs no shift). A pure function of tensors with no read-back: without a
    gradient, ``torch.compile(fullgraph=True)`` takes it whole (a test holds it)."""
    m = flow_measurements(x_i, points.flow_px, points.uv1_px, camera, mask=mask, min_parallax_px=min_parallax_px,
                          jacobians=jacobians)
    upd = epipolar_update(m, points.sigma_px, parallax_inflation=update.parallax_inflation)
    innovation = upd.innovation if first else upd.innovation - (upd.H @ (mean - x_i)[:, None, :, None]).squeeze(-1)
    result = gated_update(mean, cov, H=upd.H, residual=innovation, noise_cov=upd.noise_cov, gate=update.gate,
                          sequential=update.sequential, valid=m.valid, likelihood=likelihood)
    if update.recheck.mode != "off":
        result = _recheck(result, mean, cov, upd, innovation, m.valid, update)
    return FlowIteration(m, result)


def _recheck(first: UpdateResult, mean: Tensor, cov: Tensor, upd: EpipolarUpdate, innovation: Tensor,
             valid: Tensor, update: FlowUpdate) -> UpdateResult:
    """The update ``first`` made again from the prior ``(mean, cov)`` with each point weighed
    by ``update.recheck`` on its NIS against the posterior of the others
    (:func:`~flowins.filter.ekf.left_out_nis`); the prior's NIS and likelihood kept from
    ``first``, the weights those of both gates."""
    nis = left_out_nis(innovation[..., 0], upd.H[..., 0, :], upd.noise_cov[..., 0, 0], first.weight, mean,
                       first.mean, first.cov)
    keep = update.recheck.weights(nis, 1)  # (r, M)
    again = gated_update(mean, cov, H=upd.H * keep[..., None, None], residual=innovation * keep.unsqueeze(-1),
                         noise_cov=upd.noise_cov, gate=update.gate, sequential=update.sequential, valid=valid,
                         likelihood=False)
    failed = first.failed if again.failed is None else again.failed if first.failed is None \
        else first.failed | again.failed
    return UpdateResult(again.mean, again.cov, first.nis, again.weight * keep, first.nll, failed)


def stack_points(points: list[FlowPoints], *, like: Tensor, lengths: list[Tensor] | None = None,
                 pad_to: int | None = None) -> tuple[FlowPoints, Tensor | None]:
    """The points of ``r`` frames as one batch ``(r, M, 2)`` (dtype and device of ``like``) and
    the mask of real points ``(r, M)`` (None when every frame has ``M`` points), made from
    ``lengths``, the frames' counts of points as 0-dim tensors on ``like``'s device when given (no
    copy from the host). ``pad_to``: ``M`` at least this, and a mask whatever the counts (one
    shape for a compiled step)."""
    counts = [len(p) for p in points]
    M = max(counts) if pad_to is None else max(max(counts), pad_to)
    if len(points) == 1 and counts[0] == M:
        stacked = [points[0][k].unsqueeze(0) for k in range(3)]
    elif all(c == M for c in counts):
        stacked = [torch.stack([p[k] for p in points]) for k in range(3)]
    else:
        pads = [(0, 0, 0, M - c) for c in counts]
        stacked = [torch.stack([torch.nn.functional.pad(p[k], pad) for p, pad in zip(points, pads)]) for k in range(3)]
    stacked = FlowPoints(*(x if x.dtype == like.dtype and x.device == like.device else x.to(like) for x in stacked))
    if all(c == M for c in counts) and pad_to is None:
        return stacked, None
    rows = torch.tensor(counts, device=like.device) if lengths is None else torch.stack(lengths)
    mask = torch.arange(M, device=like.device) < rows.unsqueeze(-1)
    return stacked, mask


def stack_cameras(cameras: list[FlowCamera]) -> FlowCamera:
    """One camera for the batch: the shared one, or ``K``, ``R_ci``, ``t_ci`` stacked per row.

    A stacked camera is kept for the next frames of the same cameras (the last few
    combinations, with the cameras themselves, so their identities stay valid), so that the
    terms it caches (:class:`~flowins.measurements.flow.FlowCamera`) are built once, not
    once per frame; cameras with a gradient are stacked afresh."""
    if all(c is cameras[0] for c in cameras):
        return cameras[0]
    if any(c.tracked for c in cameras):
        return FlowCamera(*(torch.stack([getattr(c, k) for c in cameras]) for k in ("K", "R_ci", "t_ci")))
    key = tuple(id(c) for c in cameras)
    if key in _STACKED:
        _STACKED.move_to_end(key)
        return _STACKED[key][1]
    with torch.inference_mode(False):  # plain tensors, usable by later runs with gradients too
        stacked = FlowCamera(*(torch.stack([getattr(c, k) for c in cameras]) for k in ("K", "R_ci", "t_ci")))
    _STACKED[key] = (tuple(cameras), stacked)
    while len(_STACKED) > 8:
        _STACKED.popitem(last=False)
    return stacked


#: recently stacked cameras by the identities of their rows' cameras (:func:`stack_cameras`)
_STACKED: OrderedDict[tuple[int, ...], tuple[tuple[FlowCamera, ...], FlowCamera]] = OrderedDict()
