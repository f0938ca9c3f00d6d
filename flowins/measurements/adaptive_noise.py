"""Adaptive measurement noise: a small network over the IMU's recent readings that scales a
pseudo-measurement's 1-σs at each update.

A constant σ cannot say *when* a measurement deserves trust: a car's "no sideways velocity"
holds on a straight road and fails in a tight turn or over a bump. As ai-imu-dr does for its
pseudo-measurements, :class:`AdaptiveNoise` reads the IMU's last ``samples`` readings before an
update (:func:`imu_windows`: the gyroscope in rad/s and the accelerometer in g, 6 channels) and
returns one factor per σ,

    s = exp(B tanh(z / B)),   B = decades · ln 10,

where ``z`` is its output, so each factor stays within ``10^±decades`` of 1 whatever the
weights are. Its last layer starts at zero: an untrained module is the constant σs exactly.
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

#: the IMU readings a factor reads: 1 s at 100 Hz
WINDOW_SAMPLES = 100


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


class AdaptiveNoise(nn.Module):
    """IMU windows ``(E, 6, S)`` -> σ factors ``(E, outputs)`` (module docstring)."""

    def __init__(self, outputs: int = 2, *, channels: int = 8, decades: float = 1.0) -> None:
        super().__init__()
        if not decades > 0:
            raise ValueError(f"AdaptiveNoise: decades={decades!r}; expected a number > 0")
        f64 = {"dtype": torch.float64}
        self.conv1 = nn.Conv1d(6, channels, 9, stride=2, **f64)
        self.conv2 = nn.Conv1d(channels, channels, 9, stride=2, **f64)
        self.head = nn.Linear(channels, outputs, **f64)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        self.register_buffer("decades", torch.tensor(float(decades), **f64))

    def forward(self, windows: Tensor) -> Tensor:
        x = torch.relu(self.conv1(windows.to(self.head.weight.dtype)))
        x = torch.relu(self.conv2(x))
        z = self.head(x.mean(-1))
        scale = self.decades * math.log(10.0)
        return torch.exp(scale * torch.tanh(z / scale))
