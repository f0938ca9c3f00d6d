"""Shared timing helper of the benchmark scripts (they import it from their own folder)."""
from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence


def interleaved_ms(
    fns: Sequence[Callable[[], object]],
    repeats: int,
    *,
    reduce: Callable[[list[float]], float] = statistics.median,
    warmup: bool = True,
    sync: Callable[[], None] | None = None,
) -> list[float]:
    """Milliseconds of each of ``fns``, reduced (median by default) over ``repeats``
    rounds that run every function once, interleaved: a shared CPU's speed drifts
    over minutes, and the ratios between the rows should not. ``warmup`` runs one
    untimed round first; ``sync`` (e.g. ``torch.cuda.synchronize``) runs before each
    clock reading."""
    if warmup:
        for fn in fns:
            fn()
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(repeats):
        for fn, ts in zip(fns, times):
            if sync is not None:
                sync()
            start = time.perf_counter()
            fn()
            if sync is not None:
                sync()
            ts.append((time.perf_counter() - start) * 1e3)
    return [reduce(ts) for ts in times]
