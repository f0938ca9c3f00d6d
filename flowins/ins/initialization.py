"""Initialisation from a stationary start (the paper's device is held still for about 5 s).

Over the stationary window the mean specific force ``f̄`` points up in the body
frame, which fixes roll and pitch; the mean angular rate is the gyroscope bias
(Earth's rotation, 7.3e-5 rad/s, is below consumer-grade noise and ignored); yaw
is not observable and is set to ``yaw_rad`` with a large variance ("yaw free").
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from flowins.geometry import quaternion as quat
from flowins.state import CORE_DIM, STATE, STATE_DIM, make_state, symmetrize


@dataclass(frozen=True)
class InitialUncertainty:
    """1-σ of the initial state (units of each state block)."""

    position_m: float = 0.01
    velocity_mps: float = 0.05
    roll_pitch_rad: float = math.radians(2.0)
    yaw_rad: float = math.pi
    acc_bias_mps2: float = 0.1
    gyro_bias_rps: float = 2e-3
    acc_scale: float = 0.02
    #: variance along the quaternion itself (its length); rotations ignore it,
    #: it only keeps the 4x4 block positive definite
    quaternion_radial: float = 1e-3
    #: nugget between the current pose and its augmented copy
    augmentation_nugget_var: float = 1e-9


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
    T[STATE.p_prev, STATE.p] = torch.eye(3, dtype=core_cov.dtype)
    T[STATE.q_prev, STATE.q] = torch.eye(4, dtype=core_cov.dtype)
    cov = T @ core_cov @ T.T
    idx = torch.arange(CORE_DIM, STATE_DIM)
    cov[idx, idx] += nugget_var
    return symmetrize(cov)


def stationary_initialization(
    *,
    t_s: Tensor,
    acc_mps2: Tensor,
    gyro_rps: Tensor,
    duration_s: float = 5.0,
    yaw_rad: float = 0.0,
    position_m: Tensor | None = None,
    uncertainty: InitialUncertainty = InitialUncertainty(),
    max_acc_std_mps2: float = 0.3,
    max_gyro_std_rps: float = 0.05,
    dtype: torch.dtype = torch.float64,
    name: str = "IMU",
) -> tuple[Tensor, Tensor]:
    """Prior ``(mean (26,), cov (26, 26))`` at ``t_s[0]`` from the first ``duration_s`` seconds.

    Raises:
        ValueError: if the window holds fewer than 10 samples, or if the device was
            visibly moving in it (standard deviation of the specific force above
            ``max_acc_std_mps2`` or of the rate above ``max_gyro_std_rps``); the
            message names the rows and the offending statistic.
    """
    t = torch.as_tensor(t_s, dtype=torch.float64)
    window = t <= t[0] + duration_s
    n = int(window.sum())
    if n < 10:
        raise ValueError(
            f"{name}: the stationary initialisation needs at least 10 samples in the first "
            f"{duration_s} s, found {n} (rows 0..{n - 1})"
        )
    acc = torch.as_tensor(acc_mps2, dtype=dtype)[window]
    gyro = torch.as_tensor(gyro_rps, dtype=dtype)[window]
    acc_std = float(acc.std(dim=0).max())
    gyro_std = float(gyro.std(dim=0).max())
    if acc_std > max_acc_std_mps2 or gyro_std > max_gyro_std_rps:
        raise ValueError(
            f"{name}: rows 0..{n - 1} (the first {duration_s} s) are not stationary: accelerometer std "
            f"{acc_std:.3g} m/s² (limit {max_acc_std_mps2}), gyroscope std {gyro_std:.3g} rad/s "
            f"(limit {max_gyro_std_rps}); shorten duration_s to the still part or raise the limits"
        )
    f = acc.mean(dim=0)
    roll = torch.atan2(f[1], f[2])
    pitch = torch.atan2(-f[0], torch.sqrt(f[1] ** 2 + f[2] ** 2))
    q = quat.from_euler(roll, pitch, torch.tensor(yaw_rad, dtype=dtype))
    u = uncertainty
    p = torch.zeros(3, dtype=dtype) if position_m is None else torch.as_tensor(position_m, dtype=dtype)
    mean = make_state(p=p, v=torch.zeros(3, dtype=dtype), q=q, b_w=gyro.mean(dim=0))

    core = torch.zeros(CORE_DIM, CORE_DIM, dtype=dtype)

    def block(sl: slice, std: float) -> None:
        core[sl, sl] = torch.eye(sl.stop - sl.start, dtype=dtype) * std**2

    block(STATE.p, u.position_m)
    block(STATE.v, u.velocity_mps)
    block(STATE.b_a, u.acc_bias_mps2)
    block(STATE.b_w, u.gyro_bias_rps)
    block(STATE.T_a, u.acc_scale)
    # stacked, not torch.tensor(...): the uncertainties may be learned tensors with a gradient
    rpy = torch.stack([torch.as_tensor(v, dtype=dtype) for v in (u.roll_pitch_rad, u.roll_pitch_rad, u.yaw_rad)])
    core[STATE.q, STATE.q] = orientation_covariance(q, rpy, u.quaternion_radial)
    return mean, augmented_covariance(core, u.augmentation_nugget_var)
