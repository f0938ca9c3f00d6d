"""The filter's node chain: what the EKF reports, node by node, and the events that act on it.

The filter keeps a *chain of nodes*. A node is a time at which the filter reports
its estimate: every ``output_every``-th IMU sample, every measurement event and the
end of the run (:func:`flowins.filter.runner.run_filters` schedules them). Each node
stores its predicted and filtered Gaussians and the transition ``Φ`` from the
previous node's filtered state (the product of the step Jacobians in between).
Events act on the newest node: an update replaces its filtered Gaussian
(:mod:`flowins.filter.updater`); a linear prediction (pose forgetting) appends a new
node at the same time. The RTS smoother (:mod:`flowins.filter.smoother`) runs on this
chain, so it is exact through every prediction, forgetting and augmentation step.
"""
from __future__ import annotations

from bisect import bisect_left
from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import torch
from torch import Tensor

from flowins.filter.compiling import Compiler
from flowins.filter.ekf import UpdateResult, linear_predict, waits_cost
from flowins.state import normalize_quaternions, symmetrize


class Event(Protocol):
    """A measurement (or any filter operation) at ``time_s``, acting on one run's chain
    (a :class:`ChainBuilder`) through ``apply``."""

    time_s: float
    name: str

    def apply(self, chain: ChainBuilder) -> None: ...


@runtime_checkable
class BatchEvent(Event, Protocol):
    """An :class:`Event` that can also act on several runs of a batch at once.

    Events of one type whose ``batch_key()`` are equal act together: the scheduler
    (:func:`flowins.filter.runner.apply_events`) calls ``apply_batch(chain, rows, events)``
    once for them, with ``events[i]`` on the row ``rows[i]`` of the :class:`BatchChain`.
    """

    def batch_key(self) -> Hashable: ...

    @classmethod
    def apply_batch(cls, chain: BatchChain, rows: Sequence[int], events: Sequence[BatchEvent]) -> None: ...


class RowBatchEvent:
    """A base for :class:`BatchEvent` types whose one-run ``apply`` is their batch step on the
    run's own row: a subclass writes ``batch_key`` and ``apply_batch`` only.

    An event type whose events carry data for the device may also define a classmethod
    ``place(events, like) -> events``: the same events with their tensors in ``like``'s dtype
    and device, moved together before the pass (:func:`place_events`), so that the pass copies
    nothing from the host per event."""

    def apply(self, chain: ChainBuilder) -> None:
        type(self).apply_batch(chain.batch, [chain.row], [self])


def place_events(events: Sequence[Event], like: Tensor) -> list[Event]:
    """``events`` (in their order) with those of each type that defines ``place`` replaced by its
    placed copies (:class:`RowBatchEvent`): one move per type, not one per event."""
    by_type: dict[type, list[int]] = {}
    for i, event in enumerate(events):
        if hasattr(type(event), "place"):
            by_type.setdefault(type(event), []).append(i)
    out = list(events)
    for kind, where in by_type.items():
        for i, placed in zip(where, kind.place([events[i] for i in where], like), strict=True):
            out[i] = placed
    return out


#: unflushed node columns a :class:`BatchChain` with row stores holds before it moves them to
#: the stores (bytes of their ``D x D`` matrices): small enough that the join it copies them
#: through is reused from the heap, large enough that a flush is a few operations per node run
FLUSH_BYTES = 16 << 20
#: the most rows a chain gives stores of their own (more rows gather theirs at the end)
STORE_ROWS = 4


class _RowStore:
    """One row's finished nodes in tensors of their own, filled as the pass goes
    (:meth:`BatchChain._flush`), so that :meth:`BatchChain.finish` hands views of them over
    instead of copying every node into fresh memory at the end. ``capacity`` nodes are
    reserved (untouched memory costs nothing); more grow the tensors by doubling."""

    NAMES = ("transition", "pred_mean", "mean", "cov")

    def __init__(self, capacity: int) -> None:
        self.capacity = max(1, int(capacity))
        self.count = 0
        self.parts: dict[str, Tensor] = {}
        self.updated: list[bool] = []  # per stored node: whether an update replaced it
        self.updated_pred: Tensor | None = None  # (capacity, D, D) the updated nodes' predictions
        self.updated_count = 0

    def _room(self, part: Tensor | None, used: int, needed: int, event_shape: tuple[int, ...],
              like: Tensor) -> Tensor:
        """``part``, or a tensor of ``max(capacity, twice its size, needed)`` nodes of ``event_shape``
        holding its first ``used`` nodes, when it has fewer than ``needed``."""
        if part is not None and part.shape[0] >= needed:
            return part
        grown = like.new_empty(max(self.capacity if part is None else 2 * part.shape[0], needed), *event_shape)
        if part is not None:
            grown[:used].copy_(part[:used])
        return grown

    def reserve(self, name: str, like: Tensor, extra: int) -> Tensor:
        """The tensor of ``name`` (nodes of ``like``'s event shape), with room for ``extra`` more."""
        part = self._room(self.parts.get(name), self.count, self.count + extra, tuple(like.shape[2:]), like)
        self.parts[name] = part
        return part

    def add_updated(self, covs: list[Tensor]) -> None:
        """Append the predicted covariances of updated nodes, in node order."""
        if not covs:
            return
        needed = self.updated_count + len(covs)
        self.updated_pred = self._room(self.updated_pred, self.updated_count, needed, tuple(covs[0].shape), covs[0])
        torch.stack(covs, out=self.updated_pred[self.updated_count: needed])
        self.updated_count = needed


def _cast(values: Tensor) -> type:
    """The Python type a deferred log value of ``values``'s dtype becomes (:meth:`BatchChain.log_rows`)."""
    return bool if values.dtype == torch.bool else float if values.is_floating_point() or values.is_complex() else int


def raise_if_failed(failed: Tensor | None, what: str, rows: Sequence[int] | None = None,
                    t_s: Sequence[float] | None = None) -> None:
    """A ``ValueError`` naming ``what``, the batch rows where ``failed`` holds (``rows``: the
    run each entry of ``failed`` is; default its index) and, with ``t_s`` (each entry's time),
    when. A read of one flag from the device: call it where the pass may wait
    (:meth:`BatchChain.check_failed` defers it where a wait costs)."""
    if failed is None or not bool(failed.any()):
        return
    bad = torch.nonzero(failed.reshape(-1))[:, 0].tolist()
    rows = [i if rows is None else rows[i] for i in bad]
    when = "" if t_s is None else f" at t = {t_s[bad[0]]:.3f} s"
    raise ValueError(f"{what}{when}: a factorisation failed in batch row(s) {rows[:10]}"
                     + (" ..." if len(rows) > 10 else "") + ": the state covariance is not positive semi-definite "
                     "even with a jitter of 1e-6 of its largest variance, or the innovation covariance is singular")


class BatchChain:
    """The node chains of ``B`` runs, grown together (:func:`~flowins.filter.runner.run_filters`).

    Nodes are stored in chunks of columns ``(B, n, ...)``: a propagation adds the nodes of
    an IMU run at once, an event's linear prediction one column. A column is one of row
    ``b``'s own nodes or, where the row has nothing there (fewer nodes in that run, no
    such event, the row's run is over), padding that :meth:`finish` leaves out. The last
    column holds the newest node of every row whose run goes on, so an update replaces
    it without touching the rest. When an event's prediction acts on some rows only, the
    others' newest node moves to the new column (a copy, the old one becomes padding), so
    that stays true. A node's predicted covariance differs from its filtered one only where
    an update acted: the tracks :meth:`finish` hands over keep it at those nodes alone
    (:attr:`FilterTrack.updated_pred_cov`), a third less memory than every node's.

    ``capacity`` (the nodes each row expects, e.g. from :func:`~flowins.filter.runner.chain_bytes`'s
    count): with at most :data:`STORE_ROWS` rows and no gradient to keep, each row's finished
    nodes move to tensors of its own as the pass goes (:class:`_RowStore`), and :meth:`finish`
    hands views of them over: no copy of the whole chain into fresh memory at the end.
    """

    def __init__(self, rows: int, *, likelihood: bool = False, capacity: Sequence[int] | None = None,
                 compiler: Compiler | None = None) -> None:
        self.rows = rows
        #: how events run their pure steps (:class:`~flowins.filter.compiling.Compiler`: eager by default)
        self.compiler = Compiler(None, reason="filter.compile=false") if compiler is None else compiler
        #: whether updates add their innovation negative log-likelihood (:meth:`add_likelihood`)
        self.likelihood = likelihood
        self._nll: list[list[Tensor]] = [[] for _ in range(rows)]
        self._nll_count: list[list[Tensor]] = [[] for _ in range(rows)]
        #: per row: the times of its nodes, its log, what its events carry from one to the
        #: next (e.g. GNSS fixes held back for the heading), its changes of frame
        self.t_s: list[list[float]] = [[] for _ in range(rows)]
        self._logs: list[list[dict[str, Any]]] = [[] for _ in range(rows)]
        self.memories: list[dict[str, Any]] = [{} for _ in range(rows)]
        #: what events carry from one to the next on the state's device, one entry per row
        #: (e.g. the flow's gated frames in a row; :meth:`row_state`): read by no one in the pass
        self._states: dict[str, Tensor] = {}
        self._row_indices: dict[tuple[int, ...], Tensor] = {}  # :meth:`row_index`
        #: log values still on the device (:meth:`log_rows`): the entries (by their place in the
        #: event's rows, with their row), each value's name and type, whether the last column says
        #: which entries stay, the values ``(r, k)``
        self._pending: list[tuple[list[tuple[int, int, dict[str, Any]]], tuple[tuple[str, type], ...], bool,
                                  Tensor]] = []
        self.frame_changes: list[list[tuple[int, Tensor, Tensor, Tensor]]] = [[] for _ in range(rows)]
        self._columns: list[list[int]] = [[] for _ in range(rows)]  # each row's own node columns
        self._current = [False] * rows  # whether the last column is the row's newest node
        self._count = 0
        self._transition: list[Tensor] = []  # chunks (B, n, 26, 26)
        self._pred_mean: list[Tensor] = []  # chunks (B, n, 26)
        self._pred_cov: list[Tensor] = []
        #: per row: its columns whose filtered Gaussian an update replaced, each with a view of
        #: its predicted covariance (elsewhere the prediction is the filtered Gaussian itself)
        self._updated: list[dict[int, Tensor]] = [{} for _ in range(rows)]
        self._mean: list[Tensor] = []  # chunks; the last is (B, 1, 26)
        self._cov: list[Tensor] = []
        self._finished = False
        #: update failure flags not read yet (:meth:`check_failed`): (flags, what, rows, times)
        self._failures: list[tuple[Tensor, str, list[int], list[float]]] = []
        use_stores = capacity is not None and rows <= STORE_ROWS and not torch.is_grad_enabled()
        self._stores = [_RowStore(c) for c in capacity] if use_stores else None
        self._start = 0  # the first column the chunk lists hold (the ones before are in the stores)
        self._stored = [0] * rows  # per row: how many of its own columns are in its store

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

    def check_failed(self, failed: Tensor | None, what: str, rows: Sequence[int]) -> None:
        """An update's failure flags ``(r,)`` for ``rows``: raised now (:func:`raise_if_failed`,
        naming the rows and the time) where reading them back is free (the CPU, eager), kept as
        a tensor where it costs (a GPU, or ``torch.compile``: :func:`~flowins.filter.ekf.waits_cost`)
        and raised by :meth:`raise_failures` at the end of the pass, naming the first
        failure's time and rows."""
        if failed is None:
            return
        failed = failed.reshape(len(rows), -1).any(-1)  # a row's blocks: one flag per row
        times = [self.time_s(b) for b in rows]
        if waits_cost(failed):
            self._failures.append((failed.detach().reshape(-1), what, list(rows), times))
        else:
            raise_if_failed(failed, what, rows, times)

    def raise_failures(self) -> None:
        """Raise the first failure :meth:`check_failed` kept (one read of all their flags)."""
        if not self._failures:
            return
        flags = torch.stack([f.any() for f, *_ in self._failures]).tolist()
        failures, self._failures = self._failures, []
        for flag, (failed, what, rows, times) in zip(flags, failures):
            if flag:
                raise_if_failed(failed, what, rows, times)

    def _append(self, transition: Tensor, pred_mean: Tensor, pred_cov: Tensor, mean: Tensor, cov: Tensor) -> None:
        """Append columns ``(B, n, ...)``; ``mean``, ``cov`` are the filtered Gaussians of the
        last column ``(B, 1, ...)`` (the others' are their predictions)."""
        n = pred_mean.shape[1]
        if self._stores is not None and self._count > self._start:
            D = pred_cov.shape[-1]
            if (self._count - self._start) * self.rows * D * D * pred_cov.element_size() >= FLUSH_BYTES:
                self._flush()
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
        index = self.row_index(rows)
        return self.mean[index], self.cov[index]

    def row_index(self, rows: Sequence[int]) -> Tensor:
        """``rows`` as an index on the state's device, kept for the pass (the same rows come back
        event after event: their index is copied from the host once, not at every event)."""
        key = tuple(rows)
        index = self._row_indices.get(key)
        if index is None:
            index = self._row_indices[key] = torch.tensor(key, dtype=torch.long, device=self.mean.device)
        return index

    def row_state(self, name: str, rows: Sequence[int], *, shape: tuple[int, ...] = (),
                  dtype: torch.dtype = torch.int64) -> Tensor:
        """What events carry under ``name`` for the rows ``rows``, ``(r, *shape)`` on the state's
        device (zeros of ``dtype`` until set): counts, the first fix of a run of rejections."""
        values = self._states.get(name)
        if values is None:
            values = self._states[name] = torch.zeros(self.rows, *shape, dtype=dtype, device=self.mean.device)
        if list(rows) == list(range(self.rows)):
            return values
        return values[self.row_index(rows)]

    def set_row_state(self, name: str, rows: Sequence[int], values: Tensor) -> None:
        """Set what events carry under ``name`` for the rows ``rows`` to ``values`` ``(r, ...)``."""
        every = self.row_state(name, range(self.rows), shape=tuple(values.shape[1:]), dtype=values.dtype)
        if list(rows) == list(range(self.rows)):
            self._states[name] = values
        else:
            self._states[name] = every.index_copy(0, self.row_index(rows), values)

    def _check_current(self, rows: Sequence[int]) -> None:
        for b in rows:
            if not self._current[b]:
                raise RuntimeError(f"BatchChain: row {b} has no current node (its run is over)")

    def update_rows(self, rows: Sequence[int], mean: Tensor, cov: Tensor,
                    infos: Sequence[dict[str, Any]] | None = None, values: dict[str, Tensor] | None = None) -> None:
        """Replace the newest filtered Gaussian of the rows ``rows`` by ``mean`` ``(r, 26)``,
        ``cov`` ``(r, 26, 26)``; ``infos[i]`` (when not empty) goes to row ``rows[i]``'s log, with
        ``values`` (:meth:`log_rows`)."""
        self._check_current(rows)
        column, predicted = self._count - 1, self._pred_cov[-1]
        for b in rows:
            self._updated[b].setdefault(column, predicted[b, -1])
        if list(rows) == list(range(self.rows)):
            self._mean[-1], self._cov[-1] = mean.unsqueeze(1), cov.unsqueeze(1)
        else:
            index = self.row_index(rows)
            self._mean[-1] = self._mean[-1].index_copy(0, index, mean.unsqueeze(1))
            self._cov[-1] = self._cov[-1].index_copy(0, index, cov.unsqueeze(1))
        self.log_rows(rows, infos, values)

    def add_likelihood(self, rows: Sequence[int], nll: Tensor, count: Tensor) -> None:
        """Add an update's innovation negative log-likelihood ``nll`` ``(r,)`` of ``count`` ``(r,)``
        scalar measurements to the rows ``rows`` (kept only when :attr:`likelihood`)."""
        if not self.likelihood:
            return
        for i, b in enumerate(rows):
            self._nll[b].append(nll[i])
            self._nll_count[b].append(count[i])

    @property
    def logs(self) -> list[list[dict[str, Any]]]:
        """Each row's log entries, their values complete (:meth:`settle_logs`)."""
        self.settle_logs()
        return self._logs

    def log_rows(self, rows: Sequence[int], infos: Sequence[dict[str, Any]] | None,
                 values: dict[str, Tensor] | None = None, keep: Tensor | None = None) -> None:
        """Append ``infos[i]`` (when not empty), with the node's time, to row ``rows[i]``'s log.

        ``values``: facts still on the device, ``(r,)`` tensors by name; entry ``i`` gets
        ``values[name][i]`` (a ``bool``, ``int`` or ``float`` as the tensor's dtype) when the logs
        are read (:attr:`logs`, :meth:`finish`): the pass does not wait for them, and all its
        values come back in one read. ``keep`` ``(r,)`` bool: entry ``i`` stays in the log only
        where it holds (an event that acted on some rows, decided on the device)."""
        entries = []
        for i, (b, info) in enumerate(zip(rows, infos or ())):
            if info:
                entry = {"t_s": self.time_s(b), **info}
                self._logs[b].append(entry)
                entries.append((i, b, entry))
        if (values or keep is not None) and entries:
            casts = tuple((name, _cast(t)) for name, t in (values or {}).items())
            columns = [t.detach().to(torch.float64) for t in (values or {}).values()]
            if keep is not None:
                columns.append(keep.to(torch.float64))
            self._pending.append((entries, casts, keep is not None, torch.stack(columns, -1)))

    def settle_logs(self) -> None:
        """Write the log values :meth:`log_rows` left on the device into their entries, and drop
        the entries not kept (one read)."""
        if not self._pending:
            return
        pending, self._pending = self._pending, []
        flat = torch.cat([values.reshape(-1) for *_, values in pending]).tolist()
        at, dropped = 0, {}
        for entries, casts, kept, values in pending:
            k = values.shape[-1]
            for i, b, entry in entries:
                row = flat[at + k * i: at + k * (i + 1)]
                entry.update((name, cast(value)) for (name, cast), value in zip(casts, row))
                if kept and not row[-1]:
                    dropped.setdefault(b, set()).add(id(entry))
            at += values.numel()
        for b, gone in dropped.items():
            self._logs[b][:] = [entry for entry in self._logs[b] if id(entry) not in gone]

    def linear_predict_rows(self, rows: Sequence[int], A: Tensor, Q: Tensor, b: Tensor | None = None,
                            infos: Sequence[dict[str, Any]] | None = None, *, select: Tensor | None = None,
                            values: dict[str, Tensor] | None = None, keep: Tensor | None = None) -> None:
        """A node at the same time on the rows ``rows``: ``m = A m + b``, ``P = A P Aᵀ + Q``
        (``A``, ``Q`` ``(r or 1, 26, 26)``, ``b`` ``(r or 1, 26)``). ``select`` ``(26,)``: ``A`` is
        the identity's rows ``select`` (a copy of state entries), so ``A m = m[select]`` and
        ``A P Aᵀ = P[select][:, select]`` exactly, without matrix products. ``infos``, ``values``,
        ``keep``: the log entries (:meth:`log_rows`)."""
        self._check_current(rows)
        everyone = list(rows) == list(range(self.rows))
        index = None if everyone else self.row_index(rows)
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
                old = self._columns[row][-1]
                self._columns[row][-1] = column
                if old in self._updated[row]:  # the updated node moves, with its prediction
                    self._updated[row][column] = self._updated[row].pop(old)
        self._append(*(c.unsqueeze(1) for c in columns))
        self.log_rows(rows, infos, values, keep)

    def _flush(self) -> None:
        """Move every column the chunk lists hold to the rows' stores; the lists are then empty.
        Only between a column's last change and the next (at an append: no event acts on a node
        but the newest, and the newest's owners are settled once a column follows it)."""
        end = self._count
        held = sum(c.shape[1] for c in self._transition)
        if held != end - self._start:
            raise RuntimeError(f"BatchChain: the chunks hold {held} columns, expected {end - self._start}")
        joined = {name: (chunks[0] if len(chunks) == 1 else torch.cat(chunks, dim=1))
                  for name, chunks in (("transition", self._transition), ("pred_mean", self._pred_mean),
                                       ("mean", self._mean), ("cov", self._cov))}
        for b, store in enumerate(self._stores):
            columns = self._columns[b]
            first, last = self._stored[b], bisect_left(columns, end, self._stored[b])
            if last == first:
                continue
            local = [c - self._start for c in columns[first:last]]
            k = last - first
            run = local[-1] - local[0] == k - 1  # one contiguous run of columns: a slice
            index = None if run else torch.tensor(local, dtype=torch.long, device=joined["cov"].device)
            for name, part in joined.items():
                target = store.reserve(name, part, k)[store.count: store.count + k]
                target.copy_(part[b, local[0]: local[0] + k] if run else part[b].index_select(0, index))
            updated = self._updated[b]
            own_updated = sorted(c for c in updated if c < end)
            flags = [False] * k
            for c in own_updated:
                flags[bisect_left(columns, c, first, last) - first] = True
            store.add_updated([updated.pop(c) for c in own_updated])
            store.updated.extend(flags)
            store.count += k
            self._stored[b] = last
        for chunks in (self._transition, self._pred_mean, self._pred_cov, self._mean, self._cov):
            chunks.clear()
        self._start = end

    def _finish_stores(self) -> list[tuple[Tensor, ...]]:
        """Each row's ``(transition, pred_mean, mean, cov, updated, updated_pred_cov)`` as views of
        its store, after the last flush; the chain keeps its newest nodes."""
        newest = (self._transition[-1][:, -1:], self._pred_mean[-1][:, -1:], self._pred_cov[-1][:, -1:],
                  self._mean[-1], self._cov[-1])
        self._flush()
        self._transition, self._pred_mean, self._pred_cov, self._mean, self._cov = ([part] for part in newest)
        out = []
        for store in self._stores:
            n = store.count
            parts = tuple(store.parts[name][:n] for name in _RowStore.NAMES)
            covs = parts[3]
            updated_pred = store.updated_pred[: store.updated_count] if store.updated_pred is not None else covs[:0].clone()
            out.append((*parts, torch.tensor(store.updated, dtype=torch.bool, device=covs.device), updated_pred))
        return out

    def finish(self) -> list[FilterTrack]:
        """Each row's :class:`FilterTrack` (its own nodes only). With row stores the tracks are
        views of them (after a last flush); otherwise the chain's storage is handed over part by
        part (each part's columns are freed once the rows have copied theirs, so the nodes are
        not held twice). After it the chain keeps only its newest nodes (:attr:`mean`, :attr:`cov`)."""
        self.raise_failures()
        if self._finished:
            raise RuntimeError("BatchChain.finish: the chain is finished already (it hands its nodes over once)")
        self._finished = True
        if self._stores is not None:
            return [self._track(b, *parts) for b, parts in enumerate(self._finish_stores())]
        # the predicted covariances of the updated nodes only (a copy: the chunks they view go)
        updated = []
        for b in range(self.rows):
            columns = sorted(self._updated[b])
            mask = torch.zeros(len(self._columns[b]), dtype=torch.bool)
            if columns:
                own, wanted = torch.tensor(self._columns[b]), torch.tensor(columns)
                where = torch.searchsorted(own, wanted)
                if not torch.equal(own[where.clamp(max=own.shape[0] - 1)], wanted):
                    raise RuntimeError(f"BatchChain.finish: row {b} has updated columns that are not its nodes")
                mask[where] = True
            covs = [self._updated[b][c] for c in columns]
            updated.append((mask, torch.stack(covs) if covs else self._cov[-1][b, :0].clone()))
            self._updated[b] = {}
        self._pred_cov = self._pred_cov[-1:]  # the rest is held by no one now
        own = []
        for name in ("_transition", "_pred_mean", "_mean", "_cov"):
            chunks = getattr(self, name)
            setattr(self, name, chunks[-1:])
            own.append(self._own_columns(chunks))
        return [self._track(b, *(part[b] for part in own), updated[b][0].to(own[2][b].device), updated[b][1])
                for b in range(self.rows)]

    def _track(self, b: int, transition: Tensor, pred_mean: Tensor, mean: Tensor, cov: Tensor, mask: Tensor,
               updated_pred_cov: Tensor) -> FilterTrack:
        """Row ``b``'s :class:`FilterTrack` from its nodes."""
        nll = (torch.stack(self._nll[b]).sum() if self._nll[b] else mean.new_zeros(())) if self.likelihood else None
        count = float(torch.stack(self._nll_count[b]).sum()) if self._nll_count[b] else 0.0
        return FilterTrack(t_s=torch.tensor(self.t_s[b], dtype=torch.float64), transition=transition,
                           pred_mean=pred_mean, updated=mask, updated_pred_cov=updated_pred_cov,
                           node_mean=mean, node_cov=cov, log=self.logs[b],
                           frame_changes=self.frame_changes[b], nll=nll, nll_count=count)

    def _own_columns(self, chunks: list[Tensor]) -> list[Tensor]:
        """Per row, its own columns of ``chunks`` (``(B, n, ...)`` each) in one tensor of its own.

        A few rows gather theirs from the chunks (one copy, :meth:`_own_columns_by_row`). Many
        rows would each gather from every chunk, thousands of small pieces per row (on a GPU
        each piece is a launch), so the chunks are joined once and freed, and each row takes its
        columns from the join (a second copy) or, where every row owns every column, is a view
        of it (docs/performance.md times both for 64 runs)."""
        if self.rows <= 4 or len(chunks) == 1:
            return self._own_columns_by_row(chunks)
        full = torch.cat(chunks, dim=1)
        chunks.clear()  # the caller's list: its columns are held once, in the join
        total = full.shape[1]
        if all(len(columns) == total for columns in self._columns):  # each row owns every column
            return list(full.unbind(0))  # views that share the join, nothing of it unused
        return [full[b].index_select(0, torch.tensor(columns, dtype=torch.long, device=full.device))
                for b, columns in enumerate(self._columns)]

    def _own_columns_by_row(self, chunks: list[Tensor]) -> list[Tensor]:
        """:meth:`_own_columns` row by row: one copy, each chunk taken whole where the row owns
        all of it, else only the columns it owns (their indices moved to the device at once)."""
        sizes = torch.tensor([c.shape[1] for c in chunks])
        ends = sizes.cumsum(0)
        starts = (ends - sizes).tolist()
        plans, indices = [], []  # per row: (chunk, whole or the place of its index in indices)
        for b in range(self.rows):
            columns = torch.tensor(self._columns[b], dtype=torch.long)
            # how many of the row's columns fall in each chunk (columns are increasing)
            cut = torch.searchsorted(columns, ends).tolist()
            pieces, first = [], 0
            for chunk, start, last in zip(chunks, starts, cut):
                if last == first:
                    continue
                if last - first == chunk.shape[1]:
                    pieces.append((chunk, None))
                else:
                    pieces.append((chunk, len(indices)))
                    indices.append(columns[first:last] - start)
                first = last
            plans.append(pieces)
        if indices:
            moved = torch.cat(indices).to(chunks[0].device).split([len(i) for i in indices])
        out = []
        for b, pieces in enumerate(plans):
            parts = [chunk[b] if at is None else chunk[b].index_select(0, moved[at]) for chunk, at in pieces]
            out.append(torch.cat(parts) if parts else chunks[0][b, :0].clone())  # cat copies even one piece
        return out


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
    #: ``(J,)`` bool: the nodes whose filtered Gaussian an update replaced; at every other node
    #: the prediction is the filtered Gaussian
    updated: Tensor
    updated_pred_cov: Tensor  # (U, 26, 26) the predicted covariances of the U updated nodes, in order
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

    @property
    def pred_cov(self) -> Tensor:
        """Predicted covariances ``(J, 26, 26)``: the filtered ones, but the prediction where an
        update acted (built on each call: the chain keeps only those)."""
        index = torch.nonzero(self.updated).squeeze(-1)
        return self.node_cov.index_copy(0, index, self.updated_pred_cov) if index.numel() else self.node_cov.clone()

    def key_nodes(self) -> Tensor:
        """``(J,)`` bool: the updated nodes and the last, where the RTS smoother's recursion runs
        (:func:`~flowins.filter.smoother.rts_smooth`)."""
        keys = self.updated.clone()
        keys[-1] = True
        return keys

    def in_final_frame(self, *, marginal: int | None = None) -> NodeTrack:
        """The filtered nodes with those before each change of frame re-expressed after it
        (``m ↦ A m + b``, ``P ↦ A P Aᵀ + Q``): each node is still the filter's estimate from
        the data up to its time, relative to its start; only its frame is the final one.
        ``marginal``: the first ``marginal`` state entries only (None: all)."""
        D = self.node_mean.shape[-1]
        c = D if marginal is None else marginal
        changes = marginal_frame_changes(self.frame_changes, c, D, where=f"FilterTrack.in_final_frame(marginal={marginal})")
        mean, cov = self.node_mean[:, :c], self.node_cov[:, :c, :c]
        if not changes:
            return NodeTrack(self.t_s, mean, cov)
        mean, cov = to_final_frame(mean, cov, changes)
        return NodeTrack(self.t_s, normalize_quaternions(mean), symmetrize(cov))


@dataclass
class NodeTrack(_NodeOutputs):
    """Nodes ``t_s (J,)``, ``node_mean (J, 26)``, ``node_cov (J, 26, 26)`` and their outputs."""

    t_s: Tensor
    node_mean: Tensor
    node_cov: Tensor


def marginal_frame_changes(frame_changes, dim: int, size: int, *, where: str) -> list:
    """The ``(node, A, b, Q)`` of ``frame_changes`` (of states of ``size`` entries) for the first
    ``dim`` entries, ``1 <= dim <= size`` (``where`` names the caller in the errors); a change must
    not mix the later entries into them (``A[:dim, dim:] = 0``, as a heading alignment's
    block-diagonal map does at any pose's boundary)."""
    if not 1 <= dim <= size:
        raise ValueError(f"{where}: expected 1 .. {size}, the state's size, or None")
    if dim == size:
        return list(frame_changes)
    out = []
    for node, A, b, Q in frame_changes:
        if A.shape[-1] > dim and bool((A[:dim, dim:] != 0).any()):
            raise ValueError(f"{where}: the change of frame at node {node} mixes state entries beyond the first "
                             f"{dim} into them; take the whole state (marginal=None)")
        out.append((node, A[:dim, :dim], b[:dim], Q[:dim, :dim]))
    return out


def to_final_frame(mean: Tensor, cov: Tensor, frame_changes) -> tuple[Tensor, Tensor]:
    """Nodes ``(J, 26)``, ``(J, 26, 26)`` before each change of frame ``(node, A, b, Q)``
    re-expressed in the frame after it: ``m ↦ A m + b``, ``P ↦ A P Aᵀ + Q``."""
    for node, A, b, Q in reversed(frame_changes):
        mean = torch.cat(((mean[:node] @ A.T) + b, mean[node:]))
        cov = torch.cat((A @ cov[:node] @ A.T + Q, cov[node:]))
    return mean, cov
