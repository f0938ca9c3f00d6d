"""Unit quaternions and rotations, Hamilton convention, scalar first ``(w, x, y, z)``.

All functions are pure, batched over any leading dimensions, work in float32
and float64, and are differentiable everywhere (including at the identity):
small-angle cases use ``torch.where`` between a Taylor series and the exact
expression evaluated at a safe argument, never a Python ``if`` on tensor values.

A quaternion ``q`` of the state maps body (IMU) vectors to the world frame:
``v_world = q ⊙ v_body ⊙ q*`` (the paper's notation), i.e. ``R(q) @ v_body``.
"""
from __future__ import annotations

import torch
from torch import Tensor

from flowins.constants import cached_constant
from flowins.linalg import dot

# Below this squared angle the Taylor series (exact to ~theta^6) replaces the
# trigonometric expressions; both are accurate there, the series has a finite
# derivative at zero.
_SMALL_ANGLE_SQ = 1e-6


def _check(q: Tensor, name: str = "q") -> None:
    if q.shape[-1] != 4:
        raise ValueError(f"{name} must have last dimension 4 (w, x, y, z), got shape {tuple(q.shape)}")


def identity(*batch: int, dtype: torch.dtype | None = None, device=None) -> Tensor:
    """The identity quaternion with the given batch shape."""
    q = torch.zeros(*batch, 4, dtype=dtype, device=device)
    q[..., 0] = 1.0
    return q


def _naive_multiply(a: Tensor, b: Tensor) -> Tensor:
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


@cached_constant
def _constants(dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """Structure constants: the product ``(16, 4)`` and the rotation matrix ``(16, 9)`` as
    linear maps of the outer product ``a_j b_k`` (resp. ``q_j q_k``)."""
    e = torch.eye(4, dtype=torch.float64)
    product = torch.stack([_naive_multiply(e[j], e[k]) for j in range(4) for k in range(4)])  # (16, 4)
    rot = torch.zeros(4, 4, 3, 3, dtype=torch.float64)
    # R = (w² - |u|²) I + 2 u uᵀ + 2 w [u]x for unit q = (w, u)
    for i in range(3):
        rot[0, 0, i, i] += 1.0
        for j in range(1, 4):
            rot[j, j, i, i] -= 1.0
        for k in range(3):
            rot[i + 1, k + 1, i, k] += 2.0
    skew = {(2, 1): 1, (1, 2): -1, (0, 2): 1, (2, 0): -1, (1, 0): 1, (0, 1): -1}  # [u]x entries
    idx = {(2, 1): 0, (1, 2): 0, (0, 2): 1, (2, 0): 1, (1, 0): 2, (0, 1): 2}
    for (r, c), sign in skew.items():
        rot[0, idx[(r, c)] + 1, r, c] += 2.0 * sign
    return product.to(dtype=dtype, device=device), rot.reshape(16, 9).to(dtype=dtype, device=device)


def _outer(a: Tensor, b: Tensor) -> Tensor:
    return (a.unsqueeze(-1) * b.unsqueeze(-2)).flatten(-2)  # (..., 4, 4) -> (..., 16), a view


def multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product ``a ⊙ b`` of ``(..., 4)`` quaternions (broadcasting).

    Computed as one matrix product of the outer product ``a bᵀ`` with the
    algebra's structure constants (fewer kernel launches than 16 scalar products).
    """
    _check(a, "a")
    _check(b, "b")
    product, _ = _constants(a.dtype, a.device)
    return _outer(a, b) @ product


def conjugate(q: Tensor) -> Tensor:
    """``q* = (w, -x, -y, -z)``; the inverse of a unit quaternion."""
    _check(q)
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def normalize(q: Tensor) -> Tensor:
    """``q / |q|`` (a zero quaternion stays zero instead of becoming NaN)."""
    _check(q)
    return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True).clamp_min(torch.finfo(q.dtype).tiny ** 0.5)


def left_matrix(q: Tensor) -> Tensor:
    """``L(q)`` with ``q ⊙ p = L(q) @ p``; shape ``(..., 4, 4)`` (one product with the
    structure constants)."""
    _check(q)
    left, _ = _product_matrices(q.dtype, q.device)
    return (q @ left).reshape(*q.shape[:-1], 4, 4)


def right_matrix(q: Tensor) -> Tensor:
    """``R(q)`` with ``p ⊙ q = R(q) @ p``; shape ``(..., 4, 4)``."""
    _check(q)
    _, right = _product_matrices(q.dtype, q.device)
    return (q @ right).reshape(*q.shape[:-1], 4, 4)


@cached_constant
def _product_matrices(dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """``(4, 16)`` maps of ``a`` to the flattened ``L(a)`` and of ``b`` to ``R(b)``: with the
    product constants ``(a ⊙ b)_i = Σ_jk a_j b_k P[4j + k, i]``, ``L(a)_ik = Σ_j a_j P[4j + k, i]``
    and ``R(b)_ij = Σ_k b_k P[4j + k, i]``."""
    product, _ = _constants(dtype, device)
    P = product.reshape(4, 4, 4)  # [j, k, i]
    return P.permute(0, 2, 1).reshape(4, 16), P.permute(1, 2, 0).reshape(4, 16)


def to_matrix(q: Tensor) -> Tensor:
    """Rotation matrix ``(..., 3, 3)`` of a quaternion, normalised first.

    Normalising inside makes the matrix invariant to the quaternion's length, so
    its Jacobian has no component along ``q`` (the over-parametrised radial
    direction of the 4-vector state). ``R`` is a quadratic form in ``q``, computed as
    one matrix product of ``q qᵀ / |q|²`` with constant coefficients.
    """
    _check(q)
    _, rot = _constants(q.dtype, q.device)
    norm_sq = (q * q).sum(-1, keepdim=True).clamp_min(torch.finfo(q.dtype).tiny ** 0.5)
    return ((_outer(q, q) / norm_sq) @ rot).reshape(*q.shape[:-1], 3, 3)


def to_matrix_jacobian(q: Tensor) -> Tensor:
    """``∂R/∂q_k`` ``(..., 4, 3, 3)`` of :func:`to_matrix` (normalisation included).

    With ``R = M(q qᵀ) / |q|²`` for the constant linear map ``M``:
    ``∂R/∂q_k = M(e_k qᵀ + q e_kᵀ) / |q|² - 2 q_k R / |q|²``.
    """
    _check(q)
    _, rot = _constants(q.dtype, q.device)
    eye = torch.eye(4, dtype=q.dtype, device=q.device)
    qe = q.unsqueeze(-2)  # (..., 1, 4)
    # (e_k qᵀ + q e_kᵀ)[i, j] = δ_ik q_j + q_i δ_jk, for k = 0..3: (..., 4, 16)
    d_outer = (_outer(eye, qe) + _outer(qe, eye))
    norm_sq = (q * q).sum(-1).clamp_min(torch.finfo(q.dtype).tiny ** 0.5)[..., None, None, None]
    R = ((_outer(q, q) @ rot).reshape(*q.shape[:-1], 1, 3, 3)) / norm_sq
    dR = (d_outer @ rot).reshape(*q.shape[:-1], 4, 3, 3) / norm_sq
    return dR - 2.0 * q[..., :, None, None] * R / norm_sq


def rotate(q: Tensor, v: Tensor) -> Tensor:
    """``q ⊙ v ⊙ q*`` for vectors ``v`` ``(..., 3)`` (``q`` normalised first)."""
    if v.shape[-1] != 3:
        raise ValueError(f"v must have last dimension 3, got shape {tuple(v.shape)}")
    return (to_matrix(q) @ v.unsqueeze(-1)).squeeze(-1)


def from_matrix(R: Tensor) -> Tensor:
    """Unit quaternion ``(..., 4)`` with ``w >= 0`` from a rotation matrix ``(..., 3, 3)``.

    Shepperd's method without branches: all four candidate solutions are
    computed from clamped (hence finite) square roots and the best-conditioned
    one is selected per batch element.
    """
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3), got {tuple(R.shape)}")
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    trace = m00 + m11 + m22
    tiny = torch.finfo(R.dtype).eps
    # candidate k is computed from the largest of (w, x, y, z)
    d = torch.stack((trace, m00 - m11 - m22, m11 - m00 - m22, m22 - m00 - m11), -1)
    s = 2.0 * torch.sqrt((1.0 + d).clamp_min(tiny))  # 4 * component
    r21, r12 = R[..., 2, 1], R[..., 1, 2]
    r02, r20 = R[..., 0, 2], R[..., 2, 0]
    r10, r01 = R[..., 1, 0], R[..., 0, 1]
    cands = torch.stack(
        (
            torch.stack((0.25 * s[..., 0], (r21 - r12) / s[..., 0], (r02 - r20) / s[..., 0], (r10 - r01) / s[..., 0]), -1),
            torch.stack(((r21 - r12) / s[..., 1], 0.25 * s[..., 1], (r01 + r10) / s[..., 1], (r02 + r20) / s[..., 1]), -1),
            torch.stack(((r02 - r20) / s[..., 2], (r01 + r10) / s[..., 2], 0.25 * s[..., 2], (r12 + r21) / s[..., 2]), -1),
            torch.stack(((r10 - r01) / s[..., 3], (r02 + r20) / s[..., 3], (r12 + r21) / s[..., 3], 0.25 * s[..., 3]), -1),
        ),
        dim=-2,
    )
    best = d.argmax(dim=-1, keepdim=True)
    q = torch.gather(cands, -2, best.unsqueeze(-1).expand(*best.shape[:-1], 1, 4)).squeeze(-2)
    q = torch.where(q[..., :1] < 0, -q, q)
    return normalize(q)


def _half_angle_terms(theta_sq: Tensor, *, derivative: bool = False) -> Tensor:
    """``(cos(r/2), sin(r/2)/r)`` from ``r² = θ²``, and with ``derivative`` also
    ``k = (r cos(r/2)/2 - sin(r/2))/r³`` (so that ``∂(sθ)/∂θ = s I + k θθᵀ``), stacked
    ``(..., 2 or 3)``; below ``r² = 10⁻⁶`` their Taylor series (one quadratic in ``r²`` for
    all of them), so values and gradients are finite at 0."""
    small = theta_sq < _SMALL_ANGLE_SQ
    safe_sq = torch.where(small, 1.0, theta_sq)
    r = torch.sqrt(safe_sq)
    half = 0.5 * r
    cos, sin = torch.cos(half), torch.sin(half)
    terms = [cos, sin / r]
    if derivative:
        terms.append((half * cos - sin) / (safe_sq * r))
    a, b, c = _taylor_coefficients(len(terms), theta_sq.dtype, theta_sq.device)
    x = theta_sq.unsqueeze(-1)
    taylor = (x * c + b) * x + a
    return torch.where(small.unsqueeze(-1), taylor, torch.stack(terms, -1))


@cached_constant
def _taylor_coefficients(count: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    """Coefficients of ``r⁰, r², r⁴`` of ``cos(r/2)``, ``sin(r/2)/r`` and ``k``, each ``(count,)``."""
    table = torch.tensor([[1.0, 0.5, -1.0 / 24.0], [-1.0 / 8.0, -1.0 / 48.0, 1.0 / 960.0],
                          [1.0 / 384.0, 1.0 / 3840.0, 0.0]], dtype=dtype, device=device)
    return table[0, :count].clone(), table[1, :count].clone(), table[2, :count].clone()


def from_rotation_vector(rotvec: Tensor) -> Tensor:
    """The paper's ``𝒬{ω}``: unit quaternion of the rotation vector ``(..., 3)``.

    ``𝒬{θ} = (cos(|θ|/2), sin(|θ|/2) θ/|θ|)``, exact for any angle and smooth
    (with finite gradients) at ``θ = 0``.
    """
    if rotvec.shape[-1] != 3:
        raise ValueError(f"rotation vector must have last dimension 3, got shape {tuple(rotvec.shape)}")
    cs = _half_angle_terms(dot(rotvec, rotvec))
    return torch.cat((cs[..., :1], cs[..., 1:] * rotvec), dim=-1)


def to_rotation_vector(q: Tensor) -> Tensor:
    """Inverse of :func:`from_rotation_vector` (the shortest rotation, angle in [0, π]).

    ``θ = 2 atan2(|u|, w) u/|u|`` with ``q = (w, u)`` taken with ``w >= 0``;
    the small-angle branch uses ``2 u / w (1 - |u|²/(3 w²))`` so the result and its
    gradient are finite at the identity.
    """
    q = normalize(q)
    q = torch.where(q[..., :1] < 0, -q, q)
    w, u = q[..., 0], q[..., 1:]
    n_sq = (u * u).sum(-1)
    small = n_sq < _SMALL_ANGLE_SQ
    n = torch.sqrt(torch.where(small, torch.ones_like(n_sq), n_sq))
    w_safe = torch.where(small, w, torch.ones_like(w))
    exact = 2.0 * torch.atan2(n, w) / n
    taylor = 2.0 / w_safe * (1.0 - n_sq / (3.0 * w_safe * w_safe))
    return torch.where(small, taylor, exact).unsqueeze(-1) * u


def from_euler(roll: Tensor, pitch: Tensor, yaw: Tensor) -> Tensor:
    """Quaternion of ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (z-y-x intrinsic, aerospace)."""
    ex = torch.stack((roll, torch.zeros_like(roll), torch.zeros_like(roll)), -1)
    ey = torch.stack((torch.zeros_like(pitch), pitch, torch.zeros_like(pitch)), -1)
    ez = torch.stack((torch.zeros_like(yaw), torch.zeros_like(yaw), yaw), -1)
    return multiply(multiply(from_rotation_vector(ez), from_rotation_vector(ey)), from_rotation_vector(ex))


def to_euler(q: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(roll, pitch, yaw)`` of :func:`from_euler`'s convention."""
    R = to_matrix(q)
    yaw = torch.atan2(R[..., 1, 0], R[..., 0, 0])
    pitch = torch.asin((-R[..., 2, 0]).clamp(-1.0, 1.0))
    roll = torch.atan2(R[..., 2, 1], R[..., 2, 2])
    return roll, pitch, yaw


def angle_between(a: Tensor, b: Tensor) -> Tensor:
    """Rotation angle (rad) of ``a* ⊙ b``, in [0, π]."""
    return to_rotation_vector(multiply(conjugate(normalize(a)), normalize(b))).norm(dim=-1)


def cumulative_product(q: Tensor) -> Tensor:
    """Inclusive prefix products ``q_0, q_0⊙q_1, q_0⊙q_1⊙q_2, ...`` of ``(..., K, 4)``.

    Computed as a log-depth (Hillis-Steele) scan, so a run of ``K`` steps costs
    ``⌈log2 K⌉`` batched products rather than ``K`` sequential ones.
    """
    _check(q)
    if q.ndim < 2:
        raise ValueError(f"expected (..., K, 4) quaternions, got shape {tuple(q.shape)}")
    q = q.movedim(-2, 0)
    n = q.shape[0]
    shift = 1
    while shift < n:
        q = torch.cat((q[:shift], multiply(q[:-shift], q[shift:])), dim=0)
        shift *= 2
    return q.movedim(0, -2)


# --------------------------------------------------------------------------- Jacobians


def skew(a: Tensor) -> Tensor:
    """``[a]×`` ``(..., 3, 3)`` of ``a`` ``(..., 3)``: ``[a]× b = a × b``."""
    x, y, z = a.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack(
        (torch.stack((o, -z, y), -1), torch.stack((z, o, -x), -1), torch.stack((-y, x, o), -1)), dim=-2
    )


def from_rotation_vector_with_jacobian(theta: Tensor) -> tuple[Tensor, Tensor]:
    """``𝒬{θ}`` ``(..., 4)`` and ``∂𝒬{θ}/∂θ`` ``(..., 4, 3)`` from shared terms.

    With ``r = |θ|``, ``c = cos(r/2)``, ``s = sin(r/2)/r`` and
    ``k = (r cos(r/2)/2 - sin(r/2))/r³``: ``𝒬{θ} = (c, s θ)``, ``∂c/∂θ = -(s/2) θᵀ`` and
    ``∂(sθ)/∂θ = s I + k θθᵀ``; branch-free and finite at ``θ = 0``.
    """
    if theta.shape[-1] != 3:
        raise ValueError(f"rotation vector must have last dimension 3, got shape {tuple(theta.shape)}")
    csk = _half_angle_terms(dot(theta, theta), derivative=True)
    c, s, k = csk[..., :1], csk[..., 1:2], csk[..., 2:]
    E = torch.cat((c, s * theta), dim=-1)
    # rows (-½ s θᵀ; s I + k θθᵀ) = s [0; I] + (-½ s, k θ) θᵀ
    w = torch.cat((-0.5 * s, k * theta), dim=-1)
    return E, s.unsqueeze(-1) * _lower_identity(theta.dtype, theta.device) + w.unsqueeze(-1) * theta.unsqueeze(-2)


@cached_constant
def _lower_identity(dtype: torch.dtype, device: torch.device) -> Tensor:
    """``(4, 3)``: a zero row above the identity."""
    return torch.cat((torch.zeros(1, 3, dtype=dtype, device=device), torch.eye(3, dtype=dtype, device=device)))


def rotate_jacobian(q: Tensor, a: Tensor) -> Tensor:
    """``∂(C(q/|q|) a)/∂q`` ``(..., 3, 4)`` for a (not necessarily unit) quaternion ``q``.

    ``C(q) a = M(q qᵀ) a`` is quadratic in ``q``; with ``N(q, a)`` ``(..., 3, 4)`` its
    derivative ``∂(M(q qᵀ) a)/∂q`` (bilinear in ``q`` and ``a``: one product of the
    outer product ``q aᵀ`` with constants), the normalisation gives
    ``(N - N q qᵀ / |q|²) / |q|²``.
    """
    N = (_outer_qa(q, a) @ _rotate_derivative_constants(q.dtype, q.device)).reshape(*q.shape[:-1], 3, 4)
    norm_sq = (q * q).sum(-1)[..., None, None]
    return (N - (N @ q.unsqueeze(-1)) * q.unsqueeze(-2) / norm_sq) / norm_sq


def _outer_qa(q: Tensor, a: Tensor) -> Tensor:
    return (q.unsqueeze(-1) * a.unsqueeze(-2)).flatten(-2)  # (..., 4, 3) -> (..., 12), a view


@cached_constant
def _rotate_derivative_constants(dtype: torch.dtype, device: torch.device) -> Tensor:
    """``(12, 12)``: row ``3j + l`` (``q_j a_l``), column ``4k + i``: ``∂(C(q) a)_k/∂q_i`` per
    ``q_j a_l``, i.e. ``M[4i + j, 3k + l] + M[4j + i, 3k + l]`` with ``M`` the rotation constants."""
    _, rot = _constants(torch.float64, torch.device("cpu"))
    M = rot.reshape(4, 4, 3, 3)  # [i, j, k, l]
    sym = M + M.transpose(0, 1)
    return sym.permute(1, 3, 2, 0).reshape(12, 12).to(dtype=dtype, device=device)
