"""Strapdown mechanization: the paper's dynamical model ``f(x, ε)`` (Sec. "Inertial Navigation").

For one IMU sample ``k`` with ``Δt_k = t_k - t_{k-1}`` (non-equidistant), corrected inputs

    a_k = T_a ⊙ (ã_k - b_a) + ε^a          (specific force, body frame, m/s²)
    ω_k = ω̃_k - b_ω + ε^ω                   (angular rate, body frame, rad/s)

the paper's equation reads

    p_k = p_{k-1} + v_{k-1} Δt_k
    v_k = v_{k-1} + [q_k ⊙ a_k ⊙ q_k* - g] Δt_k
    q_k = q_{k-1} ⊙ 𝒬{ω_k Δt_k}

and the biases, the scale and the augmented pose keep constant dynamics (plus an
optional random walk ``b ← b + ε^b``, off by default as in the paper).

This literal scheme (``scheme="paper"``) is first order: it rotates the specific
force with the orientation at the *end* of the step and moves the position with
the velocity at its *start*, which leaves a systematic sculling error on
periodic motion (on a simulated walk with 1.8 Hz bounce and sway, noise-free
100 Hz input, 2.9 m after 60 s). ``scheme="midpoint"`` (the default) keeps the
same state, inputs and noise but integrates to second order:

    q_k = q_{k-1} ⊙ 𝒬{ω_k Δt_k}                       (as in the paper)
    v_k = v_{k-1} + [q_½ ⊙ a_k ⊙ q_½* - g] Δt_k,       q_½ = q_{k-1} ⊙ 𝒬{ω_k Δt_k / 2}
    p_k = p_{k-1} + (v_{k-1} + v_k) Δt_k / 2

``g = (0, 0, g0)`` in the local ENU world frame: a device at rest measures the
specific force ``+g0`` upwards, so ``q ⊙ ã ⊙ q* - g = 0``.

Accelerometer model behind the correction: ``ã = a_true / T_a + b_a`` (elementwise),
i.e. ``T_a`` is the multiplicative correction of the raw reading; it is 1 for a
perfect sensor.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from flowins.config import bounded, check_fields
from flowins.constants import STANDARD_GRAVITY_MPS2, cached_constant
from flowins.geometry import quaternion as quat
from flowins.state import NOISE, NOISE_DIM, STATE_DIM, State, join, split



def gravity_vector(gravity_mps2: float | Tensor, *, like: Tensor) -> Tensor:
    """``g = (0, 0, g0)`` in the ENU world frame, dtype and device of ``like``."""
    g = torch.as_tensor(gravity_mps2, dtype=like.dtype, device=like.device)
    z = torch.zeros_like(g)
    return torch.stack((z, z, g), dim=-1)


def mechanize(
    x: Tensor,
    noise: Tensor,
    acc_mps2: Tensor,
    gyro_rps: Tensor,
    dt_s: Tensor,
    gravity_mps2: float | Tensor = STANDARD_GRAVITY_MPS2,
    scheme: str = "midpoint",
) -> Tensor:
    """One step of the mechanization, ``x_k = f(x_{k-1}, ε_k)``.

    Args:
        x: state ``(..., 26)`` at ``t_{k-1}`` (or ``(..., 19 + 7 N)`` with a window of ``N`` cloned
            poses, all constant).
        noise: process noise ``ε_k`` ``(..., 15)`` in the :data:`flowins.state.NOISE`
            layout (zeros for the mean prediction).
        acc_mps2: accelerometer sample ``ã_k`` ``(..., 3)``.
        gyro_rps: gyroscope sample ``ω̃_k`` ``(..., 3)``.
        dt_s: ``Δt_k`` ``(...)``; ``Δt = 0`` is the identity map.
        gravity_mps2: magnitude ``g0`` of gravity.
        scheme: ``"midpoint"`` (second order) or ``"paper"`` (the literal equation).

    Returns:
        state ``(..., D)`` at ``t_k``, ``D`` that of ``x``. Pure and differentiable (``torch.func``-friendly).
    """
    s = split(x)
    dt = torch.as_tensor(dt_s, dtype=x.dtype, device=x.device).unsqueeze(-1)
    eps_a = noise[..., NOISE.acc]
    eps_w = noise[..., NOISE.gyro]
    acc = s.T_a * (acc_mps2 - s.b_a) + eps_a
    omega = gyro_rps - s.b_w + eps_w
    check_scheme(scheme)
    q_new = quat.multiply(s.q, quat.from_rotation_vector(omega * dt))
    q_rot = q_new if scheme == "paper" else quat.multiply(s.q, quat.from_rotation_vector(0.5 * omega * dt))
    v_new = s.v + (quat.rotate(q_rot, acc) - gravity_vector(gravity_mps2, like=x)) * dt
    p_new = s.p + (s.v if scheme == "paper" else 0.5 * (s.v + v_new)) * dt
    out = join(
        State(
            p=p_new,
            v=v_new,
            q=q_new,
            b_a=s.b_a + noise[..., NOISE.b_a],
            b_w=s.b_w + noise[..., NOISE.b_w],
            T_a=s.T_a + noise[..., NOISE.T_a],
            p_prev=s.p_prev,
            q_prev=s.q_prev,
        )
    )
    if x.shape[-1] == STATE_DIM:
        return out
    # a window of N > 1 cloned poses: the further clones are constant as well
    return torch.cat((out, x[..., STATE_DIM:].expand(*out.shape[:-1], x.shape[-1] - STATE_DIM)), -1)


SCHEMES = ("midpoint", "paper")


def check_scheme(scheme: str) -> None:
    if scheme not in SCHEMES:
        raise ValueError(f"mechanization scheme must be one of {SCHEMES}, got {scheme!r}")


@dataclass(frozen=True)
class ProcessNoise:
    """Continuous-time IMU noise parameters (the paper's ``Σ^a``, ``Σ^ω`` and random walks).

    All are 1-σ spectral densities, as in a datasheet or a Kalibr/EuRoC
    ``sensor.yaml``; scalars apply to all three axes, ``(3,)`` tensors per axis.

    Attributes:
        acc_noise: accelerometer white noise, m/s²/√Hz.
        gyro_noise: gyroscope white noise, rad/s/√Hz.
        acc_bias_walk: accelerometer bias random walk, m/s³/√Hz (0 = off, the paper).
        gyro_bias_walk: gyroscope bias random walk, rad/s²/√Hz (0 = off).
        acc_scale_walk: accelerometer scale random walk, 1/s/√Hz (0 = off).
        discretization: ``"density"`` (default) makes the per-sample input noise
            variance ``σ²/Δt_k``, so that the velocity and angle random walks grow
            as ``σ² t`` whatever the sampling; ``"paper"`` takes the paper's
            ``Q_k = blkdiag(Σ^a Δt_k, Σ^ω Δt_k)`` literally with ``Σ = σ²``.
            The two agree up to a constant factor ``Δt²`` for uniform sampling.
    """

    acc_noise: float | Tensor = bounded(3e-3, minimum=0.0)
    gyro_noise: float | Tensor = bounded(2e-4, minimum=0.0)
    acc_bias_walk: float | Tensor = bounded(0.0, minimum=0.0)
    gyro_bias_walk: float | Tensor = bounded(0.0, minimum=0.0)
    acc_scale_walk: float | Tensor = bounded(0.0, minimum=0.0)
    discretization: Literal["density", "paper"] = "density"

    def __post_init__(self) -> None:
        check_fields(self)

    def covariance(self, dt_s: Tensor) -> Tensor:
        """Diagonal ``Q_k`` ``(..., 15, 15)`` for steps ``Δt_k`` ``(...)``, NOISE layout."""
        return torch.diag_embed(self.variances(dt_s))

    def variances(self, dt_s: Tensor) -> Tensor:
        """The diagonal of :meth:`covariance`, ``(..., 15)``: the squared densities times
        ``1/Δt`` (``density``; 0 for a ``Δt = 0`` padding step, whose Jacobian column is zero
        anyway) or ``Δt`` (``paper``) for the white inputs, times ``Δt`` for the walks:
        :meth:`squared_densities` times :meth:`variance_scales`."""
        return self.squared_densities(dt_s.dtype, dt_s.device) * self.variance_scales(dt_s)

    def squared_densities(self, dtype: torch.dtype, device: torch.device | str) -> Tensor:
        """``σ²`` per noise axis ``(15,)`` in the NOISE layout: the part of :meth:`variances` that
        carries the parameters' gradient."""
        values = (self.acc_noise, self.gyro_noise, self.acc_bias_walk, self.gyro_bias_walk, self.acc_scale_walk)
        if any(isinstance(v, Tensor) for v in values):
            return _squared_densities(values, dtype, device)
        return _cached_squared_densities(tuple(float(v) for v in values), dtype, device)  # plain numbers: built once

    def variance_scales(self, dt_s: Tensor) -> Tensor:
        """``(..., 15)``: what :meth:`squared_densities` is multiplied by for steps ``Δt`` ``(...)``,
        a function of the steps alone (no parameter, so no gradient): ``1/Δt`` (``density``; 0 for
        ``Δt = 0``) or ``Δt`` (``paper``) for the white inputs, ``Δt`` for the walks. A pass keeps
        these for all its steps and multiplies each segment's by the densities, so that the
        gradient of each segment's noise reaches the parameters without passing through an
        array of every step (whose backward would fill that whole array once per segment)."""
        dt = dt_s.unsqueeze(-1)
        if self.discretization == "density":
            # white input noise sampled over Δt has variance σ²/Δt (0 for Δt = 0, gradient included)
            white_scale = (dt > 0) / dt.clamp_min(torch.finfo(dt.dtype).tiny)
        else:
            white_scale = dt
        return torch.where(_WHITE_INPUTS.to(dt_s.device), white_scale, dt)


#: which of the 15 noise axes are white inputs (accelerometer, gyroscope) rather than walks
_WHITE_INPUTS = torch.zeros(NOISE_DIM, dtype=torch.bool)
_WHITE_INPUTS[NOISE.acc] = True
_WHITE_INPUTS[NOISE.gyro] = True


def _squared_densities(values, dtype: torch.dtype, device) -> Tensor:
    """``σ²`` per noise axis ``(15,)`` in the NOISE layout from the five densities."""

    def per_axis(value: float | Tensor) -> Tensor:
        v = torch.as_tensor(value, dtype=dtype, device=device)
        return (v * v).expand(3) if v.ndim == 0 else v * v

    out = torch.cat([per_axis(v) for v in values])
    assert out.shape[-1] == NOISE_DIM
    return out


_cached_squared_densities = cached_constant(_squared_densities)
