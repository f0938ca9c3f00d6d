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

from typing import NamedTuple

import torch
from torch import Tensor

from flowins.constants import cached_constant
from flowins.geometry import quaternion as quat
from flowins.ins.mechanization import check_scheme
from flowins.state import CORE, CORE_DIM, NOISE, NOISE_DIM, STATE_DIM, split


class StepPieces(NamedTuple):
    """What one mechanization step computes and its Jacobians reuse (batched over steps).

    ``q`` is the attitude before the step, ``E = 𝒬{θ}``, ``q_rot`` the attitude
    that rotates the specific force (``q ⊙ E`` for ``paper``, ``q ⊙ 𝒬{θ/2}`` for
    ``midpoint``) with ``E_rot`` its increment, ``dE`` the Jacobians ``∂𝒬/∂θ`` at ``θ``
    (and at ``θ/2`` for ``midpoint``) ``(..., 1 or 2, 4, 3)``, ``R_E`` the right-product
    matrices of ``E`` (and ``E_rot``) ``(..., 1 or 2, 4, 4)``, ``C = C(q_rot)``,
    ``acc_unbiased = ã - b_a`` and ``a = T_a ⊙ acc_unbiased``.
    """

    q: Tensor
    theta: Tensor
    E: Tensor
    E_rot: Tensor
    dE: Tensor
    R_E: Tensor
    q_rot: Tensor
    C: Tensor
    acc_unbiased: Tensor
    a: Tensor
    T_a: Tensor
    dt: Tensor  # (..., 1)


def rotation_increments(theta: Tensor, scheme: str) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(E, E_rot, dE, R_E)``: ``𝒬{θ}``, the increment that rotates the specific force
    (``𝒬{θ}`` itself for ``paper``, ``𝒬{θ/2}`` for ``midpoint``), the Jacobians
    ``∂𝒬/∂θ`` at ``θ`` (and ``θ/2``) ``(..., 1 or 2, 4, 3)`` and the right-product
    matrices ``R(E)`` (and ``R(E_rot)``) ``(..., 1 or 2, 4, 4)``, in one call."""
    check_scheme(scheme)
    if scheme == "paper":
        E, dE = quat.from_rotation_vector_with_jacobian(theta)
        return E, E, dE.unsqueeze(-3), quat.right_matrix(E).unsqueeze(-3)
    Es, dE = quat.from_rotation_vector_with_jacobian(torch.stack((theta, 0.5 * theta), dim=-2))
    return Es[..., 0, :], Es[..., 1, :], dE, quat.right_matrix(Es)


def step_pieces(x: Tensor, acc_mps2: Tensor, gyro_rps: Tensor, dt_s: Tensor, scheme: str) -> StepPieces:
    """:class:`StepPieces` of ``mechanize`` at the states ``x`` ``(..., D)`` (the core only matters)."""
    s = split(x)
    dt = dt_s.unsqueeze(-1)
    theta = (gyro_rps - s.b_w) * dt
    E, E_rot, dE, R_E = rotation_increments(theta, scheme)
    q_rot = quat.multiply(s.q, E_rot)
    acc_unbiased = acc_mps2 - s.b_a
    return StepPieces(
        s.q, theta, E, E_rot, dE, R_E, q_rot, quat.to_matrix(q_rot), acc_unbiased, s.T_a * acc_unbiased, s.T_a, dt
    )


def core_jacobians_from_pieces(pieces: StepPieces, scheme: str) -> tuple[Tensor, Tensor]:
    """Core blocks of ``(F_x, F_ε)``, ``(..., 19, 19)`` and ``(..., 19, 15)`` (the
    :data:`flowins.state.CORE` rows and columns), from a step's :class:`StepPieces`.

    The augmented pose is constant under the mechanization, so the full Jacobians
    are these blocks embedded with an identity (:func:`embed_core`). The matrices are
    assembled row block by row block (``p``, ``v``, ``q``, then the constant rows of
    the biases and the scale) with few, large tensor operations.
    """
    check_scheme(scheme)
    q, theta, E, E_rot, dE, R_E, q_rot, C, acc_unbiased, a, T_a, dt = pieces
    batch = q.shape[:-1]
    dt3 = dt.unsqueeze(-1)  # (..., 1, 1)
    # -Δt, -Δt/2 (the θ and θ/2 increments' ∂/∂b_ω) and Δt/2, in one product
    dts = dt3.unsqueeze(-3) * _dt_factors(dt3.dtype, dt3.device)  # (..., 3, 1, 1)
    # ∂(q ⊙ 𝒬{θ})/∂b_ω (and of 𝒬{θ/2}): -Δt L(q) ∂𝒬/∂θ (-Δt/2 for the half increment)
    LJ = (quat.left_matrix(q).unsqueeze(-3) @ dE) * dts[..., : dE.shape[-3], :, :]  # (..., 1|2, 4, 3)
    dq_dbw = LJ[..., 0, :, :]  # (..., 4, 3)
    dq_dq = R_E[..., 0, :, :]
    if scheme == "paper":
        drot = torch.cat((dq_dq, dq_dbw), dim=-1)  # (..., 4, 7): ∂q_rot/∂(q, b_ω)
    else:
        drot = torch.cat((R_E[..., 1, :, :], LJ[..., 1, :, :]), dim=-1)
    dv = dt3 * (quat.rotate_jacobian(q_rot, a) @ drot)  # (..., 3, 7): ∂v'/∂(q, b_ω)
    dtC = dt3 * C
    # the velocity rows over the columns q, b_a, b_w, T_a (resp. the noises acc, gyro)
    v_row = torch.cat((dv[..., :4], dtC * (-T_a).unsqueeze(-2), dv[..., 4:], dtC * acc_unbiased.unsqueeze(-2)), -1)
    v_noise = torch.cat((dtC, -dv[..., 4:]), -1)  # (..., 3, 6)
    zeros, walks_G, bottom_F, left_F, pv_F = _core_constants(q.dtype, q.device)
    q_row = torch.cat((dq_dq, zeros.expand(*batch, 4, 3), dq_dbw, zeros.expand(*batch, 4, 3)), -1)  # (..., 4, 13)
    q_noise = torch.cat((zeros.expand(*batch, 4, 3), -dq_dbw), -1)  # (..., 4, 6)
    if scheme == "midpoint":
        # p' = p + v Δt + (Δt/2)(v' - v): (Δt/2) x the velocity rows without their identity
        half = dts[..., 2, :, :]
        p_row, p_noise = half * v_row, half * v_noise
    else:
        p_row, p_noise = torch.zeros_like(v_row), torch.zeros_like(v_noise)
    # rows p, v, q: constant left columns (p, v) with Δt I at ∂p/∂v, then the rest
    top = torch.cat((left_F + dt3 * pv_F, torch.cat((p_row, v_row, q_row), -2)), -1)  # (..., 10, 19)
    F = torch.cat((top, bottom_F.expand(*batch, CORE_DIM - 10, CORE_DIM)), -2)
    G_top = torch.nn.functional.pad(torch.cat((p_noise, v_noise, q_noise), -2), (0, NOISE_DIM - 6))
    G = torch.cat((G_top, walks_G.expand(*batch, CORE_DIM - 10, NOISE_DIM)), -2)
    return F, G


@cached_constant
def _dt_factors(dtype: torch.dtype, device: torch.device) -> Tensor:
    """The step's factors of Δt ``(3, 1, 1)``: -1 and -1/2 (∂θ/∂b_ω of the increments θ and θ/2), 1/2."""
    return torch.tensor([-1.0, -0.5, 0.5], dtype=dtype, device=device).reshape(3, 1, 1)


@cached_constant
def _core_constants(dtype: torch.dtype, device: torch.device) -> tuple[Tensor, ...]:
    """Constant pieces of the core Jacobians: a ``(4, 3)`` zero block, the bias and scale
    rows of ``F_ε`` (identity from each walk noise) and of ``F_x`` (identity), the ``p, v, q``
    rows' ``p, v`` columns without and with ``Δt`` (``∂p/∂v``)."""
    if CORE.names != ("p", "v", "q", "b_a", "b_w", "T_a") or NOISE.names[:2] != ("acc", "gyro"):
        raise AssertionError("core_jacobians_from_pieces assembles the rows for the layout p, v, q, b_a, b_w, T_a")
    eye = torch.eye(CORE_DIM, dtype=dtype, device=device)
    walks = torch.zeros(CORE_DIM, NOISE_DIM, dtype=dtype, device=device)
    for name in ("b_a", "b_w", "T_a"):
        walks[CORE.slice(name), NOISE.slice(name)] = torch.eye(3, dtype=dtype, device=device)
    left = eye[:10, :6].clone()
    pv = torch.zeros(10, 6, dtype=dtype, device=device)
    pv[CORE.p, CORE.v] = torch.eye(3, dtype=dtype, device=device)
    return (torch.zeros(4, 3, dtype=dtype, device=device), walks[10:].clone(), eye[10:].clone(), left, pv)


def pad_core(M: Tensor, *, dim: int = STATE_DIM) -> Tensor:
    """``(…, 19, k)`` or ``(…, 19, 19)`` core block -> zero-padded full-state rows
    ``(…, D, k)``, resp. ``(…, D, D)`` when the block is square, for a state of ``D = dim``
    entries (``19 + 7 N``: 26 for the one cloned pose of the paper, the default)."""
    extra = dim - CORE_DIM
    return torch.nn.functional.pad(M, (0, extra if M.shape[-1] == CORE_DIM else 0, 0, extra))


def embed_core(F_core: Tensor, G_core: Tensor | None = None, *, dim: int = STATE_DIM) -> tuple[Tensor, Tensor | None]:
    """Full-state ``(…, D, D)`` transition (identity on the cloned poses) and ``(…, D, 15)``
    noise Jacobian (zero rows there) from their core blocks, ``D = dim`` (default 26)."""
    F = pad_core(F_core, dim=dim) + _augmented_identity(F_core.dtype, F_core.device, dim)
    return F, None if G_core is None else pad_core(G_core, dim=dim)


@cached_constant
def _augmented_identity(dtype: torch.dtype, device: torch.device, dim: int = STATE_DIM) -> Tensor:
    """``(D, D)``: identity on the cloned poses, zero on the core (one per ``D = dim``)."""
    return torch.diag((torch.arange(dim, device=device) >= CORE_DIM).to(dtype))


def mechanization_jacobians(
    x: Tensor, acc_mps2: Tensor, gyro_rps: Tensor, dt_s: Tensor, scheme: str = "midpoint"
) -> tuple[Tensor, Tensor]:
    """``(F_x, F_ε)`` of ``mechanize`` at ``(x, ε = 0)``, ``(..., D, D)`` and ``(..., D, 15)`` for
    states ``x`` ``(..., D)``, ``D = 19 + 7 N`` (26 for the paper's one cloned pose).

    Exact (not approximated) closed forms; batched over any leading dimensions,
    e.g. all ``K`` steps of a run at once with ``x`` holding the state before each step.

    For ``scheme="midpoint"`` the velocity rows use ``q_½ = q ⊙ 𝒬{θ/2}`` in place of
    ``q'``, and the position rows become ``∂p'/∂· = ∂p/∂· + Δt ∂v/∂· + (Δt/2)(∂v'/∂· - ∂v/∂·)``.
    """
    return embed_core(*core_jacobians_from_pieces(step_pieces(x, acc_mps2, gyro_rps, dt_s, scheme), scheme),
                      dim=x.shape[-1])
