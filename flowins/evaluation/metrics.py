"""Trajectory error metrics: time association, interpolation, alignment, RMSE.

The estimate and the reference are sampled at different times. Each reference
time ``τ`` inside the estimate's span is associated with the two estimate samples
``t_k <= τ <= t_{k+1}`` that bracket it, and the estimate is interpolated there:

    p̂(τ) = (1 - w) p_k + w p_{k+1},   w = (τ - t_k) / (t_{k+1} - t_k)

(orientations by slerp). A reference time is kept only when the nearer of the
two samples is within ``max_dt_s``, so gaps in the estimate are never bridged
silently. The interpolated estimate is then aligned to the reference
(:func:`flowins.evaluation.alignment.umeyama`) and the per-point Euclidean error
and its RMSE are reported, as in the paper's evaluation (Procrustes-aligned RMSE).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from flowins.data.streams import PoseStream
from flowins.evaluation.alignment import (
    Alignment,
    align_yaw,
    apply_alignment,
    apply_alignment_to_quaternions,
    check_points,
    heading_directions,
    identity_alignment,
    relative_heading,
    umeyama,
)
from flowins.geometry import quaternion

ALIGN_MODES = ("se3", "sim3", "none")


class Association(NamedTuple):
    """Which reference samples have an estimate, and how to interpolate it.

    ref_index: ``(K,)`` long, indices into the reference arrays (increasing).
    est_left: ``(K,)`` long, index ``k`` of the estimate sample at or before the reference time.
    weight: ``(K,)`` float64 in [0, 1], the weight of sample ``k + 1`` (``k`` gets ``1 - weight``).
    """

    ref_index: Tensor
    est_left: Tensor
    weight: Tensor


def _check_times(t_s: Tensor, name: str, *, min_len: int = 1) -> None:
    if not isinstance(t_s, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor of shape (N,), got {type(t_s).__name__}")
    if t_s.ndim != 1:
        raise ValueError(f"{name} must have shape (N,), got {tuple(t_s.shape)}")
    if not t_s.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor, got dtype {t_s.dtype}")
    if t_s.shape[0] < min_len:
        raise ValueError(f"{name} needs at least {min_len} samples, got {t_s.shape[0]}")
    bad = ~torch.isfinite(t_s)
    if bool(bad.any()):
        row = int(bad.nonzero()[0, 0])
        raise ValueError(f"{name} contains NaN or inf; first bad row is {name}[{row}] = {t_s[row].item()}")
    not_increasing = t_s[1:] <= t_s[:-1]
    if bool(not_increasing.any()):
        row = int(not_increasing.nonzero()[0, 0]) + 1
        raise ValueError(
            f"{name} must be strictly increasing; first bad row is {name}[{row}] = {t_s[row].item()!r} "
            f"after {name}[{row - 1}] = {t_s[row - 1].item()!r}"
        )


def associate(t_est_s: Tensor, t_ref_s: Tensor, *, max_dt_s: float) -> Association:
    """Associate reference times ``(M,)`` with the estimate's times ``(N,)``.

    Args:
        t_est_s: ``(N,)`` estimate sample times (s), strictly increasing, ``N >= 2``.
        t_ref_s: ``(M,)`` reference sample times (s), strictly increasing.
        max_dt_s: tolerance (s): a reference time is kept only if the nearest
            estimate sample is at most this far away.

    Returns:
        :class:`Association` for the ``K`` reference times inside
        ``[t_est_s[0], t_est_s[-1]]`` that pass the tolerance.

    Raises:
        ValueError: bad times (naming the argument and the first bad row), a negative
            or non-finite ``max_dt_s``, or no reference time associated (the message
            gives both time spans).
    """
    _check_times(t_est_s, "t_est_s", min_len=2)
    _check_times(t_ref_s, "t_ref_s")
    max_dt_s = float(max_dt_s)
    if not (max_dt_s >= 0.0 and max_dt_s < float("inf")):
        raise ValueError(f"max_dt_s must be a finite number >= 0, got {max_dt_s}")

    t_est = t_est_s.detach().to(torch.float64).contiguous()
    t_ref = t_ref_s.detach().to(torch.float64).to(t_est.device).contiguous()
    n = t_est.shape[0]
    inside = (t_ref >= t_est[0]) & (t_ref <= t_est[-1])
    left = (torch.searchsorted(t_est, t_ref, right=True) - 1).clamp(0, n - 2)
    t_left, t_right = t_est[left], t_est[left + 1]
    nearest_dt = torch.minimum(t_ref - t_left, t_right - t_ref)
    keep = inside & (nearest_dt <= max_dt_s)
    if not bool(keep.any()):
        raise ValueError(
            f"no reference time could be associated: estimate covers [{t_est[0].item():.6f}, {t_est[-1].item():.6f}] s, "
            f"reference covers [{t_ref[0].item():.6f}, {t_ref[-1].item():.6f}] s, none within {max_dt_s} s "
            "of an estimate sample"
        )
    ref_index = keep.nonzero().squeeze(-1)
    left = left[ref_index]
    weight = ((t_ref[ref_index] - t_left[ref_index]) / (t_right[ref_index] - t_left[ref_index])).clamp(0.0, 1.0)
    return Association(ref_index=ref_index, est_left=left, weight=weight)


def _check_association(values: Tensor, association: Association, name: str, width: int) -> None:
    if values.ndim != 2 or values.shape[-1] != width:
        raise ValueError(f"{name} must have shape (N, {width}), got {tuple(values.shape)}")
    if association.est_left.numel() and int(association.est_left.max()) + 1 >= values.shape[0]:
        raise ValueError(
            f"{name} has {values.shape[0]} rows but the association refers to row "
            f"{int(association.est_left.max()) + 1}; was it built from a different time array?"
        )


def interpolate_positions(pos: Tensor, association: Association) -> Tensor:
    """Linear interpolation ``(1 - w) p_k + w p_{k+1}`` of ``(N, 3)`` positions → ``(K, 3)``."""
    _check_association(pos, association, "pos", 3)
    w = association.weight.to(device=pos.device, dtype=pos.dtype).unsqueeze(-1)
    left = association.est_left.to(pos.device)
    return (1.0 - w) * pos[left] + w * pos[left + 1]


def interpolate_quaternions(q: Tensor, association: Association) -> Tensor:
    """Slerp of ``(N, 4)`` unit quaternions (w, x, y, z) → ``(K, 4)``.

    ``q_k ⊙ 𝒬{w · log(q_k* ⊙ q_{k+1})}``, along the shorter arc (the sign of
    ``q_{k+1}`` does not matter), smooth when consecutive samples are equal.
    """
    _check_association(q, association, "q", 4)
    w = association.weight.to(device=q.device, dtype=q.dtype).unsqueeze(-1)
    left = association.est_left.to(q.device)
    q0 = quaternion.normalize(q[left])
    q1 = quaternion.normalize(q[left + 1])
    delta = quaternion.to_rotation_vector(quaternion.multiply(quaternion.conjugate(q0), q1))
    return quaternion.multiply(q0, quaternion.from_rotation_vector(w * delta))


def position_rmse(est: Tensor, ref: Tensor) -> Tensor:
    """``sqrt(1/K Σ |est_i - ref_i|²)`` of ``(..., K, 3)`` positions → ``(...)`` (m)."""
    if est.shape != ref.shape or est.ndim < 2 or est.shape[-1] != 3:
        raise ValueError(
            f"est and ref must both have shape (..., K, 3), got {tuple(est.shape)} and {tuple(ref.shape)}"
        )
    if est.shape[-2] == 0:
        raise ValueError("est and ref are empty (K = 0): the RMSE of no points is undefined")
    return ((est - ref) ** 2).sum(dim=-1).mean(dim=-1).sqrt()


def chunk_rmse(t_est_s: Tensor, pos_est: Tensor, t_ref_s: Tensor, pos_ref: Tensor, chunk_s: float, *,
               max_dt_s: float = 0.1) -> list[tuple[float, float, float]]:
    """``[(start_s, end_s, rmse_m)]``: the position RMSE of each consecutive ``chunk_s`` piece of a
    long run, each piece aligned on its own by a yaw rotation and a translation
    (:func:`~flowins.evaluation.alignment.align_yaw`, the alignment of the training loss's
    windows): how the error a window loss sees grows along the run. The pieces cut the
    associated reference times from the first; a last piece shorter than half of ``chunk_s``
    joins the one before, and a piece with fewer than 3 associated samples is left out."""
    if not chunk_s > 0:
        raise ValueError(f"chunk_s must be > 0, got {chunk_s!r}")
    association = associate(t_est_s, t_ref_s, max_dt_s=max_dt_s)
    est = interpolate_positions(pos_est, association)
    ref = pos_ref[association.ref_index.to(pos_ref.device)].to(est)
    t = t_ref_s[association.ref_index.to(t_ref_s.device)].to(torch.float64)
    if t.numel() == 0:
        return []
    t0, t1 = float(t[0]), float(t[-1])
    edges = [t0 + k * chunk_s for k in range(int((t1 - t0) // chunk_s) + 1)] + [t1]
    if len(edges) > 2 and edges[-1] - edges[-2] < 0.5 * chunk_s:
        del edges[-2]
    out = []
    for k, (a, b) in enumerate(zip(edges[:-1], edges[1:])):
        inside = ((t >= a) & ((t <= b) if k == len(edges) - 2 else (t < b))).to(est.device)
        if int(inside.sum()) < 3:
            continue
        e, r = est[inside].detach(), ref[inside]
        out.append((a, b, float(position_rmse(apply_alignment(align_yaw(e, r), e), r))))
    return out


class SegmentErrors(NamedTuple):
    """Relative errors over segments of fixed durations (:func:`segment_errors`).

    lengths_s: the segment durations (s) that have at least one segment.
    rmse_m: ``(L,)`` RMS of the displacement error per duration (m).
    heading_rmse_rad: ``(L,)`` RMS of the heading-change error per duration (rad), or None
        without orientations.
    counts: segments per duration.
    """

    lengths_s: tuple[float, ...]
    rmse_m: Tensor
    heading_rmse_rad: Tensor | None
    counts: tuple[int, ...]


def segment_errors(
    t_s: Tensor,
    est: Tensor,
    ref: Tensor,
    lengths_s: tuple[float, ...] | list[float],
    *,
    q_est: Tensor | None = None,
    q_ref: Tensor | None = None,
    tolerance_s: float = 0.1,
) -> SegmentErrors:
    """Displacement (and heading) errors over every segment ``[t_i, t_j]`` of each duration.

    ``est`` and ``ref`` are ``(K, 3)`` positions at the common times ``t_s`` (``(K,)``,
    increasing: an associated and interpolated estimate, :func:`associate`). For each
    duration ``L`` every sample ``i`` starts a segment ending at the first sample ``j`` with
    ``t_j >= t_i + L``, kept when ``t_j - t_i - L <= tolerance_s``. Its error is
    ``d̂ - d`` with ``d = p_j - p_i``:

    * with orientations (``q_est``, ``q_ref``, ``(K, 4)``), each displacement in its own
      heading frame at ``i`` (rotated by ``-ψ_i``, :func:`heading_directions`): the relative
      error of the KITTI odometry metric, free of any alignment. Heading error carried into
      ``i`` cancels; heading and scale drift over the segment cost. The heading-change error
      ``(ψ̂_j - ψ̂_i) - (ψ_j - ψ_i)`` (wrapped to ``(-π, π]``) is returned too.
    * without, in the world frame as given (the caller aligns the estimate first).

    Returns the RMS error of each duration that has a segment (:class:`SegmentErrors`).
    """
    if est.shape != ref.shape or est.ndim != 2 or est.shape[-1] != 3 or t_s.shape != est.shape[:1]:
        raise ValueError(f"segment_errors: expected t_s (K,), est and ref (K, 3); got {tuple(t_s.shape)}, "
                         f"{tuple(est.shape)} and {tuple(ref.shape)}")
    if (q_est is None) != (q_ref is None):
        raise ValueError("segment_errors: q_est and q_ref must be given together (both or neither)")
    if any(not float(length) > 0.0 for length in lengths_s):
        raise ValueError(f"segment_errors: every segment duration must be > 0 s, got {list(lengths_s)}")
    t = t_s.to(dtype=torch.float64, device=est.device)
    if q_est is not None:
        h_est, h_ref = heading_directions(q_est), heading_directions(q_ref.to(est))
    kept, rmse, heading, counts = [], [], [], []
    for length in lengths_s:
        j = torch.searchsorted(t, t + (float(length) - 1e-9))  # a time stamp a rounding error short of L counts
        ok = j < t.shape[0]
        i = torch.nonzero(ok).reshape(-1)
        j = j[ok]
        ok = (t[j] - t[i] - float(length)) <= tolerance_s
        i, j = i[ok], j[ok]
        if i.numel() == 0:
            continue
        d_est, d_ref = est[j] - est[i], ref[j] - ref[i]
        if q_est is not None:
            d_est, d_ref = _into_heading(d_est, h_est[i]), _into_heading(d_ref, h_ref[i])
            # the angle from the true turn to the estimated one
            miss = relative_heading(relative_heading(h_ref[i], h_ref[j]), relative_heading(h_est[i], h_est[j]))
            heading.append(torch.sqrt(torch.atan2(miss[:, 1], miss[:, 0]).square().mean() + 1e-16))
        err = d_est - d_ref
        rmse.append(torch.sqrt((err * err).sum(-1).mean() + 1e-12))
        kept.append(float(length))
        counts.append(int(i.numel()))
    empty = est.new_zeros(0)
    return SegmentErrors(tuple(kept), torch.stack(rmse) if rmse else empty,
                         (torch.stack(heading) if heading else empty) if q_est is not None else None, tuple(counts))


def _into_heading(d: Tensor, h: Tensor) -> Tensor:
    """World vectors ``(K, 3)`` in the heading frames ``h`` ``(K, 2)`` (rotated by ``-ψ``)."""
    return torch.stack((h[:, 0] * d[:, 0] + h[:, 1] * d[:, 1], h[:, 0] * d[:, 1] - h[:, 1] * d[:, 0], d[:, 2]), dim=-1)


@dataclass(frozen=True)
class TrajectoryErrors:
    """Errors of an estimate at the ``K`` associated reference times.

    rmse_m: RMSE of the aligned positions (m).
    errors_m: ``(K,)`` Euclidean error per associated point (m).
    aligned_est: ``(K, 3)`` interpolated and aligned estimate (m).
    ref: ``(K, 3)`` reference positions (m).
    t_s: ``(K,)`` reference times (s).
    alignment: the transform applied to the estimate (identity for ``align="none"``).
    num_associated: ``K``.
    orientation_errors_rad: ``(K,)`` angle between aligned estimated and reference orientation, if given.
    orientation_rmse_rad: their RMSE (rad), if orientations were given.
    """

    rmse_m: float
    errors_m: Tensor
    aligned_est: Tensor
    ref: Tensor
    t_s: Tensor
    alignment: Alignment
    num_associated: int
    orientation_errors_rad: Tensor | None = None
    orientation_rmse_rad: float | None = None


def trajectory_errors(
    t_est_s: Tensor,
    pos_est: Tensor,
    t_ref_s: Tensor,
    pos_ref: Tensor,
    *,
    max_dt_s: float = 0.05,
    align: str = "se3",
    q_est: Tensor | None = None,
    q_ref: Tensor | None = None,
) -> TrajectoryErrors:
    """Associate, interpolate, align and measure an estimated trajectory.

    Args:
        t_est_s: ``(N,)`` estimate times (s); pos_est: ``(N, 3)`` estimated positions (m).
        t_ref_s: ``(M,)`` reference times (s); pos_ref: ``(M, 3)`` reference positions (m).
        max_dt_s: association tolerance (s), see :func:`associate`.
        align: ``"se3"`` rotation + translation (Procrustes, the paper's choice),
            ``"sim3"`` also a scale, ``"none"`` compare in the given frames.
        q_est: optional ``(N, 4)`` estimated orientations (w, x, y, z);
        q_ref: optional ``(M, 4)`` reference orientations; give both or neither.

    Returns:
        :class:`TrajectoryErrors`. The alignment is estimated from positions only
        and then also applied to the orientations.
    """
    if align not in ALIGN_MODES:
        raise ValueError(f"align must be one of {ALIGN_MODES}, got {align!r}")
    if (q_est is None) != (q_ref is None):
        raise ValueError("q_est and q_ref must be given together (both or neither)")
    check_points(pos_est, "pos_est")
    check_points(pos_ref, "pos_ref")
    if pos_est.ndim != 2 or pos_ref.ndim != 2:
        raise ValueError(f"pos_est and pos_ref must have shape (N, 3), got {tuple(pos_est.shape)} and {tuple(pos_ref.shape)}")
    for t, p, tn, pn in ((t_est_s, pos_est, "t_est_s", "pos_est"), (t_ref_s, pos_ref, "t_ref_s", "pos_ref")):
        if t.shape[:1] != p.shape[:1]:
            raise ValueError(f"{tn} has {t.shape[0]} samples but {pn} has {p.shape[0]} rows")
    if pos_est.dtype != pos_ref.dtype:
        raise ValueError(f"pos_est and pos_ref must have the same dtype, got {pos_est.dtype} and {pos_ref.dtype}")

    association = associate(t_est_s, t_ref_s, max_dt_s=max_dt_s)
    k = int(association.ref_index.shape[0])
    if align != "none" and k < 3:
        raise ValueError(
            f"align={align!r} needs at least 3 associated points, got {k} "
            f"(increase max_dt_s={max_dt_s} or check the time stamps)"
        )
    est = interpolate_positions(pos_est, association)
    ref = pos_ref[association.ref_index.to(pos_ref.device)].to(est.device)  # a track on a GPU, the truth on the CPU
    t_s = t_ref_s[association.ref_index.to(t_ref_s.device)]

    if align == "none":
        alignment = identity_alignment(dtype=est.dtype, device=est.device)
        aligned = est
    else:
        alignment = umeyama(est, ref, with_scale=align == "sim3")
        aligned = apply_alignment(alignment, est)

    errors_m = (aligned - ref).norm(dim=-1)
    rmse_m = float(position_rmse(aligned, ref))

    orientation_errors = None
    orientation_rmse = None
    if q_est is not None and q_ref is not None:
        for q, t, qn, tn in ((q_est, t_est_s, "q_est", "t_est_s"), (q_ref, t_ref_s, "q_ref", "t_ref_s")):
            if q.ndim != 2 or q.shape[-1] != 4 or q.shape[0] != t.shape[0]:
                raise ValueError(f"{qn} must have shape ({t.shape[0]}, 4) to match {tn}, got {tuple(q.shape)}")
            bad = ~torch.isfinite(q).all(dim=-1)
            if bool(bad.any()):
                row = int(bad.nonzero()[0, 0])
                raise ValueError(f"{qn} contains NaN or inf; first bad row is {qn}[{row}] = {q[row].tolist()}")
        q_interp = interpolate_quaternions(q_est, association)
        q_aligned = apply_alignment_to_quaternions(alignment, q_interp)
        q_ref_k = q_ref[association.ref_index.to(q_ref.device)].to(q_aligned.device)
        orientation_errors = quaternion.angle_between(q_aligned, q_ref_k)
        orientation_rmse = float(orientation_errors.square().mean().sqrt())

    return TrajectoryErrors(
        rmse_m=rmse_m,
        errors_m=errors_m,
        aligned_est=aligned,
        ref=ref,
        t_s=t_s,
        alignment=alignment,
        num_associated=k,
        orientation_errors_rad=orientation_errors,
        orientation_rmse_rad=orientation_rmse,
    )


#: a ground truth that spans less (m, largest distance from its mean) leaves the alignment's rotation undetermined
MIN_TRUTH_EXTENT_M = 0.5


def truth_extent_problem(truth: PoseStream | None) -> str | None:
    """Why ``truth`` can't score a track (it barely moves), or None."""
    if truth is None:
        return None
    extent = float(torch.linalg.vector_norm(truth.pos_m - truth.pos_m.mean(0), dim=-1).max())
    if extent >= MIN_TRUTH_EXTENT_M:
        return None
    return (f"{truth.name}: the ground truth stays within {extent:.3g} m of its mean (< {MIN_TRUTH_EXTENT_M} m), so "
            "the alignment's rotation is undetermined: no RMSE is computed (n/a); the tracks are written as TUM files")
