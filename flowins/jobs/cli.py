"""What a job prints when it stops on a user's mistake: ``error: <message>``, exit status 2.

A flowins ``ValueError`` (bad input, a config value, a file that is not what it should be)
or an ``OSError`` (a missing or unreadable file) is the user's to fix: the job prints the
message alone, with no traceback, logs it, and exits with status 2. Any other exception is
a flowins bug and keeps its traceback. ``HYDRA_FULL_ERROR=1`` shows the traceback of a
user error too.
"""
from __future__ import annotations

import functools
import logging
import os
import sys
from collections.abc import Callable
from typing import Any, TypeVar

F = TypeVar("F", bound=Callable[..., Any])

#: the exceptions that mean "the input or the config is wrong", not "flowins is wrong"
USER_ERRORS: tuple[type[BaseException], ...] = (ValueError, OSError)

log = logging.getLogger("flowins")


class BelowError(logging.Filter):
    """Lets through what is not an error: the console's stdout half (errors go to stderr)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno < logging.ERROR


class _Console(logging.Handler):
    """Writes each record as a plain line to the ``sys.stdout`` (below ERROR) or ``sys.stderr``
    (ERROR and above) of the moment it comes (a test's captured streams included)."""

    def __init__(self) -> None:
        super().__init__()
        self.setFormatter(logging.Formatter("%(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        stream = sys.stderr if record.levelno >= logging.ERROR else sys.stdout
        stream.write(self.format(record) + "\n")
        stream.flush()


def console_logging() -> None:
    """Make the ``flowins`` logger's INFO lines reach the console when nobody set up logging
    (a job run from Python, a benchmark): Hydra's ``configs/hydra/job_logging/flowins.yaml``
    already sends them to the console and to ``<output_dir>/<job>.log``."""
    log.setLevel(logging.INFO)
    configured = any(type(h) in (logging.StreamHandler, logging.FileHandler) for h in logging.getLogger().handlers)
    if not configured and not any(isinstance(h, _Console) for h in log.handlers):
        log.addHandler(_Console())


def report(error: BaseException) -> int:
    """Log ``error: <message>`` (the console and the job's log file); returns the exit status, 2."""
    console_logging()
    log.error("error: %s", error)
    return 2


def user_errors(task: F) -> F:
    """Wrap a job's entry point: a user error ends the process with ``error: …`` and
    status 2 (:data:`USER_ERRORS`); ``HYDRA_FULL_ERROR=1`` re-raises it."""

    @functools.wraps(task)
    def wrapped(*args: Any, **kwargs: Any) -> Any:
        try:
            return task(*args, **kwargs)
        except USER_ERRORS as error:
            if os.environ.get("HYDRA_FULL_ERROR") == "1":
                raise
            sys.exit(report(error))

    return wrapped  # type: ignore[return-value]
