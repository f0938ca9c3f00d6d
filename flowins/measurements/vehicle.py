"""A wheeled vehicle's motion constraint: no sideways and no vertical velocity at its non-slipping point.

A car does not slip sideways or leave the road, so between GNSS fixes the velocity of the
middle of its rear axle, in the vehicle frame, is ``(v_forward, 0, 0)`` (the non-holonomic
constraint of wheeled-vehicle navigation, as ai-imu-dr uses). The IMU sits elsewhere and
need not be aligned with the car:

* ``forward_axis``, ``up_axis`` name the IMU axes that point the car's way (KITTI's OXTS: x
  forward, z up); ``A (3, 3)`` has the IMU's forward, left (up × forward) and up unit axes as
  rows;
* ``mount_pitch_rad``, ``mount_yaw_rad`` turn the IMU from there: ``R_m = Rz(ψ_m) Ry(θ_m)``,
  the attitude's Euler convention (:func:`~flowins.geometry.quaternion.from_euler`, roll 0),
  so the IMU's forward axis points ``ψ_m`` to the left of the car's, and tilts ``θ_m`` down;
  ``C_cb = R_m A`` takes IMU-frame vectors to the car's frame;
* ``lever_*_m`` place the non-slipping point ``r_c`` from the IMU along the car's forward, left
  and up axes.

With ``ω = ω̃ - b_w`` the IMU's rate (``ω̃`` the gyroscope's reading at the update's time,
the sample that covers it) the point's velocity in the car's frame is
``v_c = C_cb C(q)ᵀ v + (C_cb ω) × r_c``, and the pseudo-measurement is

    0 = S v_c + n,   S = [e_left; e_up],   n ~ N(0, diag(σ_lat², σ_up²)),

applied every ``1 / rate_hz`` seconds from the start. Its Jacobian has blocks on the
velocity (``S C_cb C(q)ᵀ``), the quaternion (``S C_cb`` times
:func:`~flowins.geometry.quaternion.rotate_jacobian` of the conjugate) and the gyroscope's
bias (``S [r_c]ₓ C_cb``). The mounting and the lever arm may be tensors with a gradient
(``train.py`` learns them as ``vehicle_mount_*`` and ``vehicle_lever_*``). The kind registers
itself as ``vehicle``: a run uses it when its streams hold ``vehicle`` (a
:class:`VehicleConstraint`: ``filter.measurements.vehicle.mode=on``, or ``auto`` on a
recording whose metadata names ``platform: vehicle``).
"""
from __future__ import annotations

from collections.abc import Hashable, Sequence
import dataclasses
from dataclasses import dataclass
from typing import Any, Literal

import torch
from torch import Tensor

from flowins.config import bounded, check_fields
from flowins.constants import STANDARD_GRAVITY_MPS2, cached_constant, scalar_like
from flowins.filter.chain import BatchChain, RowBatchEvent
from flowins.filter.updater import update_rows
from flowins.geometry import quaternion as quat
from flowins.measurements.adaptive_noise import (acceleration_g, covering_sample, imu_windows, recent_force_g,
                                                 steady_window)
from flowins.measurements.registry import MeasurementKind, NavigationContext, register
from flowins.state import STATE

AXES = {"x": (0, 1.0), "-x": (0, -1.0), "y": (1, 1.0), "-y": (1, -1.0), "z": (2, 1.0), "-z": (2, -1.0)}
MODES = ("auto", "on", "off")
#: the largest mounting angle (rad) the constraint takes: beyond it name other axes
MAX_MOUNT_RAD = 0.5


@dataclass(frozen=True)
class VehicleSettings:
    """``filter.measurements.vehicle``."""

    #: auto: on when the recording's metadata names ``platform: vehicle``; on; off
    mode: Literal["auto", "on", "off"] = "auto"
    #: σ of the sideways and of the vertical velocity in the vehicle frame (m/s)
    lateral_sigma_mps: float | Tensor = bounded(1.0, above=0.0)
    vertical_sigma_mps: float | Tensor = bounded(1.0, above=0.0)
    #: pseudo-measurements per second
    rate_hz: float = bounded(1.0, above=0.0)
    #: the IMU axes along the vehicle's forward and up directions
    forward_axis: Literal["x", "-x", "y", "-y", "z", "-z"] = "x"
    up_axis: Literal["x", "-x", "y", "-y", "z", "-z"] = "z"
    #: the IMU turned from those axes (rad): its forward axis this far down (pitch) and to the left (yaw)
    mount_pitch_rad: float | Tensor = bounded(0.0, above=-MAX_MOUNT_RAD, below=MAX_MOUNT_RAD)
    mount_yaw_rad: float | Tensor = bounded(0.0, above=-MAX_MOUNT_RAD, below=MAX_MOUNT_RAD)
    #: the non-slipping point (the rear axle's middle) from the IMU along the vehicle's forward, left, up axes (m)
    lever_forward_m: float | Tensor = bounded(0.0, above=-10.0, below=10.0)
    lever_left_m: float | Tensor = bounded(0.0, above=-10.0, below=10.0)
    lever_up_m: float | Tensor = bounded(0.0, above=-10.0, below=10.0)
    #: given: the mounting and lever arm above; fit: estimated per run from a first pass without
    #: the constraint (:func:`fit_mounting`, :mod:`flowins.mounting_pass`), used where it explains
    #: the track (its residual falls to ``fit_max_residual`` of its start or less), the above otherwise
    mounting: Literal["given", "fit"] = "given"
    fit_max_residual: float = bounded(0.25, above=0.0, maximum=1.0)
    #: not a config key: the learned network that scales both σs at each update from the IMU's
    #: recent readings (:class:`~flowins.measurements.adaptive_noise.AdaptiveNoise`: factors
    #: ``(E, 2)``, or factors and the mounting's offsets at each update ``(E, 2)``, pitch then yaw
    #: in rad, the car's slip and its pitch under acceleration; a network that ``compensates_gravity``
    #: sets them at each update from the filter's state, :class:`VehicleUpdate`), set from a checkpoint
    #: or while training (``model.adaptive=[vehicle]``); None: constant σs and the mounting above
    noise_model: Any = None

    def __post_init__(self) -> None:
        check_fields(self)
        if self.noise_model is not None and not callable(self.noise_model):
            raise ValueError(f"VehicleSettings.noise_model={self.noise_model!r}: expected None or a network (it comes "
                             "from a train.py checkpoint, model.checkpoint, not from a config)")
        if AXES[self.forward_axis][0] == AXES[self.up_axis][0]:
            raise ValueError(f"VehicleSettings.forward_axis={self.forward_axis!r} and up_axis={self.up_axis!r} "
                             "are the same axis")

    def axes(self) -> Tensor:
        """``A (3, 3)``: the IMU's forward, left and up unit axes as rows (float64)."""
        return _axes(self.forward_axis, self.up_axis, torch.float64, torch.device("cpu")).clone()

    def rows(self) -> Tensor:
        """``E (2, 3)``: the IMU's left and up unit axes as rows, with no mounting turn (float64)."""
        return self.axes()[1:]

    def vehicle_from_imu(self, like: Tensor, offset_rad: Tensor | None = None) -> Tensor:
        """``C_cb (3, 3)`` in ``like``'s dtype and device: IMU-frame vectors into the vehicle's frame;
        with ``offset_rad (R, 2)`` (pitch, yaw added to the mounting's) one per row, ``(R, 3, 3)``."""
        A = _axes(self.forward_axis, self.up_axis, like.dtype, like.device)
        if offset_rad is None and _zero(self.mount_pitch_rad) and _zero(self.mount_yaw_rad):
            return A
        pitch, yaw = scalar_like(self.mount_pitch_rad, like), scalar_like(self.mount_yaw_rad, like)
        if offset_rad is not None:
            offset_rad = offset_rad.to(like)
            pitch, yaw = pitch + offset_rad[..., 0], yaw + offset_rad[..., 1]
        return quat.to_matrix(quat.from_euler(torch.zeros_like(pitch), pitch, yaw)) @ A

    def lever_arm(self, like: Tensor) -> Tensor | None:
        """``r_c (3,)``: the non-slipping point from the IMU in the vehicle's frame; None where it is 0."""
        parts = (self.lever_forward_m, self.lever_left_m, self.lever_up_m)
        if all(_zero(p) for p in parts):
            return None
        return torch.stack([scalar_like(p, like) for p in parts])


def _zero(value: float | Tensor) -> bool:
    """A plain 0 (a tensor, which may carry a gradient, counts as set)."""
    return not isinstance(value, Tensor) and value == 0.0


@dataclass(frozen=True)
class VehicleConstraint:
    """The stream that switches the constraint on for a run; ``mounting``: the run's own fitted
    mounting, which replaces the settings' (``mounting=fit``)."""

    mounting: MountingFit | None = None


def platform_streams(platform: str | None) -> dict[str, VehicleConstraint]:
    """The streams a recording's ``platform`` (its metadata) brings: the vehicle constraint for
    ``vehicle`` (used unless ``filter.measurements.vehicle.mode=off``), none otherwise."""
    return {"vehicle": VehicleConstraint()} if platform == "vehicle" else {}


def body_velocity_jacobians(q: Tensor, v: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(v_b, ∂v_b/∂v (3, 3), ∂v_b/∂q (3, 4))`` of the body-frame velocity ``v_b = C(q)ᵀ v``."""
    q_conj = quat.conjugate(q)
    v_b = quat.rotate(q_conj, v)
    d_v = quat.to_matrix(q).transpose(-1, -2)
    d_q = quat.rotate_jacobian(q_conj, v) * _flip(q.dtype, q.device)  # ∂conj(q)/∂q = diag(1, -1, -1, -1)
    return v_b, d_v, d_q


def constraint_terms(mean: Tensor, gyro_rps: Tensor, C_cb: Tensor, lever_c: Tensor | None) -> tuple[Tensor, Tensor]:
    """``(h (..., 2), H (..., 2, D))`` of the pseudo-measurement (module docstring) at the states
    ``mean (..., D)`` with the gyroscope's readings ``gyro_rps (..., 3)``: the sideways and
    vertical velocity of the non-slipping point in the vehicle frame, and its Jacobian.
    ``C_cb`` is ``(3, 3)`` or one per state, ``(..., 3, 3)``."""
    v_b, d_v, d_q = body_velocity_jacobians(mean[..., STATE.q], mean[..., STATE.v])
    E = C_cb[..., 1:, :]  # (..., 2, 3): the vehicle's left and up axes in the IMU frame
    h = (E @ v_b.unsqueeze(-1)).squeeze(-1)
    H = mean.new_zeros(*mean.shape[:-1], 2, mean.shape[-1])
    H[..., STATE.v] = E @ d_v
    H[..., STATE.q] = E @ d_q
    if lever_c is not None:
        omega_c = (C_cb @ (gyro_rps - mean[..., STATE.b_w]).unsqueeze(-1)).squeeze(-1)
        h = h + torch.linalg.cross(omega_c, lever_c.expand_as(omega_c))[..., 1:]
        H[..., STATE.b_w] = (quat.skew(lever_c) @ C_cb)[..., 1:, :]  # ∂(C ω × r)/∂b_w = [r]ₓ C
    return h, H


@dataclass(frozen=True)
class VehicleUpdate(RowBatchEvent):
    """One non-holonomic pseudo-measurement at ``time_s`` (module docstring), with the
    gyroscope's reading ``gyro_rps (3,)`` that covers it."""

    time_s: float
    settings: VehicleSettings
    gyro_rps: Tensor
    name: str = "vehicle constraint"
    #: ``(2,)`` factors on the σs from the settings' ``noise_model``; None: the σs as they are
    sigma_scale: Tensor | None = None
    #: ``(2,)`` pitch and yaw (rad) added to the mounting at this update, from the settings'
    #: ``noise_model``; None: the mounting as it is
    mount_offset_rad: Tensor | None = None
    #: a ``noise_model`` that reads the car's acceleration (``compensates_gravity``): its angles'
    #: outputs before the acceleration's part ``(2,)`` and the mean specific force of the last
    #: 0.2 s ``(3,)`` (g, IMU axes), the angles set at the update with the filter's attitude
    angle_input: Tensor | None = None
    recent_force_g: Tensor | None = None
    #: gravity (m/s²) the acceleration is taken with
    gravity_mps2: float = STANDARD_GRAVITY_MPS2

    def batch_key(self) -> Hashable:
        """Updates with the same settings (one run's, or one config's for a batch) act together."""
        return (VehicleUpdate, id(self.settings))

    @classmethod
    def place(cls, updates: list[VehicleUpdate], like: Tensor) -> list[VehicleUpdate]:
        """The updates with their gyroscope readings (and σ factors and mounting offsets, where
        they have them) in ``like``'s dtype and device: one copy each, each update's a view of it."""
        if all(u.gyro_rps.dtype == like.dtype and u.gyro_rps.device == like.device for u in updates):
            return list(updates)
        gyro = torch.stack([u.gyro_rps for u in updates]).to(like)
        fields = {name: [getattr(u, name) for u in updates]
                  for name in ("sigma_scale", "mount_offset_rad", "angle_input", "recent_force_g")}
        placed = {name: _placed(values, like) for name, values in fields.items()}
        return [dataclasses.replace(u, gyro_rps=gyro[i], **{name: p[i] for name, p in placed.items()})
                for i, u in enumerate(updates)]

    @classmethod
    def apply_batch(cls, chain: BatchChain, rows: Sequence[int], events: Sequence[VehicleUpdate]) -> None:
        """The pseudo-measurements ``events[i]`` (one settings) on the rows ``rows[i]``, as one update."""
        settings = events[0].settings
        mean, _ = chain.newest(rows)
        r = mean.shape[0]
        gyro = torch.stack([e.gyro_rps for e in events]).to(mean)
        offset = None  # one settings: every update with its offsets, or none
        if events[0].mount_offset_rad is not None:
            offset = torch.stack([e.mount_offset_rad for e in events]).to(mean)
        elif events[0].angle_input is not None:  # the angles read the car's acceleration at this attitude
            force = torch.stack([e.recent_force_g for e in events]).to(mean)
            acceleration = acceleration_g(force, mean[..., STATE.q], events[0].gravity_mps2,
                                          acc_bias_mps2=mean[..., STATE.b_a], acc_scale=mean[..., STATE.T_a])
            offset = settings.noise_model.bounded_angles(torch.stack([e.angle_input for e in events]).to(mean),
                                                         acceleration)
        h, H = constraint_terms(mean, gyro, settings.vehicle_from_imu(mean, offset), settings.lever_arm(mean))
        sigma = torch.stack([scalar_like(s, mean) for s in (settings.lateral_sigma_mps, settings.vertical_sigma_mps)])
        sigma = sigma.expand(r, 2)
        if events[0].sigma_scale is not None:  # one settings: all of them scaled, or none
            sigma = sigma * torch.stack([e.sigma_scale for e in events]).to(mean)
        update_rows(chain, rows, H=H.unsqueeze(1), residual=-h.unsqueeze(1),
                    noise_cov=torch.diag_embed(sigma**2).unsqueeze(1), likelihood=False,
                    infos=[{"kind": "vehicle", "name": e.name} for e in events])


def _placed(values: list[Tensor | None], like: Tensor) -> list[Tensor | None]:
    """``values`` in ``like``'s dtype and device, those that are tensors as views of one copy."""
    present = [i for i, v in enumerate(values) if v is not None]
    if not present:
        return list(values)
    copy = torch.stack([values[i] for i in present]).to(like)
    out: list[Tensor | None] = [None] * len(values)
    for j, i in enumerate(present):
        out[i] = copy[j]
    return out


@cached_constant
def _axes(forward_axis: str, up_axis: str, dtype: torch.dtype, device: torch.device) -> Tensor:
    """``A (3, 3)`` of :meth:`VehicleSettings.axes` in ``dtype`` on ``device``, built once."""
    fwd_i, fwd_s = AXES[forward_axis]
    up_i, up_s = AXES[up_axis]
    forward = torch.zeros(3, dtype=torch.float64)
    up = torch.zeros(3, dtype=torch.float64)
    forward[fwd_i], up[up_i] = fwd_s, up_s
    return torch.stack((forward, torch.linalg.cross(up, forward), up)).to(dtype=dtype, device=device)


@cached_constant
def _flip(dtype: torch.dtype, device: torch.device) -> Tensor:
    return torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=dtype, device=device)


def gyro_at(t_imu_s: Tensor, gyro_rps: Tensor, times_s: Tensor) -> Tensor:
    """``(N, 3)``: the gyroscope's reading that covers each of ``times_s (N,)``: the sample ``k``
    with ``t_{k-1} < t <= t_k`` (an integrating IMU's sample ``k`` is the rate over that
    interval; the first sample at or before the first time)."""
    return gyro_rps[covering_sample(t_imu_s, times_s)]


@dataclass(frozen=True)
class MountingFit:
    """:func:`fit_mounting`'s estimate: the settings' ``mount_*_rad`` and ``lever_*_m`` values."""

    mount_pitch_rad: float
    mount_yaw_rad: float
    lever_m: tuple[float, float, float]
    #: RMS of the constraint's residual (m/s) over the samples used, before and after the fit
    rms_before_mps: float
    rms_after_mps: float
    #: samples used (those at or above the speed)
    samples: int

    @property
    def explains(self) -> float:
        """The residual's RMS after the fit as a part of its RMS before."""
        return self.rms_after_mps / max(self.rms_before_mps, 1e-300)

    def applied_to(self, settings: VehicleSettings) -> VehicleSettings:
        """``settings`` with this mounting and lever arm."""
        forward, left, up = self.lever_m
        return dataclasses.replace(settings, mount_pitch_rad=self.mount_pitch_rad, mount_yaw_rad=self.mount_yaw_rad,
                                   lever_forward_m=forward, lever_left_m=left, lever_up_m=up)

    def as_dict(self) -> dict:
        return {"mount_pitch_rad": self.mount_pitch_rad, "mount_yaw_rad": self.mount_yaw_rad,
                "lever_m": list(self.lever_m), "residual_mps": [self.rms_before_mps, self.rms_after_mps],
                "samples": self.samples}

    def overrides(self) -> list[str]:
        """The fit as ``filter.measurements.vehicle.*`` overrides."""
        key = "filter.measurements.vehicle."
        names = ("lever_forward_m", "lever_left_m", "lever_up_m")
        return ([f"{key}mount_pitch_rad={self.mount_pitch_rad:.5f}", f"{key}mount_yaw_rad={self.mount_yaw_rad:.5f}"]
                + [f"{key}{n}={x:.3f}" for n, x in zip(names, self.lever_m)])


def fit_mounting(mean: Tensor, gyro_rps: Tensor, *, forward_axis: str = "x", up_axis: str = "z",
                 min_speed_mps: float = 3.0, lever_prior_m: float = 2.0, iterations: int = 4) -> MountingFit:
    """The IMU's mounting and the lever arm that best explain a track as a car's: Gauss–Newton
    on the constraint's residual ``h`` (module docstring) over the states ``mean (N, D)`` (a
    smoothed track of a run *without* the constraint, which would pull the track to its own
    mounting) moving at ``min_speed_mps`` or faster, with their gyroscope readings
    ``gyro_rps (N, 3)``. The lever arm has a zero-mean prior of ``lever_prior_m`` per axis: its
    sideways and up parts show only in roll and pitch rates, which a car has little of.

    The yaw shows in the sideways velocity (``ψ v_forward``), the pitch in the vertical one
    (``-θ v_forward``), the lever arm's forward part in the sideways velocity of turns (``ω_z r``).
    A track whose heading is off by ``δ`` gives a yaw off by ``δ``: the fit is as good as the
    smoothed track's heading."""
    if not bool(torch.isfinite(mean).all() and torch.isfinite(gyro_rps).all()):
        raise ValueError("fit_mounting: the track or the gyroscope's readings are not finite")
    moving = mean[..., STATE.v].norm(dim=-1) >= min_speed_mps
    n = int(moving.sum())
    if n < 10:
        raise ValueError(f"fit_mounting: {n} samples at {min_speed_mps} m/s or faster; expected at least 10")

    def residual(p: Tensor) -> Tensor:
        settings = VehicleSettings(forward_axis=forward_axis, up_axis=up_axis, mount_pitch_rad=p[0],
                                   mount_yaw_rad=p[1], lever_forward_m=p[2], lever_left_m=p[3], lever_up_m=p[4])
        h, _ = constraint_terms(x, w, settings.vehicle_from_imu(x), settings.lever_arm(x))
        return torch.cat((h.reshape(-1), p[2:] / lever_prior_m))

    # outside a caller's inference mode, on plain copies: forward-mode AD drops inference tensors'
    # tangents (torch 2.11: the Jacobian comes back empty)
    with torch.inference_mode(False):
        x, w = mean[moving].detach().to(torch.float64).clone(), gyro_rps[moving].detach().to(torch.float64).clone()
        p = torch.zeros(5, dtype=torch.float64)
        before = residual(p)[:-3]
        for _ in range(iterations):
            J = torch.func.jacfwd(residual)(p)
            step = torch.linalg.lstsq(J, -residual(p).unsqueeze(-1)).solution.squeeze(-1)
            p = p + step
            p[:2] = p[:2].clamp(-0.9 * MAX_MOUNT_RAD, 0.9 * MAX_MOUNT_RAD)
    if not bool(torch.isfinite(p).all()):
        raise ValueError("fit_mounting: the fit did not converge (its estimate is not finite)")
    after = residual(p)[:-3]
    rms = lambda r: float(r.pow(2).mean().sqrt())  # noqa: E731
    return MountingFit(float(p[0]), float(p[1]), tuple(float(a) for a in p[2:]), rms(before), rms(after), n)


def vehicle_events(stream: VehicleConstraint, settings: VehicleSettings, context: NavigationContext) -> list:
    """A :class:`VehicleUpdate` every ``1 / rate_hz`` s after the start (none with ``mode=off``)."""
    if settings.mode == "off":
        return []
    if context.imu is None:
        raise ValueError("vehicle constraint: the run's context has no IMU (NavigationContext.imu); "
                         "its updates need the gyroscope's readings")
    if stream.mounting is not None:
        settings = stream.mounting.applied_to(settings)
    step = 1.0 / settings.rate_hz
    times = torch.arange(context.t_start_s + step, context.t_end_s + 1e-9, step, dtype=torch.float64)
    gyro = gyro_at(context.imu.t_s, context.imu.gyro_rps, times)
    scale = offset = angle_input = force = [None] * len(times)
    if settings.noise_model is not None and len(times):
        imu = context.imu
        windows = imu_windows(imu.t_s, imu.acc_mps2, imu.gyro_rps, times)
        steady = steady_window(settings.vehicle_from_imu(windows)[2].detach())  # the car's up axis in the IMU frame
        network = settings.noise_model
        if getattr(network, "compensates_gravity", False):  # angles at each update, from the filter's attitude
            (scale, angle_input), force = network.split(windows, steady), recent_force_g(windows)
        else:
            scale = network(windows, steady)
            if isinstance(scale, tuple):  # factors and the mounting's offsets
                scale, offset = scale
    return [VehicleUpdate(t, settings, gyro[i], sigma_scale=scale[i], mount_offset_rad=offset[i],
                          angle_input=angle_input[i], recent_force_g=force[i], gravity_mps2=context.gravity_mps2)
            for i, t in enumerate(times.tolist())]


register(MeasurementKind("vehicle", VehicleSettings, vehicle_events, default_stream=VehicleConstraint))
