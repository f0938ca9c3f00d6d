"""A smooth synthetic walk with exact IMU readings, noisy IMU and GNSS.

The walk: a person holds the device still for ``stationary_s`` seconds, then walks
a closed, non-square loop (a Fourier-series curve of about ``perimeter_m``) at
about ``speed_mps``, with walking bounce and hand sway, device pointing forward and
slightly down. Position and orientation are closed-form functions of time (the
speed ramp is a C³ polynomial smoothstep), so velocity, acceleration and angular
rate come from ``torch.func.jacfwd`` exactly, and the ideal IMU readings are exact
derivatives of the trajectory.

Body (IMU) frame: x forward, y left, z up; world frame: local ENU.
This is the small generator the filter's tests and the INS+GNSS demo use; the
full scene simulator with images builds on it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor
from torch.func import jacfwd, vmap

from flowins.geometry import quaternion as quat
from flowins.constants import STANDARD_GRAVITY_MPS2

if TYPE_CHECKING:
    from flowins.data.streams import GnssStream, ImuStream, PoseStream

# Fourier coefficients of the loop (unit scale): a rounded, non-square block
_LOOP_X = ((1, 1.0, 0.0), (3, -0.09, 0.0), (2, 0.06, 0.05))
_LOOP_Y = ((1, 0.0, 0.72), (3, 0.0, 0.07), (2, -0.04, 0.03))


def _smoothstep_integral(x: Tensor) -> Tensor:
    """``∫₀ˣ S₇``, ``S₇ = 35x⁴ - 84x⁵ + 70x⁶ - 20x⁷`` clamped to [0, 1] (C³ ramp)."""
    xc = x.clamp(0.0, 1.0)
    ramp = 7 * xc**5 - 14 * xc**6 + 10 * xc**7 - 2.5 * xc**8
    return ramp + (x - 1.0).clamp_min(0.0)  # slope 1 after the ramp


def _smoothstep(x: Tensor) -> Tensor:
    xc = x.clamp(0.0, 1.0)
    return 35 * xc**4 - 84 * xc**5 + 70 * xc**6 - 20 * xc**7


@dataclass(frozen=True)
class WalkConfig:
    duration_s: float = 300.0
    stationary_s: float = 5.0
    ramp_s: float = 3.0
    perimeter_m: float = 360.0
    speed_mps: float = 1.2
    height_m: float = 1.5
    pitch_rad: float = math.radians(-12.0)
    bounce_m: float = 0.03
    step_hz: float = 1.8
    sway_rad: float = math.radians(3.0)


class Walk:
    """Closed-form pose ``(p(t), R(t))`` of the walk; batched over times."""

    def __init__(self, config: WalkConfig = WalkConfig()):
        self.config = config
        s = torch.linspace(0, 2 * math.pi, 4001, dtype=torch.float64)
        pts = self._curve(s)
        unit_perimeter = float((pts[1:] - pts[:-1]).norm(dim=-1).sum())
        self.scale = config.perimeter_m / unit_perimeter

    @staticmethod
    def _curve(s: Tensor) -> Tensor:
        x = sum(a * torch.cos(k * s) + b * torch.sin(k * s) for k, a, b in _LOOP_X)
        y = sum(a * torch.cos(k * s) + b * torch.sin(k * s) for k, a, b in _LOOP_Y)
        return torch.stack((x, y), -1)

    def _activity(self, t: Tensor) -> Tensor:
        c = self.config
        return _smoothstep((t - c.stationary_s) / c.ramp_s)

    def _arc(self, t: Tensor) -> Tensor:
        c = self.config
        distance = c.speed_mps * c.ramp_s * _smoothstep_integral((t - c.stationary_s) / c.ramp_s)
        return 2 * math.pi * distance / c.perimeter_m

    def position(self, t: Tensor) -> Tensor:
        """``(..., 3)`` ENU position of the IMU at times ``t`` ``(...)``."""
        c = self.config
        s = self._arc(t)
        xy = self.scale * (self._curve(s) - self._curve(torch.zeros_like(s)))
        z = c.height_m + c.bounce_m * self._activity(t) * torch.sin(2 * math.pi * c.step_hz * t)
        return torch.cat((xy, z.unsqueeze(-1)), -1)

    def _angles(self, t: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        c = self.config
        s = self._arc(t)
        tangent = jacfwd(self._curve)(s) if s.ndim == 0 else vmap(jacfwd(self._curve))(s.reshape(-1)).reshape(*s.shape, 2)
        yaw = torch.atan2(tangent[..., 1], tangent[..., 0])
        act = self._activity(t)
        roll = c.sway_rad * act * torch.sin(math.pi * c.step_hz * t)
        pitch = c.pitch_rad + 0.5 * c.sway_rad * act * torch.sin(2 * math.pi * c.step_hz * t + 0.7)
        return roll, pitch, yaw

    def quaternion(self, t: Tensor) -> Tensor:
        """``(..., 4)`` body->world orientation at times ``t``."""
        return quat.from_euler(*self._angles(t))

    def rotation(self, t: Tensor) -> Tensor:
        return quat.to_matrix(self.quaternion(t))

    def velocity(self, t: Tensor) -> Tensor:
        return vmap(jacfwd(self.position))(t.reshape(-1)).reshape(*t.shape, 3)

    def imu(self, t: Tensor, gravity_mps2: float = STANDARD_GRAVITY_MPS2) -> tuple[Tensor, Tensor]:
        """Exact specific force ``(N, 3)`` (m/s²) and body angular rate ``(N, 3)`` (rad/s)."""
        return body_readings(self.rotation, jacfwd(self.position), t, gravity_mps2)


def body_readings(rotation, velocity, t_s: Tensor, gravity_mps2: float = STANDARD_GRAVITY_MPS2) -> tuple[Tensor, Tensor]:
    """Exact specific force ``(N, 3)`` (m/s²) and body rate ``(N, 3)`` (rad/s) of a trajectory.

    ``rotation(t)`` (body -> world, ``(3, 3)``) and ``velocity(t)`` (``(3,)`` m/s) are
    differentiable functions of a scalar time: ``f = Rᵀ (v̇ + g e_z)``, ``[ω]ₓ = Rᵀ Ṙ``.
    """
    t = t_s.reshape(-1)
    acc_world = vmap(jacfwd(velocity))(t)
    R = vmap(rotation)(t)
    R_dot = vmap(jacfwd(rotation))(t)
    g = torch.tensor([0.0, 0.0, gravity_mps2], dtype=t.dtype)
    f_body = (R.transpose(-1, -2) @ (acc_world + g).unsqueeze(-1)).squeeze(-1)
    W = R.transpose(-1, -2) @ R_dot  # skew(ω_body)
    omega = torch.stack((W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]), -1)
    return f_body, omega


def increment_imu(walk: Walk, t_s: Tensor, gravity_mps2: float = STANDARD_GRAVITY_MPS2) -> tuple[Tensor, Tensor]:
    """Ideal readings ``(N, 3)``, ``(N, 3)`` of an integrating IMU at sample times ``t_s`` ``(N,)``.

    Sample ``k >= 1`` is the constant input over ``(t_{k-1}, t_k]`` that reproduces
    the true motion increment, as a coning- and sculling-compensated
    delta-angle/delta-velocity IMU reports it:

        ω_k = Log(q_{k-1}* ⊙ q_k) / Δt_k
        f_k = C(q_{k-1} ⊙ 𝒬{ω_k Δt_k / 2})ᵀ ((v_k - v_{k-1}) / Δt_k + g)

    so the attitude and velocity of the midpoint mechanization are exact at the
    sample times and only the trapezoidal position step approximates. Sample 0 is
    the instantaneous reading at ``t_0``.
    """
    q = walk.quaternion(t_s)
    v = walk.velocity(t_s)
    dt = (t_s[1:] - t_s[:-1]).unsqueeze(-1)
    theta = quat.to_rotation_vector(quat.multiply(quat.conjugate(q[:-1]), q[1:]))
    omega = theta / dt
    q_mid = quat.multiply(q[:-1], quat.from_rotation_vector(0.5 * theta))
    g = torch.tensor([0.0, 0.0, gravity_mps2], dtype=t_s.dtype)
    world = (v[1:] - v[:-1]) / dt + g
    f = (quat.to_matrix(q_mid).transpose(-1, -2) @ world.unsqueeze(-1)).squeeze(-1)
    f0, w0 = walk.imu(t_s[:1], gravity_mps2)
    return torch.cat((f0, f)), torch.cat((w0, omega))


@dataclass(frozen=True)
class ImuErrors:
    """Consumer-grade MEMS errors (iPad-like defaults)."""

    acc_noise: float = 3e-3  # m/s²/√Hz
    gyro_noise: float = 2e-4  # rad/s/√Hz
    acc_bias_std: float = 0.05  # m/s², turn-on
    gyro_bias_std: float = 0.01  # rad/s, turn-on
    acc_bias_walk: float = 1e-4  # m/s³/√Hz
    gyro_bias_walk: float = 1e-5  # rad/s²/√Hz
    acc_scale_std: float = 0.01  # relative, turn-on


@dataclass(frozen=True)
class Vibration:
    """Rotor- or engine-like vibration of the IMU: a few sinusoids per axis at random
    frequencies in ``band_hz`` with random phases, from the first sample to ``until_s``
    (``None``: the whole recording). Each reading is the vibration's mean over the
    interval the sample ends, as for the rest of the simulated IMU (an integrating
    sensor: tones above half the rate are attenuated, not aliased to low frequencies);
    ``acc_mps2`` and ``gyro_rps`` are the RMS per axis of what the readings show."""

    acc_mps2: float = 0.0
    gyro_rps: float = 0.0
    band_hz: tuple[float, float] = (50.0, 200.0)
    until_s: float | None = None
    tones: int = 4

    def __post_init__(self) -> None:
        if self.acc_mps2 < 0 or self.gyro_rps < 0 or self.tones < 1 or not 0 < self.band_hz[0] <= self.band_hz[1]:
            raise ValueError(f"Vibration: need acc_mps2, gyro_rps >= 0, tones >= 1 and 0 < band_hz[0] <= band_hz[1]; got {self}")


def vibrate(t_s: Tensor, acc_mps2: Tensor, gyro_rps: Tensor, vibration: Vibration,
            generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """``(acc, gyro)`` ``(N, 3)`` with ``vibration`` added (unchanged when both amplitudes are 0).

    Tone ``sin(2πf t + φ)`` read over ``(t_{k-1}, t_k]`` is
    ``(cos(2πf t_{k-1} + φ) - cos(2πf t_k + φ)) / (2πf Δt_k)``; sample 0 reads it at ``t_0``.
    """
    if vibration.acc_mps2 == 0 and vibration.gyro_rps == 0:
        return acc_mps2, gyro_rps
    lo, hi = vibration.band_hz
    on = t_s <= vibration.until_s if vibration.until_s is not None else torch.ones_like(t_s, dtype=torch.bool)

    def shake(rms: float) -> Tensor:  # (N, 3) read vibration with RMS `rms` per axis over the rows `on`
        f = lo + (hi - lo) * torch.rand(3, vibration.tones, generator=generator, dtype=torch.float64)
        phase = 2 * math.pi * torch.rand(3, vibration.tones, generator=generator, dtype=torch.float64)
        angle = 2 * math.pi * f * t_s[:, None, None] + phase  # (N, 3, tones)
        dt = torch.diff(t_s)[:, None, None]
        mean = (torch.cos(angle[:-1]) - torch.cos(angle[1:])) / (2 * math.pi * f * dt)
        wave = torch.cat((torch.sin(angle[:1]), mean)).sum(-1)
        scale = rms / wave[on].pow(2).mean(0).sqrt().clamp_min(1e-12)
        return wave * scale * on.to(t_s.dtype).unsqueeze(-1)

    return acc_mps2 + shake(vibration.acc_mps2), gyro_rps + shake(vibration.gyro_rps)


@dataclass(frozen=True)
class Imperfections:
    """Real sensors' imperfections the simulator can add (each off by default).

    ``gyro_bias_rps`` / ``acc_bias_mps2``: constant offsets added to every reading (rad/s,
    m/s²), on top of the :class:`ImuErrors` biases. ``acc_range_mps2`` / ``gyro_range_rps``:
    readings clipped to ``±`` this (saturation; None: no clip). ``drop_fraction``: the
    fraction of samples dropped (rows removed), in runs of ``drop_run`` consecutive
    samples, as a logger that loses packets does."""

    gyro_bias_rps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    acc_bias_mps2: tuple[float, float, float] = (0.0, 0.0, 0.0)
    acc_range_mps2: float | None = None
    gyro_range_rps: float | None = None
    drop_fraction: float = 0.0
    drop_run: int = 1

    def __post_init__(self) -> None:
        def number(value: object) -> bool:
            return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)

        for key in ("gyro_bias_rps", "acc_bias_mps2"):
            value = getattr(self, key)
            if not isinstance(value, (tuple, list)) or len(value) != 3 or not all(number(v) for v in value):
                raise ValueError(f"Imperfections.{key}={value!r}; expected a tuple of 3 finite numbers")
            object.__setattr__(self, key, tuple(float(v) for v in value))
        for key in ("acc_range_mps2", "gyro_range_rps"):
            value = getattr(self, key)
            if value is not None and not (number(value) and value > 0):
                raise ValueError(f"Imperfections.{key}={value!r}; expected a finite number > 0 or None (no clip)")
        if not (number(self.drop_fraction) and 0.0 <= self.drop_fraction < 0.5):
            raise ValueError(f"Imperfections.drop_fraction={self.drop_fraction!r}; expected 0 <= drop_fraction < 0.5")
        if isinstance(self.drop_run, bool) or not isinstance(self.drop_run, int) or self.drop_run < 1:
            raise ValueError(f"Imperfections.drop_run={self.drop_run!r}; expected an integer >= 1")


#: added to the seed for the generator of :func:`imperfect` (the recording's own stream stays untouched)
_IMPERFECTIONS_SEED = 6_700_417


def imperfections_generator(seed: int) -> torch.Generator:
    """The generator :func:`imperfect` draws the dropped rows from, for a recording of ``seed``."""
    return torch.Generator().manual_seed(seed + _IMPERFECTIONS_SEED)


def dropped_runs(n: int, drop_fraction: float, drop_run: int, generator: torch.Generator) -> Tensor:
    """The kept rows ``(K,)`` (int64, increasing) of ``n`` rows once ``round(drop_fraction n /
    drop_run)`` runs of ``drop_run`` rows are dropped; no random draw when none is.

    The runs never touch the first or last row and never meet (a kept row between any two):
    each run with the kept row after it is a block of ``drop_run + 1`` rows placed in rows
    ``1 .. n-1``; ``k`` such blocks leave ``n - 1 - k (drop_run + 1)`` free rows, and the
    blocks' places follow from ``k`` distinct draws among ``n - 1 - k drop_run`` slots
    (sorted draw ``p_i``: block ``i`` starts at row ``1 + p_i + i drop_run``)."""
    runs = round(drop_fraction * n / drop_run)
    if runs == 0:
        return torch.arange(n)
    slots = n - 1 - runs * drop_run
    if slots < runs:
        raise ValueError(f"Imperfections: {runs} runs of drop_run={drop_run} rows (drop_fraction={drop_fraction}) "
                         f"do not fit apart from each other and from the ends in {n} rows")
    places = torch.randperm(slots, generator=generator)[:runs].sort().values
    starts = 1 + places + drop_run * torch.arange(runs)
    dropped = (starts[:, None] + torch.arange(drop_run)).reshape(-1)
    keep = torch.ones(n, dtype=torch.bool)
    keep[dropped] = False
    return keep.nonzero()[:, 0]


def imperfect(t_s: Tensor, acc_mps2: Tensor, gyro_rps: Tensor, imperfections: Imperfections,
              generator: torch.Generator) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(t_s, acc, gyro, kept_rows)``: the readings ``(N, 3)`` with ``imperfections``.

    In order: the constant biases added, the readings clipped to ``±range``, then rows
    dropped (:func:`dropped_runs`, runs chosen with ``generator``). ``kept_rows`` ``(K,)``
    indexes the input rows that remain (``arange(N)`` when none is dropped). With the
    default :class:`Imperfections` the inputs come back as they are and no random number
    is drawn."""
    acc, gyro = acc_mps2, gyro_rps
    if any(imperfections.acc_bias_mps2):
        acc = acc + torch.tensor(imperfections.acc_bias_mps2, dtype=acc.dtype, device=acc.device)
    if any(imperfections.gyro_bias_rps):
        gyro = gyro + torch.tensor(imperfections.gyro_bias_rps, dtype=gyro.dtype, device=gyro.device)
    if imperfections.acc_range_mps2 is not None:
        acc = acc.clamp(-imperfections.acc_range_mps2, imperfections.acc_range_mps2)
    if imperfections.gyro_range_rps is not None:
        gyro = gyro.clamp(-imperfections.gyro_range_rps, imperfections.gyro_range_rps)
    n = t_s.shape[0]
    kept = dropped_runs(n, imperfections.drop_fraction, imperfections.drop_run, generator).to(t_s.device)
    if kept.shape[0] == n:
        return t_s, acc, gyro, kept
    return t_s[kept], acc[kept], gyro[kept], kept


def imperfect_truth(errors: dict[str, Tensor], imperfections: Imperfections, kept_rows: Tensor) -> dict[str, Tensor]:
    """The true IMU errors of :func:`corrupt_imu` after :func:`imperfect`: the constant
    biases added to ``b_a`` and ``b_w`` ``(N, 3)``, the per-row entries at ``kept_rows``
    (``T_a`` ``(3,)`` stays). Clipping has no error state: it is not in the truth."""
    n = errors["b_a"].shape[0]
    out = dict(errors)
    for key, bias in (("b_a", imperfections.acc_bias_mps2), ("b_w", imperfections.gyro_bias_rps)):
        if any(bias):
            out[key] = out[key] + torch.tensor(bias, dtype=out[key].dtype, device=out[key].device)
    if kept_rows.shape[0] != n:
        out = {key: value[kept_rows] if key in ("b_a", "b_w") else value for key, value in out.items()}
    return out


def sample_times(duration_s: float, rate_hz: float, jitter: float, generator: torch.Generator) -> Tensor:
    """Non-equidistant sample times from 0 to about ``duration_s``; ``jitter`` is relative."""
    n = int(round(duration_s * rate_hz))
    dt = (1.0 + jitter * (2 * torch.rand(n, generator=generator, dtype=torch.float64) - 1)) / rate_hz
    return torch.cat((torch.zeros(1, dtype=torch.float64), torch.cumsum(dt, 0)))


def corrupt_imu(
    t_s: Tensor, f_true: Tensor, w_true: Tensor, errors: ImuErrors, generator: torch.Generator
) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
    """Noisy readings ``ã = f / T_a + b_a + n``, ``ω̃ = ω + b_ω + n`` and the true error states.

    White noise of density σ sampled over Δt has standard deviation σ/√Δt;
    biases start from a random turn-on value and random-walk.
    """
    n = t_s.shape[0]
    dt = torch.diff(t_s, prepend=t_s[:1] - (t_s[1] - t_s[0]))

    def randn(*shape: int) -> Tensor:
        return torch.randn(*shape, generator=generator, dtype=torch.float64)

    b_a = errors.acc_bias_std * randn(3) + torch.cumsum(errors.acc_bias_walk * dt.sqrt().unsqueeze(-1) * randn(n, 3), 0)
    b_w = errors.gyro_bias_std * randn(3) + torch.cumsum(errors.gyro_bias_walk * dt.sqrt().unsqueeze(-1) * randn(n, 3), 0)
    scale = 1.0 + errors.acc_scale_std * randn(3)  # T_a, the correction factor
    acc = f_true / scale + b_a + errors.acc_noise / dt.sqrt().unsqueeze(-1) * randn(n, 3)
    gyro = w_true + b_w + errors.gyro_noise / dt.sqrt().unsqueeze(-1) * randn(n, 3)
    return acc, gyro, {"b_a": b_a, "b_w": b_w, "T_a": scale}


def gnss_track(
    walk: Walk, t_s: Tensor, generator: torch.Generator, *, min_acc_m: float = 3.0, max_acc_m: float = 25.0
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Noisy ENU fixes ``(G, 3)`` with horizontal/vertical 1-σ ``(G,)`` consistent with the noise.

    The accuracy radius varies smoothly between ``min_acc_m`` and ``max_acc_m``.
    Returns ``(true_enu, measured_enu, h_acc, v_acc)``.
    """
    truth = walk.position(t_s)
    phase = torch.rand(3, generator=generator, dtype=torch.float64) * 2 * math.pi
    u = 0.5 + 0.25 * torch.sin(2 * math.pi * t_s / 97.0 + phase[0]) + 0.25 * torch.sin(2 * math.pi * t_s / 41.0 + phase[1])
    h_acc = min_acc_m + (max_acc_m - min_acc_m) * u**2
    v_acc = 1.5 * h_acc
    noise = torch.randn(t_s.shape[0], 3, generator=generator, dtype=torch.float64)
    measured = truth + noise * torch.stack((h_acc, h_acc, v_acc), -1)
    return truth, measured, h_acc, v_acc


@dataclass(frozen=True)
class Recording:
    """A synthetic recording: sensor streams plus everything that is true."""

    imu: ImuStream
    gnss: GnssStream
    truth: PoseStream
    imu_errors: dict[str, Tensor]
    walk: Walk


def synthetic_walk_recording(
    *,
    duration_s: float = 300.0,
    seed: int = 0,
    imu_rate_hz: float = 100.0,
    imu_jitter: float = 0.1,
    gnss_rate_hz: float = 1.0,
    truth_rate_hz: float = 10.0,
    imu_errors: ImuErrors = ImuErrors(),
    vibration: Vibration = Vibration(),
    imperfections: Imperfections = Imperfections(),
    walk: WalkConfig | None = None,
    origin: tuple[float, float, float] = (60.1699, 24.9384, 20.0),
    gravity_mps2: float = STANDARD_GRAVITY_MPS2,
) -> Recording:
    """IMU (with MEMS errors), 1 Hz GNSS (lat/lon/alt around Helsinki) and the true poses.

    Each IMU sample is the true specific force and rate at the middle of the
    interval it ends (the sample represents its interval, as an integrating
    sensor's does), corrupted by :func:`corrupt_imu`, shaken by ``vibration``
    (:func:`vibrate`) and given ``imperfections`` (:func:`imperfect`; its dropped rows are
    drawn from a generator of their own, so the rest of the recording, GNSS included, is
    the one without them). ``imu_errors`` stays the truth of the readings returned: the
    constant biases added, the rows kept. Deterministic in ``seed``.
    """
    from flowins.data.streams import GnssStream, ImuStream, PoseStream
    from flowins.geometry.geodesy import LocalTangentPlane

    gen = torch.Generator().manual_seed(seed)
    w = Walk(walk or WalkConfig(duration_s=duration_s))
    t = sample_times(duration_s, imu_rate_hz, imu_jitter, gen)
    t_mid = torch.cat((t[:1], 0.5 * (t[1:] + t[:-1])))
    f_true, w_true = w.imu(t_mid, gravity_mps2)
    acc, gyro, errors = corrupt_imu(t, f_true, w_true, imu_errors, gen)
    acc, gyro = vibrate(t, acc, gyro, vibration, gen)
    t_imu, acc, gyro, kept = imperfect(t, acc, gyro, imperfections, imperfections_generator(seed))
    errors = imperfect_truth(errors, imperfections, kept)
    t_gnss = torch.arange(1.0 / gnss_rate_hz, float(t[-1]), 1.0 / gnss_rate_hz, dtype=torch.float64)
    _, enu, h_acc, v_acc = gnss_track(w, t_gnss, gen)
    plane = LocalTangentPlane(*origin)
    start = w.position(t[:1])[0]
    lat, lon, alt = plane.to_geodetic(enu - start)  # the walk starts at the origin
    t_truth = torch.arange(0.0, float(t[-1]), 1.0 / truth_rate_hz, dtype=torch.float64)
    return Recording(
        imu=ImuStream(t_imu, acc, gyro, name="synthetic IMU"),
        gnss=GnssStream(t_gnss, lat, lon, alt, h_acc, v_acc, name="synthetic GNSS"),
        truth=PoseStream(t_truth, w.position(t_truth) - start, w.quaternion(t_truth), name="synthetic ground truth"),
        imu_errors=errors,
        walk=w,
    )


def noisy_truth(truth, *, position_sigma_m: float, attitude_sigma_rad: float, generator: torch.Generator,
                name: str = "noisy ground truth"):
    """``truth`` (a :class:`~flowins.data.streams.PoseStream` with orientations) as a motion-capture
    system would record it: white noise of ``position_sigma_m`` per axis on the positions and a
    rotation vector of ``attitude_sigma_rad`` per axis on the orientations (body frame)."""
    from flowins.data.streams import PoseStream

    n = truth.t_s.shape[0]
    turn = quat.from_rotation_vector(attitude_sigma_rad * torch.randn(n, 3, generator=generator, dtype=torch.float64))
    shift = position_sigma_m * torch.randn(n, 3, generator=generator, dtype=torch.float64)
    return PoseStream(truth.t_s, truth.pos_m + shift, quat.multiply(truth.quat_wxyz, turn), name=name)
