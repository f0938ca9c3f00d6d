"""Least-squares alignment of two point sets (Umeyama 1991, orthogonal Procrustes).

An estimated trajectory lives in its own world frame; before comparing it with
ground truth it is aligned by the rigid (or similarity) transform that minimises
the squared position error over all associated points:

    min_{c, R, t}  1/N Σ_i |y_i - (c R x_i + t)|²,   R ∈ SO(3), c > 0.

Closed form (Umeyama, "Least-squares estimation of transformation parameters
between two point patterns", PAMI 1991, eqs. 38-42): with centred points
``x̃ = x - μ_x``, ``ỹ = y - μ_y``, the cross-covariance ``Σ = 1/N Σ ỹ x̃ᵀ = U D Vᵀ``,

    S = diag(1, 1, det(U) det(V))          (the reflection fix, det R = +1)
    R = U S Vᵀ
    c = tr(D S) / σ_x²,   σ_x² = 1/N Σ |x̃|²   (1 when no scale is estimated)
    t = μ_y - c R μ_x

Everything is batched over leading dimensions and differentiable (through
``torch.linalg.svd``; its gradient is undefined only when singular values of
``Σ`` repeat, e.g. for perfectly symmetric point sets).
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from flowins.geometry import quaternion
from flowins.geometry.procrustes import planar_rotation


class Alignment(NamedTuple):
    """``target ≈ scale * rotation @ source + translation``.

    rotation: ``(..., 3, 3)`` proper rotation (det = +1).
    translation: ``(..., 3)`` in the target's units (m).
    scale: ``(...)`` dimensionless; exactly 1 for an SE(3) alignment.
    """

    rotation: Tensor
    translation: Tensor
    scale: Tensor


def _index_str(index: tuple[int, ...]) -> str:
    return ", ".join(str(i) for i in index)


def check_points(points: Tensor, name: str, *, min_points: int = 1) -> None:
    """Raise ``ValueError`` unless ``points`` is a finite floating ``(..., N, 3)`` tensor with ``N >= min_points``."""
    if not isinstance(points, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor of shape (..., N, 3), got {type(points).__name__}")
    if points.ndim < 2 or points.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., N, 3), got {tuple(points.shape)}")
    if not points.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor, got dtype {points.dtype}")
    if points.shape[-2] < min_points:
        raise ValueError(f"{name} needs at least {min_points} points, got {points.shape[-2]} (shape {tuple(points.shape)})")
    bad = ~torch.isfinite(points).all(dim=-1)
    if bool(bad.any()):
        first = tuple(int(i) for i in bad.nonzero()[0])
        raise ValueError(
            f"{name} contains NaN or inf; first bad row is {name}[{_index_str(first)}] = "
            f"{points[first].tolist()}"
        )


def _check_extent(centred: Tensor, points: Tensor, name: str) -> None:
    """Reject point sets whose spread is zero up to rounding (all points identical)."""
    extent = centred.norm(dim=-1).amax(dim=-1)  # (...)
    magnitude = points.abs().amax(dim=(-2, -1))
    tol = 64.0 * torch.finfo(points.dtype).eps * magnitude
    degenerate = extent <= tol
    if bool(degenerate.any()):
        where = tuple(int(i) for i in degenerate.nonzero()[0])
        at = f" (batch index {_index_str(where)})" if where else ""
        raise ValueError(
            f"{name} has no spatial extent{at}: all {points.shape[-2]} points are identical, "
            "so the trajectory cannot be aligned (rotation is undetermined)"
        )


def umeyama(source: Tensor, target: Tensor, *, with_scale: bool = False) -> Alignment:
    """The transform mapping ``source`` onto ``target`` in the least-squares sense.

    Args:
        source: ``(..., N, 3)`` points to be moved (e.g. the estimated positions, m).
        target: ``(..., N, 3)`` corresponding points (e.g. ground truth, m), same dtype.
        with_scale: also estimate a scale ``c > 0`` (Sim(3)); otherwise ``c = 1`` (SE(3)).

    Returns:
        :class:`Alignment` with ``target ≈ scale * rotation @ source + translation``.

    Raises:
        ValueError: shapes differ, ``N < 3``, NaN/inf in either argument (the first
            bad row is named), dtypes differ, or either point set has no spatial extent.

    Collinear point sets are accepted; the rotation about their common line is then
    arbitrary, but the aligned positions and hence the RMSE are still well defined.
    """
    check_points(source, "source", min_points=3)
    check_points(target, "target", min_points=3)
    if source.shape != target.shape:
        raise ValueError(
            f"source and target must have the same shape (..., N, 3), got {tuple(source.shape)} and {tuple(target.shape)}"
        )
    if source.dtype != target.dtype:
        raise ValueError(f"source and target must have the same dtype, got {source.dtype} and {target.dtype}")

    mu_s = source.mean(dim=-2)  # (..., 3)
    mu_t = target.mean(dim=-2)
    xs = source - mu_s.unsqueeze(-2)  # (..., N, 3)
    xt = target - mu_t.unsqueeze(-2)
    _check_extent(xs, source, "source")
    _check_extent(xt, target, "target")

    n = source.shape[-2]
    sigma = xt.transpose(-1, -2) @ xs / n  # (..., 3, 3) = 1/N Σ ỹ x̃ᵀ
    u, d, vh = torch.linalg.svd(sigma)
    # det(U) det(V) is ±1; flip the last singular direction when it is -1.
    det_sign = torch.linalg.det(u) * torch.linalg.det(vh)
    last = torch.where(det_sign < 0, -torch.ones_like(det_sign), torch.ones_like(det_sign))
    s_diag = torch.stack((torch.ones_like(last), torch.ones_like(last), last), dim=-1)  # (..., 3)
    rotation = (u * s_diag.unsqueeze(-2)) @ vh  # U diag(s) Vᵀ

    if with_scale:
        var_s = (xs * xs).sum(dim=-1).mean(dim=-1)  # (...)
        scale = (d * s_diag).sum(dim=-1) / var_s
    else:
        scale = torch.ones(source.shape[:-2], dtype=source.dtype, device=source.device)

    translation = mu_t - scale.unsqueeze(-1) * (rotation @ mu_s.unsqueeze(-1)).squeeze(-1)
    return Alignment(rotation=rotation, translation=translation, scale=scale)


def identity_alignment(*batch: int, dtype: torch.dtype | None = None, device=None) -> Alignment:
    """The alignment that changes nothing (``R = I``, ``t = 0``, ``c = 1``)."""
    rotation = torch.eye(3, dtype=dtype, device=device).expand(*batch, 3, 3).clone()
    translation = torch.zeros(*batch, 3, dtype=dtype, device=device)
    scale = torch.ones(batch, dtype=dtype, device=device)
    return Alignment(rotation=rotation, translation=translation, scale=scale)


def apply_alignment(alignment: Alignment, points: Tensor) -> Tensor:
    """``scale * rotation @ p + translation`` for points ``(..., 3)`` (one alignment for all points).

    For a batched alignment ``(B, 3, 3)`` pass points ``(B, N, 3)``.
    """
    if points.shape[-1] != 3:
        raise ValueError(f"points must have last dimension 3, got shape {tuple(points.shape)}")
    rotated = points @ alignment.rotation.transpose(-1, -2)
    scale, translation = alignment.scale, alignment.translation
    if scale.ndim > 0:  # batched alignment: broadcast over the point axis
        scale = scale[..., None, None]
        translation = translation.unsqueeze(-2)
    return scale * rotated + translation


def apply_alignment_to_quaternions(alignment: Alignment, q: Tensor) -> Tensor:
    """Rotate orientations ``(..., 4)`` (w, x, y, z) into the target frame: ``q_R ⊙ q``.

    The scale does not affect orientations. For a batched alignment ``(B, 3, 3)``
    pass ``q`` of shape ``(B, N, 4)``.
    """
    if q.shape[-1] != 4:
        raise ValueError(f"q must have last dimension 4 (w, x, y, z), got shape {tuple(q.shape)}")
    q_r = quaternion.from_matrix(alignment.rotation).to(q.dtype)
    if q_r.ndim > 1:
        q_r = q_r.unsqueeze(-2)
    return quaternion.multiply(q_r, q)


def align_yaw(source: Tensor, target: Tensor) -> Alignment:
    """The rotation about ``z`` and translation mapping ``source`` onto ``target`` (4 DoF).

    The alignment for trajectories whose gravity direction is known (an INS): only
    the heading and the origin are free. With centred points, the angle maximising
    ``Σ ỹᵀ R_z(θ) x̃`` is ``θ = atan2(Σ (x̃ × ỹ)_z, Σ x̃_xy · ỹ_xy)``; ``t = μ_y - R_z μ_x``.
    Well defined for a straight (collinear) track, unlike the 3-D rotation of
    :func:`umeyama`. Points ``(..., N, 3)``, ``N >= 1``.
    """
    check_points(source, "source", min_points=1)
    check_points(target, "target", min_points=1)
    if source.shape != target.shape:
        raise ValueError(f"source and target must have the same shape, got {tuple(source.shape)} and {tuple(target.shape)}")
    mu_s, mu_t = source.mean(dim=-2), target.mean(dim=-2)
    theta = planar_rotation(source, target).theta_rad
    c, s = torch.cos(theta), torch.sin(theta)
    one, zero = torch.ones_like(c), torch.zeros_like(c)
    rotation = torch.stack((c, -s, zero, s, c, zero, zero, zero, one), -1).reshape(*c.shape, 3, 3)
    translation = mu_t - (rotation @ mu_s.unsqueeze(-1)).squeeze(-1)
    return Alignment(rotation=rotation, translation=translation, scale=torch.ones_like(c))


def heading_directions(q: Tensor) -> Tensor:
    """``(..., 2)`` unit horizontal direction ``(cos ψ, sin ψ)`` of the body x axis of
    orientations ``(..., 4)`` (w, x, y, z; body to world, z up): the heading without the
    roll and pitch. Smooth everywhere but where the body x axis is vertical, where it stays
    finite (a 1e-12 floor under the norm)."""
    w, x, y, z = q.unbind(-1)
    n2 = (q * q).sum(-1)
    forward = torch.stack((n2 - 2 * (y * y + z * z), 2 * (x * y + w * z)), dim=-1)
    return forward / torch.sqrt((forward * forward).sum(-1, keepdim=True) + 1e-12)


def relative_heading(h_a: Tensor, h_b: Tensor) -> Tensor:
    """``(..., 2)`` the turn from headings ``h_a`` to ``h_b`` (``(..., 2)`` unit ``(cos, sin)``,
    :func:`heading_directions`) as ``(cos, sin)`` of ``ψ_b - ψ_a``: ``h_b · conj(h_a)``."""
    return torch.stack((h_b[..., 0] * h_a[..., 0] + h_b[..., 1] * h_a[..., 1],
                        h_b[..., 1] * h_a[..., 0] - h_b[..., 0] * h_a[..., 1]), dim=-1)


def align_start(p_est: Tensor, q_est: Tensor, p_ref: Tensor, q_ref: Tensor) -> Alignment:
    """The rotation about ``z`` and translation mapping one estimated pose onto a reference
    pose (positions ``(3,)``, orientations ``(4,)`` w, x, y, z): the turn between their
    headings (:func:`heading_directions`) and the offset between their positions. The frame
    in which an INS started from this pose would have no error at all."""
    c, s = relative_heading(heading_directions(q_est), heading_directions(q_ref.to(q_est))).unbind(-1)
    one, zero = torch.ones_like(c), torch.zeros_like(c)
    rotation = torch.stack((c, -s, zero, s, c, zero, zero, zero, one), -1).reshape(3, 3)
    translation = p_ref.to(p_est) - rotation @ p_est
    return Alignment(rotation=rotation, translation=translation, scale=one)
