"""Reading PyTorch files that a user passes in, without running code from them.

``torch.load`` unpickles: a file made to do so runs any code it likes while it is
read. :func:`load_tensors` reads with ``weights_only=True``, so a file yields
tensors, numbers (NumPy's numeric scalars too: checkpoints often keep an epoch or a
score as one), strings, lists, tuples and dicts, and nothing else; a file that asks
for anything more is refused before any of it runs. Every loader of a file a
user names (a ``train.py`` checkpoint, FlowNet 2.0 and SpyNet weights) goes
through this one function, so every refusal reads the same way.
"""
from __future__ import annotations

import functools
import os
import pickle
import re
from pathlib import Path
from typing import Any

import torch


def load_tensors(path: str | os.PathLike, *, argument: str, expected: str, map_location: Any = "cpu") -> Any:
    """``torch.load(path, weights_only=True)`` with errors that name the argument and the file.

    Args:
        path: the file.
        argument: what the user set to name it (``model.checkpoint``, ``flow.checkpoint``),
            the first words of every error.
        expected: what the file should be (``a .ckpt written by train.py``), for errors.
        map_location: as for ``torch.load``.

    Raises:
        ValueError: the file does not exist, is not a PyTorch file, or holds Python
            objects other than tensors and plain values (the error names the first
            one torch met; nothing in the file has run).
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{argument}: {path} is not a file; expected {expected}")
    try:
        with torch.serialization.safe_globals(_numpy_scalars()):
            return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        wanted = re.search(r"unsupported GLOBAL (\S+)", str(exc))
        if wanted is None:  # not a pickle torch.load understands (garbage, another pickle protocol)
            raise ValueError(f"{argument}: cannot read {path} as a PyTorch file ({_reason(exc)}); expected {expected}") from None
        raise ValueError(
            f"{argument}: {path} asks to load the Python object {wanted[1]}; flowins reads only tensors, numbers, "
            f"strings, lists and dicts from a file, so that no file can run code, and read nothing from this one; "
            f"expected {expected}"
        ) from None
    except (RuntimeError, EOFError, OSError, ValueError) as exc:
        raise ValueError(f"{argument}: cannot read {path} as a PyTorch file ({_reason(exc)}); expected {expected}") from None


@functools.cache
def _numpy_scalars() -> list:
    """What unpickling a NumPy numeric scalar needs: its constructor (under NumPy 1's and
    2's module names) and the numeric dtypes. Data, not code: they build a number."""
    import numpy as np

    try:
        from numpy._core.multiarray import scalar
    except ImportError:  # NumPy 1
        from numpy.core.multiarray import scalar
    dtypes = {type(np.dtype(name)) for name in ("bool", "int8", "int16", "int32", "int64", "uint8", "uint16",
                                                "uint32", "uint64", "float16", "float32", "float64")}
    names = [(scalar, f"{module}.scalar") for module in ("numpy.core.multiarray", "numpy._core.multiarray")]
    return [*names, np.dtype, *sorted(dtypes, key=lambda t: t.__name__)]


def _reason(exc: Exception) -> str:
    """The line of an error from ``torch.load`` that says what went wrong (its advice to
    load with ``weights_only=False`` left out: flowins never does)."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    for line in lines:
        if line.startswith(("Unsupported", "PytorchStreamReader", "Trying to")):
            return line.split(". ")[0].rstrip(".")
    if isinstance(exc, EOFError):
        return "the file ends early"
    return lines[0] if lines else type(exc).__name__
