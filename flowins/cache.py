"""Where flowins keeps what it computes once (simulated recordings, flow pairs), and the
content keys that decide when a kept result still answers the question.

A key is a hash of everything a result depends on: the inputs' contents (not their
names), the settings, the weights, the versions of the libraries that compute it and
flowins' own source code that does. Change any of them and the key changes, so a
result is recomputed rather than served stale.
"""
from __future__ import annotations

import contextlib
import hashlib
import importlib
import json
import os
import time
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

#: hex digits of a key (64 bits: a collision among a user's cached results is not a concern)
KEY_LENGTH = 16


def cache_root() -> Path:
    """``$FLOWINS_CACHE``, default ``~/.cache/flowins``."""
    return Path(os.environ.get("FLOWINS_CACHE", Path.home() / ".cache" / "flowins"))


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike) -> Iterator[None]:
    """Hold an exclusive lock on ``folder`` (the file ``<folder>.lock`` beside it) between
    processes: two jobs (or test workers) that want the same cached simulation take turns,
    the second finding it written, instead of writing one folder at once. The lock goes with
    the process that holds it (it cannot be left stale by a crash); the lock file stays."""
    path = Path(folder)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_name(path.name + ".lock"), "a+b") as handle:
        try:
            import fcntl
        except ImportError:  # Windows
            import msvcrt

            while True:
                try:
                    msvcrt.locking(handle.fileno(), msvcrt.LK_NBLCK, 1)
                    break
                except OSError:
                    time.sleep(0.2)
            try:
                yield
            finally:
                handle.seek(0)
                msvcrt.locking(handle.fileno(), msvcrt.LK_UNLCK, 1)
        else:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(handle.fileno(), fcntl.LOCK_UN)


def file_digest(path: str | os.PathLike) -> str:
    """SHA-256 of a file's bytes (hex)."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def array_digest(array: torch.Tensor | np.ndarray) -> str:
    """SHA-256 of an array's dtype, shape and values (hex)."""
    if isinstance(array, torch.Tensor):
        array = array.detach().cpu()
        array = (array.float() if array.dtype == torch.bfloat16 else array).numpy()  # NumPy has no bfloat16
    array = np.ascontiguousarray(array)
    h = hashlib.sha256(f"{array.dtype.str}{array.shape}".encode())
    h.update(array.tobytes())
    return h.hexdigest()


def source_digest(*modules: str) -> str:
    """SHA-256 of the Python source of ``modules`` (a package stands for every ``.py`` file
    below it): the code that computes a cached result."""
    h = hashlib.sha256()
    for name in modules:
        module = importlib.import_module(name)
        path = Path(module.__file__)
        files = sorted(path.parent.rglob("*.py")) if path.name == "__init__.py" else [path]
        for file in files:
            h.update(f"{name}:{file.relative_to(path.parent).as_posix()}\0".encode())
            h.update(file.read_bytes())
    return h.hexdigest()


def library_versions() -> dict[str, str]:
    """Versions of the libraries whose numbers end up in cached results."""
    import cv2

    return {"torch": torch.__version__, "numpy": np.__version__, "opencv": cv2.__version__}


def content_key(value: Any) -> str:
    """A short key of ``value``: nested mappings, sequences, numbers and strings as they
    are; tensors and arrays by their values; ``nn.Module`` by its state dict; paths as text."""
    text = json.dumps(value, sort_keys=True, default=_canonical)
    return hashlib.sha256(text.encode()).hexdigest()[:KEY_LENGTH]


def _canonical(value: Any) -> Any:
    if isinstance(value, (torch.Tensor, np.ndarray)):
        return {"array": array_digest(value)}
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, nn.Module):
        return {"module": type(value).__qualname__, "state": {k: array_digest(v) for k, v in value.state_dict().items()}}
    if isinstance(value, (Path, os.PathLike)):
        return os.fspath(value)
    if isinstance(value, (set, frozenset)):
        return sorted(value, key=repr)
    if isinstance(value, Mapping):  # OmegaConf's DictConfig, ...
        return dict(value)
    if isinstance(value, Iterable) and not isinstance(value, (str, bytes)):  # ListConfig, ...
        return list(value)
    raise TypeError(f"content_key: cannot key a {type(value).__name__}")
