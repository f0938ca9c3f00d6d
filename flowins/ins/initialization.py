"""The filter's prior: from a still start, while moving, or from a reference pose.

*Still* (the paper's device is held still for about 5 s): over the still window the
mean specific force ``f̄`` points up in the body frame, which fixes roll and pitch;
the mean angular rate is the gyroscope bias (Earth's rotation, 7.3e-5 rad/s, is below
consumer-grade noise and ignored); yaw is not observable and is set to ``yaw_rad``
with a large variance ("yaw free"). :func:`still_interval` finds the window.

*Moving*: position, velocity and acceleration from a kinematic fit of the first
position fixes (:func:`kinematic_fit`); the attitude from two vector pairs
(:func:`two_vector_attitude`): the mean specific force is ``Rᵀ(a + g e_z)``, and
the body's forward axis points along the course over ground.

*Reference*: a given pose and velocity (a ground truth) with small σ.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from flowins.config import bounded, check_fields
from flowins.geometry import quaternion as quat
from flowins.state import CORE_DIM, STATE, STATE_DIM, make_state, symmetrize


@dataclass(frozen=True)
class InitialUncertainty:
    """1-σ of the initial state (units of each state block)."""

    position_m: float = 0.01
    velocity_mps: float = 0.05
    roll_pitch_rad: float = 0.035  # 2°
    #: the yaw's where the start does not know it (a still start, or a moving one too slow for its
    #: course), in a run with GNSS fixes: above ``filter.gnss_heading.unknown_yaw_sigma_rad`` the fixes
    #: are held until they set the heading; at or below it the yaw counts as known
    #: (``filter.init.yaw_rad`` gives it)
    yaw_rad: float = math.pi
    #: ... in a run without GNSS fixes, where ``yaw_rad`` says the yaw is unknown: it is then only the
    #: track's reference direction, which neither the IMU nor the camera observes; at a large σ every
    #: linearised flow or track update would turn it by what its own linearisation point makes up
    reference_yaw_rad: float = 1e-3
    acc_bias_mps2: float = 0.1
    gyro_bias_rps: float = 2e-3
    acc_scale: float = 0.02
    #: variance along the quaternion itself (its length); rotations ignore it,
    #: it only keeps the 4x4 block positive definite
    quaternion_radial: float = 1e-3
    #: nugget between the current pose and its augmented copy
    augmentation_nugget_var: float = 1e-9


def start_uncertainty(u: InitialUncertainty, *, reference: bool) -> InitialUncertainty:
    """``u`` with the σ a start gives a free yaw: ``u.reference_yaw_rad`` where the yaw is only the
    track's reference direction (``reference``: nothing in the run can set it), else ``u.yaw_rad``."""
    return dataclasses.replace(u, yaw_rad=u.reference_yaw_rad) if reference else u


def orientation_covariance(q: Tensor, roll_pitch_yaw_std: Tensor, radial_std: float) -> Tensor:
    """``(4, 4)`` covariance of a quaternion perturbed by small world-frame rotations.

    ``q' = 𝒬{δ} ⊙ q ≈ q + ½ R⊙(q) (0, δ)`` with ``δ ~ N(0, diag(σ²))`` about the world
    x, y, z axes, plus ``radial_std²`` along ``q``.
    """
    J = 0.5 * quat.right_matrix(q)[..., :, 1:]  # (4, 3)
    tangent = J @ torch.diag(roll_pitch_yaw_std**2) @ J.T
    return tangent + radial_std**2 * torch.outer(q, q)


def augmented_covariance(core_cov: Tensor, nugget_var: float) -> Tensor:
    """``(26, 26)`` covariance with ``(p_prev, q_prev)`` an exact copy of ``(p, q)`` plus a nugget."""
    T = torch.zeros(STATE_DIM, CORE_DIM, dtype=core_cov.dtype, device=core_cov.device)
    T[:CORE_DIM] = torch.eye(CORE_DIM, dtype=core_cov.dtype, device=core_cov.device)
    T[STATE.p_prev, STATE.p] = torch.eye(3, dtype=core_cov.dtype, device=core_cov.device)
    T[STATE.q_prev, STATE.q] = torch.eye(4, dtype=core_cov.dtype, device=core_cov.device)
    cov = T @ core_cov @ T.T
    idx = torch.arange(CORE_DIM, STATE_DIM, device=core_cov.device)
    cov[idx, idx] += nugget_var
    return symmetrize(cov)


def initial_covariance(q: Tensor, u: InitialUncertainty, *, velocity_var: Tensor | None = None,
                       position_var: Tensor | None = None, roll_pitch_yaw_std: Tensor | None = None) -> Tensor:
    """``(26, 26)`` prior covariance at attitude ``q`` with the σ of ``u``; ``velocity_var``,
    ``position_var`` ``(3,)`` and ``roll_pitch_yaw_std`` ``(3,)`` replace those of ``u``. The
    covariance has the dtype and device of ``q``; learned uncertainties on another device
    (a module's parameters) are moved there, with their gradient."""
    dtype = q.dtype
    like = {"dtype": dtype, "device": q.device}
    core = torch.zeros(CORE_DIM, CORE_DIM, **like)

    def on(x: float | Tensor) -> Tensor:
        return x.to(**like) if isinstance(x, Tensor) else torch.tensor(float(x), **like)

    def block(sl: slice, std: float | Tensor, var: Tensor | None = None) -> None:
        # stacked, not torch.tensor(...): the uncertainties may be learned tensors with a gradient
        values = on(std) ** 2 * torch.ones(sl.stop - sl.start, **like) if var is None else var
        core[sl, sl] = torch.diag(values.to(**like))

    block(STATE.p, u.position_m, position_var)
    block(STATE.v, u.velocity_mps, velocity_var)
    block(STATE.b_a, u.acc_bias_mps2)
    block(STATE.b_w, u.gyro_bias_rps)
    block(STATE.T_a, u.acc_scale)
    if roll_pitch_yaw_std is None:
        roll_pitch_yaw_std = torch.stack([on(v) for v in (u.roll_pitch_rad, u.roll_pitch_rad, u.yaw_rad)])
    core[STATE.q, STATE.q] = orientation_covariance(q, roll_pitch_yaw_std.to(**like), u.quaternion_radial)
    return augmented_covariance(core, u.augmentation_nugget_var)


def still_prior(acc_mps2: Tensor, gyro_rps: Tensor, *, yaw_rad: float = 0.0, position_m: Tensor | None = None,
                uncertainty: InitialUncertainty = InitialUncertainty()) -> tuple[Tensor, Tensor]:
    """Prior ``(mean (26,), cov (26, 26))`` of a device that was still over the samples
    ``acc_mps2``, ``gyro_rps`` ``(n, 3)``: roll and pitch from their mean specific force,
    the gyroscope bias from their mean rate, zero velocity, yaw ``yaw_rad``."""
    dtype = acc_mps2.dtype
    f = acc_mps2.mean(dim=0)
    roll = torch.atan2(f[1], f[2])
    pitch = torch.atan2(-f[0], torch.sqrt(f[1] ** 2 + f[2] ** 2))
    q = quat.from_euler(roll, pitch, torch.tensor(yaw_rad, dtype=dtype))
    p = torch.zeros(3, dtype=dtype) if position_m is None else torch.as_tensor(position_m, dtype=dtype)
    mean = make_state(p=p, v=torch.zeros(3, dtype=dtype), q=q, b_w=gyro_rps.mean(dim=0))
    return mean, initial_covariance(q, uncertainty)


# --------------------------------------------------------------------------- still interval


@dataclass(frozen=True)
class StillSettings:
    """How :func:`still_interval` judges a still start (config ``filter.init.still``).

    Attributes:
        min_s: a still start lasts at least this long.
        lowpass_hz: the specific force and rate are averaged over ``1 / lowpass_hz``
            seconds (a centred moving average) before they are judged: rotor or engine
            vibration averages out, a slow motion does not.
        max_acc_mps2: the low-passed specific force may move this far from its mean
            since the start (0.2 m/s² is a tilt of 1.2°).
        max_gyro_rps: the low-passed rate may move this far from its mean since the start.
        max_gravity_error_mps2: the mean specific force's magnitude must be within this of
            gravity (a device accelerating steadily is not still).
        zupt_hz, zupt_sigma_mps: zero-velocity updates over the still interval (0: none).
        zupt_keeps_heading: the updates are blind to a turn about the vertical, which a still
            device does not observe (:mod:`flowins.measurements.zero_velocity`); False: the
            plain update, which makes up heading information from its linearisation.
    """

    min_s: float = bounded(1.0, above=0.0)
    lowpass_hz: float = bounded(2.0, above=0.0)
    max_acc_mps2: float = bounded(0.2, above=0.0)
    max_gyro_rps: float = bounded(0.03, above=0.0)
    max_gravity_error_mps2: float = bounded(0.5, above=0.0)
    zupt_hz: float = bounded(10.0, minimum=0.0)
    zupt_sigma_mps: float = bounded(0.01, above=0.0)
    zupt_keeps_heading: bool = True

    def __post_init__(self) -> None:
        check_fields(self)


@dataclass(frozen=True)
class StillInterval:
    """Rows ``[0, end)`` of the IMU are still (``end = 0``: not even the first sample)."""

    end: int
    start_s: float
    end_s: float
    #: why it ends: the row and statistic of the first motion, or the end of the recording
    reason: str

    @property
    def duration_s(self) -> float:
        return self.end_s - self.start_s


def moving_average(x: Tensor, half_width: int) -> Tensor:
    """Moving average of ``x`` ``(N, C)`` over ``w = 2 half_width + 1`` rows: centred, and
    at the ends the first (last) full window, so every row averages ``min(w, N)`` rows."""
    n = x.shape[0]
    w = min(2 * half_width + 1, n)
    c = torch.cat((x.new_zeros(1, x.shape[1]), torch.cumsum(x, dim=0)))
    lo = (torch.arange(n) - half_width).clamp(0, n - w)
    return (c[lo + w] - c[lo]) / w


def still_interval(t_s: Tensor, acc_mps2: Tensor, gyro_rps: Tensor, settings: StillSettings = StillSettings(), *,
                   gravity_mps2: float = 9.80665) -> StillInterval:
    """The still interval at the start of a recording.

    The specific force and rate are low-passed (:func:`moving_average` over
    ``1 / settings.lowpass_hz`` s); the interval ends at the first row where either
    moves from its running mean since the start by more than ``max_acc_mps2`` /
    ``max_gyro_rps``, or where that running mean of the specific force is more than
    ``max_gravity_error_mps2`` off gravity. A motion anywhere inside a window is thus
    the window's end, never averaged into the attitude.
    """
    t = torch.as_tensor(t_s, dtype=torch.float64)
    acc = torch.as_tensor(acc_mps2, dtype=torch.float64)
    gyro = torch.as_tensor(gyro_rps, dtype=torch.float64)
    n = t.shape[0]
    dt = float(torch.diff(t).median()) if n > 1 else 1.0
    half = max(0, round(0.5 / (settings.lowpass_hz * dt)))
    acc_lp, gyro_lp = moving_average(acc, half), moving_average(gyro, half)
    count = torch.arange(1, n + 1, dtype=torch.float64).unsqueeze(-1)
    acc_ref, gyro_ref = torch.cumsum(acc_lp, 0) / count, torch.cumsum(gyro_lp, 0) / count
    acc_dev = torch.linalg.vector_norm(acc_lp - acc_ref, dim=-1)
    gyro_dev = torch.linalg.vector_norm(gyro_lp - gyro_ref, dim=-1)
    gravity_dev = (torch.linalg.vector_norm(acc_ref, dim=-1) - gravity_mps2).abs()
    tests = (
        (acc_dev > settings.max_acc_mps2, acc_dev, "low-passed specific force moved", "m/s²", "max_acc_mps2",
         settings.max_acc_mps2),
        (gyro_dev > settings.max_gyro_rps, gyro_dev, "low-passed rate moved", "rad/s", "max_gyro_rps",
         settings.max_gyro_rps),
        (gravity_dev > settings.max_gravity_error_mps2, gravity_dev, "mean specific force is off gravity by", "m/s²",
         "max_gravity_error_mps2", settings.max_gravity_error_mps2),
    )
    end, reason = n, "still to the end of the recording"
    for moved, value, what, unit, key, limit in tests:
        hit = torch.nonzero(moved)
        if hit.numel() and int(hit[0, 0]) < end:
            end = int(hit[0, 0])
            reason = (f"row {end} (t = {float(t[end]):.3f} s): {what} {float(value[end]):.3g} {unit} "
                      f"(filter.init.still.{key}={limit})")
            if key == "max_gyro_rps" and float(acc_dev[:end + 1].max()) < 0.25 * settings.max_acc_mps2:
                reason += ("; the rate moves while the specific force stays still, as a gyroscope in deg/s "
                           "would (rad/s expected)")
    if end < n:
        # a smooth start of motion crosses the limits late: the interval ends where the
        # motion rose out of the noise, the last row before ``end`` below a quarter of the limits
        level = torch.maximum(acc_dev / settings.max_acc_mps2, gyro_dev / settings.max_gyro_rps)[:end]
        quiet = torch.nonzero(level <= 0.25)
        end = int(quiet[-1, 0]) + 1 if quiet.numel() else 0
    end_s = float(t[end - 1]) if end > 0 else float(t[0])
    return StillInterval(end, float(t[0]), end_s, reason)


# --------------------------------------------------------------------------- moving start


@dataclass(frozen=True)
class KinematicFit:
    """``p(τ) = p0 + v0 τ + ½ a τ²`` fitted to position fixes, ``τ = t - t0_s``; per-axis variances."""

    t0_s: float
    position_m: Tensor  # (3,)
    velocity_mps: Tensor  # (3,)
    acceleration_mps2: Tensor  # (3,)
    position_var: Tensor  # (3,)
    velocity_var: Tensor  # (3,)
    acceleration_var: Tensor  # (3,)
    fixes: int
    span_s: float


def kinematic_fit(t_s: Tensor, position_m: Tensor, sigma_m: Tensor, *, t0_s: float,
                  acceleration_sigma_mps2: float = 1.0) -> KinematicFit:
    """Weighted least-squares fit of ``p0, v0, a`` per axis to fixes ``t_s (G,)``,
    ``position_m (G, 3)`` with 1-σ ``sigma_m (G, 3)``, evaluated at ``t0_s``.

    The acceleration has the prior ``N(0, acceleration_sigma_mps2²)`` (a few noisy
    fixes alone would tilt the attitude by their noise); with two fixes it is that
    prior alone. Needs at least two fixes at distinct times.
    """
    tau = (torch.as_tensor(t_s, dtype=torch.float64) - t0_s)
    z = torch.as_tensor(position_m, dtype=torch.float64)
    w = 1.0 / torch.as_tensor(sigma_m, dtype=torch.float64) ** 2  # (G, 3)
    if tau.shape[0] < 2:
        raise ValueError(f"kinematic_fit needs at least 2 fixes, got {tau.shape[0]}")
    A = torch.stack((torch.ones_like(tau), tau, 0.5 * tau**2), -1)  # (G, 3)
    prior = torch.diag(torch.tensor([0.0, 0.0, 1.0 / acceleration_sigma_mps2**2], dtype=torch.float64))
    # plain products: a three-operand einsum asks opt_einsum (where installed) for a path on each call
    wA = w.transpose(0, 1).unsqueeze(-1) * A  # (3 axes, G, 3)
    info = wA.transpose(-1, -2) @ A + prior  # (3 axes, 3, 3)
    rhs = (wA.transpose(-1, -2) @ z.transpose(0, 1).unsqueeze(-1)).squeeze(-1)  # (3 axes, 3)
    cov = torch.linalg.inv(info)
    coef = (cov @ rhs.unsqueeze(-1)).squeeze(-1)  # (3 axes, 3 coefficients)
    var = torch.diagonal(cov, dim1=-2, dim2=-1)
    return KinematicFit(t0_s, coef[:, 0], coef[:, 1], coef[:, 2], var[:, 0], var[:, 1], var[:, 2], int(tau.shape[0]),
                        float(tau.max() - tau.min()))


def two_vector_attitude(f_body: Tensor, f_world: Tensor, d_body: Tensor, d_world: Tensor) -> Tensor:
    """Quaternion (body -> world) with ``R f_body ∥ f_world`` exactly and ``R d_body`` in the
    plane of ``f_world`` and ``d_world``, on ``d_world``'s side (TRIAD).

    Raises ValueError when ``d`` is nearly parallel to ``f`` in either frame (no heading).
    """
    def triad(a: Tensor, b: Tensor, frame: str) -> Tensor:
        e1 = a / torch.linalg.vector_norm(a)
        cross = torch.linalg.cross(e1, b)
        size = float(torch.linalg.vector_norm(cross) / torch.linalg.vector_norm(b))
        if size < 0.1:
            raise ValueError(f"the {frame} forward direction is within {math.degrees(math.asin(size)):.1f}° of the "
                             "vertical: it sets no heading")
        e2 = cross / torch.linalg.vector_norm(cross)
        return torch.stack((e1, e2, torch.linalg.cross(e1, e2)), -1)

    R = triad(f_world, d_world, "world") @ triad(f_body, d_body, "body").T
    return quat.from_matrix(R)


_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def forward_axis(name: str, imu_to_camera_rotation: Tensor | None = None) -> Tensor:
    """The body axis ``(3,)`` that points along the motion: ``"x"``, ``"-x"``, ..., ``"-z"``,
    ``"camera"`` (the optical axis, from the IMU->camera rotation ``(3, 3)``) or ``"auto"``
    (the camera's when there is one, else ``x``)."""
    if name == "auto":
        name = "camera" if imu_to_camera_rotation is not None else "x"
    if name == "camera":
        if imu_to_camera_rotation is None:
            raise ValueError("filter.init.moving.forward_axis=camera needs the camera calibration (imu_to_camera); "
                             "the recording has none: give x, -x, y, -y, z or -z")
        R = torch.as_tensor(imu_to_camera_rotation, dtype=torch.float64)
        return R.T @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    sign, axis = (-1.0, name[1:]) if name.startswith("-") else (1.0, name)
    if axis not in _AXES:
        raise ValueError(f"filter.init.moving.forward_axis={name!r}; expected auto, camera, x, -x, y, -y, z or -z")
    return sign * torch.tensor(_AXES[axis], dtype=torch.float64)


def moving_prior(*, acc_mps2: Tensor, position_m: Tensor, velocity_mps: Tensor, acceleration_mps2: Tensor,
                 forward_b: Tensor, position_var: Tensor, velocity_var: Tensor, acceleration_var: Tensor,
                 heading_sigma_rad: float, min_speed_mps: float = 1.0, gravity_mps2: float = 9.80665,
                 uncertainty: InitialUncertainty = InitialUncertainty(),
                 heading_rad: float | None = None) -> tuple[Tensor, Tensor, dict]:
    """Prior of a moving device: ``(mean (26,), cov (26, 26), facts)``.

    Roll and pitch from the mean specific force ``f̄`` of ``acc_mps2 (n, 3)`` (a short
    window) matched to ``a + g e_z`` (``a`` the acceleration in that window); the
    heading from the course over ground of ``velocity_mps`` along ``forward_b``, with
    σ² = (σ_v⊥ / |v|)² + ``heading_sigma_rad``²; or ``heading_rad`` when given. Slower
    than ``max(min_speed_mps, 3 σ_v)`` the course says nothing: the yaw is free
    (``uncertainty.yaw_rad``). Gyroscope bias 0 (a moving device does not show it).
    """
    dtype = torch.float64
    f_body = torch.as_tensor(acc_mps2, dtype=dtype).mean(dim=0)
    a = torch.as_tensor(acceleration_mps2, dtype=dtype)
    up = a + torch.tensor([0.0, 0.0, gravity_mps2], dtype=dtype)
    v = torch.as_tensor(velocity_mps, dtype=dtype)
    speed = float(torch.linalg.vector_norm(v[:2]))
    sigma_v = float(velocity_var[:2].max().sqrt())
    facts: dict = {"speed_mps": speed}
    if heading_rad is not None:
        course, heading_std = float(heading_rad), float(heading_sigma_rad)
    elif speed >= max(min_speed_mps, 3.0 * sigma_v):
        course = math.atan2(float(v[1]), float(v[0]))
        heading_std = math.hypot(sigma_v / speed, heading_sigma_rad)
    else:
        course, heading_std = 0.0, float(uncertainty.yaw_rad)
        facts["heading"] = (f"free: the speed {speed:.2f} m/s is below max(min_speed_mps={min_speed_mps}, "
                            f"3 sigma={3 * sigma_v:.2f} m/s)")
    d_world = torch.tensor([math.cos(course), math.sin(course), 0.0], dtype=dtype)
    q = two_vector_attitude(f_body, up, torch.as_tensor(forward_b, dtype=dtype), d_world)
    tilt_std = math.hypot(float(acceleration_var[:2].max().sqrt()) / gravity_mps2, float(uncertainty.roll_pitch_rad))
    facts.update(heading_deg=math.degrees(course), heading_sigma_deg=math.degrees(heading_std),
                 tilt_sigma_deg=math.degrees(tilt_std))
    p = torch.as_tensor(position_m, dtype=dtype)
    mean = make_state(p=p, v=v, q=q)
    rpy = torch.tensor([tilt_std, tilt_std, heading_std], dtype=dtype)
    cov = initial_covariance(q, uncertainty, velocity_var=torch.as_tensor(velocity_var, dtype=dtype),
                             position_var=torch.as_tensor(position_var, dtype=dtype), roll_pitch_yaw_std=rpy)
    return mean, cov, facts
