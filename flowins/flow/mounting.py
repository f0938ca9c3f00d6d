"""Is the camera mounted as the calibration says? ``imu_to_camera``'s rotation seen by the data.

Between the two frames of a pair the camera turns by ``R_c`` and the IMU by ``R_b``; on one
rigid body ``R_c = R_ci R_b R_ciᵀ``, so their rotation vectors obey ``φ_c = R_ci φ_b``
(``R_ci``: the rotation of ``imu_to_camera``, ``x_cam = R_ci x_imu + t``). The gyroscope
gives ``φ_b`` (its rates integrated over the pair, :func:`gyro_rotations`); the flow gives
``φ_c`` (the turn alone where it explains the pair's points, else an essential matrix fitted
with RANSAC and the one of its two rotations that turns less, :func:`camera_rotations`).
:func:`check_mounting` solves Wahba's problem ``ω_c ≈ R ω_b`` on the mean rates ``ω = φ / Δt``
of every pair (a hand–eye fit over the recording):

* **A constant gyroscope bias is no fault**: both sets are centred (a bias shifts every
  ``ω_b`` by the same vector), so the fit needs no bias estimate;
* **Cauchy weights** (iteratively reweighted) let pairs whose flow fails count little;
* **a weak prior at the configured rotation** (``prior_sigma_rad``) holds the directions the
  recording never turns about (a car that only yaws) where the calibration puts them: the
  data decide the rest;
* **the verdict** compares the configured rotation with the fit: a warning when they differ
  by more than ``bound_rad`` *and* the data see the difference (``δᵀ H δ`` above
  ``chi2``, ``H`` the fit's information from the residual scatter), so that neither an
  unexcited axis nor a poorly textured recording raises one;
* **mirrored gyroscope axes** (two swapped, or one negated) map the rates by a reflection,
  which no rotation reproduces: the best reflection of the data alone is set against the best
  rotation (the fall in their residual sum of squares over the reflection's residual
  variance, pairs either map leaves far out trimmed); above ``chi2`` the check says so.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from flowins.flow.pairs import FlowPairs
from flowins.geometry import quaternion
from flowins.geometry.procrustes import wahba_rotation

#: χ²(3) at 1 - 1e-4: a difference the residual scatter explains less often than this is seen
CHI2_3DOF = 21.11


@dataclass(frozen=True)
class MountingCheck:
    """The configured ``imu_to_camera`` rotation against the data (:func:`check_mounting`).

    Attributes:
        pairs: frame pairs whose flow gave a camera rotation.
        configured_wxyz, suggested_wxyz: the configured rotation and the fitted one (w, x, y, z).
        angle_rad: the angle between them.
        configured_error_rps, suggested_error_rps: the median rate of the camera's rotation
            each leaves unexplained (rad/s; nan without a fit).
        significance: ``δᵀ H δ`` of the difference (see the module docstring).
        warn: whether the configured rotation is off (both tests of the module docstring).
        reason: why there is no verdict ("" when there is one).
        mirrored_error_rps: the median rate the best reflection leaves unexplained (rad/s).
        mirrored: whether that reflection beats every rotation beyond chance (the gyroscope's
            axes mirrored: two swapped, or one negated).
    """

    pairs: int
    configured_wxyz: tuple[float, float, float, float]
    suggested_wxyz: tuple[float, float, float, float]
    angle_rad: float
    configured_error_rps: float
    suggested_error_rps: float
    significance: float
    warn: bool
    reason: str = ""
    mirrored_error_rps: float = math.nan
    mirrored: bool = False

    def describe(self) -> str:
        """One sentence: the warning with the suggested rotation, or the agreement."""
        if self.reason:
            return f"imu_to_camera's rotation not checked: {self.reason}"
        q = ", ".join(f"{x:.4f}" for x in self.suggested_wxyz)
        R = quaternion.to_matrix(torch.tensor(self.suggested_wxyz, dtype=torch.float64))
        rows = "; ".join(" ".join(f"{x:.3f}" for x in row) for row in R.tolist())
        errors = (f"over {self.pairs} frame pairs the configured rotation leaves "
                  f"{math.degrees(self.configured_error_rps):.2f}°/s of the camera's rotation unexplained "
                  f"(median), the data's own fit {math.degrees(self.suggested_error_rps):.2f}°/s")
        if self.mirrored:
            return (f"the gyroscope's axes look mirrored (two swapped, or one negated): no rotation maps its rates "
                    f"onto the camera's turns from the flow, a reflection does ({errors}; the best reflection "
                    f"{math.degrees(self.mirrored_error_rps):.2f}°/s): check the IMU's axis order and signs before "
                    "imu_to_camera")
        if self.warn:
            return (f"imu_to_camera: the camera's flow and the gyroscope put the camera "
                    f"{math.degrees(self.angle_rad):.1f}° from the configured rotation: {errors}; the data suggest "
                    f"rotation [{q}] (qw, qx, qy, qz; as a matrix [{rows}]): check the calibration "
                    "(imu_to_camera, or camera_to_imu, its inverse)")
        return (f"imu_to_camera agrees with the camera's flow and the gyroscope: their fit is "
                f"{math.degrees(self.angle_rad):.1f}° from it; {errors}")


def gyro_rotations(t_s: Tensor, gyro_rps: Tensor, t1_s: Tensor, t2_s: Tensor) -> Tensor:
    """Rotation vectors ``(P, 3)`` of the body turn from ``t1_s`` to ``t2_s`` ``(P,)``: the
    rotation vector of ``R_{b1 b2}`` (body at ``t2`` to body at ``t1``), integrated from the
    rates (midpoint rule between samples, the rate held within a sample step)."""
    t = torch.as_tensor(t_s, dtype=torch.float64)
    gyro = torch.as_tensor(gyro_rps, dtype=torch.float64)
    rates = 0.5 * (gyro[1:] + gyro[:-1])  # (N-1, 3), over [t_k, t_k+1]
    steps = quaternion.from_rotation_vector(rates * torch.diff(t).unsqueeze(-1))
    q = torch.cat((quaternion.identity(1, dtype=t.dtype), quaternion.cumulative_product(steps)))  # body_k -> body_0

    def at(times: Tensor) -> Tensor:
        k = (torch.searchsorted(t, times, right=True) - 1).clamp(0, t.shape[0] - 2)
        partial = quaternion.from_rotation_vector(rates[k] * (times - t[k]).unsqueeze(-1))
        return quaternion.multiply(q[k], partial)

    return quaternion.to_rotation_vector(quaternion.multiply(quaternion.conjugate(at(t1_s)), at(t2_s)))


def camera_rotations(pairs: FlowPairs, K: Tensor, *, max_points: int = 300, threshold_px: float = 1.0,
                     max_angle_rad: float = math.radians(45.0)) -> tuple[Tensor, Tensor]:
    """Rotation vectors ``(P, 3)`` of the camera turn over each pair (of ``R_{c1 c2}``,
    camera at ``t2`` to camera at ``t1``; ideal pinhole pixels, intrinsics ``K`` ``(3, 3)``)
    and a ``(P,)`` bool: whether the pair gave one.

    At most ``max_points`` of the pair's points, those of lowest σ first, are used. Where a
    turn alone explains them (median distance within ``threshold_px / 2``: no parallax, and an
    essential matrix would be degenerate) that turn is the camera's. Otherwise an essential
    matrix fitted with RANSAC (``threshold_px`` on the image) decomposes into two rotations;
    the one that turns less is the camera's (the other differs by a half turn).
    A pair with fewer than 8 points, no essential matrix or a turn over ``max_angle_rad``
    gives none."""
    import cv2

    cv2.setRNGSeed(0)  # RANSAC's draws: the same verdict on every run
    K = torch.as_tensor(K, dtype=torch.float64)
    f = 0.5 * float(K[0, 0] + K[1, 1])
    K_inv = torch.linalg.inv(K)
    out = torch.zeros(len(pairs), 3, dtype=torch.float64)
    ok = torch.zeros(len(pairs), dtype=torch.bool)
    chosen: dict[int, tuple[Tensor, Tensor]] = {}
    for k, p in enumerate(pairs.points):
        uv1 = p.uv1_px.to(torch.float64)
        uv2 = uv1 + p.flow_px.to(torch.float64)
        sigma = p.sigma_px.to(torch.float64).norm(dim=-1)
        finite = torch.isfinite(uv1).all(-1) & torch.isfinite(uv2).all(-1) & torch.isfinite(sigma)
        index = torch.nonzero(finite)[:, 0]
        if index.numel() >= 8:
            index = index[torch.argsort(sigma[index], stable=True)[:max_points]]
            x1 = (torch.cat((uv1[index], torch.ones_like(uv1[index, :1])), -1) @ K_inv.T)[:, :2]
            x2 = (torch.cat((uv2[index], torch.ones_like(uv2[index, :1])), -1) @ K_inv.T)[:, :2]
            chosen[k] = (x1, x2)
    if not chosen:
        return out, ok
    keys = list(chosen)
    x1 = torch.nn.utils.rnn.pad_sequence([chosen[k][0] for k in keys], batch_first=True, padding_value=float("nan"))
    x2 = torch.nn.utils.rnn.pad_sequence([chosen[k][1] for k in keys], batch_first=True, padding_value=float("nan"))
    R_turn, median_px = pure_turns(x1, x2, f)
    phi_turn = quaternion.to_rotation_vector(quaternion.from_matrix(R_turn))
    for j, k in enumerate(keys):
        if float(median_px[j]) <= 0.5 * threshold_px:  # no parallax: an essential matrix is degenerate
            candidates = [phi_turn[j]]
        else:
            E, _ = cv2.findEssentialMat(chosen[k][0].numpy(), chosen[k][1].numpy(), np.eye(3),
                                        method=cv2.USAC_ACCURATE, prob=0.999, threshold=threshold_px / f)
            if E is None or E.shape[0] < 3 or not np.isfinite(E[:3]).all():
                continue
            # OpenCV's R maps camera-1 points to camera-2 points (R_{c2 c1}); its transpose is R_{c1 c2}
            candidates = [-quaternion.to_rotation_vector(quaternion.from_matrix(torch.from_numpy(R)))
                          for R in cv2.decomposeEssentialMat(E[:3])[:2]]
        best = min(candidates, key=lambda v: float(v.norm()))
        if float(best.norm()) <= max_angle_rad:
            out[k], ok[k] = best, True
    return out, ok


def pure_turns(x1: Tensor, x2: Tensor, f: float, iterations: int = 5) -> tuple[Tensor, Tensor]:
    """Rotations ``R_{c1 c2}`` ``(P, 3, 3)`` of a camera that only turns, fitted per pair to
    normalised image points ``x1``, ``x2`` ``(P, N, 2)`` (rows of NaN pad a pair;
    ``[x1, 1] ∝ R [x2, 1]``: Wahba's problem on their bearings, Cauchy-reweighted), and the
    ``(P,)`` median distance in pixels (focal length ``f``) of ``x1`` from ``x2`` so turned.
    A turn alone, or a scene too far for the baseline to show, leaves that distance at the
    noise; any parallax leaves more."""
    valid = torch.isfinite(x1).all(-1) & torch.isfinite(x2).all(-1)
    x1, x2 = x1.nan_to_num(0.0), x2.nan_to_num(0.0)
    b1 = torch.nn.functional.normalize(torch.cat((x1, torch.ones_like(x1[..., :1])), -1), dim=-1)
    b2 = torch.nn.functional.normalize(torch.cat((x2, torch.ones_like(x2[..., :1])), -1), dim=-1)
    w = valid.to(x1.dtype)
    nan = torch.full_like(w, float("nan"))
    for _ in range(iterations + 1):
        R = wahba_rotation(b2, b1, w)
        turned = b2 @ R.transpose(-1, -2)
        r = f * (turned[..., :2] / turned[..., 2:].clamp_min(1e-9) - x1).norm(dim=-1)
        r = torch.where(valid, torch.where(turned[..., 2] > 0, r, torch.full_like(r, float("inf"))), nan)
        median = r.nanmedian(-1).values
        scale = (1.4826 * median).clamp_min(1e-9).unsqueeze(-1)
        w = torch.where(valid, 1.0 / (1.0 + (r / (2.385 * scale)) ** 2), torch.zeros_like(w))
    return R, median


def _fit(omega_b: Tensor, omega_c: Tensor, configured: Tensor, prior_weight: float, iterations: int
         ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The robust centred Wahba fit: ``(R, weights (P,), centred ω_b, residual variance)``."""
    w = torch.ones_like(omega_b[:, 0])
    R = configured
    for i in range(iterations + 1):
        c_b = (w.unsqueeze(-1) * omega_b).sum(0) / w.sum()
        c_c = (w.unsqueeze(-1) * omega_c).sum(0) / w.sum()
        s_b, s_c = omega_b - c_b, omega_c - c_c
        if i > 0:
            r = (s_c - s_b @ R.T).norm(dim=-1)
            scale = (1.4826 * r.median()).clamp_min(1e-12)
            w = 1.0 / (1.0 + (r / (2.385 * scale)) ** 2)
        r2 = (s_c - s_b @ R.T).pow(2).sum(-1)
        variance = ((w * r2).sum() / (3.0 * w.sum())).clamp_min(1e-18)
        R = wahba_rotation(s_b, s_c, w / variance, prior=configured, prior_weight=prior_weight)
    r2 = (s_c - s_b @ R.T).pow(2).sum(-1)
    variance = ((w * r2).sum() / (3.0 * w.sum())).clamp_min(1e-18)
    return R, w, s_b, variance


def _median_error(omega_b: Tensor, omega_c: Tensor, R: Tensor) -> float:
    """The median unexplained rate ``|ω_c - R ω_b|`` (both centred at their medians: no bias)."""
    r = omega_c - omega_b @ R.T
    return float((r - r.median(0).values).norm(dim=-1).median())


def _reflection(omega_b: Tensor, omega_c: Tensor, chi2: float) -> tuple[Tensor, bool]:
    """The best reflection ``(3, 3)`` mapping the centred ``ω_b`` onto ``ω_c`` (data alone),
    and whether it beats the best rotation: ``(RSS_rotation - RSS_reflection) / σ² > chi2``
    with ``σ²`` the reflection's residual variance per component, over the pairs both maps
    leave within 3 robust σ of the better one."""
    s_b, s_c = omega_b - omega_b.median(0).values, omega_c - omega_c.median(0).values
    U, _, Vh = torch.linalg.svd(s_c.T @ s_b)
    d = float(torch.linalg.det(U @ Vh))
    rotation = U @ torch.diag(torch.tensor([1.0, 1.0, d], dtype=U.dtype)) @ Vh
    reflection = U @ torch.diag(torch.tensor([1.0, 1.0, -d], dtype=U.dtype)) @ Vh
    r_rot = (s_c - s_b @ rotation.T).pow(2).sum(-1)
    r_ref = (s_c - s_b @ reflection.T).pow(2).sum(-1)
    best = torch.minimum(r_rot, r_ref)
    keep = best <= (3.0 * 1.4826) ** 2 * best.sqrt().median() ** 2
    variance = (r_ref[keep].sum() / (3 * keep.sum())).clamp_min(1e-18)
    return reflection, bool((r_rot[keep].sum() - r_ref[keep].sum()) / variance > chi2)


def check_mounting(
    t_s: Tensor,
    gyro_rps: Tensor,
    pairs: FlowPairs,
    K: Tensor,
    configured_wxyz: Tensor,
    *,
    min_pairs: int = 20,
    min_rate_rps: float = math.radians(2.0),
    bound_rad: float = math.radians(5.0),
    chi2: float = CHI2_3DOF,
    prior_sigma_rad: float = math.radians(20.0),
    iterations: int = 6,
) -> MountingCheck:
    """The configured ``imu_to_camera`` rotation ``configured_wxyz`` ``(4,)`` against the
    rotation the gyroscope (``t_s`` ``(N,)``, ``gyro_rps`` ``(N, 3)``) and the flow of
    ``pairs`` (ideal pinhole pixels, intrinsics ``K``) imply (module docstring).

    Args:
        min_pairs: fewer pairs with a camera rotation give no verdict.
        min_rate_rps: no verdict when the gyroscope's rates spread less than this (rms about
            their mean): nothing turns.
        bound_rad, chi2: the configured rotation is off when it is over ``bound_rad`` from the
            fit and ``δᵀ H δ > chi2``.
        prior_sigma_rad: the prior's σ at the configured rotation.
    """
    configured_q = quaternion.normalize(torch.as_tensor(configured_wxyz, dtype=torch.float64))
    as_tuple = tuple(float(x) for x in configured_q)
    nan = math.nan

    def no_verdict(reason: str, n: int) -> MountingCheck:
        return MountingCheck(n, as_tuple, as_tuple, 0.0, nan, nan, 0.0, False, reason)

    if len(pairs) == 0:
        return no_verdict("no frame pairs", 0)
    phi_c, ok = camera_rotations(pairs, K)
    dt = (pairs.t2_s - pairs.t1_s).to(torch.float64)
    t = torch.as_tensor(t_s, dtype=torch.float64)
    ok &= (pairs.t1_s >= t[0]) & (pairs.t2_s <= t[-1])
    n = int(ok.sum())
    if n < min_pairs:
        return no_verdict(f"{n} frame pairs gave a camera rotation (at least {min_pairs} needed)", n)
    omega_c = phi_c[ok] / dt[ok].unsqueeze(-1)
    omega_b = gyro_rotations(t, gyro_rps, pairs.t1_s[ok].to(torch.float64), pairs.t2_s[ok].to(torch.float64))
    omega_b = omega_b / dt[ok].unsqueeze(-1)
    spread = float((omega_b - omega_b.mean(0)).pow(2).sum(-1).mean().sqrt())
    if spread < min_rate_rps:
        return no_verdict(f"the gyroscope's rates spread by {math.degrees(spread):.2f}°/s over the frame pairs "
                          f"(at least {math.degrees(min_rate_rps):.1f}°/s needed): the camera hardly turns", n)
    configured = quaternion.to_matrix(configured_q)
    R, w, s_b, variance = _fit(omega_b, omega_c, configured, 1.0 / prior_sigma_rad**2, iterations)
    # the information on a turn δ of the fit (R -> exp(δ) R): Σ w [R s_b]×ᵀ [R s_b]× / σ²
    J = quaternion.skew(s_b @ R.T)
    H = (w.view(-1, 1, 1) * J.transpose(-1, -2) @ J).sum(0) / variance
    delta = quaternion.to_rotation_vector(quaternion.from_matrix(configured @ R.T))
    significance = float(delta @ H @ delta)
    angle = float(delta.norm())
    suggested = tuple(float(x) for x in quaternion.from_matrix(R))
    error = _median_error(omega_b, omega_c, R)
    mirror, mirrored = _reflection(omega_b, omega_c, chi2)
    off = angle > bound_rad and significance > chi2
    return MountingCheck(n, as_tuple, suggested, angle, _median_error(omega_b, omega_c, configured), error,
                         significance, off or mirrored, "", _median_error(omega_b, omega_c, mirror), mirrored)
