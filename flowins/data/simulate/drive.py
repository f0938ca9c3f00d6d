"""A simulated car drive: moving from the first sample, open-sky GNSS with an outage.

The scenario a car recording poses: the IMU's first sample is taken at speed (8–15 m/s),
so no still start exists; GNSS fixes come at ``gnss_rate_hz`` with ``gnss_sigma_m``
open-sky accuracy, except for ``outage_s`` in the middle of the drive (a tunnel); the
IMU has automotive-grade MEMS errors. There is no camera. The ground truth is exact.

Trajectory (closed form in the velocity): speed ``v(t)``, heading ``ψ(t)`` and road
grade ``θ(t)`` are sums of sinusoids, so the velocity
``v [cos θ cos ψ, cos θ sin ψ, sin θ]`` of the car's non-slipping point (the middle of its
rear axle) and its derivatives are exact; the position is its integral by 8-point
Gauss–Legendre quadrature over 0.25 s pieces (exact to rounding for these smooth inputs).
The car's axes: x along the velocity, z up from the road, rolled by
``roll_per_lateral_rad`` per m/s² of lateral acceleration. What makes a constant σ of the
vehicle constraint wrong: the nose turns into a turn by ``slip_per_lateral_rad`` per m/s² of
lateral acceleration (the rear axle slips sideways), pitches by ``pitch_per_acceleration_rad``
per m/s² of forward acceleration (nose down when braking), and the road has bumps
(``bump_height_m`` every ``bump_every_s``; each a Gaussian of ``bump_width_s`` in time), where
the car moves up and down. Each 0 switches it off.

The IMU is mounted on the car: its axes are the car's turned by ``imu_mount_yaw_rad`` about
the car's up axis, then ``imu_mount_pitch_rad`` about the turned lateral axis (the
attitude's Euler convention, :func:`~flowins.geometry.quaternion.from_euler`; the vehicle
constraint's ``mount_*_rad``), and the non-slipping point lies ``imu_lever_m`` from it
along the car's forward, left and up axes (the constraint's ``lever_*_m``). The readings,
the GNSS fixes and the ground truth are the IMU's (both 0 by default: the IMU's axes are the
car's, at the non-slipping point). World frame: local ENU with its origin at the start of
the drive.
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.func import jacfwd, vmap

from flowins.cache import cache_root, content_key, folder_lock, library_versions, source_digest
from flowins.data.sequence import Sequence
from flowins.data.simulate.gnss import GnssErrors, simulate_fixes
from flowins.data.simulate.scenario import SIMULATOR_CODE, open_simulation, seal_simulation
from flowins.data.streams import GnssStream, ImuStream, PoseStream
from flowins.data.synthetic import (ImuErrors, Imperfections, body_readings, corrupt_imu, imperfect, imperfect_truth,
                                    imperfections_generator, increment_imu, sample_times)
from flowins.geometry import quaternion as quat
from flowins.geometry.geodesy import LocalTangentPlane
from flowins.constants import STANDARD_GRAVITY_MPS2

#: automotive-grade MEMS (the filter's ``configs/imu/simulated_drive.yaml`` holds the same densities)
AUTOMOTIVE_IMU = ImuErrors(
    acc_noise=1.5e-3, gyro_noise=1.5e-4, acc_bias_std=0.03, gyro_bias_std=1e-3,
    acc_bias_walk=5e-5, gyro_bias_walk=5e-6, acc_scale_std=0.005,
)

# (amplitude, period s, phase rad) of the sinusoids: speed m/s, yaw rate rad/s, grade rad
_SPEED = ((2.0, 97.0, 0.4), (1.0, 41.0, 2.1), (0.5, 17.0, 0.9))
_YAW_RATE = ((0.08, 71.0, 0.0), (0.05, 29.0, 1.3), (0.03, 13.0, 2.6))
_GRADE = ((0.02, 83.0, 0.7), (0.01, 37.0, 1.9))


@dataclass(frozen=True)
class DriveConfig:
    duration_s: float = 300.0
    seed: int = 0
    mean_speed_mps: float = 11.5
    heading_rad: float = 0.5
    roll_per_lateral_rad: float = 0.01
    #: the car's nose turned into a turn by this per m/s² of lateral acceleration (its rear axle slips out)
    slip_per_lateral_rad: float = 0.005
    #: the car's nose up by this per m/s² of forward acceleration (down when braking)
    pitch_per_acceleration_rad: float = 0.01
    #: the road's slopes (a sum of sinusoids up to about 0.03 rad) times this: 0 for a flat road
    grade_scale: float = 1.0
    #: bumps in the road: this high, one every ``bump_every_s``, each ``exp(-(Δt / bump_width_s)²)`` in time
    bump_height_m: float = 0.03
    bump_every_s: float = 15.0
    bump_width_s: float = 0.1
    imu_rate_hz: float = 100.0
    imu_jitter: float = 0.05
    imu_errors: ImuErrors = AUTOMOTIVE_IMU
    gnss_rate_hz: float = 1.0
    gnss_sigma_m: float = 1.0
    gnss_correlation_s: float = 10.0
    #: no fixes for this long around the middle of the drive (0: none)
    outage_s: float = 60.0
    groundtruth_rate_hz: float = 10.0
    origin: tuple[float, float, float] = (49.0110, 8.4164, 115.0)  # Karlsruhe, ellipsoidal height
    gravity_mps2: float = STANDARD_GRAVITY_MPS2
    #: constant biases, clipping and dropped rows of the IMU (none by default)
    imperfections: Imperfections = Imperfections()
    #: the IMU turned from the car's axes (rad; module docstring)
    imu_mount_pitch_rad: float = 0.0
    imu_mount_yaw_rad: float = 0.0
    #: the car's non-slipping point from the IMU along the car's forward, left and up axes (m)
    imu_lever_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if not isinstance(self.imperfections, Imperfections):
            raise ValueError(f"DriveConfig.imperfections={self.imperfections!r}; expected an Imperfections")
        if self.duration_s < 20.0:
            raise ValueError(f"DriveConfig.duration_s={self.duration_s}; expected >= 20 s")
        if not 0.0 <= self.grade_scale <= 10.0:
            raise ValueError(f"DriveConfig.grade_scale={self.grade_scale}; expected a factor in [0, 10] on the road's "
                             "slopes (0: a flat road)")
        if not (self.bump_every_s > 0.0 and self.bump_width_s > 0.0 and self.bump_height_m >= 0.0):
            raise ValueError(f"DriveConfig: bump_height_m={self.bump_height_m}, bump_every_s={self.bump_every_s}, "
                             f"bump_width_s={self.bump_width_s}; expected a height >= 0 and times > 0")
        if not 0.0 <= self.outage_s < self.duration_s - 10.0:
            raise ValueError(f"DriveConfig.outage_s={self.outage_s}; expected in [0, duration_s - 10)")

    def outage(self) -> tuple[float, float]:
        """``(t0, t1)`` s of the GNSS outage."""
        middle = 0.5 * self.duration_s
        return middle - 0.5 * self.outage_s, middle + 0.5 * self.outage_s

    def as_plain(self) -> dict[str, Any]:
        """The configuration as JSON-ready dicts, lists, numbers and strings."""
        return json.loads(json.dumps(asdict(self), default=str))

    def key(self) -> str:
        return content_key({"scenario": "drive", "config": self.as_plain(),
                            "code": source_digest(*SIMULATOR_CODE), "libraries": library_versions()})


def _waves(t: Tensor, terms: tuple[tuple[float, float, float], ...]) -> Tensor:
    return sum(a * torch.sin(2 * math.pi * t / T + p) for a, T, p in terms)


def _wave_rate(t: Tensor, terms: tuple[tuple[float, float, float], ...]) -> Tensor:
    """``d/dt`` of :func:`_waves`."""
    return sum(a * 2 * math.pi / T * torch.cos(2 * math.pi * t / T + p) for a, T, p in terms)


def _wave_integral(t: Tensor, terms: tuple[tuple[float, float, float], ...]) -> Tensor:
    """``∫₀ᵗ`` of :func:`_waves`."""
    return sum(a * T / (2 * math.pi) * (math.cos(p) - torch.cos(2 * math.pi * t / T + p)) for a, T, p in terms)


class Drive:
    """Closed-form velocity and attitude of the drive, its position by quadrature; batched over
    times. ``quaternion``, ``rotation``, ``velocity`` and ``position`` are the IMU's; ``car_*``
    the car's (its non-slipping point's)."""

    def __init__(self, config: DriveConfig = DriveConfig()):
        self.config = config
        c = config
        self._mounted = c.imu_mount_pitch_rad != 0.0 or c.imu_mount_yaw_rad != 0.0
        self._lever = any(x != 0.0 for x in c.imu_lever_m)

    def speed(self, t: Tensor) -> Tensor:
        return self.config.mean_speed_mps + _waves(t, _SPEED)

    def _track(self, t: Tensor) -> tuple[Tensor, Tensor]:
        """``(grade, heading)`` rad of the velocity."""
        return self.config.grade_scale * _waves(t, _GRADE), self.config.heading_rad + _wave_integral(t, _YAW_RATE)

    def _angles(self, t: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The car's roll, pitch and yaw: the track's, rolled and slipped by the lateral
        acceleration and pitched by the longitudinal one."""
        c = self.config
        grade, heading = self._track(t)
        lateral = self.speed(t) * _waves(t, _YAW_RATE)  # centripetal acceleration, m/s² (to the left)
        along = _wave_rate(t, _SPEED)  # m/s²
        roll = c.roll_per_lateral_rad * lateral
        pitch = -grade - c.pitch_per_acceleration_rad * along  # nose up climbing and accelerating (pitch < 0)
        return roll, pitch, heading + c.slip_per_lateral_rad * lateral  # the nose into the turn

    def _bumps(self, t: Tensor) -> tuple[Tensor, Tensor]:
        """``(height m, its rate m/s)`` of the road's bumps at ``t``: ``h exp(-((t - t_k) / w)²)``
        at ``t_k = (k + 1/2) · bump_every_s``."""
        c = self.config
        k = torch.arange(int(c.duration_s // c.bump_every_s) + 1, dtype=t.dtype)
        u = (t.unsqueeze(-1) - (k + 0.5) * c.bump_every_s) / c.bump_width_s
        bell = c.bump_height_m * torch.exp(-u * u)
        return bell.sum(-1), (-2.0 * u / c.bump_width_s * bell).sum(-1)

    def car_quaternion(self, t: Tensor) -> Tensor:
        """``(..., 4)`` car->world orientation."""
        return quat.from_euler(*self._angles(t))

    def quaternion(self, t: Tensor) -> Tensor:
        """``(..., 4)`` IMU->world orientation: the car's turned by the mounting."""
        q = self.car_quaternion(t)
        if not self._mounted:
            return q
        c = self.config
        mount = quat.from_euler(*(torch.tensor(a, dtype=t.dtype) for a in (0.0, c.imu_mount_pitch_rad,
                                                                            c.imu_mount_yaw_rad)))
        return quat.multiply(q, mount.expand_as(q))

    def rotation(self, t: Tensor) -> Tensor:
        return quat.to_matrix(self.quaternion(t))

    def _lever_world(self, t: Tensor) -> Tensor:
        """``(..., 3)``: the non-slipping point from the IMU in the world frame, ``C_wc(t) r_c``."""
        r = torch.tensor(self.config.imu_lever_m, dtype=t.dtype)
        return (quat.to_matrix(self.car_quaternion(t)) @ r).reshape(*t.shape, 3)

    def velocity(self, t: Tensor) -> Tensor:
        """``(..., 3)`` ENU velocity of the IMU, m/s: the car's less the lever arm's turn."""
        v = self.car_velocity(t)
        if not self._lever:
            return v
        turn = vmap(jacfwd(self._lever_world))(t.reshape(-1))
        return v - turn.reshape(*t.shape, 3)

    def position(self, t: Tensor) -> Tensor:
        """``(..., 3)`` ENU position of the IMU (the car's non-slipping point at ``t = 0`` is the origin)."""
        p = self.car_position(t)
        return p - self._lever_world(t) if self._lever else p

    def _track_velocity(self, t: Tensor) -> Tensor:
        """``(..., 3)`` ENU velocity along the track (no bumps), m/s."""
        grade, yaw = self._track(t)
        direction = torch.stack((torch.cos(grade) * torch.cos(yaw), torch.cos(grade) * torch.sin(yaw), torch.sin(grade)), -1)
        return self.speed(t).unsqueeze(-1) * direction

    def car_velocity(self, t: Tensor) -> Tensor:
        """``(..., 3)`` ENU velocity of the car's non-slipping point, m/s: the track's and the bumps'."""
        v = self._track_velocity(t)
        if self.config.bump_height_m == 0.0:
            return v
        _, rate = self._bumps(t)
        return v + torch.stack((torch.zeros_like(rate), torch.zeros_like(rate), rate), -1)

    def car_position(self, t: Tensor) -> Tensor:
        """``(..., 3)`` ENU position of the car's non-slipping point (origin at ``t = 0``): the
        track velocity's integral, and the bumps' heights."""
        nodes, weights = np.polynomial.legendre.leggauss(8)
        nodes, weights = torch.tensor(nodes, dtype=t.dtype), torch.tensor(weights, dtype=t.dtype)
        flat = t.reshape(-1)
        top = float(flat.max()) if flat.numel() else 0.0
        breaks = torch.unique(torch.cat((torch.arange(0.0, top, 0.25, dtype=t.dtype), flat, flat.new_zeros(1))))
        a, b = breaks[:-1], breaks[1:]
        mid, half = 0.5 * (a + b), 0.5 * (b - a)
        samples = self._track_velocity(mid[:, None] + half[:, None] * nodes)  # (pieces, 8, 3)
        pieces = half[:, None] * (weights[None, :, None] * samples).sum(1)
        at_breaks = torch.cat((breaks.new_zeros(1, 3), torch.cumsum(pieces, 0)))
        p = at_breaks[torch.searchsorted(breaks, flat)].reshape(*t.shape, 3)
        if self.config.bump_height_m == 0.0:
            return p
        height = self._bumps(t)[0] - self._bumps(torch.zeros((), dtype=t.dtype))[0]
        return p + torch.stack((torch.zeros_like(height), torch.zeros_like(height), height), -1)

    def imu(self, t: Tensor, gravity_mps2: float = STANDARD_GRAVITY_MPS2) -> tuple[Tensor, Tensor]:
        """Exact specific force ``(N, 3)`` and body rate ``(N, 3)``."""
        return body_readings(self.rotation, self.velocity, t, gravity_mps2)


def default_drive_dir(config: DriveConfig) -> Path:
    """``$FLOWINS_CACHE/simulated/drive-<key>``."""
    return cache_root() / "simulated" / f"drive-{config.key()}"


def drive_sequence(config: DriveConfig = DriveConfig()) -> tuple[Sequence, dict[str, Tensor]]:
    """The drive as a :class:`Sequence` (IMU, GNSS, ground truth) and its true IMU errors.

    ``config.imperfections`` apply to the IMU as in the walk (:func:`~flowins.data.synthetic.imperfect`,
    dropped rows drawn from a generator of their own); the true errors are those of the rows kept."""
    gen = torch.Generator().manual_seed(config.seed)
    drive = Drive(config)
    t = sample_times(config.duration_s, config.imu_rate_hz, config.imu_jitter, gen)
    f_true, w_true = increment_imu(drive, t, config.gravity_mps2)
    acc, gyro, imu_truth = corrupt_imu(t, f_true, w_true, config.imu_errors, gen)
    t_imu, acc, gyro, kept = imperfect(t, acc, gyro, config.imperfections, imperfections_generator(config.seed))
    imu_truth = imperfect_truth(imu_truth, config.imperfections, kept)
    t_end = float(t[-1])
    t_gnss = torch.arange(0.5 / config.gnss_rate_hz, t_end, 1.0 / config.gnss_rate_hz, dtype=torch.float64)
    errors = GnssErrors(rate_hz=config.gnss_rate_hz, min_acc_m=config.gnss_sigma_m, max_acc_m=config.gnss_sigma_m,
                        correlation_s=config.gnss_correlation_s, smoothing_s=0.0, multipath_probability=0.0)
    enu, h_acc, v_acc, _ = simulate_fixes(drive.position(t_gnss), torch.zeros_like(t_gnss), errors, gen)
    t0, t1 = config.outage()
    keep = (t_gnss < t0) | (t_gnss >= t1) if config.outage_s > 0 else torch.ones_like(t_gnss, dtype=torch.bool)
    lat, lon, alt = LocalTangentPlane(*config.origin).to_geodetic(enu[keep])
    t_gt = torch.arange(0.0, t_end, 1.0 / config.groundtruth_rate_hz, dtype=torch.float64)
    metadata: dict[str, Any] = {
        "source": "flowins simulator (drive)",
        "imu": "simulated_drive",
        "simulation": {"key": config.key(), "scenario": "drive",
                       "config": config.as_plain()},
        "world_frame": "local ENU (x east, y north, z up); origin at the start of the drive",
        "gnss_origin_lat_lon_alt": list(config.origin),
        "gnss_outage_s": [t0, t1] if config.outage_s > 0 else None,
    }
    metadata["name"] = f"simulated drive (seed {config.seed})"  # the folder's name is the cache key
    sequence = Sequence(
        ImuStream(t_imu, acc, gyro, name="simulated car IMU"),
        name=metadata["name"],
        gnss=GnssStream(t_gnss[keep], lat, lon, alt, h_acc[keep], v_acc[keep], name="simulated GNSS"),
        groundtruth=PoseStream(t_gt, drive.position(t_gt), drive.quaternion(t_gt), name="simulated ground truth"),
        metadata=metadata,
    )
    return sequence, imu_truth


def simulate_drive(out: str | Path | None = None, config: DriveConfig = DriveConfig(), *,
                   overwrite: bool = False) -> Sequence:
    """Write the drive to ``out`` (default :func:`default_drive_dir`) in the flowins folder
    format, or read it back when the folder holds it already (the walk's caching rules)."""
    in_cache = out is None
    out = Path(out) if out is not None else default_drive_dir(config)
    key = config.key()
    with folder_lock(out):
        held = open_simulation(out, key, overwrite=overwrite, in_cache=in_cache)
        return held if held is not None else _simulate_drive(out, config, key)


def _simulate_drive(out: Path, config: DriveConfig, key: str) -> Sequence:
    """Simulate the drive of ``config`` into the empty folder ``out`` and seal it as ``key``."""
    from flowins.data.folder import write_folder

    sequence, imu_truth = drive_sequence(config)
    write_folder(sequence, out, overwrite=True)
    (out / "truth").mkdir(exist_ok=True)
    np.savetxt(
        out / "truth" / "imu_errors.csv",
        torch.cat((sequence.imu.t_s.unsqueeze(-1), imu_truth["b_a"], imu_truth["b_w"]), -1).numpy(),
        delimiter=",", header="t,bax,bay,baz,bwx,bwy,bwz", comments="", fmt="%.17g",
    )
    return seal_simulation(out, key)


__all__ = ["AUTOMOTIVE_IMU", "Drive", "DriveConfig", "default_drive_dir", "drive_sequence", "simulate_drive"]
