"""How the filter starts on a recording: still, moving, or from the ground truth (``filter.init``).

``auto`` (the default) looks at the recording: a still start of at least
``still.min_s`` (:func:`~flowins.ins.initialization.still_interval`, which the GNSS
fixes in it must not contradict) starts ``still``; otherwise enough GNSS fixes at the
start allow ``moving``; otherwise it is an error that names the three modes.
``groundtruth`` is chosen only by name. The choice, why it was made and what it set
come back as a :class:`Start`, which the evaluation prints and writes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import torch
from torch import Tensor

from flowins.config import check_fields
from flowins.data.streams import ImuStream, PoseStream
from flowins.geometry.procrustes import rotation_2d
from flowins.measurements.gnss_heading import fit_heading
from flowins.geometry import quaternion as quat
from flowins.ins.initialization import (
    InitialUncertainty,
    StillSettings,
    initial_covariance,
    kinematic_fit,
    moving_prior,
    still_interval,
    still_prior,
)
from flowins.state import STATE, make_state


@dataclass(frozen=True)
class MovingSettings:
    """A start in motion (config ``filter.init.moving``).

    Attributes:
        window_s: roll and pitch from the mean specific force over the first ``window_s``.
        fit_s: position, velocity and acceleration from the GNSS fixes of the first
            ``fit_s`` seconds (:func:`~flowins.ins.initialization.kinematic_fit`).
        acceleration_sigma_mps2: prior σ of the acceleration in that fit (and, without
            GNSS, of the acceleration the tilt cannot tell from gravity).
        forward_axis: the body axis along the motion: ``auto`` (the camera's optical axis
            when the recording has a calibration, else ``x``), ``camera``, ``x``, ``-x``, ...
        heading_sigma_rad: σ of the angle between that axis and the course over ground.
        min_speed_mps: slower, the course sets no heading (the yaw starts free).
        velocity_mps: without GNSS: the initial velocity (east, north, up), m/s.
        velocity_sigma_mps: ... and its σ per axis.
        heading_rad: the forward axis's heading (counter-clockwise from east); None:
            the course of ``velocity_mps`` (with GNSS: of the fixes).
        max_wait_s: with fewer than two fixes in the first ``fit_s``, the start waits: it
            starts at the first fix, fitted to the fixes of the ``fit_s`` after it (or up to
            the second fix, if that comes later), when the first fix comes within this of the
            recording's start and the second within this of the first (what the IMU is
            trusted to bridge); the rows before it are not filtered.
    """

    window_s: float = 1.0
    fit_s: float = 10.0
    acceleration_sigma_mps2: float = 1.0
    forward_axis: str = "auto"
    heading_sigma_rad: float = 0.2
    min_speed_mps: float = 1.0
    velocity_mps: tuple[float, float, float] | None = None
    velocity_sigma_mps: float = 1.0
    heading_rad: float | None = None
    max_wait_s: float = 60.0


@dataclass(frozen=True)
class GroundtruthSettings:
    """A start from the recording's ground truth (config ``filter.init.groundtruth``)."""

    position_sigma_m: float = 0.01
    velocity_sigma_mps: float = 0.05
    attitude_sigma_rad: float = 0.01
    #: the velocity is the mean over this much of the ground truth after the start
    velocity_window_s: float = 0.2


@dataclass(frozen=True)
class StartSettings:
    """``filter.init``: ``mode`` (auto | still | moving | groundtruth) and each mode's settings."""

    mode: Literal["auto", "still", "moving", "groundtruth"] = "auto"
    still: StillSettings = field(default_factory=StillSettings)
    moving: MovingSettings = field(default_factory=MovingSettings)
    groundtruth: GroundtruthSettings = field(default_factory=GroundtruthSettings)
    #: the still start's yaw (it is free: σ = InitialUncertainty.yaw_rad)
    yaw_rad: float = 0.0

    def __post_init__(self) -> None:
        check_fields(self)


@dataclass
class Start:
    """The filter's start: its prior at IMU row ``index`` and how it was found."""

    mode: str
    index: int
    t_s: float
    mean: Tensor  # (26,)
    cov: Tensor  # (26, 26)
    #: why this mode (auto) or that it was asked for
    reason: str
    #: zero-velocity update times (a still start)
    zupt_times_s: list[float] = field(default_factory=list)
    facts: dict[str, Any] = field(default_factory=dict)

    def describe(self) -> str:
        """One line: the mode, when it starts and what it set."""
        f = self.facts
        if self.mode == "still":
            what = f"still for {f['still_s']:.2f} s (to {f['still_end_s']:.2f} s; {f['still_ends']})"
        elif self.mode == "moving":
            heading = f.get("heading") or f"heading {f['heading_deg']:.0f}° ± {f['heading_sigma_deg']:.0f}°"
            what = f"moving at {f['speed_mps']:.1f} m/s, {heading}, from {f['source']}"
        else:
            what = f"from the ground truth at {self.t_s:.2f} s ({f['source']})"
        return f"start: {self.mode}, {what}; {self.reason}"

    def as_dict(self) -> dict[str, Any]:
        return {"mode": self.mode, "t_s": self.t_s, "imu_row": self.index, "reason": self.reason, **self.facts}


def _fit_from_fixes(fix_t_s: Tensor, fix_enu_m: Tensor, fix_sigma_m: Tensor, t0_s: float, settings: MovingSettings):
    window = (fix_t_s >= t0_s) & (fix_t_s <= t0_s + settings.fit_s)
    if int(window.sum()) < 2:
        return None
    return kinematic_fit(fix_t_s[window], fix_enu_m[window], fix_sigma_m[window], t0_s=t0_s,
                         acceleration_sigma_mps2=settings.acceleration_sigma_mps2)


def _moving(imu: ImuStream, fit, settings: MovingSettings, forward_b: Tensor, uncertainty: InitialUncertainty,
            gravity_mps2: float, *, index: int = 0, reason: str, source: str) -> Start:
    t0 = float(imu.t_s[index])
    rows = (imu.t_s >= t0) & (imu.t_s <= t0 + settings.window_s)
    if fit is None:
        if settings.velocity_mps is None:
            raise ValueError("filter.init.mode=moving without GNSS fixes at the start (2 in the first "
                             f"filter.init.moving.fit_s={settings.fit_s} s, or the first two within "
                             f"filter.init.moving.max_wait_s={settings.max_wait_s} s) needs the initial velocity: "
                             "filter.init.moving.velocity_mps=[east,north,up] (m/s) and, unless the course of that "
                             "velocity is the heading of the forward axis, filter.init.moving.heading_rad")
        var = torch.full((3,), float(settings.velocity_sigma_mps) ** 2, dtype=torch.float64)
        acc_var = torch.full((3,), float(settings.acceleration_sigma_mps2) ** 2, dtype=torch.float64)
        p, v, a = torch.zeros(3, dtype=torch.float64), torch.tensor(settings.velocity_mps, dtype=torch.float64), None
        p_var = torch.full((3,), float(uncertainty.position_m) ** 2, dtype=torch.float64)
        source = "filter.init.moving.velocity_mps"
    else:
        p, v, a, p_var, var, acc_var = (fit.position_m, fit.velocity_mps, fit.acceleration_mps2, fit.position_var,
                                        fit.velocity_var, fit.acceleration_var)
    mean, cov, facts = moving_prior(
        acc_mps2=imu.acc_mps2[rows], position_m=p, velocity_mps=v,
        acceleration_mps2=torch.zeros(3, dtype=torch.float64) if a is None else a, forward_b=forward_b,
        position_var=p_var, velocity_var=var, acceleration_var=acc_var, heading_sigma_rad=settings.heading_sigma_rad,
        min_speed_mps=settings.min_speed_mps, gravity_mps2=gravity_mps2, uncertainty=uncertainty,
        heading_rad=settings.heading_rad)
    facts["source"] = source
    return Start("moving", index, t0, mean, cov, reason, facts=facts)


def _groundtruth(imu: ImuStream, truth: PoseStream | None, settings: GroundtruthSettings, moving: MovingSettings,
                 forward_b: Tensor, uncertainty: InitialUncertainty, gravity_mps2: float,
                 fixes: tuple[Tensor, Tensor, Tensor] | None) -> Start:
    if truth is None:
        raise ValueError("filter.init.mode=groundtruth: the recording has no ground truth; use "
                         "filter.init.mode=auto, still or moving")
    t_gt, p_gt = truth.t_s, truth.pos_m
    later = torch.nonzero(imu.t_s >= t_gt[0])
    if not later.numel() or float(imu.t_s[int(later[0, 0])]) + settings.velocity_window_s > float(t_gt[-1]):
        raise ValueError(f"filter.init.mode=groundtruth: the ground truth ({truth.name}, "
                         f"{float(t_gt[0]):.3f}..{float(t_gt[-1]):.3f} s) does not cover a start inside the IMU span")
    index = int(later[0, 0])
    t0 = float(imu.t_s[index])

    def at(t: float) -> Tensor:
        k = int(torch.searchsorted(t_gt, torch.tensor(t, dtype=torch.float64)).clamp(1, len(t_gt) - 1))
        w = (t - float(t_gt[k - 1])) / float(t_gt[k] - t_gt[k - 1])
        return (1 - w) * p_gt[k - 1] + w * p_gt[k]

    # the ground truth's frame, or (with GNSS) a fit of it onto the fixes' ENU frame
    R3, shift, source = torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), truth.name
    if fixes is not None:
        f_t, f_enu, f_sigma = fixes
        inside = (f_t >= t_gt[0]) & (f_t <= t_gt[-1])
        if int(inside.sum()) < 3:
            raise ValueError("filter.init.mode=groundtruth with GNSS: fewer than 3 fixes lie inside the ground truth's "
                             "span, so its frame can't be tied to the fixes' (east, north, up)")
        gt_at = torch.stack([at(float(t)) for t in f_t[inside]])
        fit = fit_heading(gt_at[:, :2], f_enu[inside, :2], 2 * f_sigma[inside, 0] ** 2)
        R3 = torch.block_diag(rotation_2d(fit.yaw_rad), torch.ones(1, 1, dtype=torch.float64))
        shift = torch.cat((fit.centre_fix_m - rotation_2d(fit.yaw_rad) @ fit.centre_filter_m,
                           (f_enu[inside, 2] - gt_at[:, 2]).mean().reshape(1)))
        source += f" tied to {int(fit.used.sum())} GNSS fixes (rotation {math.degrees(float(fit.yaw_rad)):.1f}°)"
    p0 = R3 @ at(t0) + shift
    v0 = R3 @ (at(t0 + settings.velocity_window_s) - at(t0)) / settings.velocity_window_s
    facts = {"source": source}
    if truth.quat_wxyz is None:
        # positions only: the attitude as for a moving start, from the ground truth's motion
        later_t = t_gt[(t_gt >= t0) & (t_gt <= t0 + moving.fit_s)]
        pos = torch.stack([R3 @ at(float(t)) + shift for t in later_t])
        sigma = torch.full_like(pos, settings.position_sigma_m)
        start = _moving(imu, kinematic_fit(later_t, pos, sigma, t0_s=t0,
                                           acceleration_sigma_mps2=moving.acceleration_sigma_mps2),
                        moving, forward_b, uncertainty, gravity_mps2, index=index, reason="", source=source)
        start.mode, start.facts["source"] = "groundtruth", source + " (positions only: the attitude from its motion)"
        return start
    k = int(torch.argmin((t_gt - t0).abs()))
    yaw_q = quat.from_rotation_vector(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
                                      * torch.atan2(R3[1, 0], R3[0, 0]))
    q = quat.multiply(yaw_q, quat.normalize(truth.quat_wxyz[k]))
    mean = make_state(p=p0, v=v0, q=q)
    sig = torch.tensor([settings.attitude_sigma_rad] * 3, dtype=torch.float64)
    cov = initial_covariance(q, uncertainty, velocity_var=torch.full((3,), settings.velocity_sigma_mps**2),
                             position_var=torch.full((3,), settings.position_sigma_m**2), roll_pitch_yaw_std=sig)
    return Start("groundtruth", index, t0, mean, cov, "", facts=facts)


def _still_from(start: Start, imu: ImuStream, settings: StillSettings, gravity_mps2: float) -> Start:
    """``start`` (from the ground truth) with what a still start adds when the IMU is still
    from its row for at least ``settings.min_s``: the gyroscope bias from the mean rate, zero
    velocity, and the zero-velocity updates over the still interval. The pose stays the
    ground truth's."""
    rows = slice(start.index, None)
    still = still_interval(imu.t_s[rows], imu.acc_mps2[rows], imu.gyro_rps[rows], settings, gravity_mps2=gravity_mps2)
    if still.end >= imu.t_s.shape[0] - start.index or still.duration_s < settings.min_s:
        return start  # not still (or still throughout: nothing to tell the bias from a tilt by)
    mean = start.mean.clone()
    mean[STATE.v] = 0.0
    mean[STATE.b_w] = imu.gyro_rps[start.index : start.index + still.end].mean(dim=0)
    zupt = []
    if settings.zupt_hz > 0:
        zupt = torch.arange(start.t_s, still.end_s + 1e-9, 1.0 / settings.zupt_hz, dtype=torch.float64).tolist()
    facts = {**start.facts, "still_s": still.duration_s, "still_end_s": still.end_s}
    facts["source"] = (f"{facts['source']}; still for {still.duration_s:.2f} s: gyroscope bias from the mean rate, "
                       "zero-velocity updates")
    return Start(start.mode, start.index, start.t_s, mean, start.cov, start.reason, zupt, facts)


def choose_start(
    imu: ImuStream,
    *,
    settings: StartSettings = StartSettings(),
    fixes: tuple[Tensor, Tensor, Tensor] | None = None,
    truth: PoseStream | None = None,
    forward_b: Tensor | None = None,
    uncertainty: InitialUncertainty = InitialUncertainty(),
    gravity_mps2: float = 9.80665,
    fused: bool = True,
) -> Start:
    """The filter's start on ``imu`` (module docstring).

    Args:
        fixes: GNSS ``(t_s (G,), enu_m (G, 3), sigma_m (G, 3))`` in the filter's frame.
        fused: whether the filter fuses ``fixes``; if not, they serve the start only
            (a still start then keeps the prior position, and the reason says so).
        truth: the recording's ground truth (``groundtruth`` mode only).
        forward_b: the body axis along the motion (:func:`~flowins.ins.initialization.forward_axis`).

    Raises:
        ValueError: the mode asked for does not fit the recording; the message says why
            and names the config keys and the other modes.
    """
    forward_b = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64) if forward_b is None else forward_b
    mode = settings.mode
    if mode == "groundtruth":
        start = _groundtruth(imu, truth, settings.groundtruth, settings.moving, forward_b, uncertainty, gravity_mps2,
                             fixes)
        start.reason = "filter.init.mode=groundtruth: the ground truth's pose and velocity, as VIO evaluations start"
        return _still_from(start, imu, settings.still, gravity_mps2)
    t0 = float(imu.t_s[0])
    fit = None if fixes is None else _fit_from_fixes(*fixes, t0, settings.moving)
    if mode in ("auto", "still"):
        still = still_interval(imu.t_s, imu.acc_mps2, imu.gyro_rps, settings.still, gravity_mps2=gravity_mps2)
        long_enough = still.duration_s >= settings.still.min_s
        contradicted = None
        if long_enough and fixes is not None:
            inside = (fixes[0] >= t0) & (fixes[0] <= still.end_s)
            if int(inside.sum()) >= 2:
                moved = kinematic_fit(fixes[0][inside], fixes[1][inside], fixes[2][inside], t0_s=t0,
                                      acceleration_sigma_mps2=1e-6)
                speed = float(torch.linalg.vector_norm(moved.velocity_mps[:2]))
                sigma = float(moved.velocity_var[:2].max().sqrt())
                if speed > max(0.5, 4.0 * sigma):
                    contradicted = (f"the IMU looks still for {still.duration_s:.2f} s but the {int(inside.sum())} GNSS "
                                    f"fixes in it move at {speed:.1f} m/s")
        still_to_end = still.end >= imu.t_s.shape[0]
        too_short = (f"the recording lasts {imu.duration_s:.2f} s, shorter than filter.init.still.min_s="
                     f"{settings.still.min_s} (it is still throughout)" if still_to_end else
                     f"still for {still.duration_s:.2f} s only (< filter.init.still.min_s={settings.still.min_s}; "
                     f"motion at {still.reason})")
        if mode == "still" or (long_enough and contradicted is None):
            if not long_enough:
                raise ValueError(
                    f"filter.init.mode=still: {too_short}. Lower filter.init.still.min_s"
                    + ("" if still_to_end else ", raise the still thresholds (filter.init.still.max_acc_mps2, "
                       "max_gyro_rps)")
                    + ", or use filter.init.mode=moving (GNSS or filter.init.moving.velocity_mps) or groundtruth")
            rows = slice(0, still.end)
            position = None if fixes is None or not fused else fixes[1][0]
            u = uncertainty if position is None else InitialUncertainty(
                **{**uncertainty.__dict__, "position_m": float(fixes[2][0].max())})
            mean, cov = still_prior(imu.acc_mps2[rows], imu.gyro_rps[rows], yaw_rad=settings.yaw_rad,
                                    position_m=position, uncertainty=u)
            zupt = []
            if settings.still.zupt_hz > 0:
                zupt = torch.arange(t0, still.end_s + 1e-9, 1.0 / settings.still.zupt_hz, dtype=torch.float64).tolist()
            reason = ("filter.init.mode=still" if mode == "still" else
                      f"auto: still for {still.duration_s:.2f} s >= filter.init.still.min_s={settings.still.min_s}")
            facts = {"still_s": still.duration_s, "still_end_s": still.end_s, "still_ends": still.reason}
            return Start("still", 0, t0, mean, cov, reason, zupt, facts)
        why_not_still = contradicted or too_short
        if fit is None and (late := _waiting_start(imu, fixes, settings.moving, forward_b, uncertainty, gravity_mps2,
                                                   reason=f"auto: not still ({why_not_still})", fused=fused)):
            return late
        if fit is None:
            raise ValueError(
                f"filter.init.mode=auto: the recording does not start still ({why_not_still}) and has fewer than 2 "
                f"GNSS fixes in its first filter.init.moving.fit_s={settings.moving.fit_s} s to start moving from. "
                "Choose filter.init.mode=still (with filter.init.still.* thresholds that fit the recording), "
                "filter.init.mode=moving with filter.init.moving.velocity_mps=[e,n,u] and heading_rad, or "
                "filter.init.mode=groundtruth")
        return _moving(imu, fit, settings.moving, forward_b, uncertainty, gravity_mps2,
                       reason=f"auto: not still ({why_not_still})", source=_fit_source(fit, fused))
    # mode == "moving"
    if fit is None and (late := _waiting_start(imu, fixes, settings.moving, forward_b, uncertainty, gravity_mps2,
                                               reason="filter.init.mode=moving", fused=fused)):
        return late
    return _moving(imu, fit, settings.moving, forward_b, uncertainty, gravity_mps2, reason="filter.init.mode=moving",
                   source="" if fit is None else _fit_source(fit, fused))


def _waiting_start(imu: ImuStream, fixes: tuple[Tensor, Tensor, Tensor] | None, settings: MovingSettings,
                   forward_b: Tensor, uncertainty: InitialUncertainty, gravity_mps2: float, *, reason: str,
                   fused: bool) -> Start | None:
    """The moving start that waits for its fixes (:func:`_waiting_fit`), saying how long it
    waited; None without fixes, or when they come too late or too far apart."""
    waiting = None if fixes is None else _waiting_fit(imu, fixes, settings)
    if waiting is None:
        return None
    row, fit, waited_s = waiting
    start = _moving(imu, fit, settings, forward_b, uncertainty, gravity_mps2, index=row, reason=reason,
                    source=_fit_source(fit, fused))
    start.facts["waited_s"] = waited_s
    start.reason += (f"; waited {waited_s:.1f} s for two GNSS fixes (fewer than 2 in the first "
                     f"filter.init.moving.fit_s={settings.fit_s} s; the rows before are not filtered)")
    return start


def _waiting_fit(imu: ImuStream, fixes: tuple[Tensor, Tensor, Tensor], settings: MovingSettings):
    """``(row, fit, waited_s)``: the kinematic fit of a start that waits for its fixes (the
    ``max_wait_s`` of :class:`MovingSettings`), or None when the fixes come too late or too
    far apart."""
    f_t, f_enu, f_sigma = fixes
    t0 = float(imu.t_s[0])
    if f_t.shape[0] < 2:
        return None
    first, second = float(f_t[0]), float(f_t[1])
    if first - t0 > settings.max_wait_s or second - first > settings.max_wait_s:
        return None
    row = int(torch.searchsorted(imu.t_s, torch.tensor(first, dtype=imu.t_s.dtype)))
    if row >= imu.t_s.shape[0]:
        return None
    t_row = float(imu.t_s[row])
    window = (f_t >= first) & (f_t <= max(first + settings.fit_s, second) + 1e-9)
    fit = kinematic_fit(f_t[window], f_enu[window], f_sigma[window], t0_s=t_row,
                        acceleration_sigma_mps2=settings.acceleration_sigma_mps2)
    return row, fit, t_row - t0


def _fit_source(fit, fused: bool) -> str:
    return f"{fit.fixes} GNSS fixes over {fit.span_s:.1f} s" + ("" if fused else " (for the start only)")
