"""How a batch of recordings is run: in this process, or split over CPU worker processes.

:func:`~flowins.navigation.navigate_batch` runs a batch in worker processes
(:mod:`flowins.parallel`) only on the CPU, with ``filter.workers`` above 1, and where nothing
carries a gradient (a graph does not cross processes); each process gets a part of about equal
work (IMU samples and flow frames, :func:`run_load`).
"""
from __future__ import annotations

import dataclasses
import functools
import logging
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol

import torch
from torch import Tensor

from flowins.parallel import can_start_workers, run_parts, split_by_load


class BatchConfig(Protocol):
    """What the split reads of a :class:`~flowins.navigation.NavigationConfig` (a dataclass)."""

    workers: int
    device: torch.device


class LoadedRun(Protocol):
    """What :func:`run_load` reads of a :class:`~flowins.navigation.NavigationRun`."""

    imu: Any  # ImuStream: t_s
    flow: Any  # FlowPairs or None
    tracks: Any  # Tracks or None


log = logging.getLogger(__name__)


def carries_gradient(*objects) -> bool:
    """Whether grad mode is on and any tensor in ``objects`` (searched through dataclasses,
    named tuples, lists, tuples, mappings and modules' parameters) requires a gradient."""
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
        elif isinstance(obj, torch.nn.Module):  # a learned network (adaptive noise)
            seen.add(id(obj))
            stack.extend(obj.parameters())
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



def batch_workers(runs: Sequence[LoadedRun], config: BatchConfig, *, gradient: bool | None = None,
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


def run_load(run: LoadedRun) -> float:
    """About how much filtering ``run`` takes: its IMU samples and :data:`FRAME_LOAD` per flow
    frame pair or track frame (splitting a batch over workers evens it out)."""
    frames = 0 if run.flow is None else len(run.flow)
    if run.tracks is not None:
        frames += len(run.tracks.frame_times)
    return float(run.imu.t_s.shape[0]) + FRAME_LOAD * frames


def navigate_in_workers(navigate_batch: Callable[..., list], runs: Sequence[LoadedRun], *,
                        config: BatchConfig, gradient: bool, progress: bool) -> list | None:
    """``navigate_batch`` on ``runs`` split into ``config.workers`` parts of about equal work
    (:func:`run_load`), each part in a worker process with ``workers=1``, the results in the
    order of ``runs``; None where the batch belongs in this process (:func:`batch_workers`,
    or this process is a worker itself, which starts no processes: said in the log)."""
    if batch_workers(runs, config, gradient=gradient, here=False) == 1:
        return None
    if not can_start_workers():
        log.info("filter: %d runs in this process: it is a worker process itself, which starts none of the "
                 "filter.workers=%d processes", len(runs), config.workers)
        return None
    parts = split_by_load([run_load(run) for run in runs], config.workers)
    log.info("filter: %d runs in %d worker processes (filter.workers=%d)", len(runs), len(parts), config.workers)
    task = functools.partial(navigate_batch, config=dataclasses.replace(config, workers=1), progress=progress)
    return run_parts(task, parts, runs)
