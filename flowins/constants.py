"""Physical constants, and constant tensors built once per dtype and device, for every run
of the process.

:func:`flowins.navigation.navigate` runs in ``torch.inference_mode`` when nothing needs a
gradient. A constant first built there would be an inference tensor, and a later run
*with* gradients in the same process could not save it for backward. Every cached
builder of constant tensors therefore goes through :func:`cached_constant`, which builds
outside inference mode.
"""
from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TypeVar

import torch

F = TypeVar("F", bound=Callable)

#: standard gravity (m/s², the CGPM's conventional value); the filter and the simulator take
#: the magnitude as a parameter, this is its default
STANDARD_GRAVITY_MPS2 = 9.80665

#: every builder decorated so far (:func:`clear_constants` empties their caches)
_BUILDERS: list = []


def cached_constant(builder: F) -> F:
    """``functools.cache`` for ``builder`` (hashable arguments: numbers, dtypes, devices,
    layouts), with the build run outside inference mode; callers must not modify the
    result in place."""

    @functools.cache
    @functools.wraps(builder)
    def build(*args, **kwargs):
        with torch.inference_mode(False):
            return builder(*args, **kwargs)

    _BUILDERS.append(build)
    return build  # type: ignore[return-value]


def clear_constants() -> None:
    """Forget every cached constant (they are rebuilt on next use)."""
    for build in _BUILDERS:
        build.cache_clear()


@cached_constant
def scalar(value: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``value`` as a 0-dim tensor, built once per value, dtype and device."""
    return torch.tensor(value, dtype=dtype, device=device)


def scalar_like(value: float | torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """``value`` in ``like``'s dtype and device: a tensor (a learned parameter) cast there, itself
    when it is there already; a number built once (:func:`scalar`), not copied from the host at
    every use."""
    if isinstance(value, torch.Tensor):
        return value if value.dtype == like.dtype and value.device == like.device else value.to(like)
    return scalar(float(value), like.dtype, like.device)
