"""Running the EKF over a recording: IMU prediction between measurement events.

The filter keeps a *chain of nodes*. A node is a time at which the filter reports
its estimate: every ``output_every``-th IMU sample, every measurement event and the
end of the run. Each node stores its predicted and filtered Gaussians and the
transition ``Φ`` from the previous node's filtered state (the product of the
step Jacobians in between). Events act on the newest node: an update replaces its
filtered Gaussian; a linear prediction (pose forgetting) appends a new node at the
same time. The RTS smoother (:mod:`flowins.filter.smoother`) runs on this chain,
so it is exact through every prediction, forgetting and augmentation step.

An event time between two IMU samples splits that sample's step in two (both parts
use the sample, as the paper's ``ã_k`` drives the whole interval ``(t_{k-1}, t_k]``).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Protocol

import torch
from torch import Tensor

from flowins.progress import progress as track_progress
from flowins.filter.ekf import UpdateResult, linear_predict
from flowins.filter.propagation import propagate_batched, propagate_reference
from flowins.ins.mechanization import STANDARD_GRAVITY_MPS2, ProcessNoise
from flowins.state import STATE_DIM, normalize_quaternions, symmetrize


class Event(Protocol):
    """A measurement (or any filter operation) at ``time_s``."""

    time_s: float
    name: str

    def apply(self, chain: ChainBuilder) -> None: ...


@dataclass
class ChainBuilder:
    """The growing node chain; events call :meth:`update` and :meth:`linear_predict`.

    Nodes are stored in chunks (a propagation adds all the nodes of an IMU run at
    once); the newest node's filtered Gaussian is always its own entry, so an
    update replaces it without touching the rest.
    """

    t_s: list[float] = field(default_factory=list)
    log: list[dict[str, Any]] = field(default_factory=list)
    #: what events carry from one to the next (e.g. GNSS fixes held back for the heading)
    memory: dict[str, Any] = field(default_factory=dict)
    #: ``(node, A, b, Q)`` of each change of frame (:meth:`change_frame`)
    frame_changes: list[tuple[int, Tensor, Tensor, Tensor]] = field(default_factory=list)
    _transition: list[Tensor] = field(default_factory=list)  # chunks (n, 26, 26)
    _pred_mean: list[Tensor] = field(default_factory=list)  # chunks (n, 26)
    _pred_cov: list[Tensor] = field(default_factory=list)
    _mean: list[Tensor] = field(default_factory=list)  # chunks; the last is (1, 26)
    _cov: list[Tensor] = field(default_factory=list)

    @property
    def mean(self) -> Tensor:
        """Filtered mean of the newest node ``(26,)``."""
        return self._mean[-1][0]

    @property
    def cov(self) -> Tensor:
        return self._cov[-1][0]

    @property
    def time_s(self) -> float:
        return self.t_s[-1]

    def add_nodes(self, t_s: Sequence[float], transition: Tensor, mean: Tensor, cov: Tensor) -> None:
        """Append ``n`` predicted nodes: times, transitions ``(n, 26, 26)``, means ``(n, 26)``, covs."""
        self.t_s.extend(float(t) for t in t_s)
        self._transition.append(transition)
        self._pred_mean.append(mean)
        self._pred_cov.append(cov)
        if mean.shape[0] > 1:
            self._mean.append(mean[:-1])
            self._cov.append(cov[:-1])
        self._mean.append(mean[-1:])
        self._cov.append(cov[-1:])

    def add_node(self, t_s: float, transition: Tensor, mean: Tensor, cov: Tensor) -> None:
        self.add_nodes([t_s], transition.unsqueeze(0), mean.unsqueeze(0), cov.unsqueeze(0))

    def update(self, result: UpdateResult | tuple[Tensor, Tensor], **info: Any) -> None:
        """Replace the newest node's filtered Gaussian by an update's result."""
        self._mean[-1] = result[0].unsqueeze(0)
        self._cov[-1] = result[1].unsqueeze(0)
        if info:
            self.log.append({"t_s": self.time_s, **info})

    def linear_predict(self, A: Tensor, Q: Tensor, b: Tensor | None = None, **info: Any) -> None:
        """Append a node at the same time: ``m = A m + b``, ``P = A P Aᵀ + Q``."""
        mean, cov = linear_predict(self.mean, self.cov, A, Q, b)
        self.add_node(self.time_s, A, mean, cov)
        if info:
            self.log.append({"t_s": self.time_s, **info})

    def change_frame(self, A: Tensor, Q: Tensor, b: Tensor, **info: Any) -> None:
        """A :meth:`linear_predict` that re-expresses the state in another frame (the heading
        alignment): the smoother maps the nodes before it into the new frame too."""
        self.linear_predict(A, Q, b, **info)
        self.frame_changes.append((len(self.t_s) - 1, A, b, Q))

    def finish(self) -> FilterTrack:
        return FilterTrack(
            t_s=torch.tensor(self.t_s, dtype=torch.float64),
            transition=torch.cat(self._transition),
            pred_mean=torch.cat(self._pred_mean),
            pred_cov=torch.cat(self._pred_cov),
            node_mean=torch.cat(self._mean),
            node_cov=torch.cat(self._cov),
            log=self.log,
            frame_changes=self.frame_changes,
        )


class _NodeOutputs:
    """Outputs of a node chain: the last node at each distinct time."""

    t_s: Tensor
    node_mean: Tensor
    node_cov: Tensor

    @property
    def output_index(self) -> Tensor:
        """Indices of the last node at each distinct time."""
        t = self.t_s
        last = torch.ones_like(t, dtype=torch.bool)
        last[:-1] = t[1:] != t[:-1]
        return torch.nonzero(last).squeeze(-1)

    @property
    def t(self) -> Tensor:
        return self.t_s[self.output_index]

    @property
    def mean(self) -> Tensor:
        return self.node_mean[self.output_index]

    @property
    def cov(self) -> Tensor:
        return self.node_cov[self.output_index]


@dataclass
class FilterTrack(_NodeOutputs):
    """The filter's node chain (``J`` nodes) and its outputs.

    ``node_*`` hold every node; :attr:`mean`, :attr:`cov` and :attr:`t` keep the
    last node at each time (a pose forgetting adds a second node at a frame time).
    """

    t_s: Tensor  # (J,) float64
    transition: Tensor  # (J, 26, 26) Φ_j from node j-1 (identity for j = 0)
    pred_mean: Tensor  # (J, 26)
    pred_cov: Tensor  # (J, 26, 26)
    node_mean: Tensor  # (J, 26) filtered
    node_cov: Tensor  # (J, 26, 26) filtered
    log: list[dict[str, Any]]
    #: ``(node, A, b, Q)``: node ``node`` re-expressed the state by ``x ↦ A x + b`` (noise
    #: ``Q``); the filter's nodes before it stay in the frame they were computed in
    frame_changes: list[tuple[int, Tensor, Tensor, Tensor]] = field(default_factory=list)

    def in_final_frame(self) -> NodeTrack:
        """The filtered nodes with those before each change of frame re-expressed after it
        (``m ↦ A m + b``, ``P ↦ A P Aᵀ + Q``): each node is still the filter's estimate from
        the data up to its time, relative to its start; only its frame is the final one."""
        if not self.frame_changes:
            return NodeTrack(self.t_s, self.node_mean, self.node_cov)
        mean, cov = to_final_frame(self.node_mean, self.node_cov, self.frame_changes)
        return NodeTrack(self.t_s, normalize_quaternions(mean), symmetrize(cov))


@dataclass
class NodeTrack(_NodeOutputs):
    """Nodes ``t_s (J,)``, ``node_mean (J, 26)``, ``node_cov (J, 26, 26)`` and their outputs."""

    t_s: Tensor
    node_mean: Tensor
    node_cov: Tensor


def to_final_frame(mean: Tensor, cov: Tensor, frame_changes) -> tuple[Tensor, Tensor]:
    """Nodes ``(J, 26)``, ``(J, 26, 26)`` before each change of frame ``(node, A, b, Q)``
    re-expressed in the frame after it: ``m ↦ A m + b``, ``P ↦ A P Aᵀ + Q``."""
    for node, A, b, Q in reversed(frame_changes):
        mean = torch.cat(((mean[:node] @ A.T) + b, mean[node:]))
        cov = torch.cat((A @ cov[:node] @ A.T + Q, cov[node:]))
    return mean, cov


def _step_grid(t_imu: Tensor, event_times: Tensor) -> tuple[Tensor, Tensor]:
    """Merged step end times and, per step, the IMU sample that drives it."""
    grid = torch.unique(torch.cat((t_imu[1:], event_times[event_times > t_imu[0]])))  # sorted
    sample = torch.searchsorted(t_imu, grid, right=False)
    return grid, sample


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
) -> FilterTrack:
    """Run the EKF from ``(mean0, cov0)`` at ``t_s[0]`` through all IMU samples and events.

    Args:
        t_s ``(N,)`` IMU times (strictly increasing; validate with
        :class:`flowins.data.ImuStream`), acc_mps2 / gyro_rps ``(N, 3)``.
        mean0 ``(26,)``, cov0 ``(26, 26)``: the prior at ``t_s[0]``; their dtype is the
            filter's dtype.
        events: measurement events, each with ``time_s`` in ``[t_s[0], t_s[-1]]``;
            events at the same time are applied in the given order.
        output_every: a node every this many IMU samples (plus one at every event).
        jacobians: ``"analytic"`` (fast, batched closed forms) or ``"autodiff"``
            (the reference: per-sample ``torch.func.jacrev``).
        scheme: mechanization scheme, ``"midpoint"`` or ``"paper"``
            (see :mod:`flowins.ins.mechanization`).
    """
    if jacobians not in ("analytic", "autodiff"):
        raise ValueError(f"jacobians must be 'analytic' or 'autodiff', got {jacobians!r}")
    if output_every < 1:
        raise ValueError(f"output_every must be >= 1, got {output_every}")
    if mean0.shape != (STATE_DIM,) or cov0.shape != (STATE_DIM, STATE_DIM):
        raise ValueError(
            f"mean0 must be ({STATE_DIM},) and cov0 ({STATE_DIM}, {STATE_DIM}); got {tuple(mean0.shape)}, {tuple(cov0.shape)}"
        )
    dtype, device = mean0.dtype, mean0.device
    t_imu = torch.as_tensor(t_s, dtype=torch.float64)
    t0 = float(t_imu[0])
    events = sorted(events, key=lambda e: e.time_s)  # stable: same-time order kept
    plan = _schedule(t_imu, events, output_every)
    grid, sample, segment_ends, events_by_step = plan.grid, plan.sample, plan.segment_ends, plan.events_by_step
    dt = torch.diff(grid, prepend=t_imu[:1]).to(dtype=dtype, device=device)
    acc = torch.as_tensor(acc_mps2)[sample].to(dtype=dtype, device=device)
    gyro = torch.as_tensor(gyro_rps)[sample].to(dtype=dtype, device=device)

    chain = ChainBuilder()
    eye = torch.eye(STATE_DIM, dtype=dtype, device=device)
    chain.add_node(t0, eye, mean0, symmetrize(cov0))
    for event in events:
        if event.time_s <= t0:
            event.apply(chain)
    propagate = propagate_batched if jacobians == "analytic" else propagate_reference
    node_index = plan.node_index
    node_t_s = grid[node_index].tolist()
    # each segment's nodes: node_index[first[i]:last[i]] (the last step of a segment is a node)
    ends = torch.tensor(segment_ends, dtype=node_index.dtype)
    first = torch.searchsorted(node_index, torch.cat((ends.new_zeros(1), ends[:-1] + 1))).tolist()
    last = torch.searchsorted(node_index, ends, right=True).tolist()
    start = 0
    segments = zip(segment_ends, first, last)
    for end, i0, i1 in track_progress(segments, total=len(segment_ends), description="filter", unit="update",
                                      enabled=progress):
        nodes = node_index[i0:i1] - start
        out = propagate(
            chain.mean,
            chain.cov,
            acc[start : end + 1],
            gyro[start : end + 1],
            dt[start : end + 1],
            nodes,
            noise=noise,
            gravity_mps2=gravity_mps2,
            scheme=scheme,
        )
        chain.add_nodes(node_t_s[i0:i1], out.transition, out.mean, out.cov)
        for event in events_by_step.get(end, []):
            event.apply(chain)
        start = end + 1
    return chain.finish()


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
    for event in events:
        if event.time_s > t0:
            step = int(torch.searchsorted(grid, torch.tensor(event.time_s, dtype=torch.float64)))
            events_by_step.setdefault(step, []).append(event)
    return _Schedule(grid, sample, torch.nonzero(is_node).squeeze(-1), segment_ends, events_by_step)
