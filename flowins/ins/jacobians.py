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

import itertools
from typing import NamedTuple

import torch
from torch import Tensor

from flowins.constants import cached_constant
from flowins.geometry import quaternion as quat
from flowins.geometry.quaternion import rotate_jacobian, rotation_vector_jacobian
from flowins.ins.mechanization import check_scheme
from flowins.state import CORE, CORE_DIM, NOISE, NOISE_DIM, STATE_DIM, _Layout, split


class StepPieces(NamedTuple):
    """What one mechanization step computes and its Jacobians reuse (batched over steps).

    ``q`` is the attitude before the step, ``E = 𝒬{θ}``, ``q_rot`` the attitude
    that rotates the specific force (``q ⊙ E`` for ``paper``, ``q ⊙ 𝒬{θ/2}`` for
    ``midpoint``) with ``E_rot`` its increment, ``C = C(q_rot)``, ``acc_unbiased =
    ã - b_a`` and ``a = T_a ⊙ acc_unbiased``.
    """

    q: Tensor
    theta: Tensor
    E: Tensor
    E_rot: Tensor
    q_rot: Tensor
    C: Tensor
    acc_unbiased: Tensor
    a: Tensor
    T_a: Tensor
    dt: Tensor  # (..., 1)


def rotation_increments(theta: Tensor, scheme: str) -> tuple[Tensor, Tensor]:
    """``(E, E_rot)``: ``𝒬{θ}`` and the increment that rotates the specific force
    (``𝒬{θ}`` itself for ``paper``, ``𝒬{θ/2}`` for ``midpoint``), in one call."""
    check_scheme(scheme)
    if scheme == "paper":
        E = quat.from_rotation_vector(theta)
        return E, E
    E, E_half = quat.from_rotation_vector(torch.stack((theta, 0.5 * theta), dim=-2)).unbind(-2)
    return E, E_half


def step_pieces(x: Tensor, acc_mps2: Tensor, gyro_rps: Tensor, dt_s: Tensor, scheme: str) -> StepPieces:
    """:class:`StepPieces` of ``mechanize`` at the states ``x`` ``(..., 26)``."""
    s = split(x)
    dt = dt_s.unsqueeze(-1)
    theta = (gyro_rps - s.b_w) * dt
    E, E_rot = rotation_increments(theta, scheme)
    q_rot = quat.multiply(s.q, E_rot)
    acc_unbiased = acc_mps2 - s.b_a
    return StepPieces(
        s.q, theta, E, E_rot, q_rot, quat.to_matrix(q_rot), acc_unbiased, s.T_a * acc_unbiased, s.T_a, dt
    )


def core_jacobians_from_pieces(pieces: StepPieces, scheme: str) -> tuple[Tensor, Tensor]:
    """Core blocks of ``(F_x, F_ε)``, ``(..., 19, 19)`` and ``(..., 19, 15)`` (the
    :data:`flowins.state.CORE` rows and columns), from a step's :class:`StepPieces`.

    The augmented pose is constant under the mechanization, so the full Jacobians
    are these blocks embedded with an identity (:func:`embed_core`).
    """
    check_scheme(scheme)
    q, theta, E, E_rot, q_rot, C, acc_unbiased, a, T_a, dt = pieces
    batch = q.shape[:-1]
    dt3 = dt.unsqueeze(-1)  # (..., 1, 1)
    if scheme == "paper":
        dq_dbw = -dt3 * (quat.left_matrix(q) @ rotation_vector_jacobian(theta))  # (..., 4, 3)
        dq_dq = quat.right_matrix(E)
        drot = torch.cat((dq_dq, dq_dbw), dim=-1)  # (..., 4, 7): ∂q_rot/∂(q, b_ω)
    else:
        J_both = rotation_vector_jacobian(torch.stack((theta, 0.5 * theta), dim=-2))  # (..., 2, 4, 3)
        LJ = quat.left_matrix(q).unsqueeze(-3) @ J_both
        dq_dbw = -dt3 * LJ[..., 0, :, :]
        R_both = quat.right_matrix(torch.stack((E, E_rot), dim=-2))  # (..., 2, 4, 4)
        dq_dq = R_both[..., 0, :, :]
        drot = torch.cat((R_both[..., 1, :, :], -0.5 * dt3 * LJ[..., 1, :, :]), dim=-1)
    dv = dt3 * (rotate_jacobian(q_rot, a) @ drot)  # (..., 3, 7): ∂v'/∂(q, b_ω)
    dv_dq, dv_dbw = dv[..., :4], dv[..., 4:]
    dtC = dt3 * C
    # the velocity rows over the contiguous columns q, b_a, b_w, T_a (resp. noises acc, gyro)
    v_row = torch.cat((dv_dq, -dtC * T_a.unsqueeze(-2), dv_dbw, dtC * acc_unbiased.unsqueeze(-2)), -1)
    v_noise = torch.cat((dtC, -dv_dbw), -1)
    eye3 = torch.eye(3, dtype=q.dtype, device=q.device)
    F_blocks = {("p", "v"): dt3 * eye3, ("q", "q"): dq_dq, ("q", "b_w"): dq_dbw, ("v", _V_COLUMNS): v_row}
    G_blocks = {("q", "gyro"): -dq_dbw, ("v", _V_NOISES): v_noise}
    if scheme == "midpoint":
        # p' = p + v Δt + (Δt/2)(v' - v): (Δt/2) x the velocity rows without their identity
        half = 0.5 * dt3
        F_blocks[("p", _V_COLUMNS)] = half * v_row
        G_blocks[("p", _V_NOISES)] = half * v_noise
    # identity on the rows no block overwrites: p, v, b_a, b_w, T_a; random walks
    # drive the bias and scale states one to one
    F = place_blocks(F_blocks, CORE, CORE, batch, like=q) + _core_identity_base(q.dtype, q.device)
    G = place_blocks(G_blocks, CORE, NOISE, batch, like=q) + _walk_base(q.dtype, q.device)
    return F, G


#: the columns (resp. noises) the velocity rows depend on, contiguous in CORE (resp. NOISE)
_V_COLUMNS = ("q", "b_a", "b_w", "T_a")
_V_NOISES = ("acc", "gyro")


def _span(layout: _Layout, names: str | tuple[str, ...]) -> slice:
    """The slice of one field, or of consecutive fields given as a tuple of names."""
    if isinstance(names, str):
        return layout.slice(names)
    parts = [layout.slice(n) for n in names]
    if any(a.stop != b.start for a, b in itertools.pairwise(parts)):
        raise ValueError(f"fields {names} are not consecutive in the layout {layout.names}")
    return slice(parts[0].start, parts[-1].stop)


@cached_constant
def _block_index(keys: tuple[tuple, ...], rows: _Layout, cols: _Layout, device: torch.device) -> Tensor:
    """Flat positions in a ``(rows.dim, cols.dim)`` matrix of the named blocks, concatenated
    (a block's row or column may span consecutive fields, given as a tuple of names)."""
    index = []
    for row_name, col_name in keys:
        r, c = _span(rows, row_name), _span(cols, col_name)
        index += [i * cols.dim + j for i in range(r.start, r.stop) for j in range(c.start, c.stop)]
    return torch.tensor(index, dtype=torch.long, device=device)


def place_blocks(
    blocks: dict[tuple, Tensor], rows: _Layout, cols: _Layout, batch: tuple[int, ...], *, like: Tensor
) -> Tensor:
    """A ``(*batch, rows.dim, cols.dim)`` matrix that is zero except for the named blocks.

    ``blocks`` maps ``(row field, column field)`` to a ``(..., r, c)`` tensor (a field may
    be a tuple of consecutive field names, for a block spanning them); all
    blocks are written in one scatter (fewer kernel launches than one slice
    assignment or concatenation per block). Differentiable.
    """
    values = torch.cat([b.expand(*batch, *b.shape[-2:]).reshape(*batch, -1) for b in blocks.values()], dim=-1)
    index = _block_index(tuple(blocks), rows, cols, like.device)
    flat = like.new_zeros(*batch, rows.dim * cols.dim).index_copy(-1, index, values)
    return flat.view(*batch, rows.dim, cols.dim)


@cached_constant
def _core_identity_base(dtype: torch.dtype, device: torch.device) -> Tensor:
    """Identity on the core rows except the ``q`` block (which the step Jacobian replaces)."""
    base = torch.eye(CORE_DIM, dtype=dtype, device=device)
    base[CORE.q, CORE.q] = 0.0
    return base


@cached_constant
def _walk_base(dtype: torch.dtype, device: torch.device) -> Tensor:
    """``∂x'/∂ε`` of the random walks: identity from each walk noise to its state."""
    base = torch.zeros(CORE_DIM, NOISE_DIM, dtype=dtype, device=device)
    for name in ("b_a", "b_w", "T_a"):
        base[CORE.slice(name), NOISE.slice(name)] = torch.eye(3, dtype=dtype, device=device)
    return base


def pad_core(M: Tensor) -> Tensor:
    """``(…, 19, k)`` or ``(…, 19, 19)`` core block -> zero-padded full-state rows
    ``(…, 26, k)``, resp. ``(…, 26, 26)`` when the block is square."""
    extra = STATE_DIM - CORE_DIM
    return torch.nn.functional.pad(M, (0, extra if M.shape[-1] == CORE_DIM else 0, 0, extra))


def embed_core(F_core: Tensor, G_core: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
    """Full-state ``(…, 26, 26)`` transition (identity on the augmented pose) and
    ``(…, 26, 15)`` noise Jacobian (zero rows there) from their core blocks."""
    aug_identity = torch.diag(
        (torch.arange(STATE_DIM, device=F_core.device) >= CORE_DIM).to(F_core.dtype)
    )
    return pad_core(F_core) + aug_identity, None if G_core is None else pad_core(G_core)


def mechanization_jacobians(
    x: Tensor, acc_mps2: Tensor, gyro_rps: Tensor, dt_s: Tensor, scheme: str = "midpoint"
) -> tuple[Tensor, Tensor]:
    """``(F_x, F_ε)`` of ``mechanize`` at ``(x, ε = 0)``, ``(..., 26, 26)`` and ``(..., 26, 15)``.

    Exact (not approximated) closed forms; batched over any leading dimensions,
    e.g. all ``K`` steps of a run at once with ``x`` holding the state before each step.

    For ``scheme="midpoint"`` the velocity rows use ``q_½ = q ⊙ 𝒬{θ/2}`` in place of
    ``q'``, and the position rows become ``∂p'/∂· = ∂p/∂· + Δt ∂v/∂· + (Δt/2)(∂v'/∂· - ∂v/∂·)``.
    """
    return embed_core(*core_jacobians_from_pieces(step_pieces(x, acc_mps2, gyro_rps, dt_s, scheme), scheme))
