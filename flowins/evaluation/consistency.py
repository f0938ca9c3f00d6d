"""Whether a filter's heading uncertainty covers its heading error.

A filter is consistent when its errors are as large as its covariance says; an overconfident one
stops listening to the measurements that would correct it. The heading is where this shows first
in inertial navigation: the IMU and a camera cannot observe it, so whatever the filter believes of
it comes from GNSS fixes (or from linearisation errors that make up information).

For estimated orientations ``q̂`` (unit quaternions, w, x, y, z, additive 4-vectors in the state as
the filter keeps them, with covariance ``P_q`` ``(4, 4)``) and the reference ``q``:

* the heading error is the angle about the world ``z`` axis of ``δR = R(q̂) R(q)ᵀ``,
  ``ψ = atan2(δR₁₀ - δR₀₁, δR₀₀ + δR₁₁)`` (exactly the angle of a pure turn about ``z``; the
  best-fitting such turn when ``δR`` also tilts);
* its 1-σ is the filter's, to first order: ``σ_ψ² = g P_q gᵀ``, ``g = ∂ψ/∂q̂`` (autograd of the
  same function);
* ``ψ / σ_ψ`` is the normalised error (its square is the heading's NEES, of one degree of freedom:
  about 1 on average for a consistent filter, and beyond 3 in 0.27 % of the nodes).

The estimate may first be rotated into the reference's frame by an alignment (the table's
Procrustes fit, :func:`~flowins.evaluation.metrics.trajectory_errors`); a constant turn of the
whole track then does not count as an error, and what is left is how the heading wanders.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor
from torch.func import jacrev, vmap

from flowins.evaluation.alignment import Alignment
from flowins.evaluation.metrics import associate, interpolate_quaternions
from flowins.geometry import quaternion


class HeadingConsistency(NamedTuple):
    """Heading errors of ``K`` estimates and the filter's own 1-σ of each."""

    t_s: Tensor  # (K,) the estimates' times
    error_rad: Tensor  # (K,) heading error ψ (estimate minus reference, about the world z), in (-π, π]
    sigma_rad: Tensor  # (K,) the filter's 1-σ of the heading

    @property
    def normalised(self) -> Tensor:
        """``(K,)`` ψ / σ_ψ (σ at least the smallest normal number)."""
        return self.error_rad / self.sigma_rad.clamp_min(torch.finfo(self.sigma_rad.dtype).tiny)

    def rms_normalised(self) -> float:
        """The root of the mean NEES: about 1 when the filter is consistent, more when overconfident."""
        return float(self.normalised.square().mean().sqrt())

    def share_beyond(self, k: float = 3.0) -> float:
        """The share of the estimates whose error is beyond ``k`` σ (0.27 % for k = 3 when consistent)."""
        return float((self.normalised.abs() > k).to(torch.float64).mean())


def heading_error(q_est: Tensor, q_ref: Tensor) -> Tensor:
    """``ψ`` ``(...)``: the angle about the world ``z`` of ``R(q_est) R(q_ref)ᵀ`` (see the module doc)
    for quaternions ``(..., 4)`` (``q_est`` need not be of unit norm: it is normalised)."""
    dR = quaternion.to_matrix(quaternion.normalize(q_est)) @ quaternion.to_matrix(q_ref).transpose(-1, -2)
    return torch.atan2(dR[..., 1, 0] - dR[..., 0, 1], dR[..., 0, 0] + dR[..., 1, 1])


def heading_consistency(q_est: Tensor, cov_q: Tensor, q_ref: Tensor, *,
                        alignment: Alignment | None = None, t_s: Tensor | None = None) -> HeadingConsistency:
    """Heading errors and the filter's σ of estimates ``q_est`` ``(K, 4)`` with covariances ``cov_q``
    ``(K, 4, 4)`` against the reference ``q_ref`` ``(K, 4)`` at the same times ``t_s`` ``(K,)``;
    ``alignment``: rotate the estimates by it first (its rotation only)."""
    if q_est.ndim != 2 or q_est.shape[-1] != 4 or q_ref.shape != q_est.shape:
        raise ValueError(f"heading_consistency: q_est and q_ref must both be (K, 4), got {tuple(q_est.shape)} "
                         f"and {tuple(q_ref.shape)}")
    if cov_q.shape != (*q_est.shape, 4):
        raise ValueError(f"heading_consistency: cov_q must be (K, 4, 4) = {(*q_est.shape, 4)}, got {tuple(cov_q.shape)}")
    # the alignment's turn as a quaternion, formed once (apply_alignment_to_quaternions: q_R ⊙ q)
    turn = None if alignment is None else quaternion.from_matrix(alignment.rotation.to(q_est))

    def error(q: Tensor, ref: Tensor) -> Tensor:
        return heading_error(q if turn is None else quaternion.multiply(turn, q), ref)

    psi = error(q_est, q_ref)
    g = vmap(jacrev(error))(q_est, q_ref)  # (K, 4)
    variance = torch.einsum("ki,kij,kj->k", g, cov_q, g).clamp_min(0.0)
    times = torch.arange(q_est.shape[0], dtype=q_est.dtype) if t_s is None else t_s
    return HeadingConsistency(times, psi, variance.sqrt())


def track_heading_consistency(t_est_s: Tensor, q_est: Tensor, cov_q: Tensor, t_ref_s: Tensor, q_ref: Tensor, *,
                              alignment: Alignment | None = None, max_dt_s: float = 0.05) -> HeadingConsistency:
    """:func:`heading_consistency` of a filter track (times ``(N,)``, orientations ``(N, 4)``, their
    covariances ``(N, 4, 4)``) against a reference track (``(M,)``, ``(M, 4)``) slerped to the
    estimates' times (estimates more than ``max_dt_s`` outside the reference's span are left out,
    as :func:`~flowins.evaluation.metrics.associate` leaves them)."""
    association = associate(t_ref_s, t_est_s, max_dt_s=max_dt_s)  # the reference at the estimates' times
    keep = association.ref_index.to(q_est.device)
    ref = interpolate_quaternions(q_ref, association)
    return heading_consistency(q_est[keep], cov_q[keep], ref, alignment=alignment, t_s=t_est_s[keep])
