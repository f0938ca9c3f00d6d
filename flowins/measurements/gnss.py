"""GNSS position measurement model.

    h(x) = p + C(q) ℓ        (antenna position in the local ENU frame, m)

with ``ℓ`` the antenna lever arm in the IMU frame (zero by default, as in the
paper), and noise ``R = s² diag(σ_h², σ_h², σ_v²)`` from the fix's reported
horizontal and vertical 1-σ accuracies, scaled by ``s`` (a tuning parameter, 1 by default).

GNSS errors are correlated in time (atmosphere, multipath, the receiver's own
filter: tens of seconds). A filter that takes them as white believes ``n`` fixes
average their errors down by ``n``. For a first-order Gauss-Markov error with
correlation time ``τ`` sampled every ``Δt`` (lag-one correlation ``ρ = exp(-Δt/τ)``)
the mean of ``n`` fixes has variance ``(σ²/n)(1 + ρ)/(1 - ρ)`` for large ``n``, so
:func:`correlation_inflation` scales each fix's ``R`` by that factor: the white-noise
filter then draws the information the fixes really hold (``τ = 0``: no change).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor
from torch.func import jacrev, vmap

from flowins.filter.chain import ChainBuilder
from flowins.filter.ekf import Gate, chi2_quantile
from flowins.filter.updater import update
from flowins.geometry import quaternion as quat
from flowins.measurements.gnss_heading import (
    HeadingAlignment,
    fit_heading,
    fit_record,
    heading_conditional_covariance,
    heading_jacobian,
    heading_noise,
    heading_transform,
)
from flowins.state import STATE, pose_slices, split


def gnss_position(x: Tensor, lever_arm_m: Tensor) -> Tensor:
    """``h(x)`` ``(..., 3)`` for states ``(..., D)`` and a lever arm ``(3,)``."""
    s = split(x)
    return s.p + quat.rotate(s.q, lever_arm_m.to(x.dtype).expand_as(s.p))


def gnss_jacobian(x: Tensor, lever_arm_m: Tensor) -> Tensor:
    """``∂h/∂x`` ``(..., 3, D)`` by ``torch.func.jacrev``."""
    jac = jacrev(gnss_position)
    if x.ndim == 1:
        return jac(x, lever_arm_m)
    flat = x.reshape(-1, x.shape[-1])
    return vmap(jac, in_dims=(0, None))(flat, lever_arm_m).reshape(*x.shape[:-1], 3, x.shape[-1])


def gnss_jacobian_analytic(x: Tensor, lever_arm_m: Tensor | None) -> Tensor:
    """Closed form of :func:`gnss_jacobian`: ``[I₃, 0, ∂(C(q)ℓ)/∂q, 0]`` ``(..., 3, D)``.

    ``lever_arm_m=None`` means a zero lever arm, whose ``∂/∂q`` block is zero.
    """
    H = x.new_zeros(*x.shape[:-1], 3, x.shape[-1])
    H[..., STATE.p] = torch.eye(3, dtype=x.dtype, device=x.device)
    if lever_arm_m is not None:
        H[..., STATE.q] = quat.rotate_jacobian(split(x).q, lever_arm_m.to(x.dtype).expand(*x.shape[:-1], 3))
    return H


def gnss_noise(h_acc_m: Tensor, v_acc_m: Tensor, scale: float | Tensor = 1.0) -> Tensor:
    """``R`` ``(..., 3, 3)`` from horizontal and vertical 1-σ accuracies ``(...)``, on their
    device (a learned ``scale`` on another device is moved there, with its gradient)."""
    if isinstance(scale, Tensor):
        scale = scale.to(device=h_acc_m.device)
    sigmas = torch.stack((h_acc_m, h_acc_m, v_acc_m), dim=-1) * scale
    return torch.diag_embed(sigmas * sigmas)


def correlation_inflation(t_s: Tensor, correlation_s: float | Tensor) -> Tensor:
    """Variance factor ``(1 + ρ) / (1 - ρ)`` ``(G,)`` per fix, ``ρ = exp(-Δt / τ)``.

    ``Δt`` is the time since the previous fix (for the first, to the next one);
    ``τ = correlation_s = 0`` gives ones.
    """
    t = torch.as_tensor(t_s, dtype=torch.float64)
    tau = torch.as_tensor(correlation_s, dtype=torch.float64)
    if bool((tau < 0).any()):
        raise ValueError(f"correlation_s (filter.gnss_correlation_s), the GNSS error correlation time, must be "
                         f">= 0 s, got {float(tau)}")
    if t.shape[0] < 2 or float(tau) == 0.0:
        return torch.ones_like(t)
    dt = torch.diff(t)
    dt = torch.cat((dt[:1], dt))
    rho = torch.exp(-dt / tau)
    return (1.0 + rho) / (1.0 - rho)


# ---------------------------------------------------------------------------
# The GNSS updater: a fix as a filter event, and what follows a run of rejected fixes
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class GnssRecovery:
    """What follows a run of GNSS fixes the gate rejected (config ``filter.gnss_recovery``).

    A filter that has drifted further than its covariance admits rejects every later
    fix, and never comes back. After ``after_rejections`` consecutive rejections the
    filter's position is reset to the latest fix, with that fix's covariance; with
    ``velocity`` its velocity too, to the mean velocity of the rejected run's fixes
    (σ² = (R_first + R_last) / Δt² + (½ ``acceleration_sigma_mps2`` Δt)²). The
    augmented previous-frame position moves with the position, so the flow's relative
    pose is kept. The reset is a linear step ``x ↦ A x + b`` with noise ``Q`` in the
    filter's chain, so the smoother sees it as a jump and does not smooth across it.
    0 switches recovery off.

    The innovations also tell an inconsistent filter that still passes the gate: when
    the NIS of the last ``nis_window`` accepted fixes sums above the χ²(3 ``nis_window``)
    quantile ``nis_probability``, the filter is reset the same way (0, the default: off;
    on the simulated walk, whose urban-canyon GNSS errors are correlated over seconds,
    a window of 10 fired on a consistent filter and made ``ins_gnss`` worse). A reset
    adds ``acc_bias_sigma_mps2`` and ``gyro_bias_sigma_rps`` to the biases' σ, so a
    filter that drifted off on biases it trusted too much can learn them again.
    """

    after_rejections: int = 3
    velocity: bool = True
    acceleration_sigma_mps2: float = 1.0
    #: added to the IMU biases' σ at a reset: a filter that drifted off has biases it trusts too much
    acc_bias_sigma_mps2: float = 0.1
    gyro_bias_sigma_rps: float = 2e-3
    nis_window: int = 0
    nis_probability: float = 1 - 1e-6

    def __post_init__(self) -> None:
        for key in ("after_rejections", "nis_window"):
            value = getattr(self, key)
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise ValueError(f"filter.gnss_recovery.{key} must be an integer >= 0, got {value!r}")
        if not 0.0 < self.nis_probability < 1.0:
            raise ValueError(f"filter.gnss_recovery.nis_probability must be in (0, 1), got {self.nis_probability!r}")
        for key in ("acceleration_sigma_mps2", "acc_bias_sigma_mps2", "gyro_bias_sigma_rps"):
            if not getattr(self, key) >= 0.0:
                raise ValueError(f"filter.gnss_recovery.{key} must be >= 0, got {getattr(self, key)!r}")


def reset_matrices(mean: Tensor, fixes: list[tuple[float, Tensor, Tensor]], recovery: GnssRecovery
                   ) -> tuple[Tensor, Tensor, Tensor, bool]:
    """``(A (D, D), b (D,), Q (D, D), velocity_reset)`` of the reset to the last of
    ``fixes`` ``[(t_s, z (3,), R (3, 3)), ...]`` (:class:`GnssRecovery`) for a state ``mean``
    ``(D,)``: ``p := z`` and every cloned pose's position moves with it (``p_k := p_k - p + z``),
    so the relative poses the flow measures are kept."""
    dim = mean.shape[-1]
    A = torch.eye(dim, dtype=mean.dtype, device=mean.device)
    b = mean.new_zeros(dim)
    Q = mean.new_zeros(dim, dim)
    t_last, z, R = fixes[-1]
    positions = [p for p, _ in pose_slices(dim)]  # p, then each clone's
    A[STATE.p, STATE.p] = 0.0
    for clone in positions[1:]:
        A[clone, STATE.p] = -torch.eye(3, dtype=mean.dtype, device=mean.device)
    for rows in positions:
        b[rows] = z
        for cols in positions:
            Q[rows, cols] = R
    t_first, z_first, R_first = fixes[0]
    span = t_last - t_first
    with_velocity = recovery.velocity and span > 0
    if with_velocity:
        A[STATE.v, STATE.v] = 0.0
        b[STATE.v] = (z - z_first) / span
        Q[STATE.v, STATE.v] = (R + R_first) / span**2 + (0.5 * recovery.acceleration_sigma_mps2 * span) ** 2 * torch.eye(
            3, dtype=mean.dtype, device=mean.device)
    Q[STATE.b_a, STATE.b_a] = recovery.acc_bias_sigma_mps2**2 * torch.eye(3, dtype=mean.dtype, device=mean.device)
    Q[STATE.b_w, STATE.b_w] = recovery.gyro_bias_sigma_rps**2 * torch.eye(3, dtype=mean.dtype, device=mean.device)
    return A, b, Q, with_velocity


@dataclass(frozen=True)
class GnssFix:
    """A GNSS position fix ``z`` (local ENU, m) with noise ``R`` ``(3, 3)``.

    With ``heading`` enabled, a fix that finds the filter's yaw unknown is held back
    until the held fixes can set it (:mod:`flowins.measurements.gnss_heading`); the fixes that
    set it are not applied again as position updates.
    """

    time_s: float
    position_m: Tensor  # (3,)
    noise_cov: Tensor  # (3, 3)
    gate: Gate = field(default_factory=Gate)
    lever_arm_m: Tensor | None = None
    name: str = "GNSS fix"
    heading: HeadingAlignment | None = None
    recovery: GnssRecovery | None = None

    def apply(self, chain: ChainBuilder) -> None:
        if self.heading is not None and self.heading.enabled and self._held_for_heading(chain):
            return
        mean = chain.mean
        lever = None if self.lever_arm_m is None else self.lever_arm_m.to(mean)
        H = gnss_jacobian_analytic(mean, lever)
        predicted = mean[STATE.p] if lever is None else gnss_position(mean, lever)
        innovation = self.position_m.to(mean) - predicted
        update(chain, H=H.reshape(1, 3, -1), residual=innovation.reshape(1, 3),
               noise_cov=self.noise_cov.to(mean).reshape(1, 3, 3), gate=self.gate, kind="gnss", name=self.name)
        entry = chain.log[-1]
        self._recover(chain, rejected=entry["accepted"] < 0.5, nis=entry["nis"])

    def _recover(self, chain: ChainBuilder, *, rejected: bool, nis: float) -> None:
        """Reset after ``after_rejections`` consecutive rejections, or when the last
        ``nis_window`` fixes' NIS say the filter is inconsistent (:class:`GnssRecovery`)."""
        r = self.recovery
        if r is None:
            return
        fix = (self.time_s, self.position_m.to(chain.mean), self.noise_cov.to(chain.mean))
        run = chain.memory.setdefault("gnss_rejected", [])
        recent = chain.memory.setdefault("gnss_recent", [])
        run[:] = run + [fix] if rejected else []
        if not rejected:
            recent[:] = (recent + [(fix, nis)])[-r.nis_window:] if r.nis_window else []
        if r.after_rejections and len(run) >= r.after_rejections:
            self._reset(chain, run, why="rejected", rejected=len(run))
        elif r.nis_window and len(recent) == r.nis_window and sum(n for _, n in recent) > chi2_quantile(
                r.nis_probability, 3 * r.nis_window):
            self._reset(chain, [f for f, _ in recent], why="inconsistent",
                        mean_nis=sum(n for _, n in recent) / r.nis_window)
        else:
            return
        run.clear()
        recent.clear()

    def _reset(self, chain: ChainBuilder, fixes: list, *, why: str, **facts) -> None:
        offset = float(torch.linalg.vector_norm(fixes[-1][1] - chain.mean[STATE.p]).detach())
        A, b, Q, with_velocity = reset_matrices(chain.mean, fixes, self.recovery)
        chain.linear_predict(A, Q, b, kind="gnss_reset", name=self.name, why=why, offset_m=offset,
                             velocity=with_velocity, **facts)

    def _held_for_heading(self, chain: ChainBuilder) -> bool:
        """Hold this fix while the yaw is unknown; align when the held fixes allow (True: held).

        The filter's track is worth waiting for only while it drifts less than a fix is
        off: once its position variance (given its yaw) has grown since the first held
        fix by more than this fix's variance, it aligns with what it holds or, if that
        cannot set the heading, gives up and applies fixes as they come from then on.
        """
        memory = chain.memory
        if memory.get("heading") in ("known", "given up"):
            return False
        a = self.heading
        mean, cov = chain.mean, chain.cov
        held = memory.setdefault("heading_fixes", [])
        if not held:
            h = heading_jacobian(mean)
            if float((h @ cov @ h).detach()) <= a.unknown_yaw_sigma_rad**2:
                memory["heading"] = "known"
                return False
        xy = slice(STATE.p.start, STATE.p.start + 2)
        filter_var = torch.diagonal(heading_conditional_covariance(mean, cov, xy)).mean()
        fix_var = torch.diagonal(self.noise_cov.to(mean)[:2, :2]).mean()
        drift_var = (filter_var - held[0][2]).clamp_min(0.0) if held else filter_var.new_zeros(())
        held.append((mean[xy], self.position_m.to(mean)[:2], filter_var, filter_var + fix_var))
        drifted = bool((drift_var > fix_var).detach())
        fixes = torch.stack([f for _, f, _, _ in held])
        fit = None
        if len(held) >= a.min_fixes and float((fixes - fixes[0]).norm(dim=-1).max().detach()) >= a.baseline_m:
            fit = fit_heading(torch.stack([p for p, _, _, _ in held]), fixes, torch.stack([v for *_, v in held]),
                              outlier_probability=a.outlier_probability)
            if not float(fit.sigma_rad.detach()) <= a.max_sigma_rad:
                fit = None
        if fit is None:
            if drifted:
                # the fixes held so far are in the past and are not applied; this one and
                # every later one are, as they come
                memory["heading"] = "given up"
                chain.log.append({"t_s": chain.time_s, "kind": "heading", "name": self.name, "status": "given up",
                                  "fixes": len(held) - 1, "reason": "the track drifted more than a fix before the "
                                  "held fixes could set the heading; they are left out, this fix and the later ones "
                                  "are applied as they come"})
                return False
            chain.log.append({"t_s": chain.time_s, "kind": "gnss", "name": self.name, "accepted": 0.0,
                              "status": "held for heading"})
            return True
        # 1. condition on the filter's own heading; 2. rotate into the fixes' frame
        h = heading_jacobian(mean).reshape(1, 1, -1)
        sigma_c = torch.as_tensor(a.condition_sigma_rad, dtype=mean.dtype, device=mean.device)
        update(chain, H=h, residual=mean.new_zeros(1, 1), noise_cov=(sigma_c**2).reshape(1, 1, 1), likelihood=False)
        A, b = heading_transform(fit, dtype=mean.dtype, dim=mean.shape[-1])
        Q = heading_noise(A @ chain.mean + b, fit)
        record = fit_record(fit)
        chain.change_frame(A, Q, b, kind="heading", name=self.name, status="aligned",
                           **{k: record[k] for k in ("yaw_rad", "sigma_rad", "fixes", "outliers")}, fit=record)
        memory["heading"] = "known"
        chain.log.append({"t_s": chain.time_s, "kind": "gnss", "name": self.name, "accepted": 0.0,
                          "status": "set the heading"})
        return True


def gnss_fixes(
    t_s: Tensor,
    position_m: Tensor,
    noise_cov: Tensor,
    *,
    gate: Gate | None = None,
    lever_arm_m: Tensor | None = None,
    name: str = "GNSS",
    heading: HeadingAlignment | None = None,
    recovery: GnssRecovery | None = None,
) -> list[GnssFix]:
    """One :class:`GnssFix` per row of ``t_s (G,)``, ``position_m (G, 3)``, ``noise_cov (G, 3, 3)``."""
    gate = gate or Gate()
    return [
        GnssFix(float(t_s[i]), position_m[i], noise_cov[i], gate, lever_arm_m, f"{name} row {i}", heading, recovery)
        for i in range(t_s.shape[0])
    ]
