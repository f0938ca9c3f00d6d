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
from flowins.filter.propagation import plan_nodes, propagate_batched, propagate_reference
from flowins.ins.mechanization import STANDARD_GRAVITY_MPS2, ProcessNoise
from flowins.state import NOISE_DIM, STATE_DIM, normalize_quaternions, symmetrize


class Event(Protocol):
    """A measurement (or any filter operation) at ``time_s``.

    ``apply`` acts on one run's chain (a :class:`ChainBuilder`). An event type may also
    offer ``batch_key()`` (a hashable; events with equal keys can act together) and a
    classmethod ``apply_batch(chain, rows, events)`` acting on the rows ``rows`` of a
    :class:`BatchChain` at once; :func:`run_filters` then groups such events across the
    runs of a batch.
    """

    time_s: float
    name: str

    def apply(self, chain: ChainBuilder) -> None: ...


class BatchChain:
    """The node chains of ``B`` runs, grown together (:func:`run_filters`).

    Nodes are stored in chunks of columns ``(B, n, ...)``: a propagation adds the nodes of
    an IMU run at once, an event's linear prediction one column. A column is one of row
    ``b``'s own nodes or, where the row has nothing there (fewer nodes in that run, no
    such event, the row's run is over), padding that :meth:`finish` leaves out. The last
    column holds the newest node of every row whose run goes on, so an update replaces
    it without touching the rest. When an event's prediction acts on some rows only, the
    others' newest node moves to the new column (a copy, the old one becomes padding), so
    that stays true.
    """

    def __init__(self, rows: int, *, likelihood: bool = False) -> None:
        self.rows = rows
        #: whether updates add their innovation negative log-likelihood (:meth:`add_likelihood`)
        self.likelihood = likelihood
        self._nll: list[list[Tensor]] = [[] for _ in range(rows)]
        self._nll_count: list[list[Tensor]] = [[] for _ in range(rows)]
        #: per row: the times of its nodes, its log, what its events carry from one to the
        #: next (e.g. GNSS fixes held back for the heading), its changes of frame
        self.t_s: list[list[float]] = [[] for _ in range(rows)]
        self.logs: list[list[dict[str, Any]]] = [[] for _ in range(rows)]
        self.memories: list[dict[str, Any]] = [{} for _ in range(rows)]
        self.frame_changes: list[list[tuple[int, Tensor, Tensor, Tensor]]] = [[] for _ in range(rows)]
        self._columns: list[list[int]] = [[] for _ in range(rows)]  # each row's own node columns
        self._current = [False] * rows  # whether the last column is the row's newest node
        self._count = 0
        self._transition: list[Tensor] = []  # chunks (B, n, 26, 26)
        self._pred_mean: list[Tensor] = []  # chunks (B, n, 26)
        self._pred_cov: list[Tensor] = []
        self._mean: list[Tensor] = []  # chunks; the last is (B, 1, 26)
        self._cov: list[Tensor] = []

    @property
    def mean(self) -> Tensor:
        """Filtered mean of each row's newest node ``(B, 26)``."""
        return self._mean[-1][:, 0]

    @property
    def cov(self) -> Tensor:
        return self._cov[-1][:, 0]

    def row(self, b: int) -> ChainBuilder:
        """Row ``b`` as a single run's chain."""
        return ChainBuilder(self, b)

    def time_s(self, b: int) -> float:
        return self.t_s[b][-1]

    def _append(self, transition: Tensor, pred_mean: Tensor, pred_cov: Tensor, mean: Tensor, cov: Tensor) -> None:
        """Append columns ``(B, n, ...)``; ``mean``, ``cov`` are the filtered Gaussians of the
        last column ``(B, 1, ...)`` (the others' are their predictions)."""
        n = pred_mean.shape[1]
        self._transition.append(transition)
        self._pred_mean.append(pred_mean)
        self._pred_cov.append(pred_cov)
        if n > 1:
            self._mean.append(pred_mean[:, :-1])
            self._cov.append(pred_cov[:, :-1])
        self._mean.append(mean)
        self._cov.append(cov)
        self._count += n

    def add_nodes(self, t_s: Sequence[Sequence[float]], transition: Tensor, mean: Tensor, cov: Tensor,
                  real: Sequence[Sequence[bool]] | None = None) -> None:
        """Append ``n`` predicted node columns: transitions ``(B, n, 26, 26)``, means ``(B, n, 26)``,
        covariances; ``real[b][j]`` whether column ``j`` is one of row ``b``'s own nodes
        (default: all), ``t_s[b]`` the times of row ``b``'s own ones, in order."""
        n = mean.shape[1]
        for b in range(self.rows):
            flags = [True] * n if real is None else real[b]
            own = [self._count + j for j in range(n) if flags[j]]
            if len(own) != len(t_s[b]):
                raise ValueError(f"BatchChain.add_nodes: row {b} has {len(own)} nodes but {len(t_s[b])} times")
            self._columns[b].extend(own)
            self.t_s[b].extend(float(t) for t in t_s[b])
            self._current[b] = bool(flags[-1]) if n else self._current[b]
        self._append(transition, mean, cov, mean[:, -1:], cov[:, -1:])

    def newest(self, rows: Sequence[int]) -> tuple[Tensor, Tensor]:
        """The newest filtered mean ``(r, 26)`` and covariance ``(r, 26, 26)`` of the rows ``rows``."""
        if list(rows) == list(range(self.rows)):
            return self.mean, self.cov
        index = torch.tensor(rows, device=self.mean.device)
        return self.mean[index], self.cov[index]

    def _check_current(self, rows: Sequence[int]) -> None:
        for b in rows:
            if not self._current[b]:
                raise RuntimeError(f"BatchChain: row {b} has no current node (its run is over)")

    def update_rows(self, rows: Sequence[int], mean: Tensor, cov: Tensor,
                    infos: Sequence[dict[str, Any]] | None = None) -> None:
        """Replace the newest filtered Gaussian of the rows ``rows`` by ``mean`` ``(r, 26)``,
        ``cov`` ``(r, 26, 26)``; ``infos[i]`` (when not empty) goes to row ``rows[i]``'s log."""
        self._check_current(rows)
        if list(rows) == list(range(self.rows)):
            self._mean[-1], self._cov[-1] = mean.unsqueeze(1), cov.unsqueeze(1)
        else:
            index = torch.tensor(rows, device=mean.device)
            self._mean[-1] = self._mean[-1].index_copy(0, index, mean.unsqueeze(1))
            self._cov[-1] = self._cov[-1].index_copy(0, index, cov.unsqueeze(1))
        self._log(rows, infos)

    def add_likelihood(self, rows: Sequence[int], nll: Tensor, count: Tensor) -> None:
        """Add an update's innovation negative log-likelihood ``nll`` ``(r,)`` of ``count`` ``(r,)``
        scalar measurements to the rows ``rows`` (kept only when :attr:`likelihood`)."""
        if not self.likelihood:
            return
        for i, b in enumerate(rows):
            self._nll[b].append(nll[i])
            self._nll_count[b].append(count[i])

    def _log(self, rows: Sequence[int], infos: Sequence[dict[str, Any]] | None) -> None:
        for b, info in zip(rows, infos or ()):
            if info:
                self.logs[b].append({"t_s": self.time_s(b), **info})

    def linear_predict_rows(self, rows: Sequence[int], A: Tensor, Q: Tensor, b: Tensor | None = None,
                            infos: Sequence[dict[str, Any]] | None = None, *, select: Tensor | None = None) -> None:
        """A node at the same time on the rows ``rows``: ``m = A m + b``, ``P = A P Aᵀ + Q``
        (``A``, ``Q`` ``(r or 1, 26, 26)``, ``b`` ``(r or 1, 26)``). ``select`` ``(26,)``: ``A`` is
        the identity's rows ``select`` (a copy of state entries), so ``A m = m[select]`` and
        ``A P Aᵀ = P[select][:, select]`` exactly, without matrix products."""
        self._check_current(rows)
        everyone = list(rows) == list(range(self.rows))
        index = None if everyone else torch.tensor(rows, device=A.device)
        mean, cov = self.newest(rows)
        if select is None:
            m, P = linear_predict(mean, cov, A, Q, None if b is None else b)
        else:
            m = mean[..., select] if b is None else mean[..., select] + b
            P = cov[..., select, :][..., select] + Q
        r = len(rows)
        A = A.expand(r, *A.shape[-2:])
        if everyone:
            columns = (A, m, P, m, P)
        else:  # the other rows' newest node moves to the new column
            last = (self._transition[-1][:, -1], self._pred_mean[-1][:, -1], self._pred_cov[-1][:, -1], self.mean, self.cov)
            columns = tuple(old.index_copy(0, index, new) for old, new in zip(last, (A, m, P, m, P)))
        column = self._count
        chosen = set(rows)
        for row in range(self.rows):
            if row in chosen:
                self._columns[row].append(column)
                self.t_s[row].append(self.t_s[row][-1])
            elif self._current[row]:
                self._columns[row][-1] = column
        self._append(*(c.unsqueeze(1) for c in columns))
        self._log(rows, infos)

    def finish(self) -> list[FilterTrack]:
        """Each row's :class:`FilterTrack` (its own nodes only)."""
        parts = [torch.cat(chunks, dim=1) for chunks in
                 (self._transition, self._pred_mean, self._pred_cov, self._mean, self._cov)]
        tracks = []
        for b in range(self.rows):
            columns = self._columns[b]
            if columns == list(range(self._count)):
                own = [part[b] for part in parts]
            else:
                index = torch.tensor(columns, device=parts[0].device)
                own = [part[b].index_select(0, index) for part in parts]
            transition, pred_mean, pred_cov, mean, cov = own
            nll = (torch.stack(self._nll[b]).sum() if self._nll[b] else mean.new_zeros(())) if self.likelihood else None
            count = float(torch.stack(self._nll_count[b]).sum()) if self._nll_count[b] else 0.0
            tracks.append(FilterTrack(t_s=torch.tensor(self.t_s[b], dtype=torch.float64), transition=transition,
                                      pred_mean=pred_mean, pred_cov=pred_cov, node_mean=mean, node_cov=cov,
                                      log=self.logs[b], frame_changes=self.frame_changes[b], nll=nll,
                                      nll_count=count))
        return tracks


class ChainBuilder:
    """One run's growing node chain; events call :meth:`update` and :meth:`linear_predict`.

    A row of a :class:`BatchChain` (a chain of its own when made without one).
    """

    def __init__(self, batch: BatchChain | None = None, row: int = 0) -> None:
        self._batch = BatchChain(1) if batch is None else batch
        self._row = row

    @property
    def batch(self) -> BatchChain:
        """The :class:`BatchChain` this chain is a row of (events acting on rows at once use it)."""
        return self._batch

    @property
    def row(self) -> int:
        """This chain's row in :attr:`batch`."""
        return self._row

    @property
    def t_s(self) -> list[float]:
        return self._batch.t_s[self._row]

    @property
    def log(self) -> list[dict[str, Any]]:
        return self._batch.logs[self._row]

    @property
    def memory(self) -> dict[str, Any]:
        """What events carry from one to the next (e.g. GNSS fixes held back for the heading)."""
        return self._batch.memories[self._row]

    @property
    def frame_changes(self) -> list[tuple[int, Tensor, Tensor, Tensor]]:
        """``(node, A, b, Q)`` of each change of frame (:meth:`change_frame`)."""
        return self._batch.frame_changes[self._row]

    @property
    def mean(self) -> Tensor:
        """Filtered mean of the newest node ``(26,)``."""
        return self._batch.mean[self._row]

    @property
    def cov(self) -> Tensor:
        return self._batch.cov[self._row]

    @property
    def time_s(self) -> float:
        return self.t_s[-1]

    def add_nodes(self, t_s: Sequence[float], transition: Tensor, mean: Tensor, cov: Tensor) -> None:
        """Append ``n`` predicted nodes: times, transitions ``(n, 26, 26)``, means ``(n, 26)``, covs
        (a chain of its own only)."""
        if self._batch.rows != 1:
            raise RuntimeError("ChainBuilder.add_nodes: only on a chain of its own (BatchChain.add_nodes for a batch)")
        self._batch.add_nodes([list(t_s)], transition.unsqueeze(0), mean.unsqueeze(0), cov.unsqueeze(0))

    def add_node(self, t_s: float, transition: Tensor, mean: Tensor, cov: Tensor) -> None:
        self.add_nodes([t_s], transition.unsqueeze(0), mean.unsqueeze(0), cov.unsqueeze(0))

    def update(self, result: UpdateResult | tuple[Tensor, Tensor], **info: Any) -> None:
        """Replace the newest node's filtered Gaussian by an update's result."""
        self._batch.update_rows([self._row], result[0].unsqueeze(0), result[1].unsqueeze(0), [info])

    @property
    def likelihood(self) -> bool:
        """Whether updates add their innovation likelihood (:meth:`BatchChain.add_likelihood`)."""
        return self._batch.likelihood

    def add_likelihood(self, nll: Tensor, count: Tensor) -> None:
        """:meth:`BatchChain.add_likelihood` of this row: scalars ``nll``, ``count``."""
        self._batch.add_likelihood([self._row], nll.reshape(1), count.reshape(1))

    def linear_predict(self, A: Tensor, Q: Tensor, b: Tensor | None = None, **info: Any) -> None:
        """Append a node at the same time: ``m = A m + b``, ``P = A P Aᵀ + Q``."""
        self._batch.linear_predict_rows([self._row], A.unsqueeze(0), Q.unsqueeze(0),
                                        None if b is None else b.unsqueeze(0), [info])

    def change_frame(self, A: Tensor, Q: Tensor, b: Tensor, **info: Any) -> None:
        """A :meth:`linear_predict` that re-expresses the state in another frame (the heading
        alignment): the smoother maps the nodes before it into the new frame too."""
        self.linear_predict(A, Q, b, **info)
        self.frame_changes.append((len(self.t_s) - 1, A, b, Q))

    def finish(self) -> FilterTrack:
        return self._batch.finish()[self._row]


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
    #: the summed innovation negative log-likelihood of the updates that report one (flow points,
    #: GNSS fixes; ``½ (NIS + log det S)`` each, gate-weighted) over ``nll_count`` scalar
    #: measurements; None unless the run asked for it (``run_filters(likelihood=True)``)
    nll: Tensor | None = None
    nll_count: float = 0.0

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


@dataclass(frozen=True)
class FilterInput:
    """One run of :func:`run_filters`: IMU samples ``t_s (N,)``, ``acc_mps2``/``gyro_rps``
    ``(N, 3)``, the prior ``mean0 (26,)``, ``cov0 (26, 26)`` at ``t_s[0]``, its events and,
    optionally, its own process noise (default: the batch's)."""

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
        mean0 ``(26,)``, cov0 ``(26, 26)``: the prior at ``t_s[0]``; their dtype is the
            filter's dtype.
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


class _Run(NamedTuple):
    """One run's schedule, ready to step: its samples and the segments between events."""

    t0: float
    acc: Tensor  # (S, 3) the reading driving each step
    gyro: Tensor
    dt: Tensor  # (S,)
    variances: Tensor  # (S, 15) the steps' process noise variances
    segments: list[tuple[int, int, list[int], list[float], list]]  # first, last step, node steps, times, events
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
) -> list[FilterTrack]:
    """Run ``B`` filters in one batched pass: each run as :func:`run_filter` runs it alone.

    The runs may differ in length, IMU rate, events and their times. They step together
    segment by segment (the IMU samples up to each run's next event): the shorter
    segments are padded with ``Δt = 0`` steps, which are exact identities, and every
    operation acts on a leading batch dimension. Events of the same kind at the same
    segment are applied together where their type offers ``apply_batch``
    (:class:`Event`), one run at a time otherwise. Each run's track equals its run
    alone up to rounding (tests check 1e-10 in float64).

    Args:
        runs: the :class:`FilterInput` of each run; every ``mean0`` has the same dtype and
            device (the filter's).
        noise: the process noise of the runs without their own.
        output_every, gravity_mps2, jacobians, scheme, likelihood: as for :func:`run_filter`, for
            all runs.
    """
    if jacobians not in ("analytic", "autodiff"):
        raise ValueError(f"jacobians must be 'analytic' or 'autodiff', got {jacobians!r}")
    if output_every < 1:
        raise ValueError(f"output_every must be >= 1, got {output_every}")
    if not runs:
        return []
    like = runs[0].mean0
    for i, run in enumerate(runs):
        if run.mean0.shape != (STATE_DIM,) or run.cov0.shape != (STATE_DIM, STATE_DIM):
            raise ValueError(f"run {i}: mean0 must be ({STATE_DIM},) and cov0 ({STATE_DIM}, {STATE_DIM}); "
                             f"got {tuple(run.mean0.shape)}, {tuple(run.cov0.shape)}")
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
    chain = BatchChain(B, likelihood=likelihood)
    eye = torch.eye(STATE_DIM, dtype=dtype, device=device)
    chain.add_nodes([[plan.t0] for plan in plans], eye.expand(B, 1, STATE_DIM, STATE_DIM),
                    torch.stack([run.mean0 for run in runs]).unsqueeze(1),
                    symmetrize(torch.stack([run.cov0 for run in runs])).unsqueeze(1))
    apply_events(chain, [plan.early for plan in plans])
    # every run's steps in one flat array, and a padding step (Δt = 0) at its end
    offsets = torch.tensor([0] + [plan.dt.shape[0] for plan in plans]).cumsum(0).tolist()
    pad = offsets[-1]
    flat = None if B == 1 else [torch.cat([getattr(plan, name) for plan in plans] + [zero])
                                 for name, zero in (("acc", like.new_zeros(1, 3)), ("gyro", like.new_zeros(1, 3)),
                                                    ("dt", like.new_zeros(1)), ("variances", like.new_zeros(1, NOISE_DIM)))]
    count = max(len(plan.segments) for plan in plans)
    for k in track_progress(range(count), total=count, description="filter", unit="update", enabled=progress):
        segments = [plan.segments[k] if k < len(plan.segments) else None for plan in plans]
        L = max(last - first + 1 for first, last, *_ in filter(None, segments))
        if B == 1:
            first, last = segments[0][:2]
            acc, gyro, dt, variances = (getattr(plans[0], name)[first:last + 1].unsqueeze(0)
                                        for name in ("acc", "gyro", "dt", "variances"))
            node_steps = [[step - first for step in segments[0][2]]]
        else:
            index, node_steps = [], []
            for offset, segment in zip(offsets, segments):
                if segment is None:
                    index.append([pad] * L)
                    node_steps.append([])
                    continue
                first, last, steps = segment[:3]
                shift = L - (last - first + 1)  # padding steps first: the last step is the segment's
                index.append([pad] * shift + list(range(offset + first, offset + last + 1)))
                node_steps.append([step - first + shift for step in steps])
            index = torch.tensor(index, device=device)
            acc, gyro, dt, variances = (part[index] for part in flat)
        nodes = plan_nodes(node_steps, L, device=device)
        if jacobians == "analytic":
            out = propagate_batched(chain.mean, chain.cov, acc, gyro, dt, nodes, variances=variances,
                                    gravity_mps2=gravity_mps2, scheme=scheme)
        else:
            out = propagate_reference(chain.mean[0], chain.cov[0], acc[0], gyro[0], dt[0],
                                      torch.tensor(node_steps[0]), noise=noises[0], gravity_mps2=gravity_mps2,
                                      scheme=scheme)
            out = type(out)(*(t.unsqueeze(0) for t in out))
        chain.add_nodes([[] if segment is None else segment[3] for segment in segments],
                        out.transition, out.mean, out.cov, real=nodes.real)
        apply_events(chain, [[] if segment is None else segment[4] for segment in segments])
    return chain.finish()


def apply_events(chain: BatchChain, events: Sequence[Sequence[Event]]) -> None:
    """Apply ``events[b]`` (in order) to row ``b`` of ``chain``, for every row.

    The ``i``-th events of all rows act together: those whose types offer ``batch_key``
    and ``apply_batch`` (:class:`Event`), grouped by key, in one call per group; the rest
    one row at a time through :meth:`BatchChain.row`.
    """
    for i in range(max((len(e) for e in events), default=0)):
        groups: dict[Any, list[tuple[int, Event]]] = {}
        for b, row_events in enumerate(events):
            if i >= len(row_events):
                continue
            event = row_events[i]
            key = event.batch_key() if hasattr(event, "batch_key") else None
            if key is None:
                event.apply(chain.row(b))
            else:
                groups.setdefault(key, []).append((b, event))
        for members in groups.values():
            type(members[0][1]).apply_batch(chain, [b for b, _ in members], [e for _, e in members])


def _prepare(run: FilterInput, output_every: int, dtype: torch.dtype, device: torch.device,
             noise: ProcessNoise) -> _Run:
    """One run's steps (IMU samples and event times), segments, nodes and events."""
    t_imu = torch.as_tensor(run.t_s, dtype=torch.float64)
    t0 = float(t_imu[0])
    events = sorted(run.events, key=lambda e: e.time_s)  # stable: same-time order kept
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
        segments.append((start, end, steps, times, plan.events_by_step.get(end, [])))
        start = end + 1
    return _Run(t0, acc, gyro, dt, noise.variances(dt), segments, [e for e in events if e.time_s <= t0])


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
