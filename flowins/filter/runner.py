"""Running the EKF over a recording: IMU prediction between measurement events.

The runs of a batch step together from event to event; the IMU propagation between
events appends nodes to a :class:`~flowins.filter.chain.BatchChain`, and each event
acts on its newest node (:class:`~flowins.filter.chain.Event`). An event time between
two IMU samples splits that sample's step in two (both parts use the sample, as the
paper's ``ã_k`` drives the whole interval ``(t_{k-1}, t_k]``).
"""
from __future__ import annotations

import functools
from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from flowins.memory import available_memory_bytes, describe_bytes
from flowins.progress import progress as track_progress
from flowins.filter.chain import BatchChain, BatchEvent, Event, FilterTrack, place_events
from flowins.filter.compiling import Compiler
from flowins.filter.propagation import (NodePlan, Propagated, pad_plan, plan_nodes, propagate_batched,
                                       propagate_reference)
from flowins.ins.mechanization import STANDARD_GRAVITY_MPS2, ProcessNoise
from flowins.state import NOISE_DIM, STATE_DIM, symmetrize, window_size


def _step_grid(t_imu: Tensor, event_times: Tensor) -> tuple[Tensor, Tensor]:
    """Merged step end times and, per step, the IMU sample that drives it."""
    grid = torch.unique(torch.cat((t_imu[1:], event_times[event_times > t_imu[0]])))  # sorted
    sample = torch.searchsorted(t_imu, grid, right=False)
    return grid, sample


@dataclass(frozen=True)
class FilterInput:
    """One run of :func:`run_filters`: IMU samples ``t_s (N,)``, ``acc_mps2``/``gyro_rps``
    ``(N, 3)``, the prior ``mean0 (D,)``, ``cov0 (D, D)`` at ``t_s[0]`` (``D = 19 + 7 N``: 26 for the
    paper's one cloned pose, more with a window of ``N`` clones, :func:`flowins.filter.augmentation.with_window`),
    its events and, optionally, its own process noise (default: the batch's)."""

    t_s: Tensor
    acc_mps2: Tensor
    gyro_rps: Tensor
    mean0: Tensor
    cov0: Tensor
    events: Sequence[Event] = ()
    noise: ProcessNoise | None = None


def run_filter(
    *,
    t_s: Tensor,
    acc_mps2: Tensor,
    gyro_rps: Tensor,
    mean0: Tensor,
    cov0: Tensor,
    noise: ProcessNoise,
    events: Sequence[Event] = (),
    output_every: int = 10,
    gravity_mps2: float = STANDARD_GRAVITY_MPS2,
    jacobians: str = "analytic",
    scheme: str = "midpoint",
    progress: bool = False,
    likelihood: bool = False,
) -> FilterTrack:
    """Run the EKF from ``(mean0, cov0)`` at ``t_s[0]`` through all IMU samples and events.

    Args:
        t_s ``(N,)`` IMU times (strictly increasing; validate with
        :class:`flowins.data.ImuStream`), acc_mps2 / gyro_rps ``(N, 3)``.
        mean0 ``(D,)``, cov0 ``(D, D)``: the prior at ``t_s[0]``, ``D = 19 + 7 N`` (26 for the paper's
            one cloned pose); their dtype is the filter's dtype.
        events: measurement events, each with ``time_s`` in ``[t_s[0], t_s[-1]]``;
            events at the same time are applied in the given order.
        output_every: a node every this many IMU samples (plus one at every event).
        jacobians: ``"analytic"`` (fast, batched closed forms) or ``"autodiff"``
            (the reference: per-sample ``torch.func.jacrev``).
        scheme: mechanization scheme, ``"midpoint"`` or ``"paper"``
            (see :mod:`flowins.ins.mechanization`).
        likelihood: sum the innovation negative log-likelihood of the updates that report
            one (:attr:`FilterTrack.nll`).

    The one-run case of :func:`run_filters`.
    """
    run = FilterInput(t_s, acc_mps2, gyro_rps, mean0, cov0, events)
    return run_filters([run], noise=noise, output_every=output_every, gravity_mps2=gravity_mps2,
                       jacobians=jacobians, scheme=scheme, progress=progress, likelihood=likelihood)[0]


class Segment(NamedTuple):
    """The IMU steps of one run up to its next event, and what follows them."""

    first: int  # the first step
    last: int  # the last step (the event's)
    node_steps: list[int]  # the steps that end at a node of the chain
    node_times: list[float]  # those nodes' times
    events: list  # the events at the last step


class _Run(NamedTuple):
    """One run's schedule, ready to step: its samples and the segments between events."""

    t0: float
    acc: Tensor  # (S, 3) the reading driving each step
    gyro: Tensor
    dt: Tensor  # (S,)
    scales: Tensor  # (S, 15) the steps' process noise variances over the squared densities (no gradient)
    squared: Tensor  # (15,) the squared densities (the parameters' gradient)
    segments: list[Segment]
    early: list  # events at the start time


def run_filters(
    runs: Sequence[FilterInput],
    *,
    noise: ProcessNoise,
    output_every: int = 10,
    gravity_mps2: float = STANDARD_GRAVITY_MPS2,
    jacobians: str = "analytic",
    scheme: str = "midpoint",
    progress: bool = False,
    likelihood: bool = False,
    description: str = "filter",
    compiler: Compiler | None = None,
) -> list[FilterTrack]:
    """Run ``B`` filters in one batched pass: each run as :func:`run_filter` runs it alone.

    The runs may differ in length, IMU rate, events and their times. They step together
    segment by segment (the IMU samples up to each run's next event): the shorter
    segments are padded with ``Δt = 0`` steps, which are exact identities, and every
    operation acts on a leading batch dimension. Events of the same kind at the same
    segment are applied together where they are batched events
    (:class:`~flowins.filter.chain.BatchEvent`, :func:`apply_events`), one run at a time
    otherwise. Each run's track equals its run alone up to rounding (tests check 1e-10
    in float64).

    Args:
        runs: the :class:`FilterInput` of each run; every ``mean0`` has the same size ``D``
            (``19 + 7 N``), dtype and device (the filter's).
        noise: the process noise of the runs without their own.
        output_every, gravity_mps2, jacobians, scheme, likelihood: as for :func:`run_filter`, for
            all runs.
        progress, description: report the pass's progress under this name.
        compiler: how events run their pure steps (:mod:`flowins.filter.compiling`; None: eagerly).
    """
    if jacobians not in ("analytic", "autodiff"):
        raise ValueError(f"jacobians must be 'analytic' or 'autodiff', got {jacobians!r}")
    if output_every < 1:
        raise ValueError(f"output_every must be >= 1, got {output_every}")
    if not runs:
        return []
    like = runs[0].mean0
    dim = _state_size(runs[0], 0)
    for i, run in enumerate(runs):
        if _state_size(run, i) != dim:
            raise ValueError(f"run {i}: mean0 has {run.mean0.shape[-1]} entries, run 0's {dim}; the runs of a "
                             f"batch have one state size (one window of cloned poses)")
        if run.mean0.dtype != like.dtype or run.mean0.device != like.device:
            raise ValueError(f"run {i}: mean0 is {run.mean0.dtype} on {run.mean0.device}, run 0's "
                             f"{like.dtype} on {like.device}; a batch has one dtype and device")
    if jacobians == "autodiff" and len(runs) > 1:  # the reference path: one run at a time
        return [run_filters([run], noise=noise, output_every=output_every, gravity_mps2=gravity_mps2,
                            jacobians=jacobians, scheme=scheme, likelihood=likelihood)[0] for run in runs]
    dtype, device = like.dtype, like.device
    noises = [run.noise or noise for run in runs]
    plans = [_prepare(run, output_every, dtype, device, n) for run, n in zip(runs, noises)]
    B = len(runs)
    chain = BatchChain(B, likelihood=likelihood, capacity=[expected_nodes(run, output_every) for run in runs],
                       compiler=compiler)
    eye = torch.eye(dim, dtype=dtype, device=device)
    chain.add_nodes([[plan.t0] for plan in plans], eye.expand(B, 1, dim, dim),
                    torch.stack([run.mean0 for run in runs]).unsqueeze(1),
                    symmetrize(torch.stack([run.cov0 for run in runs])).unsqueeze(1))
    apply_events(chain, [plan.early for plan in plans])
    # every run's steps in one flat array, and a padding step (Δt = 0) at its end
    offsets = torch.tensor([0] + [plan.dt.shape[0] for plan in plans]).cumsum(0).tolist()
    # compiled: every segment's steps, nodes and intervals padded to a few fixed sizes (:func:`_segment_steps`)
    compiled = chain.compiler.enabled and chain.compiler.all_steps and jacobians == "analytic"
    flat = None if B == 1 and not compiled else [
        torch.cat([getattr(plan, name) for plan in plans] + [zero])
        for name, zero in (("acc", like.new_zeros(1, 3)), ("gyro", like.new_zeros(1, 3)),
                           ("dt", like.new_zeros(1)), ("scales", like.new_zeros(1, NOISE_DIM)))]
    # the steps' noise, segment by segment: the densities times the steps' scales
    # (ProcessNoise.variance_scales), so that no segment's gradient passes through all steps
    squared = torch.stack([plan.squared for plan in plans]).unsqueeze(1)  # (B, 1, 15)
    count = max(len(plan.segments) for plan in plans)
    steps = _place_steps([_segment_steps(plans, offsets, k, compiled=compiled) for k in range(count)], device)
    for k in track_progress(range(count), total=count, description=description, unit="update", enabled=progress):
        segments = [plan.segments[k] if k < len(plan.segments) else None for plan in plans]
        nodes, index, node_steps, extra, compile_this = steps[k]
        if index is None:
            first, last = segments[0].first, segments[0].last
            acc, gyro, dt, scales = (getattr(plans[0], name)[first:last + 1].unsqueeze(0)
                                     for name in ("acc", "gyro", "dt", "scales"))
        else:
            acc, gyro, dt, scales = (part[index] for part in flat)
        variances = squared * scales
        if jacobians == "analytic":
            propagate = functools.partial(chain.compiler, propagate_batched) if compile_this else propagate_batched
            out = propagate(chain.mean, chain.cov, acc, gyro, dt, nodes._replace(real=[]), variances=variances,
                            gravity_mps2=gravity_mps2, scheme=scheme)
            if extra:  # the padding nodes added for the compiled shape (the first ones), dropped
                out = Propagated(*(t[:, extra:] for t in out))
        else:
            out = propagate_reference(chain.mean[0], chain.cov[0], acc[0], gyro[0], dt[0],
                                      torch.tensor(node_steps[0]), noise=noises[0], gravity_mps2=gravity_mps2,
                                      scheme=scheme)
            out = type(out)(*(t.unsqueeze(0) for t in out))
        chain.add_nodes([[] if segment is None else segment.node_times for segment in segments],
                        out.transition, out.mean, out.cov, real=nodes.real)
        apply_events(chain, [[] if segment is None else segment.events for segment in segments])
    return chain.finish()


#: the largest segment a compiled pass propagates compiled: the flow frames' rhythm (10 IMU steps
#: between frames, a node on the output grid and one at the frame). Longer segments (an IMU and
#: GNSS stretch: 100 steps, 10 nodes) are few and each size would cost a compile: they run eagerly
COMPILED_STEPS, COMPILED_NODES = 16, 2


class _SegmentSteps(NamedTuple):
    """Segment ``k`` of every run, ready to propagate (:func:`_segment_steps`)."""

    plan: NodePlan  # the nodes (padding nodes first), on the host until placed
    index: Tensor | list[list[int]] | None  # each row's steps in the runs' flat steps (None: one run's slice)
    node_steps: list[list[int]]  # each row's node steps
    extra: int  # padding nodes added before the plan's own for a compiled shape (dropped after)
    compiled: bool  # the segment runs through the pass's compiler


def _segment_steps(plans: Sequence[_Run], offsets: list[int], k: int, *, compiled: bool = False) -> _SegmentSteps:
    """Segment ``k`` of every run, padded to one length ``L`` (padding steps first).

    ``compiled`` (a compiled pass): a segment of up to :data:`COMPILED_STEPS` steps and
    :data:`COMPILED_NODES` nodes per row is padded to exactly that many, every interval to ``L``
    slots, so that the pass's propagation meets one shape; a larger one runs eagerly."""
    segments = [plan.segments[k] if k < len(plan.segments) else None for plan in plans]
    L = max(last - first + 1 for first, last, *_ in filter(None, segments))
    nodes = max(len(segment.node_steps) for segment in filter(None, segments))
    compiled = compiled and L <= COMPILED_STEPS and nodes <= COMPILED_NODES
    if compiled:
        L = COMPILED_STEPS
    elif len(plans) == 1:
        node_steps = [[step - segments[0].first for step in segments[0].node_steps]]
        return _SegmentSteps(plan_nodes(node_steps, L), None, node_steps, 0, False)
    pad = offsets[-1]
    index, node_steps = [], []
    for offset, segment in zip(offsets, segments):
        if segment is None:
            index.append([pad] * L)
            node_steps.append([])
            continue
        first, last, steps = segment.first, segment.last, segment.node_steps
        shift = L - (last - first + 1)  # padding steps first: the last step is the segment's
        index.append([pad] * shift + list(range(offset + first, offset + last + 1)))
        node_steps.append([step - first + shift for step in steps])
    plan = plan_nodes(node_steps, L)
    if not compiled:
        return _SegmentSteps(plan, index, node_steps, 0, False)
    extra = COMPILED_NODES - plan.node_step.shape[1]
    plan = pad_plan(plan, nodes=COMPILED_NODES, slots=L, sentinel=len(plans) * L)
    return _SegmentSteps(plan, index, node_steps, extra, True)


def _place_steps(steps: list[_SegmentSteps], device: torch.device) -> list[_SegmentSteps]:
    """The segments' node plans and step indices moved to ``device`` in one copy: a pass copies
    nothing from the host per segment (on a GPU a copy from pageable memory waits for the queue).
    The plans keep which nodes are the rows' own, less the padding added for a compiled shape."""
    parts = []
    for step in steps:
        parts += [step.plan.group, step.plan.node_step] + ([] if step.index is None else [torch.tensor(step.index)])
    if not parts:
        return []
    moved = iter(torch.cat([p.reshape(-1) for p in parts]).to(device).split([p.numel() for p in parts]))
    out = []
    for step in steps:
        plan = step.plan
        group, node_step = next(moved).view(plan.group.shape), next(moved).view(plan.node_step.shape)
        index = None if step.index is None else next(moved).view(len(step.index), -1)
        real = [flags[step.extra:] for flags in plan.real]
        out.append(step._replace(plan=NodePlan(group, node_step, real), index=index))
    return out


def expected_nodes(run: FilterInput, output_every: int) -> int:
    """The nodes a run's chain gets at most, as :func:`chain_bytes` counts them."""
    return int(run.t_s.shape[0]) // output_every + 2 * len(run.events) + 1


def chain_bytes(runs: Sequence[FilterInput], *, output_every: int = 10) -> int:
    """About how many bytes the node chain of :func:`run_filters` over ``runs`` (one batch) holds
    when the pass ends: per node a transition and a covariance, ``D x D`` each, two means, and at
    each updated node its predicted covariance besides (:class:`~flowins.filter.chain.BatchChain`).

    A run has a node every ``output_every`` IMU samples, at the end, and at most two per event
    (at its time, and a linear prediction such as a pose copy), of which at most one is updated:
    ``N // output_every + 2 E + 1`` nodes, ``E`` updated, for ``N`` samples and ``E`` events, an
    upper estimate where events append fewer. The rows of a batch share their columns, so the
    batch holds ``B`` times its largest run's nodes."""
    if not runs:
        return 0
    D = runs[0].mean0.shape[-1]
    nodes = max(expected_nodes(run, output_every) for run in runs)
    updated = max(len(run.events) for run in runs)
    return len(runs) * ((2 * nodes + updated) * D * D + 2 * nodes * D) * runs[0].mean0.element_size()


def _state_size(run: FilterInput, i: int) -> int:
    """``D`` of run ``i``'s prior: ``mean0`` ``(D,)``, ``cov0`` ``(D, D)``, ``D = 19 + 7 N`` (ValueError otherwise)."""
    shape, cov_shape = tuple(run.mean0.shape), tuple(run.cov0.shape)
    dim = shape[0] if len(shape) == 1 else -1
    try:
        window_size(dim)
    except ValueError:
        dim = -1
    if dim < 0 or cov_shape != (dim, dim):
        raise ValueError(f"run {i}: mean0 must be (D,) and cov0 (D, D) with D = 19 + 7 N, N >= 1 cloned poses "
                         f"({STATE_DIM} for the paper's one); got {shape}, {cov_shape}")
    return dim


def apply_events(chain: BatchChain, events: Sequence[Sequence[Event]]) -> None:
    """Apply ``events[b]`` (in order) to row ``b`` of ``chain``, for every row.

    The ``i``-th events of all rows act together: the :class:`BatchEvent` ones, grouped
    by type and ``batch_key()``, in one ``apply_batch`` call per group; the others one row
    at a time through :meth:`BatchChain.row`.
    """
    for i in range(max((len(e) for e in events), default=0)):
        groups: dict[tuple[type, Hashable], list[tuple[int, BatchEvent]]] = {}
        for b, row_events in enumerate(events):
            if i >= len(row_events):
                continue
            event = row_events[i]
            if _acts_in_batches(event):
                groups.setdefault((type(event), event.batch_key()), []).append((b, event))
            else:
                event.apply(chain.row(b))
        for (kind, _), members in groups.items():
            kind.apply_batch(chain, [b for b, _ in members], [e for _, e in members])


#: per event type, whether it is a :class:`BatchEvent` (a runtime protocol check inspects the
#: class's members, tens of microseconds: once per type, not once per event and row)
_BATCH_EVENT_TYPES: dict[type, bool] = {}


def _acts_in_batches(event: Event) -> bool:
    kind = type(event)
    acts = _BATCH_EVENT_TYPES.get(kind)
    if acts is None:
        acts = _BATCH_EVENT_TYPES[kind] = isinstance(event, BatchEvent)
    return acts


def _prepare(run: FilterInput, output_every: int, dtype: torch.dtype, device: torch.device,
             noise: ProcessNoise) -> _Run:
    """One run's steps (IMU samples and event times), segments, nodes and events."""
    t_imu = torch.as_tensor(run.t_s, dtype=torch.float64)
    t0 = float(t_imu[0])
    events = sorted(run.events, key=lambda e: e.time_s)  # stable: same-time order kept
    events = place_events(events, torch.empty(0, dtype=dtype, device=device))  # their data moved once, not per event
    plan = _schedule(t_imu, events, output_every)
    dt = torch.diff(plan.grid, prepend=t_imu[:1]).to(dtype=dtype, device=device)
    acc = torch.as_tensor(run.acc_mps2)[plan.sample].to(dtype=dtype, device=device)
    gyro = torch.as_tensor(run.gyro_rps)[plan.sample].to(dtype=dtype, device=device)
    node_index = plan.node_index.tolist()
    node_t_s = plan.grid[plan.node_index].tolist()
    segments, start, j = [], 0, 0
    for end in plan.segment_ends:
        steps, times = [], []
        while j < len(node_index) and node_index[j] <= end:
            steps.append(node_index[j])
            times.append(node_t_s[j])
            j += 1
        segments.append(Segment(start, end, steps, times, plan.events_by_step.get(end, [])))
        start = end + 1
    return _Run(t0, acc, gyro, dt, noise.variance_scales(dt), noise.squared_densities(dtype, device), segments,
                [e for e in events if e.time_s <= t0])


class _Schedule(NamedTuple):
    grid: Tensor  # (S,) the step times: the IMU samples and the event times
    sample: Tensor  # (S,) the IMU sample each step's reading comes from
    node_index: Tensor  # steps that are nodes: the output grid, events, the end
    segment_ends: list[int]  # a propagation ends at each event step and at the end
    events_by_step: dict[int, list[Event]]  # the events applied after each step (after t_s[0])


def _schedule(t_imu: Tensor, events: Sequence[Event], output_every: int) -> _Schedule:
    """Where the filter steps, keeps nodes and stops for events (events sorted by time,
    each checked to lie inside the IMU's time span)."""
    t0, t_end = float(t_imu[0]), float(t_imu[-1])
    for event in events:
        if not t0 <= event.time_s <= t_end:
            raise ValueError(
                f"{event.name}: time {event.time_s:.6f} s is outside the IMU time span "
                f"[{t0:.6f}, {t_end:.6f}] s; crop the stream or the IMU to overlap"
            )
    event_times = torch.tensor([e.time_s for e in events], dtype=torch.float64)
    grid, sample = _step_grid(t_imu, event_times)
    # node flags per step: output grid, events, the end
    is_node = torch.zeros(grid.shape[0], dtype=torch.bool)
    on_sample = grid == t_imu[sample]
    is_node |= on_sample & (sample % output_every == 0)
    event_step = torch.searchsorted(grid, event_times[event_times > t0])
    is_node[event_step] = True
    is_node[-1] = True
    # a segment ends at each event step (the mean must be recomputed after updates)
    segment_ends = sorted(set(event_step.tolist()) | {grid.shape[0] - 1})
    events_by_step: dict[int, list[Event]] = {}
    later = [event for event in events if event.time_s > t0]
    for event, step in zip(later, event_step.tolist()):
        events_by_step.setdefault(step, []).append(event)
    return _Schedule(grid, sample, torch.nonzero(is_node).squeeze(-1), segment_ends, events_by_step)


#: a filter pass's peak memory over its node chain's (:func:`chain_bytes`):
#: the chain and the smoother's work, and for a batch of more than four rows the chain's copy
#: into the tracks. Measured: the 300 s walk's two sparse rows at ``filter.tracks.window=10``
#: estimate 2.9 GB and peak at 5.1 GB resident (docs/performance.md)
PEAK_OVER_CHAIN = 2.5


def memory_warning(inputs: Sequence[FilterInput], *, output_every: int,
                   available: int | None | str = "ask") -> str | None:
    """Why a filter pass over ``inputs`` (one batch) may not fit in memory, or None: its estimated
    peak (:data:`PEAK_OVER_CHAIN` times :func:`chain_bytes`) against 80 %
    of the memory free on the state's device (``available`` bytes; ``"ask"``: as
    :func:`~flowins.memory.available_memory_bytes` tells; None: unknown, no warning)."""
    if not inputs:
        return None
    device = inputs[0].mean0.device
    if available == "ask":
        available = available_memory_bytes(device)
    need = PEAK_OVER_CHAIN * chain_bytes(inputs, output_every=output_every)
    if available is None or need <= 0.8 * available:
        return None
    D = inputs[0].mean0.shape[-1]
    window = window_size(D)
    longest = max(float(run.t_s[-1] - run.t_s[0]) for run in inputs)
    return (f"this filter pass may need about {describe_bytes(need)} ({len(inputs)} run(s) in one batch, the longest "
            f"{longest:.0f} s; a state of {D} entries, {window} cloned pose(s), whose node chain keeps {D} x {D} "
            f"matrices at every node), and the {device.type.upper()} has {describe_bytes(available)} free. A smaller "
            f"filter.tracks.window, fewer combinations or seeds at once, or a shorter sequence (sequence.end_s) needs less")
