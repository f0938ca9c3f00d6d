"""Heading alignment from GNSS fixes: the filter's yaw, unobservable at a still start, set
from the track the fixes draw.

A stationary start fixes roll and pitch but not yaw (:mod:`flowins.ins.initialization`
starts it with σ = π). A linearised GNSS update cannot turn a heading that is wrong by
tens of degrees: the position error it has to explain grows with the distance walked,
so the fixes are rejected by the gate or pull the track sideways. While the yaw is
unknown, the fixes are therefore held back; once they span ``baseline_m``, the rigid
horizontal transform that best maps the filter's positions at the fix times onto the
fixes (weighted 2D Procrustes) is estimated,

    g_i ≈ R(ψ) (p_i - c_p) + c_g,    weights w_i = 1 / (σ²_g,i + σ²_p,i),

with ``c_p``, ``c_g`` the weighted centroids, and the filter is reset in two steps:

1. *Condition on the filter's own heading*: an update that observes the rotation
   of ``q`` about the world vertical (:func:`heading_jacobian`) as zero with
   ``condition_sigma_rad``. It removes the σ = π yaw and the position and velocity
   errors linearly tied to it; what is left is the track's error in its own heading
   frame.
2. *Rotate into the fixes' frame*: the state map ``x ↦ A x + b`` rotates ``p``,
   ``v``, ``p_prev`` (and every further cloned pose's position) about the vertical through
   ``c_p``, moves ``c_p`` to ``c_g`` and left-multiplies ``q``, ``q_prev`` (and every further
   clone's quaternion) by the yaw quaternion; biases and scale are body
   quantities and stay. The estimate's uncertainty enters as process noise
   ``Q = J_θ Σ_θ J_θᵀ`` with ``θ = (ψ, c_g)``, ``σ²_ψ = 1 / Σ w_i |p_i - c_p|²`` and
   ``Σ_c = I / Σ w_i`` (the rotation about the centroid and the centroid are
   uncorrelated).

For fixed ``θ`` the map is linear, so the chain records it as a linear step and the RTS
smoother carries the rotation back over the held-back stretch. Fixes whose normalised
residual exceeds the χ²₂ gate are left out of the fit one at a time, worst first (multipath).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch
from torch import Tensor

from flowins.config import bounded, check_fields
from flowins.filter.ekf import chi2_quantile
from flowins.geometry import quaternion as quat
from flowins.geometry.procrustes import planar_rotation, rotation_2d
from flowins.state import STATE, STATE_DIM, pose_slices, split, symmetrize, window_layout, window_size


@dataclass(frozen=True)
class HeadingAlignment:
    """When and how GNSS fixes set an unknown heading (see the module docstring).

    Attributes:
        enabled: hold fixes while the yaw is unknown (default); False applies every
            fix as it comes, as the paper does (on the simulated walk with flow the
            linearised updates then did not turn the unknown yaw, and most fixes
            failed the gate).
        unknown_yaw_sigma_rad: the heading counts as unknown while the filter's yaw σ
            exceeds this at a fix; a filter started with a known yaw never aligns.
        baseline_m: align once the held-back fixes reach this far from the first one.
        max_sigma_rad: ... and the fit's σ_ψ is at most this (a filter track too short
            or too uncertain waits for more fixes).
        drifted_max_sigma_rad: once the track has drifted more than a fix is off (waiting
            brings no better fit), it aligns if the fit's σ_ψ is at most this (or
            ``max_sigma_rad``, the larger), and gives up if not: the held fixes are left out
            and the later ones applied as they come, the yaw still free.
        min_fixes: at least this many fixes in the fit.
        outlier_probability: χ²₂ acceptance of a fix's residual in the fit.
        condition_sigma_rad: σ of the step-1 yaw conditioning.
        second_pass: the RTS smoother of a run whose heading these fixes set runs on a
            second filter pass from the start (:func:`flowins.second_pass.smoother_tracks`),
            so that every fix, the held ones too, reaches the smoother; the filter's own
            estimates stay those of the first, causal pass. Off by default: it costs one
            more filter pass per such run.
    """

    enabled: bool = True
    unknown_yaw_sigma_rad: float = bounded(0.5, above=0.0)
    baseline_m: float = bounded(20.0, minimum=0.0)
    max_sigma_rad: float = bounded(0.2, above=0.0)
    drifted_max_sigma_rad: float = bounded(0.2, above=0.0)
    min_fixes: int = bounded(3, minimum=2)  # a rotation needs two points
    outlier_probability: float = 0.999
    condition_sigma_rad: float = bounded(1e-4, above=0.0)
    second_pass: bool = False

    def __post_init__(self) -> None:
        check_fields(self)

    @property
    def drifted_limit_rad(self) -> float:
        """The largest σ_ψ a drifted track's fit may have to set the heading."""
        return max(self.max_sigma_rad, self.drifted_max_sigma_rad)


def heading_jacobian(x: Tensor) -> Tensor:
    """``∂θ_z/∂x`` ``(..., D)``: the rotation angle about the world vertical of a change of ``q``.

    ``q + δq = (1, ½δθ) ⊙ q`` gives ``δθ = 2 vec(δq ⊙ q*)``, whose vertical component
    is row ``z`` of ``2 R⊙(q*)``. Unlike an Euler yaw it is defined at every attitude
    (a phone held upright has its body x axis near the vertical).
    """
    H = x.new_zeros(x.shape)
    H[..., STATE.q] = 2.0 * quat.right_matrix(quat.conjugate(split(x).q))[..., 3, :]
    return H


def heading_conditional_covariance(x: Tensor, P: Tensor, sl: slice, *, noise_var: float = 0.0) -> Tensor:
    """Covariance ``(..., k, k)`` of the block ``sl`` of ``P (..., D, D)`` given the heading of ``q``
    (its rotation about the vertical, :func:`heading_jacobian`) of ``x (..., D)``, observed
    exactly or, with ``noise_var``, with that variance."""
    h = heading_jacobian(x)
    Ph = (P @ h.unsqueeze(-1)).squeeze(-1)
    s = ((h * Ph).sum(-1) + noise_var).clamp_min(torch.finfo(P.dtype).tiny)
    return P[..., sl, sl] - Ph[..., sl].unsqueeze(-1) * Ph[..., sl].unsqueeze(-2) / s[..., None, None]


class HeadingFit(NamedTuple):
    yaw_rad: Tensor  # ψ, rotation from the filter's heading frame to the fixes' (about z)
    sigma_rad: Tensor  # σ_ψ
    centre_filter_m: Tensor  # c_p (2,)
    centre_fix_m: Tensor  # c_g (2,)
    centre_var_m2: Tensor  # Σ_c = centre_var I₂
    used: Tensor  # (n,) bool, fixes kept in the fit


def fit_heading(filter_xy_m: Tensor, fix_xy_m: Tensor, var_m2: Tensor, *, outlier_probability: float = 0.999) -> HeadingFit:
    """Weighted 2D Procrustes fit ``fix ≈ R(ψ)(filter - c_p) + c_g`` (module docstring).

    Args:
        filter_xy_m ``(n, 2)``: the filter's horizontal positions at the fix times.
        fix_xy_m ``(n, 2)``: the fixes.
        var_m2 ``(n,)``: each pair's variance per axis (fix plus filter).

    While the worst residual ``w_i |r_i|²`` exceeds χ²₂(outlier_probability), that fix
    is left out and the fit repeated, for at most a fifth of the fixes (at least two are kept). ``σ_ψ`` is infinite when the
    filter's positions do not spread (no rotation is observable).
    """
    n = filter_xy_m.shape[0]
    if fix_xy_m.shape != (n, 2) or filter_xy_m.shape != (n, 2) or var_m2.shape != (n,):
        raise ValueError(f"fit_heading expects (n, 2), (n, 2), (n,); got {tuple(filter_xy_m.shape)}, "
                         f"{tuple(fix_xy_m.shape)}, {tuple(var_m2.shape)}")
    fit = fit_heading_batch(filter_xy_m.unsqueeze(0), fix_xy_m.unsqueeze(0), var_m2.unsqueeze(0), [n],
                            outlier_probability=outlier_probability)
    return HeadingFit(*(part[0] for part in fit))


def fit_heading_batch(filter_xy_m: Tensor, fix_xy_m: Tensor, var_m2: Tensor, counts: Sequence[int], *,
                      outlier_probability: float = 0.999) -> HeadingFit:
    """:func:`fit_heading` of ``r`` sets of fixes at once: ``filter_xy_m``, ``fix_xy_m`` ``(r, N, 2)``,
    ``var_m2`` ``(r, N)``, set ``i`` the first ``counts[i]`` of its ``N`` rows (the rest is
    padding, of any finite value). The fields of the result have ``r`` first; ``used`` is
    ``(r, N)``, False on the padding. Each set leaves out its own outliers, as alone: a fix
    left out weighs zero in the sums."""
    r, N = var_m2.shape
    if len(counts) != r or min(counts, default=2) < 2 or max(counts, default=0) > N:
        raise ValueError(f"fit_heading needs at least 2 fixes per set, at most N = {N}; got {list(counts)}")
    valid = torch.arange(N, device=var_m2.device) < torch.tensor(list(counts), device=var_m2.device).unsqueeze(-1)
    w = torch.where(valid, 1.0 / torch.where(valid, var_m2, torch.ones_like(var_m2)), torch.zeros_like(var_m2))
    used = valid
    threshold = chi2_quantile(outlier_probability, 2)
    floors = [max(2, n - n // 5) for n in counts]
    while True:
        psi, c_p, c_g, info, W = planar_rotation(filter_xy_m, fix_xy_m, w * used)
        moved = (rotation_2d(psi).unsqueeze(-3) @ (filter_xy_m - c_p.unsqueeze(-2)).unsqueeze(-1)).squeeze(-1)
        resid = fix_xy_m - c_g.unsqueeze(-2) - moved
        score = torch.where(used, (w * (resid * resid).sum(-1)).detach(), torch.zeros_like(w))
        worst_score, worst = score.max(-1)
        facts = torch.stack((worst_score, worst.to(score.dtype), used.sum(-1).to(score.dtype)), -1).tolist()
        drop = [i for i, (s, _, kept) in enumerate(facts) if s > threshold and kept > floors[i]]
        if not drop:
            break
        used = used.clone()
        for i in drop:
            used[i, int(facts[i][1])] = False  # the worst fix only: one outlier drags every residual of the first fit
    sigma = torch.where(info > 0, info.clamp_min(torch.finfo(info.dtype).tiny).rsqrt(), torch.full_like(info, torch.inf))
    return HeadingFit(psi, sigma, c_p, c_g, 1.0 / W, used)


def heading_transform(fit: HeadingFit, *, dtype: torch.dtype = torch.float64, dim: int = STATE_DIM) -> tuple[Tensor, Tensor]:
    """The state map ``x ↦ A x + b`` of the fit: ``A (D, D)``, ``b (D,)`` for a state of ``D = dim``
    entries (``19 + 7 N``; 26, the default, for the paper's one cloned pose). Every pose's position
    (``p`` and each clone's) is rotated about the vertical and shifted, ``v`` rotated, every
    pose's quaternion left-multiplied by the yaw quaternion; the rest is kept."""
    psi = fit.yaw_rad.to(dtype)
    R2 = rotation_2d(psi)
    like = {"dtype": dtype, "device": psi.device}
    R3 = torch.block_diag(R2, torch.ones(1, 1, **like))
    zero = torch.zeros_like(psi)
    L = quat.left_matrix(torch.stack((torch.cos(0.5 * psi), zero, zero, torch.sin(0.5 * psi))))
    shift = fit.centre_fix_m.to(dtype) - R2 @ fit.centre_filter_m.to(dtype)
    shift3 = torch.cat((shift, shift.new_zeros(1)))
    layout = window_layout(window_size(dim))
    poses = pose_slices(dim)
    positions = {p.start for p, _ in poses}
    quaternions = {q.start for _, q in poses}
    blocks, shifts = [], []
    for name, size in layout.sizes:
        start = layout.slice(name).start
        if start in positions:
            blocks.append(R3)
            shifts.append(shift3)
            continue
        blocks.append(R3 if start == STATE.v.start else L if start in quaternions else torch.eye(size, **like))
        shifts.append(torch.zeros(size, **like))
    return torch.block_diag(*blocks), torch.cat(shifts)


def fit_record(fit: HeadingFit) -> dict[str, Any]:
    """The fit as plain numbers, for a log entry (:func:`fit_from_record` reads it back)."""
    return {"yaw_rad": float(fit.yaw_rad.detach()), "sigma_rad": float(fit.sigma_rad.detach()),
            "centre_filter_m": [float(x) for x in fit.centre_filter_m.detach().reshape(-1)],
            "centre_fix_m": [float(x) for x in fit.centre_fix_m.detach().reshape(-1)],
            "centre_var_m2": float(fit.centre_var_m2.detach()), "fixes": int(fit.used.sum()),
            "outliers": int((~fit.used).sum())}


def fit_from_record(record: dict[str, Any], *, dtype: torch.dtype = torch.float64,
                    device: torch.device | str = "cpu") -> HeadingFit:
    """The :class:`HeadingFit` of a log entry written with :func:`fit_record` (no gradient)."""
    like = {"dtype": dtype, "device": device}
    n = int(record["fixes"]) + int(record["outliers"])
    used = torch.arange(n, device=device) < int(record["fixes"])
    return HeadingFit(torch.tensor(record["yaw_rad"], **like), torch.tensor(record["sigma_rad"], **like),
                      torch.tensor(record["centre_filter_m"], **like), torch.tensor(record["centre_fix_m"], **like),
                      torch.tensor(record["centre_var_m2"], **like), used)


def aligned_prior_covariance(mean: Tensor, cov: Tensor, aligned_mean: Tensor, fit: HeadingFit, *,
                             condition_sigma_rad: float) -> Tensor:
    """A prior covariance ``(D, D)`` aligned with ``fit`` as the filter aligns its state (module
    docstring): ``cov`` conditioned on the heading of ``mean`` with ``condition_sigma_rad``,
    mapped by :func:`heading_transform`, plus the fit's :func:`heading_noise` at ``aligned_mean``
    (the prior's mean in the fixes' frame). It starts a second filter pass whose heading is known
    from its first sample, with no more certainty than the run's own prior and the fit give."""
    # the residual is 0: only the covariance changes
    conditioned = symmetrize(heading_conditional_covariance(mean, cov, slice(None), noise_var=condition_sigma_rad**2))
    A, _ = heading_transform(fit, dtype=mean.dtype, dim=mean.shape[-1])
    A = A.to(mean.device)
    return symmetrize(A @ conditioned @ A.T + heading_noise(aligned_mean, fit))


def heading_noise(x: Tensor, fit: HeadingFit) -> Tensor:
    """``Q = J_θ Σ_θ J_θᵀ`` ``(D, D)`` at the transformed state ``x`` ``(D,)``, ``θ = (ψ, c_g)``
    (every pose's position and quaternion, ``p``, ``q`` and each clone's, and ``v`` depend on ``θ``)."""
    s = split(x)
    poses = pose_slices(x.shape[-1])
    J = x.new_zeros(x.shape[-1], 3)
    S = x.new_tensor([[0.0, -1.0], [1.0, 0.0]])
    e_z = x.new_tensor([0.0, 0.0, 0.0, 1.0])
    for sl, _ in poses:
        rel = x[sl][:2] - fit.centre_fix_m.to(x)
        J[sl.start : sl.start + 2, 0] = S @ rel
        J[sl.start : sl.start + 2, 1:] = torch.eye(2, dtype=x.dtype, device=x.device)
    J[STATE.v.start : STATE.v.start + 2, 0] = S @ s.v[:2]
    for _, sl in poses:
        J[sl, 0] = 0.5 * quat.multiply(e_z, x[sl])
    sigma = torch.stack((fit.sigma_rad**2, fit.centre_var_m2, fit.centre_var_m2)).to(x)
    return (J * sigma) @ J.T
