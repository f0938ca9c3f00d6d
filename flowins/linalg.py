"""Batched linear algebra split into slices that the device's solvers take.

cuSOLVER's batched ``eigh`` of 65,536 ``4 x 4`` matrices (the triangulations of 256
recordings with 256 points each) stopped with ``CUSOLVER_STATUS_INTERNAL_ERROR`` on an
H200 (torch 2.11, CUDA 13), and others report the same routine failing above about 32k
matrices (mujocolab/mjlab pull request 732). :func:`in_slices` computes such calls over at
most :data:`CUDA_SLICE` matrices at a time on CUDA and in one call elsewhere, with the same
values and gradients.
"""
from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

#: most matrices handed to one batched solver call on CUDA
CUDA_SLICE = 16384


def in_slices(fn: Callable[..., Tensor | tuple[Tensor, ...]], *matrices: Tensor, batch_dims: int,
              limit: int | None = None) -> Tensor | tuple[Tensor, ...]:
    """``fn(*matrices)``, computed over slices of the first ``batch_dims`` dimensions (shared
    by every input and every output) of at most ``limit`` entries each and concatenated (a
    tuple of outputs comes back as a plain tuple).
    ``limit`` None: :data:`CUDA_SLICE` on CUDA, no slicing elsewhere."""
    batch = matrices[0].shape[:batch_dims]
    for m in matrices:
        if m.shape[:batch_dims] != batch:
            raise ValueError(f"in_slices: batch shapes {tuple(batch)} and {tuple(m.shape[:batch_dims])} differ")
    n = math.prod(batch)
    if limit is None:
        limit = CUDA_SLICE if matrices[0].is_cuda else n
    if n <= limit:
        return fn(*matrices)
    flat = [m.reshape(n, *m.shape[batch_dims:]) for m in matrices]
    parts = [fn(*(m[i:i + limit] for m in flat)) for i in range(0, n, limit)]
    if isinstance(parts[0], Tensor):
        out = torch.cat(parts)
        return out.reshape(*batch, *out.shape[1:])
    return tuple(torch.cat(column).reshape(*batch, *column[0].shape[1:]) for column in zip(*parts, strict=True))
