"""How well can a causal filter do with a recording's GNSS fixes? An oracle's RMSE.

Table I scores a track after one rigid (Procrustes) alignment to the ground truth, so
a track is scored on its *shape*. A causal filter that uses GNSS must move its
estimate of where it is in the world each time a fix arrives, and every such
correction bends the track's shape. How much it must move depends only on the fixes'
errors, not on the rest of the filter. This module measures that floor with an
oracle:

* it knows the true motion relative to the start exactly (a perfect INS + flow);
* it knows the GNSS error model: per axis, the error of fix ``k`` is
  ``e_k = s_k z_k`` with ``s_k`` the reported 1-σ (``h_acc``, ``h_acc``, ``v_acc``)
  and ``z`` a unit first-order Gauss-Markov process, ``z_k = φ_k z_{k-1} + w_k``,
  ``φ_k = exp(-Δt_k / τ)``, ``w_k ~ N(0, 1 - φ_k²)`` (``τ = 0``: white);
* its only unknown is the constant offset ``b`` between the start and the world.
  Per axis the Kalman filter of ``(b, z)`` with a flat prior on ``b`` and
  ``y_k = b + s_k z_k`` gives the minimum-variance causal estimate ``b̂_k``
  (the generalised least-squares mean of the fixes so far); fixes whose
  innovation fails a χ² gate (three axes) are left out, as the filter's gate
  leaves out multipath fixes.

The oracle's track is ``truth(t) + b̂(t)`` (``b̂`` of the latest fix at or before
``t``; the first fix's before it, as the filter starts at the first fix), and its
aligned RMSE is the floor. A filter that also uses GNSS pays at least about this
much, unless it ignores the fixes; a filter whose relative motion drifts less than
this can only be hurt, under this metric, by following GNSS. The smoother is not
causal and has no such floor.

The fixes and the ground truth need not share a frame: the truth at the fix times
is first aligned rigidly to the fixes (Procrustes), and the fixes' errors are the
residuals. ``τ`` is estimated from those residuals when not given (the lag-1
autocorrelation of ``e_k / s_k``).
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, NamedTuple

import torch
from torch import Tensor

from flowins.data.streams import GnssStream, PoseStream
from flowins.evaluation.alignment import apply_alignment, umeyama
from flowins.filter.ekf import block_nis, joseph_update, linear_predict
from flowins.evaluation.metrics import (
    associate,
    interpolate_positions,
    trajectory_errors,
)

#: χ² quantile, 3 degrees of freedom, probability 0.999 (the filter's default GNSS gate)
CHI2_3DOF_0999 = 16.266236196238129


class OracleEstimates(NamedTuple):
    offset_m: Tensor  # (G, 3) b̂ after each fix
    offset_sigma_m: Tensor  # (G, 3) its 1-σ
    used: Tensor  # (G,) bool: the fix passed the gate


def offset_estimates(
    errors_m: Tensor,
    sigma_m: Tensor,
    t_s: Tensor,
    *,
    correlation_s: float,
    gate: float | None = CHI2_3DOF_0999,
) -> OracleEstimates:
    """The causal minimum-variance estimates ``b̂_k`` of a constant offset from fixes
    ``y_k = b + s_k z_k`` (see the module docstring), three independent axes at once.

    Args:
        errors_m ``(G, D)``: the fixes' errors ``y_k`` (fix minus truth, in metres).
        sigma_m ``(G, D)``: ``s_k``, each > 0.
        t_s ``(G,)``: fix times, strictly increasing.
        correlation_s: ``τ`` (s); 0 for white errors.
        gate: χ² threshold on the summed normalised innovations of a fix (``D`` axes);
            ``None`` uses every fix.
    """
    if errors_m.ndim != 2 or sigma_m.shape != errors_m.shape or t_s.shape != errors_m.shape[:1]:
        raise ValueError(
            f"offset_estimates: errors_m and sigma_m must be (G, D) and t_s (G,); got "
            f"{tuple(errors_m.shape)}, {tuple(sigma_m.shape)}, {tuple(t_s.shape)}"
        )
    if errors_m.shape[0] == 0:
        raise ValueError("offset_estimates: no fixes")
    if not bool((sigma_m > 0).all()):
        row = int((sigma_m <= 0).any(-1).nonzero()[0])
        raise ValueError(f"offset_estimates: sigma_m must be > 0; row {row} is {sigma_m[row].tolist()}")
    if not correlation_s >= 0.0 or not math.isfinite(correlation_s):
        raise ValueError(f"offset_estimates: correlation_s must be a finite number >= 0, got {correlation_s}")
    if errors_m.shape[0] > 1 and not bool((t_s[1:] > t_s[:-1]).all()):
        row = int((t_s[1:] <= t_s[:-1]).nonzero()[0]) + 1
        raise ValueError(f"offset_estimates: t_s must be strictly increasing; row {row} is {float(t_s[row])} s")
    y, s = errors_m.to(torch.float64), sigma_m.to(torch.float64)
    G, D = y.shape
    dt = torch.diff(t_s.to(torch.float64), prepend=t_s[:1].to(torch.float64))
    phi = torch.exp(-dt / correlation_s) if correlation_s > 0 else torch.zeros_like(dt)
    # per axis a state (b, z) with a flat prior on b, handled exactly as the first fix's value;
    # the D axes are a batch of 2-state filters with the filter core's algebra, and the
    # gate is joint: the fix's NIS summed over its axes
    zeros = torch.zeros(D, 1, 1, dtype=torch.float64)
    mean = torch.zeros(D, 2, dtype=torch.float64)
    P = torch.zeros(D, 2, 2, dtype=torch.float64)
    started = False
    offsets, sigmas, used = [], [], []
    for k in range(G):
        if started:
            # predict: z ← φ z + w: A = diag(1, φ), Q = diag(0, 1 - φ²)
            A = torch.diag(torch.stack((torch.ones((), dtype=torch.float64), phi[k])))
            Q = torch.diag(torch.stack((torch.zeros((), dtype=torch.float64), 1.0 - phi[k] ** 2)))
            mean, P = linear_predict(mean, P, A, Q)
            H = torch.stack((torch.ones(D, dtype=torch.float64), s[k]), -1).unsqueeze(-2)  # (D, 1, 2): y = b + s z
            innovation = y[k].unsqueeze(-1) - (H @ mean.unsqueeze(-1)).squeeze(-1)  # (D, 1)
            nis = block_nis(P, innovation.unsqueeze(-2), H.unsqueeze(-3), zeros.unsqueeze(-3))
            accept = gate is None or float(nis.sum()) <= gate
            if accept:
                mean, P, _ = joseph_update(mean, P, innovation, H, zeros)
        else:
            # the first fix sets b + s z; b's variance is then s², z's 1, and they are
            # perfectly anti-correlated (only their sum is known)
            accept = True
            mean = torch.stack((y[k], torch.zeros(D, dtype=torch.float64)), -1)
            P = torch.zeros(D, 2, 2, dtype=torch.float64)
            P[:, 0, 0] = s[k] ** 2
            P[:, 1, 1] = 1.0
            P[:, 0, 1] = P[:, 1, 0] = -s[k]
            started = True
        offsets.append(mean[:, 0].clone())
        sigmas.append(P[:, 0, 0].clamp_min(0.0).sqrt())
        used.append(accept)
    return OracleEstimates(torch.stack(offsets), torch.stack(sigmas), torch.tensor(used))


def estimate_correlation_s(normalised_errors: Tensor, t_s: Tensor, *, outlier_sigma: float = 3.0) -> float:
    """``τ`` (s) of a first-order Gauss-Markov process from samples ``(G, D)`` of roughly
    unit variance at times ``t_s`` ``(G,)``: ``-Δt / ln ρ̂`` with ``ρ̂`` the lag-1
    autocorrelation over all axes and ``Δt`` the median spacing; 0 when ``ρ̂ ≤ 0``.

    Samples more than ``outlier_sigma`` from the median on any axis (multipath) are
    left out, and so are the pairs they belong to.
    """
    if normalised_errors.shape[0] < 3:
        raise ValueError(f"estimate_correlation_s: needs at least 3 fixes, got {normalised_errors.shape[0]}")
    z = normalised_errors.to(torch.float64)
    clean = ((z - z.median(0).values).abs() <= outlier_sigma).all(-1)
    pairs = clean[1:] & clean[:-1]
    if int(pairs.sum()) < 2:
        raise ValueError(
            f"estimate_correlation_s: only {int(pairs.sum())} consecutive pairs of fixes within {outlier_sigma} sigma; "
            "give the correlation time instead"
        )
    z = z - z[clean].mean(0)
    variance = (z[clean] ** 2).mean()
    rho = float((z[1:] * z[:-1])[pairs].sum(-1).mean() / (z.shape[1] * variance))
    if rho <= 0.0:
        return 0.0
    rho = min(rho, 1.0 - 1e-9)
    return float(-torch.diff(t_s.to(torch.float64)).median()) / math.log(rho)


class GnssFloor(NamedTuple):
    """The oracle's aligned RMSE and what it used."""

    rmse_m: float  # the oracle track's RMSE after Procrustes alignment to the truth
    horizontal_rmse_m: float  # the same with the vertical offset known (only the horizontal fixes used)
    correlation_s: float  # τ used
    fixes_used: int
    fixes: int
    error_sigma_m: tuple[float, float, float]  # RMS of the fixes' errors per axis (E, N, U), gated fixes only
    track_t_s: Tensor  # (K,) truth times of the oracle track
    track_m: Tensor  # (K, 3) the oracle track, in the fixes' frame


def gnss_floor(
    fix_t_s: Tensor,
    fix_m: Tensor,
    fix_sigma_m: Tensor,
    truth_t_s: Tensor,
    truth_m: Tensor,
    *,
    correlation_s: float | None = None,
    gate: float | None = CHI2_3DOF_0999,
    max_dt_s: float = 0.05,
) -> GnssFloor:
    """The RMSE floor of a causal GNSS filter on a recording (see the module docstring).

    Args:
        fix_t_s ``(G,)``, fix_m ``(G, 3)`` fixes in any local metric frame (e.g. ENU),
        fix_sigma_m ``(G, 3)`` their 1-σ per axis; truth_t_s ``(M,)``, truth_m ``(M, 3)``
        the ground-truth positions in any frame.
        correlation_s: ``τ`` of the GNSS errors (s); ``None`` estimates it from the residuals.
        max_dt_s: how close a truth sample must be to a fix time to be interpolated there.
    """
    if fix_m.ndim != 2 or fix_m.shape[-1] != 3 or fix_sigma_m.shape != fix_m.shape or fix_t_s.shape != fix_m.shape[:1]:
        raise ValueError(
            f"gnss_floor: fix_m and fix_sigma_m must be (G, 3) and fix_t_s (G,); got {tuple(fix_m.shape)}, "
            f"{tuple(fix_sigma_m.shape)}, {tuple(fix_t_s.shape)}"
        )
    if not bool((fix_sigma_m > 0).all()):
        row = int((fix_sigma_m <= 0).any(-1).nonzero()[0])
        raise ValueError(f"gnss_floor: fix_sigma_m must be > 0; row {row} is {fix_sigma_m[row].tolist()}")
    truth_t = truth_t_s.to(torch.float64)
    truth = truth_m.to(torch.float64)
    association = associate(truth_t, fix_t_s.to(torch.float64), max_dt_s=max_dt_s)
    keep = association.ref_index
    if keep.numel() < 3:
        raise ValueError(
            f"gnss_floor: only {keep.numel()} fixes lie within the ground truth's time span "
            f"[{float(truth_t[0]):.3f}, {float(truth_t[-1]):.3f}] s; need at least 3"
        )
    t = fix_t_s.to(torch.float64)[keep]
    fixes = fix_m.to(torch.float64)[keep]
    sigma = fix_sigma_m.to(torch.float64)[keep]
    truth_at_fix = interpolate_positions(truth, association)
    # the truth in the fixes' frame: one rigid transform, then the fixes' errors
    to_fix_frame = umeyama(truth_at_fix, fixes)
    errors = fixes - apply_alignment(to_fix_frame, truth_at_fix)
    if correlation_s is None:
        correlation_s = estimate_correlation_s(errors / sigma, t)
    estimates = offset_estimates(errors, sigma, t, correlation_s=correlation_s, gate=gate)
    # the oracle's track at every truth sample: the truth plus the offset of the latest fix
    latest = (torch.searchsorted(t, truth_t, right=True) - 1).clamp_min(0)
    truth_in_fix_frame = apply_alignment(to_fix_frame, truth)

    def rmse(track: Tensor) -> float:
        return trajectory_errors(truth_t, track, truth_t, truth, align="se3", max_dt_s=max_dt_s).rmse_m

    offset = estimates.offset_m
    track = truth_in_fix_frame + offset[latest]
    horizontal = torch.cat((offset[:, :2], torch.zeros_like(offset[:, 2:])), -1)
    used = estimates.used
    err_rms = errors[used].pow(2).mean(0).sqrt()
    return GnssFloor(
        rmse_m=rmse(track),
        horizontal_rmse_m=rmse(truth_in_fix_frame + horizontal[latest]),
        correlation_s=float(correlation_s),
        fixes_used=int(used.sum()),
        fixes=int(used.numel()),
        error_sigma_m=tuple(float(v) for v in err_rms),
        track_t_s=truth_t,
        track_m=track,
    )


def gnss_floor_metrics(gnss: GnssStream, truth: PoseStream, *, correlation_s: float | None = None) -> dict[str, Any]:
    """:func:`~flowins.evaluation.gnss_floor.gnss_floor` of a sequence's fixes against its truth
    (``correlation_s``: the GNSS errors' τ; estimated from them when None)."""
    enu, cov, _ = gnss.enu()
    floor = gnss_floor(gnss.t_s, enu, cov.diagonal(dim1=-2, dim2=-1).sqrt(), truth.t_s, truth.pos_m,
                       correlation_s=correlation_s)
    return {
        "rmse_m": floor.rmse_m,
        "horizontal_rmse_m": floor.horizontal_rmse_m,
        "correlation_s": floor.correlation_s,
        "fixes_used": floor.fixes_used,
        "fixes": floor.fixes,
        "error_rms_enu_m": list(floor.error_sigma_m),
    }


def describe_gnss_floor(floor: Mapping[str, Any]) -> str:
    e, n, u = floor["error_rms_enu_m"]
    return (
        f"GNSS floor (flowins.evaluation.gnss_floor): a causal filter that knew the motion exactly and weighted\n"
        f"the fixes by their true error model would score {floor['rmse_m']:.2f} m ({floor['horizontal_rmse_m']:.2f} m "
        f"if it also knew the height); the fixes'\nerrors are {e:.1f}/{n:.1f}/{u:.1f} m RMS (E/N/U), correlated over "
        f"{floor['correlation_s']:.1f} s ({floor['fixes_used']} of {floor['fixes']} fixes pass the gate).\n"
        f"A GNSS filter scores below it only by trusting the fixes less than they deserve; the smoother has no such floor."
    )
