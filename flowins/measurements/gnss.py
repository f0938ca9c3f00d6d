"""GNSS position measurement model.

    h(x) = p + C(q) ℓ        (antenna position in the local ENU frame, m)

with ``ℓ`` the antenna lever arm in the IMU frame (zero by default, as in the
paper), and noise ``R = s² diag(σ_h², σ_h², σ_v²)`` from the fix's reported
horizontal and vertical 1-σ accuracies, scaled by ``s`` (a tuning parameter, 1 by default).

GNSS errors are correlated in time (atmosphere, multipath, the receiver's own
filter: tens of seconds). A filter that takes them as white believes ``n`` fixes
average their errors down by ``n``. For a first-order Gauss-Markov error with
correlation time ``τ`` sampled every ``Δt`` (lag-one correlation ``ρ = exp(-Δt/τ)``)
the mean of ``n`` fixes has variance ``(σ²/n)(1 + ρ)/(1 - ρ)`` for large ``n``, so
:func:`correlation_inflation` scales each fix's ``R`` by that factor: the white-noise
filter then draws the information the fixes really hold (``τ = 0``: no change).
"""
from __future__ import annotations

import torch
from torch import Tensor
from torch.func import jacrev, vmap

from flowins.geometry import quaternion as quat
from flowins.state import STATE, split


def gnss_position(x: Tensor, lever_arm_m: Tensor) -> Tensor:
    """``h(x)`` ``(..., 3)`` for states ``(..., 26)`` and a lever arm ``(3,)``."""
    s = split(x)
    return s.p + quat.rotate(s.q, lever_arm_m.to(x.dtype).expand_as(s.p))


def gnss_jacobian(x: Tensor, lever_arm_m: Tensor) -> Tensor:
    """``∂h/∂x`` ``(..., 3, 26)`` by ``torch.func.jacrev``."""
    jac = jacrev(gnss_position)
    if x.ndim == 1:
        return jac(x, lever_arm_m)
    flat = x.reshape(-1, x.shape[-1])
    return vmap(jac, in_dims=(0, None))(flat, lever_arm_m).reshape(*x.shape[:-1], 3, x.shape[-1])


def gnss_jacobian_analytic(x: Tensor, lever_arm_m: Tensor | None) -> Tensor:
    """Closed form of :func:`gnss_jacobian`: ``[I₃, 0, ∂(C(q)ℓ)/∂q, 0]`` ``(..., 3, 26)``.

    ``lever_arm_m=None`` means a zero lever arm, whose ``∂/∂q`` block is zero.
    """
    H = x.new_zeros(*x.shape[:-1], 3, x.shape[-1])
    H[..., STATE.p] = torch.eye(3, dtype=x.dtype, device=x.device)
    if lever_arm_m is not None:
        H[..., STATE.q] = quat.rotate_jacobian(split(x).q, lever_arm_m.to(x.dtype).expand(*x.shape[:-1], 3))
    return H


def gnss_noise(h_acc_m: Tensor, v_acc_m: Tensor, scale: float | Tensor = 1.0) -> Tensor:
    """``R`` ``(..., 3, 3)`` from horizontal and vertical 1-σ accuracies ``(...)``."""
    sigmas = torch.stack((h_acc_m, h_acc_m, v_acc_m), dim=-1) * scale
    return torch.diag_embed(sigmas * sigmas)


def correlation_inflation(t_s: Tensor, correlation_s: float | Tensor) -> Tensor:
    """Variance factor ``(1 + ρ) / (1 - ρ)`` ``(G,)`` per fix, ``ρ = exp(-Δt / τ)``.

    ``Δt`` is the time since the previous fix (for the first, to the next one);
    ``τ = correlation_s = 0`` gives ones.
    """
    t = torch.as_tensor(t_s, dtype=torch.float64)
    tau = torch.as_tensor(correlation_s, dtype=torch.float64)
    if bool((tau < 0).any()):
        raise ValueError(f"correlation_s (filter.gnss_correlation_s), the GNSS error correlation time, must be "
                         f">= 0 s, got {float(tau)}")
    if t.shape[0] < 2 or float(tau) == 0.0:
        return torch.ones_like(t)
    dt = torch.diff(t)
    dt = torch.cat((dt[:1], dt))
    rho = torch.exp(-dt / tau)
    return (1.0 + rho) / (1.0 - rho)
