"""Progress of long work: a bar on a terminal, a log line about every 10 % elsewhere.

On a terminal (stderr is a TTY) :func:`progress` draws a tqdm bar. In a log file, a pipe
or a notebook cell captured to a file, a bar's carriage-return updates become thousands of
lines; there it logs ``<description>: 30% (90/300 pairs, 12.1 s)`` to the ``flowins``
logger when each further tenth of the work is done, from ``min_seconds`` (5 s) on: work
that is done sooner says nothing. Inside :func:`reported_as` (a worker process,
:mod:`flowins.parallel`) it always logs, each description preceded by the worker's name.
"""
from __future__ import annotations

import contextlib
import logging
import sys
import time
from collections.abc import Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")

log = logging.getLogger("flowins")

#: the name progress is reported under (:func:`reported_as`); None: a bar on a terminal
_REPORTER: str | None = None


def is_terminal() -> bool:
    stream = sys.stderr
    return _REPORTER is None and bool(getattr(stream, "isatty", lambda: False)())


@contextlib.contextmanager
def reported_as(name: str) -> Iterator[None]:
    """While inside, progress is logged as lines ``<name>: <description>: 30% ...``, never a bar
    (the workers of a process pool share one terminal)."""
    global _REPORTER
    saved, _REPORTER = _REPORTER, name
    try:
        yield
    finally:
        _REPORTER = saved


class Progress:
    """Counts work done of ``total`` and reports it (:func:`progress`); ``update(n)``, ``close()``."""

    def __init__(self, *, total: int, description: str, unit: str = "it", enabled: bool = True,
                 terminal: bool | None = None, steps: int = 10, min_seconds: float = 5.0) -> None:
        self.total, self.unit = int(total), unit
        self.description = description if _REPORTER is None else f"{_REPORTER}: {description}"
        self.enabled = enabled and self.total > 0
        self.done, self.reported, self.steps, self.min_seconds = 0, 0, steps, min_seconds
        self.start = time.perf_counter()
        self.bar = None
        if self.enabled and (is_terminal() if terminal is None else terminal):
            from tqdm.auto import tqdm

            self.bar = tqdm(total=self.total, desc=description, unit=unit, leave=False)

    def update(self, n: int = 1) -> None:
        self.done += n
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.update(n)
            return
        tenth = min(self.steps, self.done * self.steps // self.total)
        elapsed = time.perf_counter() - self.start
        if tenth > self.reported and elapsed >= self.min_seconds:
            self.reported = tenth
            log.info("%s: %d%% (%d/%d %ss, %.1f s)", self.description, round(100 * self.done / self.total),
                     self.done, self.total, self.unit, elapsed)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def progress(items: Iterable[T], *, total: int | None = None, description: str, unit: str = "it",
             enabled: bool = True, terminal: bool | None = None, min_seconds: float = 5.0) -> Iterator[T]:
    """Iterate ``items`` reporting progress (a bar on a terminal, a log line per tenth elsewhere)."""
    if total is None:
        total = len(items)  # type: ignore[arg-type]
    counter = Progress(total=total, description=description, unit=unit, enabled=enabled, terminal=terminal,
                       min_seconds=min_seconds)
    try:
        for item in items:
            yield item
            counter.update(1)
    finally:
        counter.close()
