"""Drift as odometry papers report it: the relative pose error (RPE, as evo defines it) and
KITTI's translational and rotational drift over fixed path lengths.

Both compare the motion between two samples ``i < j`` of the estimate with the truth's:
with poses ``Q`` (truth) and ``P`` (estimate) as rotation ``R`` and position ``p`` in their
world frames, the relative motions are ``Q_i⁻¹ Q_j`` and ``P_i⁻¹ P_j`` and the error is
``E = (Q_i⁻¹ Q_j)⁻¹ (P_i⁻¹ P_j)``: its translation's norm (m) and its rotation's angle
(rad). A constant rigid transform of either world frame leaves ``E`` unchanged, so no
alignment enters and an INS's unknown heading and origin cost nothing; a heading or scale
drift inside the pair costs in full.

* :func:`rpe` pairs the samples ``delta`` apart in samples, seconds or metres of the truth's
  path (evo's ``--delta``, ``--delta_unit f|m``; seconds are flowins' own, for walks), each
  pair starting where the last ended, or at every sample with ``all_pairs`` (evo's
  ``--all_pairs``); it reports the RMSE, mean and median over the pairs.
* :func:`scale_error_pct`: the estimate's size against the truth's, from a Sim(3) alignment
  (a track too large by 2 % has ``+2``), what a camera's scale bias leaves.
* :func:`kitti_drift` is the KITTI odometry benchmark's metric: from every ``step``-th
  sample, for each length ``L`` (100, 200, …, 800 m) the pair ending at the first sample whose
  path length from the start exceeds ``L``; each pair's translation error divided by ``L``
  (reported in %) and rotation error divided by ``L`` (deg/m), averaged over all pairs.

Both take tensors of matched samples: times ``(K,)``, rotations ``(K, 3, 3)`` (body to
world) and positions ``(K, 3)`` of the truth and of the estimate at the same times;
:func:`drift_metrics` matches a track to a ground truth first (``metrics.json``'s ``drift``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from flowins.evaluation.metrics import associate, interpolate_positions, interpolate_quaternions
from flowins.geometry import quaternion


def relative_errors(R_ref: Tensor, p_ref: Tensor, R_est: Tensor, p_est: Tensor, first: Tensor, last: Tensor
                    ) -> tuple[Tensor, Tensor]:
    """The translation (m) and rotation (rad) of ``E = (Q_i⁻¹ Q_j)⁻¹ (P_i⁻¹ P_j)`` for each pair
    ``(first[k], last[k])`` (``(M,)`` each; :mod:`module docstring <flowins.evaluation.drift>`)."""
    Ri, Rj = R_ref[first], R_ref[last]
    Pi, Pj = R_est[first], R_est[last]
    rel_ref_R = Ri.transpose(-1, -2) @ Rj
    rel_est_R = Pi.transpose(-1, -2) @ Pj
    rel_ref_t = (Ri.transpose(-1, -2) @ (p_ref[last] - p_ref[first]).unsqueeze(-1)).squeeze(-1)
    rel_est_t = (Pi.transpose(-1, -2) @ (p_est[last] - p_est[first]).unsqueeze(-1)).squeeze(-1)
    E_R = rel_ref_R.transpose(-1, -2) @ rel_est_R
    translation = torch.linalg.vector_norm(rel_est_t - rel_ref_t, dim=-1)  # |R_refᵀ (t_est - t_ref)|
    cos = ((E_R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
    # the angle from its sine and cosine: acos alone loses the digits of a small angle
    axis = torch.stack((E_R[..., 2, 1] - E_R[..., 1, 2], E_R[..., 0, 2] - E_R[..., 2, 0],
                        E_R[..., 1, 0] - E_R[..., 0, 1]), -1)
    rotation = torch.atan2(0.5 * torch.linalg.vector_norm(axis, dim=-1), cos)
    return translation, rotation


def path_length(p_ref: Tensor) -> Tensor:
    """``(K,)`` the distance travelled along the truth's positions ``(K, 3)`` up to each sample."""
    steps = torch.linalg.vector_norm(p_ref[1:] - p_ref[:-1], dim=-1)
    return torch.cat((steps.new_zeros(1), steps.cumsum(0)))


@dataclass(frozen=True)
class RelativePoseError:
    """:func:`rpe`: statistics over the pairs (translation in m, rotation in rad)."""

    delta: float
    unit: str
    pairs: int
    translation_rmse_m: float
    translation_mean_m: float
    translation_median_m: float
    rotation_rmse_rad: float
    rotation_mean_rad: float


def rpe(t_s: Tensor, R_ref: Tensor, p_ref: Tensor, R_est: Tensor, p_est: Tensor, *, delta: float,
        unit: str = "s", all_pairs: bool = False) -> RelativePoseError:
    """The relative pose error over pairs ``delta`` apart (``unit``: ``"f"`` samples, ``"s"``
    seconds, ``"m"`` metres of the truth's path): a pair from sample ``i`` ends at the first
    sample at least ``delta`` on; the next pair starts where it ended (evo's default) or, with
    ``all_pairs``, at the next sample. Raises ValueError when no pair fits."""
    if not delta > 0:
        raise ValueError(f"rpe: delta={delta!r}: expected a number > 0")
    if unit == "f":
        if delta != int(delta):
            raise ValueError(f"rpe: delta={delta!r} samples: expected a whole number")
        axis = torch.arange(t_s.shape[0], dtype=torch.float64)
    elif unit == "s":
        axis = t_s.to(torch.float64)
    elif unit == "m":
        axis = path_length(p_ref.to(torch.float64))
    else:
        raise ValueError(f"rpe: unit={unit!r}: expected f (samples), s (seconds) or m (metres)")
    ends = torch.searchsorted(axis, axis + delta - 1e-9 * max(1.0, abs(delta)))  # first sample >= start + delta
    first, last = [], []
    i, n = 0, axis.shape[0]
    while i < n and int(ends[i]) < n:
        first.append(i)
        last.append(int(ends[i]))
        i = int(ends[i]) if not all_pairs else i + 1
    if not first:
        raise ValueError(f"rpe: no pair of samples {delta:g} {unit} apart in {n} samples")
    trans, rot = relative_errors(R_ref, p_ref, R_est, p_est, torch.tensor(first), torch.tensor(last))
    return RelativePoseError(delta=float(delta), unit=unit, pairs=len(first),
                             translation_rmse_m=float(trans.pow(2).mean().sqrt()),
                             translation_mean_m=float(trans.mean()), translation_median_m=float(trans.median()),
                             rotation_rmse_rad=float(rot.pow(2).mean().sqrt()), rotation_mean_rad=float(rot.mean()))


#: KITTI's segment lengths (m)
KITTI_LENGTHS_M = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)


@dataclass(frozen=True)
class KittiDrift:
    """:func:`kitti_drift`: the mean translational drift (% of the length) and rotational drift
    (deg/m) over every segment, the segments counted, and the same per length."""

    translation_pct: float
    rotation_deg_per_m: float
    segments: int
    per_length: dict[float, tuple[float, float, int]]  # L -> (translation %, rotation deg/m, segments)


def kitti_drift(R_ref: Tensor, p_ref: Tensor, R_est: Tensor, p_est: Tensor, *,
                lengths_m: tuple[float, ...] = KITTI_LENGTHS_M, step: int = 10) -> KittiDrift | None:
    """KITTI's odometry drift (module docstring): segments from every ``step``-th sample; None
    when the truth's path is shorter than the shortest length."""
    dist = path_length(p_ref.to(torch.float64))
    starts = torch.arange(0, dist.shape[0], step)
    first, last, length = [], [], []
    for L in lengths_m:
        ends = torch.searchsorted(dist, dist[starts] + L, right=True)  # first sample beyond start + L
        keep = ends < dist.shape[0]
        first.append(starts[keep])
        last.append(ends[keep])
        length.append(torch.full((int(keep.sum()),), float(L), dtype=torch.float64))
    first_t, last_t, length_t = torch.cat(first), torch.cat(last), torch.cat(length)
    if first_t.numel() == 0:
        return None
    trans, rot = relative_errors(R_ref, p_ref, R_est, p_est, first_t, last_t)
    t_rel = trans.to(torch.float64) / length_t
    r_rel = rot.to(torch.float64) / length_t
    per_length = {}
    for L in lengths_m:
        sel = length_t == L
        if bool(sel.any()):
            per_length[float(L)] = (100.0 * float(t_rel[sel].mean()), math.degrees(float(r_rel[sel].mean())),
                                    int(sel.sum()))
    return KittiDrift(translation_pct=100.0 * float(t_rel.mean()), rotation_deg_per_m=math.degrees(float(r_rel.mean())),
                      segments=int(first_t.numel()), per_length=per_length)


#: the RPE's pair span on every recording (s): about a dozen steps of a walk, 100-300 m of a drive
RPE_DELTA_S = 10.0


def drift_metrics(t_est_s: Tensor, pos_est: Tensor, q_est: Tensor, t_ref_s: Tensor, pos_ref: Tensor, q_ref: Tensor,
                  *, max_dt_s: float = 0.05, rpe_delta_s: float = RPE_DELTA_S) -> dict[str, float | int | None]:
    """A track's drift against a ground truth with orientations, for ``metrics.json``: the
    estimate interpolated at the truth's times (positions linearly, orientations by slerp;
    the truth's samples farther than ``max_dt_s`` from the track left out), then :func:`rpe`
    over ``rpe_delta_s`` (evo's pairs, each starting where the last ended) and
    :func:`kitti_drift`. A value is None where the recording is too short for it."""
    association = associate(t_est_s, t_ref_s, max_dt_s=max_dt_s)
    index = association.ref_index.to(t_ref_s.device)
    t = t_ref_s[index].to(torch.float64)
    p_e = interpolate_positions(pos_est, association).to(torch.float64).cpu()
    R_e = quaternion.to_matrix(interpolate_quaternions(q_est, association)).to(torch.float64).cpu()
    p_r = pos_ref[index].to(torch.float64).cpu()
    R_r = quaternion.to_matrix(q_ref[index]).to(torch.float64).cpu()
    out: dict[str, float | int | None] = {"rpe_delta_s": rpe_delta_s}
    try:
        result = rpe(t.cpu(), R_r, p_r, R_e, p_e, delta=rpe_delta_s, unit="s")
        out.update(rpe_pairs=result.pairs, rpe_translation_rmse_m=result.translation_rmse_m,
                   rpe_rotation_rmse_deg=math.degrees(result.rotation_rmse_rad))
    except ValueError:
        out.update(rpe_pairs=0, rpe_translation_rmse_m=None, rpe_rotation_rmse_deg=None)
    kitti = kitti_drift(R_r, p_r, R_e, p_e)
    out.update(kitti_segments=0 if kitti is None else kitti.segments,
               kitti_translation_pct=None if kitti is None else kitti.translation_pct,
               kitti_rotation_deg_per_100m=None if kitti is None else 100.0 * kitti.rotation_deg_per_m,
               scale_pct=scale_error_pct(p_e, p_r))
    return out


def scale_error_pct(p_est: Tensor, p_ref: Tensor) -> float | None:
    """How much larger the estimate's positions ``(K, 3)`` are than the truth's, in %: ``100 (1 / c - 1)``
    with ``c`` the scale of their Sim(3) alignment ``p_ref ≈ c R p_est + t`` (Umeyama's; evo's
    ``--correct_scale``). None where the truth has no extent (a still recording)."""
    from flowins.evaluation.alignment import umeyama

    try:
        return 100.0 * (1.0 / float(umeyama(p_est, p_ref, with_scale=True).scale) - 1.0)
    except ValueError:
        return None

