"""Analytic Jacobians of :func:`flowins.ins.mechanization.mechanize`, batched over steps.

The reference is ``torch.func.jacrev`` of ``mechanize``; ``tests/ins`` checks that the
two agree to 1e-9 in float64. These closed forms let the filter linearise a whole
run of IMU samples in a handful of batched tensor operations.

With ``θ = (ω̃ - b_ω) Δt``, ``E = 𝒬{θ}``, ``q' = q ⊙ E``, ``a = T_a ⊙ (ã - b_a)``:

    ∂p'/∂v   = Δt I
    ∂q'/∂q   = R⊙(E)                     (right-multiplication matrix)
    ∂q'/∂b_ω = -Δt L⊙(q) J_𝒬(θ)         (J_𝒬 = ∂𝒬/∂θ, 4x3)
    ∂v'/∂q   = Δt J_rot(q', a) ∂q'/∂q    (J_rot = ∂(C(q/|q|) a)/∂q, 3x4)
    ∂v'/∂b_ω = Δt J_rot(q', a) ∂q'/∂b_ω
    ∂v'/∂b_a = -Δt C(q') diag(T_a)
    ∂v'/∂T_a = Δt C(q') diag(ã - b_a)

and for the noise ``ε = (ε^a, ε^ω, ε^{b_a}, ε^{b_ω}, ε^{T_a})``: ``∂v'/∂ε^a = Δt C(q')``,
``∂q'/∂ε^ω = -∂q'/∂b_ω``, ``∂v'/∂ε^ω = -∂v'/∂b_ω`` and identities for the random walks.
"""
from __future__ import annotations

import torch
from torch import Tensor

from flowins.geometry import quaternion as quat
from flowins.ins.mechanization import check_scheme
from flowins.state import NOISE, NOISE_DIM, STATE, STATE_DIM, split

_SMALL_ANGLE_SQ = 1e-6


def _skew(a: Tensor) -> Tensor:
    x, y, z = a.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack(
        (torch.stack((o, -z, y), -1), torch.stack((z, o, -x), -1), torch.stack((-y, x, o), -1)), dim=-2
    )


def rotation_vector_jacobian(theta: Tensor) -> Tensor:
    """``∂𝒬{θ}/∂θ`` ``(..., 4, 3)``, branch-free and finite at ``θ = 0``.

    With ``r = |θ|``, ``s = sin(r/2)/r`` and ``k = (r cos(r/2)/2 - sin(r/2))/r³``:
    ``∂cos(r/2)/∂θ = -(s/2) θᵀ`` and ``∂(sθ)/∂θ = s I + k θθᵀ``.
    """
    r_sq = (theta * theta).sum(-1)
    small = r_sq < _SMALL_ANGLE_SQ
    safe_sq = torch.where(small, torch.ones_like(r_sq), r_sq)
    r = torch.sqrt(safe_sq)
    half = 0.5 * r
    s = torch.where(small, 0.5 - r_sq / 48.0 + r_sq * r_sq / 3840.0, torch.sin(half) / r)
    k = torch.where(
        small,
        -1.0 / 24.0 + r_sq / 960.0,
        (r * torch.cos(half) * 0.5 - torch.sin(half)) / (safe_sq * r),
    )
    top = (-0.5 * s).unsqueeze(-1) * theta  # (..., 3)
    eye = torch.eye(3, dtype=theta.dtype, device=theta.device)
    bottom = s[..., None, None] * eye + k[..., None, None] * theta.unsqueeze(-1) * theta.unsqueeze(-2)
    return torch.cat((top.unsqueeze(-2), bottom), dim=-2)


def rotate_jacobian(q: Tensor, a: Tensor) -> Tensor:
    """``∂(C(q/|q|) a)/∂q`` ``(..., 3, 4)`` for a (not necessarily unit) quaternion ``q``."""
    n = q.norm(dim=-1, keepdim=True)
    u = q / n
    w, r = u[..., 0], u[..., 1:]
    ra = (r * a).sum(-1)
    d_w = 2.0 * (w.unsqueeze(-1) * a + torch.linalg.cross(r, a))
    eye = torch.eye(3, dtype=q.dtype, device=q.device)
    d_r = 2.0 * (
        ra[..., None, None] * eye
        + r.unsqueeze(-1) * a.unsqueeze(-2)
        - a.unsqueeze(-1) * r.unsqueeze(-2)
        - w[..., None, None] * _skew(a)
    )
    J_u = torch.cat((d_w.unsqueeze(-1), d_r), dim=-1)  # (..., 3, 4)
    eye4 = torch.eye(4, dtype=q.dtype, device=q.device)
    projector = (eye4 - u.unsqueeze(-1) * u.unsqueeze(-2)) / n.unsqueeze(-1)
    return J_u @ projector


def mechanization_jacobians(
    x: Tensor, acc_mps2: Tensor, gyro_rps: Tensor, dt_s: Tensor, scheme: str = "midpoint"
) -> tuple[Tensor, Tensor]:
    """``(F_x, F_ε)`` of ``mechanize`` at ``(x, ε = 0)``, ``(..., 26, 26)`` and ``(..., 26, 15)``.

    Exact (not approximated) closed forms; batched over any leading dimensions,
    e.g. all ``K`` steps of a run at once with ``x`` holding the state before each step.

    For ``scheme="midpoint"`` the velocity rows use ``q_½ = q ⊙ 𝒬{θ/2}`` in place of
    ``q'``, and the position rows become ``∂p'/∂· = ∂p/∂· + Δt ∂v/∂· + (Δt/2)(∂v'/∂· - ∂v/∂·)``.
    """
    check_scheme(scheme)
    s = split(x)
    dt = dt_s.unsqueeze(-1)
    theta = (gyro_rps - s.b_w) * dt
    E = quat.from_rotation_vector(theta)
    q_new = quat.multiply(s.q, E)
    acc_unbiased = acc_mps2 - s.b_a
    a = s.T_a * acc_unbiased
    dt3 = dt.unsqueeze(-1)  # (..., 1, 1)
    dq_dq = quat.right_matrix(E)  # (..., 4, 4)
    dq_dbw = -dt3 * (quat.left_matrix(s.q) @ rotation_vector_jacobian(theta))  # (..., 4, 3)
    if scheme == "paper":
        q_rot, drot_dq, drot_dbw = q_new, dq_dq, dq_dbw
    else:
        E_half = quat.from_rotation_vector(0.5 * theta)
        q_rot = quat.multiply(s.q, E_half)
        drot_dq = quat.right_matrix(E_half)
        drot_dbw = -0.5 * dt3 * (quat.left_matrix(s.q) @ rotation_vector_jacobian(0.5 * theta))
    C = quat.to_matrix(q_rot)
    J_rot = rotate_jacobian(q_rot, a)  # (..., 3, 4)

    batch = x.shape[:-1]
    F = torch.eye(STATE_DIM, dtype=x.dtype, device=x.device).expand(*batch, STATE_DIM, STATE_DIM).clone()
    eye3 = torch.eye(3, dtype=x.dtype, device=x.device)
    F[..., STATE.p, STATE.v] = dt3 * eye3
    F[..., STATE.q, STATE.q] = dq_dq
    F[..., STATE.q, STATE.b_w] = dq_dbw
    F[..., STATE.v, STATE.q] = dt3 * (J_rot @ drot_dq)
    F[..., STATE.v, STATE.b_w] = dt3 * (J_rot @ drot_dbw)
    F[..., STATE.v, STATE.b_a] = -dt3 * C * s.T_a.unsqueeze(-2)
    F[..., STATE.v, STATE.T_a] = dt3 * C * acc_unbiased.unsqueeze(-2)

    G = x.new_zeros(*batch, STATE_DIM, NOISE_DIM)
    G[..., STATE.v, NOISE.acc] = dt3 * C
    G[..., STATE.q, NOISE.gyro] = -dq_dbw
    G[..., STATE.v, NOISE.gyro] = -dt3 * (J_rot @ drot_dbw)
    G[..., STATE.b_a, NOISE.b_a] = eye3
    G[..., STATE.b_w, NOISE.b_w] = eye3
    G[..., STATE.T_a, NOISE.T_a] = eye3
    if scheme == "midpoint":
        # p' = p + v Δt + (Δt/2)(v' - v): add (Δt/2) x (velocity rows without their identity)
        dv_F = F[..., STATE.v, :].clone()
        dv_F[..., :, STATE.v] -= eye3
        F[..., STATE.p, :] = F[..., STATE.p, :] + 0.5 * dt3 * dv_F
        G[..., STATE.p, :] = 0.5 * dt3 * G[..., STATE.v, :]
    return F, G
