"""Independent pieces of work in worker processes on the CPU, and splitting work into even parts.

A batched filter pass on the CPU is a long string of small operations: one process keeps
about one core busy, however many threads it has (they share little of each small
operation). :func:`~flowins.navigation.navigate_batch` with ``filter.workers=N``
(``NavigationConfig.workers``) therefore splits a batch of several recordings into ``N`` parts
of about equal work (:func:`split_by_load`) and filters each part in a process of its own
(:func:`run_in_processes`), one thread each.

Workers start by ``fork`` on Linux, where they inherit their inputs, and by ``spawn``
elsewhere, where their inputs are pickled to them and each imports flowins first (a few
seconds). Results come back as torch's process pool sends them: a tensor's storage moved to
shared memory and mapped here, not copied through a pipe. The workers' log records,
progress lines included (under ``worker i/N``), reach the caller's ``flowins`` logger; an
error in a worker is raised again in the caller, with the worker's traceback as its cause, and
a worker killed before it returns (the system's out-of-memory killer) raises
ChildProcessError instead of leaving the caller waiting.
"""
from __future__ import annotations

import logging
import logging.handlers
import multiprocessing
import os
import pickle
import sys
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import torch

from flowins import progress

log = logging.getLogger("flowins")

#: whether this process is a worker of :func:`run_in_processes`
_IN_WORKER = False

#: what a forked worker reads instead of a pickled copy: ``(fn, parts)`` of the running call
_INHERITED: tuple[Callable[..., Any], Sequence[tuple]] | None = None


def split_by_load(loads: Sequence[float], parts: int) -> list[list[int]]:
    """The indices of ``loads`` in ``min(parts, len(loads))`` groups of about equal total load,
    each group in ascending order, the groups by their first index.

    Longest first, each to the group with the least load so far (ties: the lower group);
    the largest group's load is at most ``4/3 - 1/(3 parts)`` times the best split's
    (Graham's bound for this rule)."""
    if parts < 1:
        raise ValueError(f"split_by_load: parts must be >= 1, got {parts}")
    if any(not load >= 0.0 for load in loads):
        raise ValueError(f"split_by_load: loads must be numbers >= 0, got {list(loads)}")
    count = min(parts, len(loads))
    groups: list[list[int]] = [[] for _ in range(count)]
    totals = [0.0] * count
    for i in sorted(range(len(loads)), key=lambda i: (-loads[i], i)):
        g = min(range(count), key=lambda g: (totals[g], g))
        groups[g].append(i)
        totals[g] += loads[i]
    return sorted((sorted(group) for group in groups), key=lambda group: group[0])


def available_cores() -> int:
    """The CPU cores this process may run on (its affinity where the system says, else all)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def can_start_workers() -> bool:
    """Whether this process may start worker processes: not when it is itself a daemonic worker
    (a data loader's), which Python's multiprocessing forbids, nor one of
    :func:`run_in_processes`'s (each has its share of the cores already)."""
    return not (multiprocessing.current_process().daemon or _IN_WORKER)


def in_distributed_run() -> bool:
    """Whether this process is one of several of a distributed run (``torch.distributed``
    initialised with more than one process: ``train.py trainer=ddp``), which has its share of
    the cores already."""
    return (torch.distributed.is_available() and torch.distributed.is_initialized()
            and torch.distributed.get_world_size() > 1)


def start_method() -> str:
    """``fork`` on Linux (the inputs are inherited, nothing is pickled to the workers), else ``spawn``."""
    return "fork" if sys.platform.startswith("linux") else "spawn"


def run_in_processes(fn: Callable[..., Any], parts: Sequence[tuple], *, method: str | None = None) -> list[Any]:
    """``[fn(*args) for args in parts]``, each call in a worker process of its own with one
    thread; ``fn`` a module-level function (or a ``functools.partial`` of one) whose results
    pickle. ``method``: ``fork`` | ``spawn`` (None: :func:`start_method`)."""
    global _INHERITED
    if not parts:
        return []
    method = method or start_method()
    context = multiprocessing.get_context(method)
    records = context.Queue()
    listener = logging.handlers.QueueListener(records, _Forward())
    forked = method == "fork"
    tasks = [(i, len(parts), None if forked else pickle.dumps((fn, args), protocol=pickle.HIGHEST_PROTOCOL))
             for i, args in enumerate(parts)]
    _INHERITED = (fn, parts) if forked else None
    listening = False
    try:
        with ProcessPoolExecutor(len(parts), mp_context=context, initializer=_start_worker,
                                 initargs=(records, log.getEffectiveLevel())) as pool:
            futures = [pool.submit(_work, task) for task in tasks]  # one process each, started here
            listener.start()  # after the workers started: no thread of this one is forked into them
            listening = True
            results = [_result(future, i, len(parts)) for i, future in enumerate(futures)]
        # the pool has shut down: each worker's queue thread wrote its last records before the
        # worker ended, so the listener's stop mark comes after them
        return results
    finally:
        if listening:
            listener.stop()
        _INHERITED = None
        records.close()


def run_parts(fn: Callable[..., Sequence[Any]], parts: Sequence[Sequence[int]], *columns: Sequence[Any],
              method: str | None = None) -> list[Any]:
    """``fn`` on the items of each part of ``parts`` (lists of indices, e.g. from
    :func:`split_by_load`), each part in a worker process (:func:`run_in_processes`): ``fn`` takes
    each of ``columns`` cut to the part's items and returns one result per item; the results in
    the items' order (an index in no part keeps None)."""
    done = run_in_processes(fn, [tuple([column[i] for i in part] for column in columns) for part in parts],
                            method=method)
    results: list[Any] = [None] * (len(columns[0]) if columns else 0)
    for part, part_results in zip(parts, done):
        if len(part_results) != len(part):
            raise ValueError(f"run_parts: {fn!r} gave {len(part_results)} results for a part of {len(part)} items")
        for i, result in zip(part, part_results):
            results[i] = result
    return results


def _result(future: Future, index: int, count: int) -> Any:
    """The result of worker ``index``; ChildProcessError where a worker process ended without
    one (killed: a pool of processes would otherwise wait for it for ever)."""
    try:
        return future.result()
    except BrokenProcessPool as error:
        raise ChildProcessError(
            f"a worker process (of {count}; waiting for worker {index + 1}) ended without returning its result: "
            "killed, e.g. by the system for lack of memory; fewer recordings per process "
            "(filter.workers) or shorter ones need less") from error


class _Forward(logging.Handler):
    """Hands a worker's record to the caller's logger of the same name."""

    def handle(self, record: logging.LogRecord) -> bool:
        logger = logging.getLogger(record.name)
        if logger.isEnabledFor(record.levelno):
            logger.handle(record)
        return True

    def emit(self, record: logging.LogRecord) -> None:  # handle() does the work
        pass


def _start_worker(records: Any, level: int) -> None:
    """In each worker: one thread, and the ``flowins`` logger's records sent to the caller."""
    global _IN_WORKER
    _IN_WORKER = True
    torch.set_num_threads(1)
    for handler in list(log.handlers):
        log.removeHandler(handler)
    log.addHandler(logging.handlers.QueueHandler(records))
    log.setLevel(level)
    log.propagate = False


def _work(task: tuple[int, int, bytes | None]) -> Any:
    index, count, payload = task
    fn, args = (_INHERITED[0], _INHERITED[1][index]) if payload is None else pickle.loads(payload)
    with progress.reported_as(f"worker {index + 1}/{count}"):
        return fn(*args)
