"""Adaptive measurement noise: a small network over the IMU's recent readings that scales a
pseudo-measurement's 1-σs at each update.

A constant σ cannot say *when* a measurement deserves trust: a car's "no sideways velocity"
holds on a straight road and fails in a tight turn or over a bump. As ai-imu-dr does for its
pseudo-measurements, :class:`AdaptiveNoise` reads the IMU's last ``samples`` readings before an
update (:func:`imu_windows`: the gyroscope in rad/s and the accelerometer in g, 6 channels) and
returns one factor per σ,

    s = exp(B tanh(z / B)),   B = decades · ln 10,

where ``z`` is its output, so each factor stays within ``10^±decades`` of 1 whatever the
weights are. With ``angles > 0`` it also returns that many angles ``α = A tanh(y / A)`` (rad),
``A = angle_bound_rad``, from further outputs ``y`` (the head's, plus a linear map of the mean
of the last ``RECENT_SAMPLES`` readings: a car's slip angle grows about linearly with its
lateral acceleration, its pitch with its forward one): for the vehicle constraint, offsets of
the mounting's pitch and yaw at each update, the car's pitch under acceleration and its slip
in a turn, which no σ can take out of the constraint (a σ only weighs a biased measurement
down). Its last layer starts at zero: an untrained module is the constant σs (and the given
mounting) exactly.

On a slope the specific force's forward part holds ``g sin(slope)``, which the linear path
reads as an acceleration. With ``compensate_gravity`` its specific-force columns read the
car's acceleration instead, ``a = T_a ⊙ (f̄ - b_a) - C(q)ᵀ (0, 0, g)`` in the IMU's axes (g),
with the filter's attitude ``q``, accelerometer bias and scale at the update
(:func:`acceleration_g`): the network's other outputs come before the filter runs
(:meth:`AdaptiveNoise.split`), the angles at each update (:meth:`AdaptiveNoise.bounded_angles`).
The state is an input there, as the gyroscope's reading is: the update's Jacobian does not
differentiate the angles; training does.

Two strided 1-D convolutions (kernel 9, stride 2, ReLU), a mean over time and a linear head:
1,042 weights for 8 channels and 2 outputs. The module is float64, as the filter is.
``train.py`` learns it through the filter (``model.adaptive=[vehicle]``,
:class:`~flowins.training.parameters.FilterParameters`) and saves it in the checkpoint.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from flowins.constants import STANDARD_GRAVITY_MPS2
from flowins.geometry import quaternion as quat

#: the IMU readings a factor reads: 1 s at 100 Hz
WINDOW_SAMPLES = 100
#: the last readings whose mean the angles' linear path reads: 0.2 s at 100 Hz
RECENT_SAMPLES = 20


def steady_window(up_in_imu: Tensor, samples: int = WINDOW_SAMPLES) -> Tensor:
    """``(1, 6, samples)``: the readings of a car going straight at a constant speed on a level
    road, the gyroscope at 0 and the specific force 1 g along ``up_in_imu (3,)`` (the car's up
    axis in the IMU frame), laid out as :func:`imu_windows` lays them."""
    reading = torch.cat((torch.zeros_like(up_in_imu), up_in_imu))
    return reading.reshape(1, 6, 1).expand(1, 6, samples)


def covering_sample(t_imu_s: Tensor, times_s: Tensor) -> Tensor:
    """``(E,)``: for each of ``times_s (E,)`` the IMU sample ``k`` with ``t_{k-1} < t <= t_k`` (an
    integrating IMU's sample ``k`` is the rate over that interval), the last one after the end."""
    k = torch.searchsorted(t_imu_s.contiguous(), times_s.to(t_imu_s.dtype).contiguous(), side="left")
    return k.clamp(max=len(t_imu_s) - 1)


def imu_windows(t_imu_s: Tensor, acc_mps2: Tensor, gyro_rps: Tensor, times_s: Tensor,
                samples: int = WINDOW_SAMPLES) -> Tensor:
    """``(E, 6, samples)``: for each of ``times_s (E,)`` the IMU samples up to the one that covers
    it (an integrating IMU's sample ``k`` covers ``(t_{k-1}, t_k]``), the gyroscope (rad/s) then
    the accelerometer (g); before the first sample the first is repeated."""
    k = covering_sample(t_imu_s, times_s)
    idx = (k.unsqueeze(-1) - samples + 1 + torch.arange(samples, device=k.device)).clamp(min=0)
    readings = torch.cat((gyro_rps, acc_mps2 / STANDARD_GRAVITY_MPS2), -1)  # (N, 6)
    return readings[idx].transpose(-1, -2)


def recent_force_g(windows: Tensor) -> Tensor:
    """``(E, 3)``: the mean specific force (g, IMU axes) of the last ``RECENT_SAMPLES`` readings of
    ``windows (E, 6, S)`` (:func:`imu_windows`)."""
    return windows[..., 3:, -RECENT_SAMPLES:].mean(-1)


def acceleration_g(force_g: Tensor, q: Tensor, gravity_mps2: float | Tensor = STANDARD_GRAVITY_MPS2, *,
                   acc_bias_mps2: Tensor | None = None, acc_scale: Tensor | None = None) -> Tensor:
    """``(..., 3)``: the acceleration (g, IMU axes) ``a = T_a ⊙ (f - b_a) - C(q)ᵀ (0, 0, g)`` of a
    measured specific force ``force_g (..., 3)`` (g, IMU axes) at the attitude ``q (..., 4)`` (IMU
    to ENU), corrected by the accelerometer's bias ``acc_bias_mps2 (..., 3)`` and scale
    ``acc_scale (..., 3)`` where given (the filter's estimates; the mechanization's model)."""
    if acc_bias_mps2 is not None:
        force_g = force_g - acc_bias_mps2.to(force_g) / STANDARD_GRAVITY_MPS2
    if acc_scale is not None:
        force_g = acc_scale.to(force_g) * force_g
    g = torch.as_tensor(gravity_mps2, dtype=force_g.dtype, device=force_g.device) / STANDARD_GRAVITY_MPS2
    return force_g - g * quat.to_matrix(q.to(force_g))[..., 2, :]  # C(q)ᵀ e_up: the third row of C(q)


class AdaptiveNoise(nn.Module):
    """IMU windows ``(E, 6, S)`` -> σ factors ``(E, outputs)``, and with ``angles > 0`` the tuple
    of them and angles ``(E, angles)`` in rad (module docstring)."""

    def __init__(self, outputs: int = 2, *, channels: int = 8, decades: float = 1.0, angles: int = 0,
                 angle_bound_rad: float = 0.05, compensate_gravity: bool = False) -> None:
        super().__init__()
        if not decades > 0:
            raise ValueError(f"AdaptiveNoise: decades={decades!r}; expected a number > 0")
        if angles and not 0 < angle_bound_rad <= 0.5:
            raise ValueError(f"AdaptiveNoise: angle_bound_rad={angle_bound_rad!r}; expected a number in (0, 0.5] rad")
        if compensate_gravity and not angles:
            raise ValueError("AdaptiveNoise: compensate_gravity=True without angles; it acts on the angles' linear path")
        f64 = {"dtype": torch.float64}
        self.outputs = outputs
        self.conv1 = nn.Conv1d(6, channels, 9, stride=2, **f64)
        self.conv2 = nn.Conv1d(channels, channels, 9, stride=2, **f64)
        self.head = nn.Linear(channels, outputs + angles, **f64)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        self.register_buffer("decades", torch.tensor(float(decades), **f64))
        if angles:  # only then: a checkpoint without angles keeps its layout
            self.recent = nn.Linear(6, angles, bias=False, **f64)
            nn.init.zeros_(self.recent.weight)
            self.register_buffer("angle_bound_rad", torch.tensor(float(angle_bound_rad), **f64))
        if compensate_gravity:  # a buffer, so that a checkpoint says so
            self.register_buffer("compensate_gravity", torch.tensor(1.0, **f64))

    @property
    def angles(self) -> int:
        """How many angles it returns beside the factors (0: factors only)."""
        return self.head.out_features - self.outputs

    @property
    def compensates_gravity(self) -> bool:
        """Whether the angles read the car's acceleration, not the specific force (module docstring)."""
        return hasattr(self, "compensate_gravity")

    def _outputs(self, windows: Tensor) -> tuple[Tensor, Tensor]:
        """``(z (E, outputs), y (E, angles))``: the factors' and the angles' outputs, unbounded
        (with ``compensate_gravity``, ``y`` without the specific force's part)."""
        windows = windows.to(self.head.weight.dtype)
        x = torch.relu(self.conv1(windows))
        x = torch.relu(self.conv2(x))
        z = self.head(x.mean(-1))
        y = z[..., self.outputs:]
        if self.angles:
            recent = windows[..., -RECENT_SAMPLES:].mean(-1)
            if self.compensates_gravity:
                y = y + recent[..., :3] @ self.recent.weight[:, :3].T
            else:
                y = y + self.recent(recent)
        return z[..., :self.outputs], y

    def split(self, windows: Tensor, steady: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
        """``(factors (E, outputs), y (E, angles) or None)``: the factors of ``windows (E, 6, S)``
        and, with angles, their outputs before :meth:`bounded_angles`, relative to those of
        ``steady (1, 6, S)`` where given (the readings of a car going straight at a constant speed
        on a level road: no slip and no pitch there, whatever the weights; the mounting's constant
        part is the mounting's, ``mount_*_rad``)."""
        with_steady = steady is not None and self.angles
        # the steady reference in the same call as the windows: a convolution's rounding may depend
        # on its batch's size, a row's within one call does not
        z, y = self._outputs(torch.cat((windows, steady.to(windows)), 0) if with_steady else windows)
        if with_steady:
            # with compensate_gravity the steady car's acceleration, 0, adds nothing
            z, y = z[:-1], y[:-1] - y[-1:]
        scale = self.decades * math.log(10.0)
        return torch.exp(scale * torch.tanh(z / scale)), (y if self.angles else None)

    def bounded_angles(self, y: Tensor, acceleration: Tensor | None = None) -> Tensor:
        """``(E, angles)`` rad: ``A tanh(y' / A)`` of :meth:`split`'s ``y (E, angles)``, where
        ``y' = y + W_f a`` with ``compensate_gravity`` (``a (E, 3)``: the car's acceleration, g,
        IMU axes, :func:`acceleration_g`; ``W_f`` the linear path's specific-force columns) and
        ``y' = y`` without."""
        if self.compensates_gravity:
            if acceleration is None:
                raise ValueError("AdaptiveNoise.bounded_angles: the network reads the car's acceleration "
                                 "(compensate_gravity); expected acceleration (E, 3) in g")
            y = y + acceleration.to(y) @ self.recent.weight[:, 3:].T
        bound = self.angle_bound_rad
        return bound * torch.tanh(y / bound)

    def forward(self, windows: Tensor, steady: Tensor | None = None,
                acceleration: Tensor | None = None) -> Tensor | tuple[Tensor, Tensor]:
        """The factors of ``windows (E, 6, S)``; with angles, the tuple of them and the angles
        (:meth:`split`, :meth:`bounded_angles`; ``acceleration (E, 3)`` where the network
        compensates gravity)."""
        factors, y = self.split(windows, steady)
        if not self.angles:
            return factors
        return factors, self.bounded_angles(y, acceleration)
