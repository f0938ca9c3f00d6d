"""Measurement events the filter runner applies at their times.

Each event is a small frozen dataclass with ``time_s``, ``name`` (used in error
messages and logs) and ``apply(chain)``; the maths lives in the pure functions of
:mod:`flowins.filter.ekf`, :mod:`flowins.filter.augmentation` and
:mod:`flowins.measurements`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from flowins.filter.augmentation import augment_pose, copy_matrices, forgetting_matrices
from flowins.filter.ekf import Gate, chi2_quantile, ekf_update
from flowins.filter.heading import (
    HeadingAlignment,
    fit_heading,
    heading_conditional_covariance,
    heading_jacobian,
    heading_noise,
    heading_transform,
)
from flowins.filter.runner import ChainBuilder

if TYPE_CHECKING:
    from flowins.flow.points import FlowPoints
    from flowins.measurements.flow import FlowCamera
from flowins.measurements.gnss import gnss_jacobian_analytic, gnss_position
from flowins.state import STATE


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
    """``(A (26, 26), b (26,), Q (26, 26), velocity_reset)`` of the reset to the last of
    ``fixes`` ``[(t_s, z (3,), R (3, 3)), ...]`` (:class:`GnssRecovery`)."""
    dim = mean.shape[-1]
    A = torch.eye(dim, dtype=mean.dtype)
    b = mean.new_zeros(dim)
    Q = mean.new_zeros(dim, dim)
    t_last, z, R = fixes[-1]
    A[STATE.p, STATE.p] = 0.0
    A[STATE.p_prev, STATE.p] = -torch.eye(3, dtype=mean.dtype)
    for rows in (STATE.p, STATE.p_prev):
        b[rows] = z
        for cols in (STATE.p, STATE.p_prev):
            Q[rows, cols] = R
    t_first, z_first, R_first = fixes[0]
    span = t_last - t_first
    with_velocity = recovery.velocity and span > 0
    if with_velocity:
        A[STATE.v, STATE.v] = 0.0
        b[STATE.v] = (z - z_first) / span
        Q[STATE.v, STATE.v] = (R + R_first) / span**2 + (0.5 * recovery.acceleration_sigma_mps2 * span) ** 2 * torch.eye(
            3, dtype=mean.dtype)
    Q[STATE.b_a, STATE.b_a] = recovery.acc_bias_sigma_mps2**2 * torch.eye(3, dtype=mean.dtype)
    Q[STATE.b_w, STATE.b_w] = recovery.gyro_bias_sigma_rps**2 * torch.eye(3, dtype=mean.dtype)
    return A, b, Q, with_velocity


@dataclass(frozen=True)
class GnssFix:
    """A GNSS position fix ``z`` (local ENU, m) with noise ``R`` ``(3, 3)``.

    With ``heading`` enabled, a fix that finds the filter's yaw unknown is held back
    until the held fixes can set it (:mod:`flowins.filter.heading`); the fixes that
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
        mean, cov = chain.mean, chain.cov
        lever = None if self.lever_arm_m is None else self.lever_arm_m.to(mean)
        H = gnss_jacobian_analytic(mean, lever)
        predicted = mean[STATE.p] if lever is None else gnss_position(mean, lever)
        innovation = self.position_m.to(mean) - predicted
        result = ekf_update(
            mean,
            cov,
            innovation=innovation.reshape(1, 3),
            H=H.reshape(1, 3, -1),
            noise_cov=self.noise_cov.to(mean).reshape(1, 3, 3),
            gate=self.gate,
        )
        accepted = float(result.weight[0].detach())
        nis = float(result.nis[0].detach())
        chain.update(result, kind="gnss", name=self.name, nis=nis, accepted=accepted)
        self._recover(chain, rejected=accepted < 0.5, nis=nis)

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
        sigma_c = torch.as_tensor(a.condition_sigma_rad, dtype=mean.dtype)
        chain.update(ekf_update(mean, cov, innovation=mean.new_zeros(1, 1), H=h, noise_cov=(sigma_c**2).reshape(1, 1, 1)))
        A, b = heading_transform(fit, dtype=mean.dtype)
        Q = heading_noise(A @ chain.mean + b, fit)
        chain.change_frame(A, Q, b, kind="heading", name=self.name, status="aligned", yaw_rad=float(fit.yaw_rad.detach()),
                           sigma_rad=float(fit.sigma_rad.detach()), fixes=int(fit.used.sum()),
                           outliers=int((~fit.used).sum()))
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


@dataclass(frozen=True)
class ZeroVelocity:
    """A zero-velocity pseudo-measurement ``0 = v + n``, ``n ~ N(0, σ² I₃)`` (a still device)."""

    time_s: float
    sigma_mps: float | Tensor = 0.01
    name: str = "zero velocity"

    def apply(self, chain: ChainBuilder) -> None:
        mean, cov = chain.mean, chain.cov
        H = torch.zeros(1, 3, mean.shape[-1], dtype=mean.dtype, device=mean.device)
        H[0, :, STATE.v] = torch.eye(3, dtype=mean.dtype, device=mean.device)
        sigma = torch.as_tensor(self.sigma_mps, dtype=mean.dtype, device=mean.device)
        result = ekf_update(mean, cov, innovation=-mean[STATE.v].reshape(1, 3), H=H,
                            noise_cov=(sigma**2 * torch.eye(3, dtype=mean.dtype, device=mean.device)).reshape(1, 3, 3))
        chain.update(result, kind="zero_velocity", name=self.name)


@dataclass(frozen=True)
class PoseAugmentation:
    """Pose forgetting then pose augmentation at ``time_s`` (the per-frame step of the paper).

    ``mode="paper"`` applies ``A⋆, Q⋆`` and the ``H⋆`` update literally;
    ``mode="limit"`` applies their ``σ → ∞`` limit (:func:`copy_pose`) as one
    linear step.
    """

    time_s: float
    sigma_p0: float | Tensor = 1e3
    sigma_q0: float | Tensor = 1e2
    nugget_var: float | Tensor = 1e-9
    mode: str = "paper"
    name: str = "pose augmentation"

    def __post_init__(self) -> None:
        if self.mode not in ("paper", "limit"):
            raise ValueError(f"PoseAugmentation.mode must be 'paper' or 'limit', got {self.mode!r}")

    def apply(self, chain: ChainBuilder) -> None:
        mean = chain.mean
        if self.mode == "paper":
            A, Q = forgetting_matrices(self.sigma_p0, self.sigma_q0, dtype=mean.dtype, device=mean.device)
            chain.linear_predict(A, Q)
            chain.update(augment_pose(chain.mean, chain.cov, nugget_var=self.nugget_var))
        else:
            # one linear step, recorded as such so the smoother sees its transition
            T, Q = copy_matrices(self.nugget_var, dtype=mean.dtype, device=mean.device)
            chain.linear_predict(T, Q)


@dataclass(frozen=True)
class FlowRecovery:
    """What follows frames whose flow the filter rejects (config ``filter.flow.recovery``).

    A filter whose velocity or attitude has gone wrong finds most flow points
    outside its gate, and the gate keeps out the very measurements that would correct
    it. After ``after_frames`` consecutive frames with at least ``min_valid`` valid
    points of which at most ``max_accepted`` (a fraction) pass the gate, the velocity's
    σ is raised by ``velocity_sigma_mps`` and the gyroscope bias's by
    ``gyro_bias_sigma_rps`` (a logged ``flow_inflate`` step), so that the next frames can
    pull the filter back. 0 frames switches it off.
    """

    after_frames: int = 5
    max_accepted: float = 0.5
    min_valid: int = 8
    velocity_sigma_mps: float = 0.5
    gyro_bias_sigma_rps: float = 2e-3

    def __post_init__(self) -> None:
        for key in ("after_frames", "min_valid"):
            value = getattr(self, key)
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise ValueError(f"filter.flow.recovery.{key} must be an integer >= 0, got {value!r}")
        if not 0.0 <= self.max_accepted < 1.0:
            raise ValueError(f"filter.flow.recovery.max_accepted must be in [0, 1), got {self.max_accepted!r}")
        for key in ("velocity_sigma_mps", "gyro_bias_sigma_rps"):
            if not getattr(self, key) >= 0.0:
                raise ValueError(f"filter.flow.recovery.{key} must be >= 0, got {getattr(self, key)!r}")

    def gated(self, valid: int, accepted: float) -> bool:
        """Whether a frame with ``valid`` points of which ``accepted`` passed counts as gated."""
        return valid >= max(self.min_valid, 1) and accepted <= self.max_accepted * valid

    def inflation(self, mean: Tensor) -> Tensor:
        """``Q (D, D)``: the covariance added to the state ``mean`` ``(D,)``."""
        Q = mean.new_zeros(mean.shape[-1], mean.shape[-1])
        Q[STATE.v, STATE.v] = self.velocity_sigma_mps**2 * torch.eye(3, dtype=mean.dtype)
        Q[STATE.b_w, STATE.b_w] = self.gyro_bias_sigma_rps**2 * torch.eye(3, dtype=mean.dtype)
        return Q


@dataclass(frozen=True)
class FlowUpdate:
    """How a frame's flow points update the filter (every field has a config entry).

    Attributes:
        n_points: points used per frame, chosen at the current state by ``selection``
            (:func:`flowins.measurements.selection.select_points`); None: all.
        selection: ``"parallax"`` | ``"sigma"`` | ``"grid"``; ``cell_px``: spreading cell.
        sigma_scale, sigma_floor_px: the flow noise used is
            ``σ = sqrt((sigma_scale σ_flow)² + sigma_floor_px²)`` per component.
        min_parallax_sigma: leave out points whose rotation-compensated parallax is
            below this many σ (0: keep all).
        parallax_inflation: inflate each point's noise by ``p² / (p² - σ²)`` (``p`` the
            measured parallax): the depth, and with it ``H_x``, is estimated from the same
            noisy flow, and without the correction a low-parallax point claims
            ``(p² + σ²) / p²`` times the information it has (errors in variables).
        gate: χ² gate on each point's scalar innovation (moving objects, bad flow).
        sequential: the paper's point-by-point update instead of one stacked update.
        iterations: relinearisations of the measurement (1: EKF, > 1: iterated EKF).
        augmentation: the pose forgetting + augmentation after the update.
        recovery: what follows frames whose flow is nearly all gated (:class:`FlowRecovery`).
    """

    n_points: int | None = 256
    selection: str = "parallax"
    cell_px: float = 80.0
    sigma_scale: float | Tensor = 1.0
    sigma_floor_px: float | Tensor = 0.25
    min_parallax_sigma: float = 1.0
    parallax_inflation: bool = True
    gate: Gate = field(default_factory=Gate)
    sequential: bool = False
    iterations: int = 1
    augmentation_mode: str = "limit"
    sigma_p0: float | Tensor = 1e3
    sigma_q0: float | Tensor = 1e2
    recovery: FlowRecovery = field(default_factory=FlowRecovery)

    def __post_init__(self) -> None:
        if self.n_points is not None and self.n_points < 1:
            raise ValueError(f"FlowUpdate.n_points must be >= 1 or None, got {self.n_points}")
        if self.iterations < 1:
            raise ValueError(f"FlowUpdate.iterations must be >= 1, got {self.iterations}")
        if self.min_parallax_sigma < 0:
            raise ValueError(f"FlowUpdate.min_parallax_sigma must be >= 0, got {self.min_parallax_sigma}")


#: every point used, no inflation, no parallax limit, no gate: the paper's update as written
PAPER_FLOW_UPDATE = FlowUpdate(n_points=None, min_parallax_sigma=0.0, parallax_inflation=False,
                               sigma_floor_px=0.0, gate=Gate(mode="off"))


@dataclass(frozen=True)
class FlowFrame:
    """A camera frame: flow updates against the augmented previous frame's pose, then
    pose forgetting and augmentation (the paper's per-frame order).

    ``points``: the flow points from the previous frame used by the filter to this
    one (:class:`~flowins.flow.points.FlowPoints`, ``M`` of them; ``M = 0`` for the
    first frame, which only augments). The update uses the epipolar component of each
    point (:func:`flowins.measurements.flow.epipolar_update`); degenerate points are
    skipped and counted in the log.
    """

    time_s: float
    points: FlowPoints
    camera: FlowCamera
    update: FlowUpdate = field(default_factory=FlowUpdate)
    name: str = "flow frame"
    #: ``"analytic"`` | ``"autodiff"``: how ``H_x``, ``H_r`` are computed
    #: (:func:`flowins.measurements.flow.flow_measurements`)
    jacobians: str = "analytic"

    def noise_sigma(self, sigma_px: Tensor) -> Tensor:
        u = self.update
        scale = torch.as_tensor(u.sigma_scale, dtype=sigma_px.dtype)
        floor = torch.as_tensor(u.sigma_floor_px, dtype=sigma_px.dtype)
        return torch.sqrt((scale * sigma_px) ** 2 + floor**2)

    def apply(self, chain: ChainBuilder) -> None:
        from flowins.measurements.flow import epipolar_update, flow_measurements
        from flowins.measurements.selection import select_points

        u = self.update
        points = self.points
        M = len(points)
        if M:
            mean, cov = chain.mean, chain.cov
            points = type(points)(points.uv1_px.to(mean), points.flow_px.to(mean), self.noise_sigma(points.sigma_px.to(mean)))
            if u.n_points is not None and M > u.n_points:
                keep = select_points(mean, points, self.camera.K, self.camera.R_ci, n_points=u.n_points,
                                     method=u.selection, cell_px=u.cell_px)
                points = points.take(keep)
            sigma = points.sigma_px
            min_parallax = u.min_parallax_sigma * torch.linalg.vector_norm(sigma, dim=-1) / 2**0.5
            x_i, result = mean, None
            for _ in range(u.iterations):
                m = flow_measurements(x_i, points.flow_px, points.uv1_px, self.camera, min_parallax_px=min_parallax,
                                      jacobians=self.jacobians)
                if not bool(m.valid.any()):
                    break
                upd = epipolar_update(m, sigma, parallax_inflation=u.parallax_inflation)
                # iterated EKF: linearised at x_i, applied to the prior (mean, cov)
                shift = (upd.H @ (mean - x_i).unsqueeze(-1)).squeeze(-1)
                result = ekf_update(mean, cov, innovation=upd.innovation - shift, H=upd.H,
                                    noise_cov=upd.noise_cov, gate=u.gate, sequential=u.sequential)
                x_i = result.mean
            info = dict(kind="flow", name=self.name, candidates=M, points=len(points), valid=int(m.valid.sum()),
                        degenerate=m.n_degenerate, behind=m.n_behind, low_parallax=m.n_low_parallax)
            accepted = 0.0 if result is None else float(result.weight.detach().sum())
            if result is not None:
                chain.update(result, accepted=accepted, **info)
            else:
                chain.log.append({"t_s": chain.time_s, "accepted": 0.0, **info})
            self._recover(chain, valid=info["valid"], accepted=accepted)
        PoseAugmentation(self.time_s, u.sigma_p0, u.sigma_q0, mode=u.augmentation_mode).apply(chain)

    def _recover(self, chain: ChainBuilder, *, valid: int, accepted: float) -> None:
        """Count consecutive gated frames; after ``recovery.after_frames`` inflate (:class:`FlowRecovery`)."""
        r = self.update.recovery
        if r.after_frames == 0:
            return
        gated = chain.memory.get("flow_gated", 0) + 1 if r.gated(valid, accepted) else 0
        chain.memory["flow_gated"] = gated
        if gated >= r.after_frames:
            eye = torch.eye(chain.mean.shape[-1], dtype=chain.mean.dtype)
            chain.linear_predict(eye, r.inflation(chain.mean), kind="flow_inflate", name=self.name, frames=gated)
            chain.memory["flow_gated"] = 0
