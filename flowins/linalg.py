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


#: the column pairs of a cyclic sweep over 4 columns
_PAIRS_4 = ((0, 1), (2, 3), (0, 2), (1, 3), (0, 3), (1, 2))


def jacobi_right_singular(A: Tensor, *, sweeps: int = 6) -> tuple[Tensor, Tensor]:
    """``(σ², V)`` of ``A`` ``(..., m, 4)`` by one-sided (Hestenes) Jacobi: the squared singular
    values ``(..., 4)`` ascending and the right singular vectors as the columns of ``V``
    ``(..., 4, 4)`` in the same order, with no LAPACK call, no data-dependent branch and no
    wait on a device (a fixed number of sweeps of plane rotations, each an elementwise update).

    Each rotation of columns ``p``, ``q`` (``α = |a_p|²``, ``β = |a_q|²``, ``γ = a_p·a_q``) makes
    them orthogonal with ``t = 2γ sgn(β - α) / (|β - α| + √((β - α)² + 4γ²))``, ``c = 1/√(1 + t²)``,
    ``s = c t``; the same rotation accumulates in ``V``. The columns converge quadratically
    to ``A V = U Σ``: six sweeps of a ``4``-column matrix reach rounding. Acting on ``A`` itself,
    not on ``AᵀA``, it keeps the small singular values' relative accuracy (``AᵀA`` squares the
    conditioning). A pair that is already orthogonal gets ``t = 0`` (also where ``α = β``)."""
    tiny = torch.finfo(A.dtype).tiny
    columns = [A[..., :, k] for k in range(4)]
    eye = torch.eye(4, dtype=A.dtype, device=A.device)
    rows_of_V = [eye[k].expand(*A.shape[:-2], 4) for k in range(4)]  # V's columns, as vectors
    for _ in range(sweeps):
        for p, q in _PAIRS_4:
            a_p, a_q = columns[p], columns[q]
            alpha, beta, gamma = (a_p * a_p).sum(-1), (a_q * a_q).sum(-1), (a_p * a_q).sum(-1)
            d = beta - alpha
            root = torch.sqrt(d * d + 4.0 * gamma * gamma + tiny)
            t = 2.0 * gamma * torch.where(d >= 0, 1.0, -1.0).to(A.dtype) / (d.abs() + root)
            c = torch.rsqrt(1.0 + t * t)
            s = c * t
            c_, s_ = c.unsqueeze(-1), s.unsqueeze(-1)
            columns[p], columns[q] = c_ * a_p - s_ * a_q, s_ * a_p + c_ * a_q
            v_p, v_q = rows_of_V[p], rows_of_V[q]
            rows_of_V[p], rows_of_V[q] = c_ * v_p - s_ * v_q, s_ * v_p + c_ * v_q
    sigma_sq = torch.stack([(a * a).sum(-1) for a in columns], -1)  # (..., 4)
    V = torch.stack(rows_of_V, -1)  # (..., 4, 4), column k rotates with column k of A
    order = torch.argsort(sigma_sq, dim=-1)
    return (torch.take_along_dim(sigma_sq, order, -1),
            torch.take_along_dim(V, order.unsqueeze(-2).expand(V.shape), -1))
