"""Batched linear algebra: solver calls split into slices the device takes, and short dot products.

:func:`dot` sums the products of short vectors (2 or 3 entries) entry by entry: torch's
reduction over a last dimension of 2 or 3 entries (``torch.linalg.vecdot``, ``(a * b).sum(-1)``)
takes several times as long on the CPU for a few thousand vectors (``benchmarks/bench_flow_filter.py``
profiles the filter).

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

#: the longest vectors :func:`dot` sums entry by entry
SHORT_DOT = 3


def dot(a: Tensor, b: Tensor) -> Tensor:
    """``Σ_i a_i b_i`` over the last dimension (broadcast like ``torch.linalg.vecdot`` of real
    tensors): entry by entry in order for up to :data:`SHORT_DOT` entries, else ``vecdot``."""
    n = a.shape[-1]
    if n != b.shape[-1] or n > SHORT_DOT:
        return torch.linalg.vecdot(a, b)
    out = a[..., 0] * b[..., 0]
    for i in range(1, n):
        out = out + a[..., i] * b[..., i]
    return out


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
