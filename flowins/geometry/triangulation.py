"""Two-view linear triangulation (the paper's Eq. for the epipolar-constrained DLT).

For cameras ``P₁, P₂`` ``(3, 4)`` and pixels ``(u₁, v₁)``, ``(u₂, v₂)`` the world point
``X̃`` (homogeneous) solves

    [ u₁ P₁[3,:] - P₁[1,:] ]
    [ v₁ P₁[3,:] - P₁[2,:] ]  X̃ = 0
    [ u₂ P₂[3,:] - P₂[1,:] ]
    [ v₂ P₂[3,:] - P₂[2,:] ]

in the least-squares sense: ``X̃`` is the right singular vector of the smallest
singular value, batched over any leading dimensions.

It is computed from the eigenvectors of ``AᵀA`` followed by one Newton step whose residual
``Aᵀ(A X̃)`` is formed from ``A``, not from ``AᵀA``: ``AᵀA`` squares the conditioning, so the
eigenvectors alone lose digits (errors up to ``ε / conditioning²``); after the step the
vector is as close to the SVD's as rounding allows (``ε / conditioning``, a test holds it
there, also at a 1 mm baseline) and ``σ₄ = |A X̃|``. The eigenvectors come from
``torch.linalg.eigh`` on the CPU and from one-sided Jacobi rotations of ``A``'s columns on a
GPU (:func:`flowins.linalg.jacobi_right_singular`: a fixed number of sweeps of elementwise
updates, no LAPACK call and no wait on the device, so the flow update can be captured as one
CUDA graph; cuSOLVER's ``eigh`` reads its error flag back to the host). Jacobi costs several
times ``eigh`` in eager mode on the CPU; both give the same point to rounding.
``benchmarks/bench_triangulation.py`` times both against ``torch.linalg.svd``.

Conditioning: the rows are formed in normalised image coordinates
(``K⁻¹ (u, v, 1)``) and with the world origin moved to camera 1's centre
(Hartley's normalisation), which leaves the projections unchanged. The result is a
homogeneous point, so points at infinity (pure rotation) are represented exactly.

The gradient of the smallest singular vector involves ``1 / (σ₃² - σ₄²)``; when the
two smallest singular values meet (zero baseline with flow consistent with a
rotation: every point on the ray fits) it is unbounded. :func:`triangulate`
therefore also returns a per-point conditioning ``(σ₃ - σ₄) / σ₁`` so that the
measurement model can down-weight and count such points.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from flowins.linalg import in_slices, jacobi_right_singular


class Triangulation(NamedTuple):
    point: Tensor  # (..., 4) homogeneous world point, unit norm (in the shifted frame: see triangulate)
    conditioning: Tensor  # (...,) (σ₃ - σ₄) / σ₁ of the DLT matrix: 0 = degenerate


def camera_matrix(R_wc: Tensor, p_wc: Tensor) -> Tensor:
    """Normalised camera matrix ``[R_wcᵀ | -R_wcᵀ p_wc]`` ``(..., 3, 4)`` (no intrinsics).

    ``R_wc`` ``(..., 3, 3)`` maps camera-frame vectors to world, ``p_wc`` ``(..., 3)`` is
    the camera centre. The paper's ``P = K [Rᵀ | -Rᵀ p]`` is ``K`` times this.
    """
    Rt = R_wc.transpose(-1, -2)
    return torch.cat((Rt, -(Rt @ p_wc.unsqueeze(-1))), dim=-1)


def dlt_matrix(P1: Tensor, P2: Tensor, x1: Tensor, x2: Tensor) -> Tensor:
    """The paper's ``4 x 4`` linear system for normalised coordinates ``x1``, ``x2`` ``(..., 2)``:
    rows ``x_r P[2] - P[r]`` of camera 1, then of camera 2."""
    return torch.cat(
        (x1.unsqueeze(-1) * P1[..., 2:3, :] - P1[..., :2, :], x2.unsqueeze(-1) * P2[..., 2:3, :] - P2[..., :2, :]),
        dim=-2,
    )


class DltSolution(NamedTuple):
    """:func:`solve_dlt`'s result: the triangulation and the pieces its derivative needs."""

    point: Tensor  # (..., 4) unit null vector, oriented in front of camera 1
    conditioning: Tensor  # (...,) (σ₃ - σ₄) / σ₁
    rows: Tensor  # (..., 4, 4) the equilibrated matrix A / |rows|
    row_norm: Tensor  # (..., 4) the row norms divided out
    eigenvalues: Tensor  # (..., 4) of rowsᵀ rows, ascending: σ₄², σ₃², σ₂², σ₁²
    eigenvectors: Tensor  # (..., 4, 4) their columns, the right singular vectors (column 0 before the Newton step)
    residual: Tensor  # (..., 4) rows @ point
    residual_sq: Tensor  # (...,) σ₄² = |rows @ point|²

    @property
    def singular_values(self) -> Tensor:
        """``(..., 4)`` of the equilibrated matrix, descending (σ₄ from the residual)."""
        top = self.eigenvalues[..., 1:].flip(-1).clamp_min(0.0).sqrt()
        return torch.cat((top, self.residual_sq.sqrt().unsqueeze(-1)), -1)


def solve_dlt(A: Tensor, P1: Tensor | None = None, *, eigen: str = "auto") -> DltSolution:
    """The smallest right singular vector of the row-equilibrated ``A`` ``(..., m, 4)``, its
    sign chosen so that the point is in front of camera ``P1`` ``(..., 3, 4)`` (None: ``[I | 0]``;
    see the module doc for how it is computed). ``eigen``: ``"eigh"``, ``"jacobi"`` or
    ``"auto"`` (Jacobi on a GPU, ``eigh`` elsewhere)."""
    if eigen not in ("auto", "eigh", "jacobi"):
        raise ValueError(f"solve_dlt: eigen must be 'auto', 'eigh' or 'jacobi', got {eigen!r}")
    tiny = torch.finfo(A.dtype).tiny
    norm = torch.linalg.vector_norm(A, dim=-1).clamp_min(tiny**0.5)
    rows = A / norm.unsqueeze(-1)  # equilibrate the rows (the solution is invariant)
    if eigen == "jacobi" or (eigen == "auto" and rows.is_cuda):
        lam, V = jacobi_right_singular(rows)  # σ² ascending, the right singular vectors
    else:
        gram = rows.transpose(-1, -2) @ rows
        lam, V = in_slices(torch.linalg.eigh, gram, batch_dims=gram.ndim - 2)  # ascending
    # Newton step X ← X - Σᵢ vᵢ vᵢᵀ (AᵀA X) / (σᵢ² - σ₄²) over the other three eigenvectors,
    # with vᵢᵀ AᵀA X = (A vᵢ)·(A X) from A itself; the gap is at least rounding (the rows have
    # unit norm, so σ₁² >= 1): a degenerate point stays finite
    AV = rows @ V
    gap = (lam[..., 1:] - lam[..., :1]).clamp_min(torch.finfo(A.dtype).eps)
    step = (AV[..., 1:].transpose(-1, -2) @ AV[..., :1]).squeeze(-1) / gap
    X = V[..., 0] - (V[..., 1:] @ step.unsqueeze(-1)).squeeze(-1)
    # unit norm, and of the sign that puts the point in front of camera 1 (the vector's sign is arbitrary)
    z1 = X[..., 2] if P1 is None else torch.linalg.vecdot(X, P1[..., 2, :])
    point = X / torch.copysign(torch.linalg.vector_norm(X, dim=-1), z1).unsqueeze(-1)
    residual = (rows @ point.unsqueeze(-1)).squeeze(-1)
    residual_sq = torch.linalg.vecdot(residual, residual)
    s31 = lam[..., 1::2].clamp_min(0.0).sqrt()  # σ₃, σ₁
    conditioning = (s31[..., 0] - residual_sq.sqrt()) / s31[..., 1].clamp_min(tiny)
    return DltSolution(point, conditioning, rows, norm, lam, V, residual, residual_sq)


def triangulate(P1: Tensor, P2: Tensor, x1: Tensor, x2: Tensor) -> Triangulation:
    """Homogeneous point ``(..., 4)`` from normalised cameras ``(..., 3, 4)`` and
    normalised image points ``x = K⁻¹ (u, v, 1)`` (first two entries) ``(..., 2)``.

    Callers should express both cameras in a frame whose origin is near camera 1
    (see :func:`flowins.measurements.flow`), which keeps the system well scaled.
    """
    solution = solve_dlt(dlt_matrix(P1, P2, x1, x2), P1)
    return Triangulation(solution.point, solution.conditioning)


def project_homogeneous(P: Tensor, X: Tensor) -> tuple[Tensor, Tensor]:
    """``(x, z)``: normalised image point ``(..., 2)`` of homogeneous ``X`` ``(..., 4)`` and its
    third coordinate ``z`` ``(...)``; with ``X`` as :func:`triangulate` orients it,
    ``z > 0`` means in front of the camera (a depth times a positive scale)."""
    y = (P @ X.unsqueeze(-1)).squeeze(-1)
    return y[..., :2] / y[..., 2:3], y[..., 2]
