"""The optical-flow measurement model of the paper (Sec. "Information Fusion").

For a flow point ``δ = (Δu, Δv)`` at pixel ``(u₁, v₁)`` of the previous frame, the
cameras ``P₁ = K [R₁ᵀ | -R₁ᵀ c₁]`` (from the augmented pose ``p⁻, q⁻``) and
``P₂ = K [R₂ᵀ | -R₂ᵀ c₂]`` (from the current pose ``p, q``), both including the
IMU→camera transform, triangulate ``X̃`` from ``(u₁, v₁)`` and ``(u₁ + Δu, v₁ + Δv)``
(:func:`flowins.geometry.triangulation.triangulate`, the paper's linear system, solved for its
smallest right singular vector)
and

    h(x, δ) = π(P₂ X̃) - π(P₁ X̃) - δ          (pixels, ``0 = h(x, δ + r)``)

``h`` is the reprojection inconsistency of the two rays: zero when the flow agrees
with the relative pose. Its Jacobians ``H_x = ∂h/∂x`` (2 x 26) and ``H_r = ∂h/∂δ``
(2 x 2) come in closed form (:func:`flow_linearisation`, the default) or from
``torch.func.jacrev`` through the triangulation under ``vmap`` (the reference,
``jacobians="autodiff"``); both are differentiable, as training needs.

Batches: every function takes leading batch dimensions ``...`` (one state per
sequence, ``M`` points per sequence, a mask for the padding of sequences with fewer
points); the camera is shared or carries the same batch dimensions.

Conditioning: the world origin is moved to camera 1's centre and the triangulation
works in normalised coordinates ``K⁻¹ (u, v, 1)``; the projections are converted back
to pixels, so ``h`` is exactly the paper's.

States with a window of ``N > 1`` cloned poses (``D = 19 + 7 N``, :mod:`flowins.state`) are
measured as their 26-dim part (the core and clone 0, the previous frame); ``H_x`` has zero
columns for the further clones.

Degenerate geometry never produces NaN or inf. A point is *degenerate* when the
triangulation's two smallest singular values meet (no baseline, or flow that only a
rotation explains: every point on the ray fits), *behind* when the solution sits at
a camera centre or behind either camera, and *low-parallax* when its viewing rays
are closer than a threshold. Such points, and the padding, get ``h = 0``, ``H = 0``
and ``valid = False``; the first three kinds are counted in :class:`FlowMeasurements`.
With a gradient to carry, the Jacobians of the valid points only are computed.
"""
from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor
from torch.func import jacrev, vmap

from flowins.constants import cached_constant
from flowins.geometry import quaternion as quat
from flowins.geometry.triangulation import camera_matrix, project_homogeneous, solve_dlt, triangulate
from flowins.linalg import dot
from flowins.state import STATE, STATE_DIM, make_state, split, window_size


class CameraTerms(NamedTuple):
    """What the flow model uses of a :class:`FlowCamera`, formed once per camera (batch dims ``...``
    where the camera has them)."""

    centre_b: Tensor  # (..., 3) the camera centre in the body frame, -R_ciᵀ t_ci
    focal: Tensor  # (..., 2) (f_x, f_y), px
    focal_mean: Tensor  # (...,) ½ (f_x + f_y), px per rad of parallax
    #: (u₁, v₁, Δu, Δv) @ pixel_map + pixel_offset: the rows [-I | x_k] (2 cameras, 2 rows, 3) of the
    #: DLT system, x_k the normalised image points (1/f, -c/f: the skew of K is not used)
    pixel_map: Tensor  # (..., 4, 12)
    pixel_offset: Tensor  # (..., 12)
    flow_map: Tensor  # (..., 3, 1, 2): -δ_as / f_s
    projection_scale: Tensor  # (..., 2, 2, 1) [s, k]: f_s for camera 1 (k = 0), -f_s for camera 2


@dataclass(frozen=True)
class FlowCamera:
    """Intrinsics ``K`` ``(3, 3)`` and the IMU→camera transform (``x_c = R_ci x_i + t_ci``); each
    ``(3, 3)``/``(3,)`` (shared by a batch) or with the batch dimensions ``(..., 3, 3)``."""

    K: Tensor
    R_ci: Tensor
    t_ci: Tensor

    @classmethod
    def from_calibration(cls, camera, imu_to_camera) -> FlowCamera:
        """From a :class:`~flowins.data.PinholeCamera` and a :class:`~flowins.geometry.camera.RigidTransform`."""
        return cls(camera.K, imu_to_camera.rotation_matrix, imu_to_camera.translation_m)

    @classmethod
    def from_sequence(cls, sequence) -> FlowCamera | None:
        """From a :class:`~flowins.data.Sequence`'s calibration; None without one."""
        if sequence is None or sequence.camera is None or sequence.imu_to_camera is None:
            return None
        return cls.from_calibration(sequence.camera, sequence.imu_to_camera)

    @property
    def batch_shape(self) -> torch.Size:
        """The batch dims the camera carries (``()`` when shared)."""
        return torch.broadcast_shapes(self.K.shape[:-2], self.R_ci.shape[:-2], self.t_ci.shape[:-1])

    @property
    def tracked(self) -> bool:
        """Whether a tensor of the camera requires a gradient (then nothing is kept between calls)."""
        return any(t.requires_grad for t in (self.K, self.R_ci, self.t_ci))

    @property
    def centre_b(self) -> Tensor:
        """The camera centre in the body (IMU) frame ``(..., 3)``: ``-R_ciᵀ t_ci``."""
        return self.terms.centre_b

    @property
    def terms(self) -> CameraTerms:
        """:class:`CameraTerms` (kept after the first use unless the camera carries a gradient)."""
        if self.tracked:
            return _camera_terms(self.K, self.R_ci, self.t_ci)
        cached = self.__dict__.get("_terms")
        if cached is None:
            with torch.inference_mode(False):  # plain tensors, usable by later runs with gradients
                cached = _camera_terms(self.K, self.R_ci, self.t_ci)
            object.__setattr__(self, "_terms", cached)
        return cached

    def to(self, like: Tensor) -> FlowCamera:
        """This camera in ``like``'s dtype and device (itself when it already is; the converted
        copy is kept unless the camera carries a gradient)."""
        if all(t.dtype == like.dtype and t.device == like.device for t in (self.K, self.R_ci, self.t_ci)):
            return self
        if self.tracked:  # carries a gradient: converted afresh, never kept
            return FlowCamera(self.K.to(like), self.R_ci.to(like), self.t_ci.to(like))
        key = (like.dtype, like.device)
        copies = self.__dict__.setdefault("_copies", {})
        if key in copies:
            return copies[key]
        with torch.inference_mode(False):  # plain tensors, usable by later runs with gradients too
            copy = FlowCamera(self.K.to(like), self.R_ci.to(like), self.t_ci.to(like))
        copies[key] = copy
        return copy

    def take(self, index: Tensor, batch: torch.Size) -> FlowCamera:
        """The camera of the flattened batch rows ``index`` ``(N,)`` (itself when shared)."""
        if not self.batch_shape:
            return self

        def rows(t: Tensor, event: int) -> Tensor:
            if t.ndim == event:
                return t
            return t.expand(*batch, *t.shape[-event:]).reshape(-1, *t.shape[-event:])[index]

        return FlowCamera(rows(self.K, 2), rows(self.R_ci, 2), rows(self.t_ci, 1))


def _camera_terms(K: Tensor, R_ci: Tensor, t_ci: Tensor) -> CameraTerms:
    pattern, offset_pattern, base, flow_pattern, signs = _pixel_patterns(K.dtype, K.device)
    f = torch.stack((K[..., 0, 0], K[..., 1, 1]), -1)
    inv = 1.0 / f
    return CameraTerms(
        centre_b=-(R_ci.transpose(-1, -2) @ t_ci.unsqueeze(-1)).squeeze(-1),
        focal=f,
        focal_mean=0.5 * (f[..., 0] + f[..., 1]),
        pixel_map=(pattern * inv[..., None, None, :]).sum(-1),
        pixel_offset=base + (offset_pattern * (-K[..., :2, 2] * inv)[..., None, :]).sum(-1),
        flow_map=-flow_pattern * inv[..., None, None, :],
        projection_scale=(f[..., :, None] * signs)[..., None],
    )


@cached_constant
def _pixel_patterns(dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Where ``1/f_r`` ``(4, 12, 2)``, ``-c_r/f_r`` ``(12, 2)`` and the ``-1`` of ``-I`` ``(12,)`` sit in the
    flattened rows ``[-I | x_k]`` (camera k, row r, column j), the pattern ``δ_as`` ``(3, 1, 2)`` and
    the camera signs ``(2,)``."""
    pattern = torch.zeros(4, 2, 2, 3, 2, dtype=torch.float64)
    offset = torch.zeros(2, 2, 3, 2, dtype=torch.float64)
    base = torch.zeros(2, 2, 3, dtype=torch.float64)
    for r in range(2):
        for k in range(2):
            pattern[r, k, r, 2, r] = 1.0  # u₁ (v₁) enters x of both cameras
            offset[k, r, 2, r] = 1.0
            base[k, r, r] = -1.0
        pattern[2 + r, 1, r, 2, r] = 1.0  # Δu (Δv) enters camera 2's
    flow = torch.zeros(3, 1, 2, dtype=torch.float64)
    flow[0, 0, 0] = flow[1, 0, 1] = 1.0
    signs = torch.tensor([1.0, -1.0], dtype=torch.float64)
    return tuple(t.to(dtype=dtype, device=device) for t in (pattern.reshape(4, 12, 2), offset.reshape(12, 2),
                                                            base.reshape(12), flow, signs))


class FlowAux(NamedTuple):
    conditioning: Tensor  # (σ₃ - σ₄) / σ₁ of the triangulation
    depth1: Tensor  # z of X̃ in camera 1 (homogeneous, X̃ of unit norm)
    depth2: Tensor  # z of X̃ in camera 2
    parallax: Tensor  # angle (rad) between the two viewing rays in the world frame


def camera_pose(q: Tensor, p: Tensor, camera: FlowCamera) -> tuple[Tensor, Tensor]:
    """``(R_wc, c_w)``: camera orientation (camera→world) ``(..., 3, 3)`` and centre ``(..., 3)``
    from the IMU pose ``(q, p)``."""
    R_wb = quat.to_matrix(q)
    R_wc = R_wb @ camera.R_ci.transpose(-1, -2)
    return R_wc, p + (R_wb @ camera.centre_b.unsqueeze(-1)).squeeze(-1)


def ray_angle(ray1: Tensor, ray2: Tensor) -> Tensor:
    """Angle (rad) between two rays ``(..., 3)`` (not necessarily unit), stable near 0 and π."""
    return torch.atan2(torch.linalg.vector_norm(torch.linalg.cross(ray1, ray2), dim=-1), dot(ray1, ray2))


def normalise_pixels(uv: Tensor, K: Tensor) -> Tensor:
    """Pixels ``(..., 2)`` -> normalised image coordinates ``K⁻¹ (u, v, 1)`` without the 1
    (``K`` ``(3, 3)`` or with the batch dims of ``uv``; its skew is not used)."""
    return (uv - K[..., :2, 2]) / torch.stack((K[..., 0, 0], K[..., 1, 1]), -1)


def _to_pixels(xy: Tensor, K: Tensor) -> Tensor:
    return xy * torch.stack((K[..., 0, 0], K[..., 1, 1]), -1) + K[..., :2, 2]


def flow_residual(x: Tensor, flow_px: Tensor, uv1_px: Tensor, camera: FlowCamera) -> tuple[Tensor, FlowAux]:
    """``h(x, δ)`` ``(..., 2)`` point by point, and the triangulation's diagnostics: the model as
    written, the reference of the closed form.

    Args:
        x ``(..., 26)`` state; flow_px ``δ`` ``(..., 2)``; uv1_px ``(..., 2)`` pixel in the previous
        frame; the camera shared or with the same batch dims.
    """
    s = split(x)
    (R1, R2), (c1, c2) = camera_pose(torch.stack((s.q_prev, s.q)), torch.stack((s.p_prev, s.p)), camera)
    P1 = camera_matrix(R1, torch.zeros_like(c1))  # world origin at camera 1's centre
    P2 = camera_matrix(R2, c2 - c1)
    x1 = normalise_pixels(uv1_px, camera.K)
    x2 = normalise_pixels(uv1_px + flow_px, camera.K)
    tri = triangulate(P1, P2, x1, x2)
    y1, z1 = project_homogeneous(P1, tri.point)
    y2, z2 = project_homogeneous(P2, tri.point)
    h = _to_pixels(y2, camera.K) - _to_pixels(y1, camera.K) - flow_px
    return h, FlowAux(tri.conditioning, z1, z2, _parallax(R1, R2, x1, x2))


def _parallax(R1: Tensor, R2: Tensor, x1: Tensor, x2: Tensor) -> Tensor:
    """Angle between the world-frame viewing rays of normalised points ``x1``, ``x2`` ``(..., 2)``."""
    ray1 = (R1 @ torch.cat((x1, torch.ones_like(x1[..., :1])), -1).unsqueeze(-1)).squeeze(-1)
    ray2 = (R2 @ torch.cat((x2, torch.ones_like(x2[..., :1])), -1).unsqueeze(-1)).squeeze(-1)
    return ray_angle(ray1, ray2)


# ----------------------------------------------------------------------------- closed form


class _PoseConstants(NamedTuple):
    select: Tensor  # (26, 14): x @ select = (p⁻, p, -q⁻, q)
    rotation: Tensor  # (16, 9): R(q) = (q qᵀ) @ rotation for unit q
    generator: Tensor  # (4, 12): G(q) = q @ generator, δφ = G dq for unit q (R ← (I + [δφ]×) R)
    mix: Tensor  # (3, 4): rows e = c₁ - c₂, o₁, e + o₂ of (p⁻, p, o₁, o₂)
    camera1: Tensor  # (3, 4) [I | 0]
    translation: Tensor  # (3, 4, 3): ∂P/∂t of [· | t] along t, [i, b, j] = δ_b3 δ_ij
    translation_back: Tensor  # (3, 4, 3): its negative


@cached_constant
def _pose_constants(dtype: torch.dtype, device: torch.device) -> _PoseConstants:
    f64 = torch.float64
    select = torch.zeros(STATE_DIM, 14, dtype=f64)
    for column, (name, sign) in zip((0, 3, 6, 10), (("p_prev", 1.0), ("p", 1.0), ("q_prev", -1.0), ("q", 1.0))):
        rows = torch.arange(STATE.slice(name).start, STATE.slice(name).stop)
        select[rows, column + torch.arange(len(rows))] = sign
    # R is quadratic in q: the coefficient of q_j q_k from R at e_j, e_k and e_j + e_k (polarisation)
    e = torch.eye(4, dtype=f64)
    single = quat.to_matrix(e)  # (4, 3, 3)
    pair = 2.0 * quat.to_matrix(e[:, None] + e[None, :])  # (4, 4, 3, 3): R((e_j + e_k)(e_j + e_k)ᵀ) unnormalised
    rotation = 0.5 * (pair - single[:, None] - single[None, :])
    rotation[range(4), range(4)] = single
    # δφ = 2 vec(dq ⊗ q*): [m, i, j] = 2 vec(e_j ⊗ e_m*)_i
    generator = 2.0 * quat.multiply(e[None, :, :], quat.conjugate(e)[:, None, :])[..., 1:].transpose(-1, -2)
    mix = torch.tensor([[1.0, -1.0, 1.0, -1.0], [0.0, 0.0, 1.0, 0.0], [1.0, -1.0, 1.0, 0.0]], dtype=f64)
    translation = torch.zeros(3, 4, 3, dtype=f64)
    translation[:, 3, :] = torch.eye(3, dtype=f64)
    return _PoseConstants(*(t.to(dtype=dtype, device=device) for t in (
        select, rotation.reshape(16, 9), generator.reshape(4, 12), mix, torch.eye(3, 4, dtype=f64), translation,
        -translation)))


def scaled_rotations(q: Tensor) -> Tensor:
    """``|q|² R(q)`` ``(..., 3, 3)`` of quaternions ``(..., 4)`` (``R(q)`` itself for unit ``q``): one
    product of ``q qᵀ`` with the constant coefficients of the quadratic form."""
    rotation = _pose_constants(q.dtype, q.device).rotation
    return ((q.unsqueeze(-1) * q.unsqueeze(-2)).view(*q.shape[:-1], 16) @ rotation).view(*q.shape[:-1], 3, 3)


def _pose_terms(x: Tensor, camera: FlowCamera, terms: CameraTerms, batch: torch.Size) -> tuple[Tensor, Tensor]:
    """The two cameras in camera 1's frame ``P₁' = [I | 0]``, ``P₂' = [R | t]`` ``(..., 2, 3, 4)``
    (``R = R₂ᵀ R₁``, ``t = R₂ᵀ (c₁ - c₂)``) and ``J`` ``(..., 12, 28)``: the derivatives of the
    12 entries of ``P₂'`` along the state ``(26)`` and along the flow ``δ`` ``(2)``.

    With ``R_k = R(q_k) R_ciᵀ``, ``c_k = p_k + o_k``, ``o_k = R(q_k) c_b`` (``c_b`` the camera
    centre in the body) and world-frame rotations ``dR(q_k) = [δφ_k]× R(q_k)``,
    ``δφ_k = G(q_k) dq_k`` (:func:`~flowins.geometry.quaternion.to_matrix` normalises, so
    ``G`` has no radial part):

        ∂P₂'/∂q⁻ = R₂ᵀ [δφ₁]× [R₁ | o₁],   ∂P₂'/∂q = -R₂ᵀ [δφ₂]× [R₁ | e + o₂],
        ∂P₂'/∂p⁻ = R₂ᵀ [0 | I],            ∂P₂'/∂p = -R₂ᵀ [0 | I]          (e = c₁ - c₂)

    column by column ``-[δφ]× n = n × G dq``. The flow ``δ_s`` moves the DLT rows of camera 2
    and ``π(P₂' X̃) - δ`` exactly as ``P₂' += -e_s P₂'[2] / f_s`` does, so it is a 13th and
    14th direction of the same kind.
    """
    C = _pose_constants(x.dtype, x.device)
    xs = x @ C.select
    positions = xs[..., :6].view(*x.shape[:-1], 2, 3)  # p⁻, p
    q = xs[..., 6:].view(*x.shape[:-1], 2, 4)  # -q⁻, q: the sign flips G(q⁻), not R(q⁻)
    norm = torch.linalg.vector_norm(q, dim=-1, keepdim=True).clamp_min(torch.finfo(x.dtype).tiny ** 0.25)
    qn = q / norm
    R_b = scaled_rotations(qn)
    G = (qn @ C.generator).view(*q.shape[:-1], 3, 4) / norm.unsqueeze(-1)  # -G(q⁻), G(q)
    R_c = R_b @ _per_row(camera.R_ci, 2, 1).transpose(-1, -2)  # (..., 2, 3, 3): R₁, R₂
    o = (R_b @ _per_row(terms.centre_b, 1, 1).unsqueeze(-1)).squeeze(-1)  # (..., 2, 3): o₁, o₂
    e = C.mix @ torch.cat((positions, o), -2)  # (..., 3, 3): e, o₁, e + o₂
    # rows of the columns: [R₁ | e], [R₁ | o₁], [R₁ | e + o₂]
    R1t = R_c[..., 0, :, :].transpose(-1, -2)
    columns = torch.cat((R1t.unsqueeze(-3).expand(*batch, 3, 3, 3), e.unsqueeze(-2)), -2)
    turn = torch.linalg.cross(columns[..., 1:, :, :].unsqueeze(-1), G.unsqueeze(-3), dim=-2)  # (..., 2, 4, 3, 4)
    pieces = {"p": C.translation_back, "p_prev": C.translation, "q": turn[..., 1, :, :, :].transpose(-3, -2),
              "q_prev": turn[..., 0, :, :, :].transpose(-3, -2)}
    inner = torch.cat([pieces[name].expand(*batch, 3, 4, size) if name in pieces else
                       _zeros(size, x.dtype, x.device).expand(*batch, 3, 4, size) for name, size in STATE.sizes]
                      + [columns[..., 0, :, :].transpose(-1, -2).unsqueeze(-1)], -1)  # (..., 3, 4, 27)
    out = R_c[..., 1, :, :].transpose(-1, -2) @ inner.view(*batch, 3, 4 * (STATE_DIM + 1))
    out = out.view(*batch, 3, 4, STATE_DIM + 1)
    P2 = out[..., STATE_DIM]  # R₂ᵀ [R₁ | e]
    cameras = torch.cat((C.camera1.expand(*batch, 1, 3, 4), P2.unsqueeze(-3)), -3)
    flow = P2[..., 2, None, :, None] * terms.flow_map  # (..., 3, 4, 2)
    return cameras, torch.cat((out[..., :STATE_DIM], flow), -1).view(*batch, 12, STATE_DIM + 2)


@cached_constant
def _zeros(size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    return torch.zeros(3, 4, size, dtype=dtype, device=device)


def _affine(v: Tensor, W: Tensor, b: Tensor) -> Tensor:
    """``v @ W + b`` ``(..., M, m)`` for ``v`` ``(..., M, n)``, ``W`` ``(n, m)``/``(..., n, m)``, ``b``
    ``(m,)``/``(..., m)``: one batched product-and-add over the flattened batch (``v`` contiguous)."""
    n, m = W.shape[-2:]
    batch = v.shape[:-2]
    rows = math.prod(batch)
    out = torch.baddbmm(b.expand(*batch, m).view(rows, 1, m), v.view(rows, *v.shape[-2:]),
                        W.expand(*batch, n, m).view(rows, n, m))
    return out.view(*v.shape[:-1], m)


def _per_row(t: Tensor, event: int, new: int) -> Tensor:
    """``t`` ``(..., *event)`` with ``new`` axes before its event dims when it has batch dims (a
    camera tensor against per-point or per-camera tensors), unchanged when shared."""
    for _ in range(new if t.ndim > event else 0):
        t = t.unsqueeze(-event - 1)
    return t


class _Linearised(NamedTuple):
    residual: Tensor  # (..., M, 2) h
    dh: Tensor | None  # (..., M, 2, 12) ∂h/∂P₂' (J maps it to the state and the flow)
    J: Tensor  # (..., 12, 28) ∂P₂'/∂(x, δ)
    conditioning: Tensor  # (..., M)
    depth: Tensor  # (..., M, 2) z in camera 1 and camera 2
    parallax: Tensor  # (..., M) rad


def _linearise(x: Tensor, flow_px: Tensor, uv1_px: Tensor, camera: FlowCamera, *, mask: Tensor | None = None,
               derivatives: bool = True) -> _Linearised:
    """``h`` of every point and, with ``derivatives``, ``∂h/∂P₂'``, in closed form (see
    :func:`flow_linearisation`); padding (``mask`` False) is computed on zeros."""
    terms = camera.terms
    batch = torch.broadcast_shapes(x.shape[:-1], camera.batch_shape)
    M = flow_px.shape[-2]
    cameras, J = _pose_terms(x, camera, terms, batch)
    uvf = torch.cat((uv1_px, flow_px), -1)  # (..., M, 4)
    if mask is not None:
        uvf = torch.where(mask.unsqueeze(-1), uvf, 0.0)
    # the DLT rows x_r P[2] - P[r] = [-I | x] P of both cameras
    L = _affine(uvf, terms.pixel_map, terms.pixel_offset).view(*batch, M, 2, 2, 3)
    A = (L @ cameras.unsqueeze(-4)).view(*batch, M, 4, 4)
    # the triangulation exactly as triangulate() solves it
    dlt = solve_dlt(A)  # camera 1 is [I | 0]
    X = dlt.point
    y = (cameras.view(*batch, 1, 6, 4) @ X.unsqueeze(-1)).view(*batch, M, 2, 3)  # P₁' X̃, P₂' X̃
    depth = y[..., 2]
    pi = y[..., :2] / y[..., 2:]
    focal = _per_row(terms.focal, 1, 1)
    h = (pi[..., 1, :] - pi[..., 0, :]) * focal - uvf[..., 2:]
    # the viewing rays in camera 1's frame, (x₁, 1) and Rᵀ (x₂, 1): the null vectors of each camera's rows
    rays = torch.linalg.cross(A[..., 0::2, :3], A[..., 1::2, :3])
    parallax = ray_angle(rays[..., 0, :], rays[..., 1, :])
    dh = _point_derivatives(L, cameras, dlt, pi, depth, terms) if derivatives else None
    return _Linearised(h, dh, J, dlt.conditioning, depth, parallax)


def _point_derivatives(L: Tensor, cameras: Tensor, dlt, pi: Tensor, depth: Tensor, terms: CameraTerms) -> Tensor:
    """``∂h/∂P₂'[a, b]`` ``(..., M, 2, 12)`` (see :func:`flow_linearisation`)."""
    X, rows = dlt.point, dlt.rows
    a, n, c = rows[..., 2:, :], dlt.row_norm[..., 2:], dlt.residual[..., 2:]  # camera 2's rows
    L2 = L[..., 1, :, :]  # (..., M, 2, 3)
    # -(σᵢ² - σ₄²): Z below is -Q W
    gap = (dlt.residual_sq.unsqueeze(-1) - dlt.eigenvalues[..., 1:]).clamp_max(-torch.finfo(X.dtype).tiny)
    V3 = dlt.eigenvectors[..., 1:]  # (..., M, 4, 3)
    # N[s, k] = ±f_s ∂π_k[s]/∂y_k = ±f_s [e_s | -π_k[s]] / z_k (+ for camera 2), Q = Σ_k N_k P_k'
    base = torch.cat((_neg_eye(X.dtype, X.device).expand(*pi.shape[:-2], 2, 2, 2),
                      pi.transpose(-1, -2).unsqueeze(-1)), -1)
    N = base * (_per_row(terms.projection_scale, 3, 1) / depth[..., None, :, None])  # (..., M, 2s, 2k, 3)
    Q = N.view(*N.shape[:-3], 2, 6) @ cameras.view(*cameras.shape[:-3], 1, 6, 4)  # (..., M, 2, 4)
    Z = (((Q @ V3) / gap.unsqueeze(-2)) @ V3.transpose(-1, -2))  # (..., M, 2, 4)
    kappa = torch.addcmul(X.unsqueeze(-2), c.unsqueeze(-1), a, value=-2.0) / n.unsqueeze(-1)  # (..., M, 2, 4)
    ZaL = (Z @ a.transpose(-1, -2)).unsqueeze(-1) * L2.unsqueeze(-3)  # (..., M, 2s, 2r, 3)
    w = (c / n).unsqueeze(-2) @ L2  # (..., M, 1, 3)
    U = torch.cat((ZaL.transpose(-1, -2), w.unsqueeze(-1).expand(*ZaL.shape[:-3], 2, 3, 1),
                   N[..., 1, :].unsqueeze(-1)), -1)
    V = torch.cat((kappa.unsqueeze(-3).expand(*kappa.shape[:-2], 2, 2, 4), Z.unsqueeze(-2),
                   X[..., None, None, :].expand(*X.shape[:-1], 2, 1, 4)), -2)
    return (U @ V).view(*U.shape[:-2], 12)


def _chain(dh: Tensor, J: Tensor) -> Tensor:
    """``∂h/∂(x, δ)`` ``(..., M, 2, 28)`` from ``∂h/∂P₂'`` ``(..., M, 2, 12)`` and ``J`` ``(..., 12, 28)``:
    one product per sequence over its ``2M`` rows (``J`` is not copied out to every point)."""
    rows = dh.reshape(*dh.shape[:-3], dh.shape[-3] * dh.shape[-2], dh.shape[-1])
    return (rows @ J).view(*dh.shape[:-1], J.shape[-1])


@cached_constant
def _neg_eye(dtype: torch.dtype, device: torch.device) -> Tensor:
    """``-δ_sj`` as ``(2, 1, 2)`` [s, ·, j]."""
    return -torch.eye(2, dtype=dtype, device=device).unsqueeze(-2)


class FlowLinearisation(NamedTuple):
    residual: Tensor  # (..., M, 2) h
    H_x: Tensor  # (..., M, 2, D)
    H_r: Tensor  # (..., M, 2, 2)
    aux: FlowAux


def flow_linearisation(x: Tensor, flow_px: Tensor, uv1_px: Tensor, camera: FlowCamera) -> FlowLinearisation:
    """``h`` and its Jacobians ``H_x``, ``H_r`` of ``M`` points at once, in closed form.

    The same function as :func:`flow_residual`, differentiated by hand (no
    ``torch.func``), for states ``x`` ``(..., 26)`` and points ``(..., M, 2)`` (a state ``(..., D)``
    with a window of cloned poses is measured as its 26-dim part, zero-padded). It is computed
    in camera 1's frame, ``P₁' = [I | 0]``, ``P₂' = [R | t]``: the DLT matrix there is the world
    one times an orthogonal matrix, so its equilibrated singular values, the projections
    and ``h`` are the same, and only the last two rows ``A_r = L_r P₂'`` (``L = [-I | x₂]``)
    depend on the pose and the flow. Each point is differentiated along the 12 entries of
    ``P₂'``; ``J = ∂P₂'/∂(x, δ)`` ``(12, 28)``, once per sequence (:func:`_pose_terms`),
    maps them to ``H_x`` and ``H_r``.

    With ``a_r = A_r / n_r`` the equilibrated rows, ``X̃`` the unit null vector, ``c_r = a_r·X̃``
    and ``v_i``, ``σ_i`` the other right singular vectors and values, the null vector moves
    along ``dA`` by (first-order perturbation of the smallest eigenvector of ``aᵀa``)

        dX̃ = -W g,   W = Σ_{i<4} v_i v_iᵀ / (σ_i² - σ₄²),
        g = Σ_r (c_r/n_r) dA_r + ((d_r - 2 c_r e_r)/n_r) a_r

    (``d_r = dA_r·X̃``, ``e_r = a_r·dA_r``). Along ``P₂'[a, b]``, ``dA_r = L_ra e_b``, so
    ``g = w_a e_b + Σ_r L_ra κ_r[b] a_r`` with ``w = Lᵀ(c/n)``, ``κ_r = (X̃ - 2 c_r a_r)/n_r``. With
    ``d π(y) = [I | -π] dy / y₃`` and ``Q = f ⊙ (∂π₂ P₂' - ∂π₁ P₁')``, ``Z = -Q W``:

        ∂h[s]/∂P₂'[a, b] = w_a Z_sb + Σ_r (Z a_r)_s L_ra κ_r[b] + f_s ∂π₂[s, a] X̃_b,

    one product ``U V`` of ``(2, 3, 4)`` by ``(2, 4, 4)`` per point. Points must be well posed
    (``s_3 > s_4``, in front of both cameras) for the derivatives to be finite: screen
    with :func:`flow_measurements`.
    """
    dim = state_size(x, "flow_linearisation")
    if dim != STATE_DIM:
        lin = flow_linearisation(x[..., :STATE_DIM], flow_px, uv1_px, camera)
        return lin._replace(H_x=pad_state(lin.H_x, dim))
    camera = camera.to(x)
    lin = _linearise(x, cast_like(flow_px, x), cast_like(uv1_px, x), camera)
    H = _chain(lin.dh, lin.J)
    aux = FlowAux(lin.conditioning, lin.depth[..., 0], lin.depth[..., 1], lin.parallax)
    return FlowLinearisation(lin.residual, H[..., :STATE_DIM], H[..., STATE_DIM:], aux)


def state_size(x: Tensor, where: str) -> int:
    """``D`` of the states ``x`` ``(..., D)``: 26, or ``19 + 7 N`` with a window of ``N`` cloned poses
    (a ValueError naming ``where`` otherwise)."""
    window_size(x.shape[-1], where=f"{where}: x of shape {tuple(x.shape)}")
    return x.shape[-1]


def pad_state(H: Tensor, dim: int) -> Tensor:
    """Jacobians ``(..., 26)`` along the 26-dim state -> ``(..., D)`` along a state with a window of
    ``N`` cloned poses, ``D = dim = 19 + 7 N``: zero columns for the clones after clone 0."""
    return torch.nn.functional.pad(H, (0, dim - STATE_DIM))


class FlowMeasurements(NamedTuple):
    """Linearised flow measurements of ``M`` points per sequence (batch dims ``...``)."""

    residual: Tensor  # (..., M, 2) h(m, δ), px (the EKF innovation is -h); 0 where not valid
    H_x: Tensor  # (..., M, 2, D); 0 where not valid
    H_r: Tensor  # (..., M, 2, 2); 0 where not valid
    valid: Tensor  # (..., M) bool: a real point, not degenerate, in front, enough parallax
    n_degenerate: Tensor  # (...) int64: real points whose triangulation is ill-conditioned
    n_behind: Tensor  # (...) int64: well-conditioned, at a camera centre or behind a camera
    n_low_parallax: Tensor  # (...) int64: well-conditioned, in front, below min_parallax_px
    parallax_px: Tensor  # (..., M) the rays' parallax angle times the focal length (0 for padding)


def flow_measurements(
    x: Tensor,
    flow_px: Tensor,
    uv1_px: Tensor,
    camera: FlowCamera,
    *,
    mask: Tensor | None = None,
    min_conditioning: float = 1e-6,
    min_depth: float = 1e-9,
    min_parallax_px: float | Tensor = 0.0,
    jacobians: str = "analytic",
) -> FlowMeasurements:
    """``h``, ``H_x``, ``H_r`` of ``M`` flow points per state ``x`` ``(..., 26)``.

    A state with a window of ``N > 1`` cloned poses ``(..., 19 + 7 N)`` is measured as its
    26-dim part (the core and clone 0), and ``H_x`` ``(..., M, 2, 19 + 7 N)`` has zero columns
    for the further clones.

    Args:
        flow_px ``(..., M, 2)``, uv1_px ``(..., M, 2)``; camera shared or with the batch dims.
        mask: ``(..., M)`` bool, False for padding (arbitrary values: never valid, never
            counted, zero everywhere); None: every point is real.
        min_conditioning: points whose triangulation conditioning
            ``(σ₃ - σ₄) / σ₁`` is below this are degenerate.
        min_depth: points with ``z ≤ min_depth`` in either camera (``X̃`` of unit
            norm: at a camera centre or behind it) are left out as well.
        min_parallax_px: points whose parallax (the angle between the two viewing
            rays, times the focal length) is below this, a scalar or per point
            ``(..., M)``, are left out: when the parallax is comparable to the flow noise
            the triangulated point, and with it ``h``, is strongly nonlinear in ``δ``.
        jacobians: ``"analytic"`` (:func:`flow_linearisation`, all points in one batch
            of closed-form derivatives) or ``"autodiff"`` (the reference: ``vmap`` of
            ``torch.func.jacrev`` of :func:`flow_residual` per point). Both are exact
            and differentiable; they agree to rounding.

    Without a gradient to carry, one closed-form pass over all points serves the screening
    and the valid points. With one (an input requires grad, or ``"autodiff"``), the points
    are screened without it and linearised again with it, every point in place, those not
    valid on a valid point's inputs (:func:`_tracked_in_place`), so that degenerate points and
    padding have no part in the gradient; ``"autodiff"`` gathers the valid ones instead.
    """
    dim = state_size(x, "flow_measurements")
    if dim != STATE_DIM:
        m = flow_measurements(x[..., :STATE_DIM], flow_px, uv1_px, camera, mask=mask, min_conditioning=min_conditioning,
                              min_depth=min_depth, min_parallax_px=min_parallax_px, jacobians=jacobians)
        return m._replace(H_x=pad_state(m.H_x, dim))
    if flow_px.shape[-1:] != (2,) or uv1_px.shape != flow_px.shape or flow_px.shape[:-2] != x.shape[:-1]:
        raise ValueError(f"flow_measurements: flow_px and uv1_px must both be (..., M, 2) with x's batch dims "
                         f"{tuple(x.shape[:-1])}; got {tuple(flow_px.shape)}, {tuple(uv1_px.shape)}")
    if mask is not None and (mask.shape != flow_px.shape[:-1] or mask.dtype != torch.bool):
        raise ValueError(f"flow_measurements: mask must be a bool tensor {tuple(flow_px.shape[:-1])}, "
                         f"got {mask.dtype} {tuple(mask.shape)}")
    if camera.batch_shape and camera.batch_shape != x.shape[:-1]:
        raise ValueError(f"flow_measurements: a batched camera must have x's batch dims {tuple(x.shape[:-1])}, "
                         f"got {tuple(camera.batch_shape)}")
    if jacobians not in ("analytic", "autodiff"):
        raise ValueError(f"flow_measurements: jacobians must be 'analytic' or 'autodiff', got {jacobians!r}")
    camera = camera.to(x)
    flow_px, uv1_px = cast_like(flow_px, x), cast_like(uv1_px, x)
    tracked = torch.is_grad_enabled() and (camera.tracked or any(t.requires_grad for t in (x, flow_px, uv1_px)))
    if jacobians == "analytic" and not tracked:
        lin = _linearise(x, flow_px, uv1_px, camera, mask=mask)
        valid, parallax_px, counts = _screen(lin, camera, mask, min_conditioning, min_depth, min_parallax_px)
        keep = valid.unsqueeze(-1)
        H = _chain(torch.where(keep.unsqueeze(-1), lin.dh, 0.0), lin.J)
        return FlowMeasurements(torch.where(keep, lin.residual, 0.0), H[..., :STATE_DIM], H[..., STATE_DIM:],
                                valid, *counts, parallax_px)
    with torch.no_grad():
        lin = _linearise(x, flow_px, uv1_px, camera, mask=mask, derivatives=False)
        valid, parallax_px, counts = _screen(lin, camera, mask, min_conditioning, min_depth, min_parallax_px)
    if jacobians == "analytic":
        return _tracked_in_place(x, flow_px, uv1_px, camera, valid, parallax_px, counts)
    return _tracked_measurements(x, flow_px, uv1_px, camera, valid, parallax_px, counts, jacobians)


def cast_like(t: Tensor, like: Tensor) -> Tensor:
    """``t`` in ``like``'s dtype and device: ``t`` itself (no operation) when it already is."""
    return t if t.dtype == like.dtype and t.device == like.device else t.to(like)


def _screen(lin: _Linearised, camera: FlowCamera, mask: Tensor | None, min_conditioning: float, min_depth: float,
            min_parallax_px: float | Tensor) -> tuple[Tensor, Tensor, tuple[Tensor, Tensor, Tensor]]:
    """``valid`` ``(..., M)``, the parallax in px ``(..., M)`` and the counts (degenerate, behind, low parallax)."""
    parallax_px = lin.parallax * _per_row(camera.terms.focal_mean, 0, 1)
    # a point exactly at a camera centre projects to 0/0: the rays meet nowhere else
    posed = (lin.conditioning > min_conditioning) & torch.isfinite(lin.residual[..., 0])
    if mask is not None:
        posed = posed & mask
        parallax_px = torch.where(mask, parallax_px, 0.0)
    posed_in_front = posed & (lin.depth.amin(-1) > min_depth)
    valid = posed_in_front & (parallax_px >= min_parallax_px)
    # real -> posed -> in front -> valid: the points each step loses
    n = torch.stack((posed, posed_in_front, valid) if mask is None else (mask, posed, posed_in_front, valid)).sum(-1)
    lost = (n[:-1] - n[1:]).unbind(0)
    return valid, parallax_px, lost if mask is not None else (valid.shape[-1] - n[0], *lost)


def _tracked_in_place(x: Tensor, flow_px: Tensor, uv1_px: Tensor, camera: FlowCamera, valid: Tensor,
                      parallax_px: Tensor, counts: tuple) -> FlowMeasurements:
    """Every point linearised again with its gradient, in place (no gather of the valid ones: the
    shapes are the inputs', and nothing is read back): a point that is not valid is computed on
    the inputs of its row's first valid point, and a row without one on a well-posed stand-in
    (:func:`_stand_in`), their results then replaced by zeros, so that degenerate points and
    padding put nothing into the graph, not even zero times an infinite derivative."""
    M = valid.shape[-1]
    if M == 0:
        return _tracked_measurements(x, flow_px, uv1_px, camera, valid, parallax_px, counts, "analytic")
    has = valid.any(-1)  # (...,)
    first = valid.to(torch.uint8).argmax(-1)[..., None, None].expand(*valid.shape[:-1], 1, 4)
    x_in, uvf_in = _stand_in(camera, x)  # (..., 26), (..., 1, 4)
    uvf = torch.cat((uv1_px, flow_px), -1)  # (..., M, 4)
    keep = valid.unsqueeze(-1)
    uvf = torch.where(keep, uvf, torch.where(has[..., None, None], uvf.gather(-2, first), uvf_in))
    lin = _linearise(torch.where(has.unsqueeze(-1), x, x_in), uvf[..., 2:], uvf[..., :2], camera)
    # zeroed after the chain rule: the state's gradient takes nothing from these rows (a NaN that
    # reaches them from further on, e.g. a padded point's σ, is not multiplied into it)
    H = torch.where(keep.unsqueeze(-1), _chain(lin.dh, lin.J), 0.0)
    parallax = torch.where(valid, lin.parallax * _per_row(camera.terms.focal_mean, 0, 1), parallax_px)
    return FlowMeasurements(torch.where(keep, lin.residual, 0.0), H[..., :STATE_DIM], H[..., STATE_DIM:], valid,
                            *counts, parallax)


def _stand_in(camera: FlowCamera, like: Tensor) -> tuple[Tensor, Tensor]:
    """A state ``(..., 26)`` (``like``'s batch dims, no gradient) and one flow point's first pixel
    and flow ``(..., 1, 4)`` that triangulate well for ``camera``: the body unrotated, the camera
    moved 1 m along its own x axis between the frames, the point 6.3 m ahead of the first camera
    and off its axis (a 9° ray angle). Kept on the camera unless it carries a gradient."""
    # traced (torch.compile) it is made afresh: older dynamo cannot trace the camera's __dict__
    compiling = torch.compiler.is_compiling()
    kept = {} if compiling else camera.__dict__.setdefault("_stand_ins", {})
    made = kept.get((like.dtype, like.device))
    if made is None:
        # plain tensors (outside a caller's inference mode), usable by later runs with gradients too
        plain = contextlib.nullcontext() if compiling else torch.inference_mode(False)
        with plain, torch.no_grad():
            K, R_ci = camera.K.detach().to(like), camera.R_ci.detach().to(like)
            ahead = 6.3
            uv1 = _to_pixels(like.new_tensor([0.31, -0.17]), K)
            uv2 = _to_pixels(like.new_tensor([0.31 - 1.0 / ahead, -0.17]), K)  # the centre 1 m along the camera's x
            p = R_ci[..., 0, :]  # the camera's x axis in the world
            zero = torch.zeros_like(p)
            q = quat.identity(dtype=like.dtype, device=like.device).expand(*p.shape[:-1], 4)
            made = (make_state(p=p, v=zero, q=q, p_prev=zero), torch.cat((uv1, uv2 - uv1), -1).unsqueeze(-2))
        if not camera.tracked and not compiling:
            kept[like.dtype, like.device] = made
    x, uvf = made
    batch = like.shape[:-1]
    return x.expand(*batch, x.shape[-1]), uvf.expand(*batch, 1, 4)


def _tracked_measurements(x: Tensor, flow_px: Tensor, uv1_px: Tensor, camera: FlowCamera, valid: Tensor,
                          parallax_px: Tensor, counts: tuple, jacobians: str) -> FlowMeasurements:
    """The valid points alone, gathered over the batch, linearised with their gradient and put back
    (the ``"autodiff"`` reference; it reads the count back)."""
    batch, M = valid.shape[:-1], valid.shape[-1]
    flat_rows = math.prod(batch)
    rows, points = valid.reshape(flat_rows, M).nonzero(as_tuple=True)
    x_v = x.reshape(flat_rows, STATE_DIM)[rows]
    flow_v = flow_px.reshape(flat_rows, M, 2)[rows, points]
    uv_v = uv1_px.reshape(flat_rows, M, 2)[rows, points]
    camera_v = camera.take(rows, batch)
    N = rows.shape[0]
    if N == 0:
        return FlowMeasurements(x.new_zeros(*batch, M, 2), x.new_zeros(*batch, M, 2, STATE_DIM),
                                x.new_zeros(*batch, M, 2, 2), valid, *counts, parallax_px)
    if jacobians == "analytic":
        lin = _linearise(x_v, flow_v.unsqueeze(-2), uv_v.unsqueeze(-2), camera_v)
        H = (lin.dh @ lin.J.unsqueeze(-3)).squeeze(-3)  # (N, 2, 28)
        h_v, Hx_v, Hr_v = lin.residual.squeeze(-2), H[..., :STATE_DIM], H[..., STATE_DIM:]
        parallax_v = lin.parallax.squeeze(-1) * camera_v.terms.focal_mean
    else:
        shared = not camera_v.batch_shape

        def residual(x_, flow_, uv_, K_, R_, t_):
            return flow_residual(x_, flow_, uv_, FlowCamera(K_, R_, t_))[0]

        dims = (0, 0, 0) + ((None,) * 3 if shared else (0, 0, 0))
        Hx_v, Hr_v = vmap(jacrev(residual, argnums=(0, 1)), in_dims=dims)(
            x_v, flow_v, uv_v, camera_v.K, camera_v.R_ci, camera_v.t_ci)
        h_v, aux = flow_residual(x_v, flow_v, uv_v, camera_v)
        parallax_v = aux.parallax * camera_v.terms.focal_mean
    index = (rows, points)

    def scatter(values: Tensor, *event: int) -> Tensor:
        return x.new_zeros(flat_rows, M, *event).index_put(index, values).reshape(*batch, M, *event)

    parallax = parallax_px.reshape(flat_rows, M).index_put(index, parallax_v).reshape(*batch, M)
    return FlowMeasurements(scatter(h_v, 2), scatter(Hx_v, 2, STATE_DIM), scatter(Hr_v, 2, 2), valid, *counts, parallax)


def dominant_direction(H_r: Tensor) -> Tensor:
    """The dominant left singular vector ``(..., 2)`` of ``2 x 2`` matrices, in closed form.

    The principal eigenvector of ``H_r H_rᵀ = [[a, b], [b, c]]`` is at the angle
    ``θ = ½ atan2(2b, a - c)`` (its sign, as any singular vector's, is arbitrary):
    ``(cos θ, cos(θ - π/2))``.
    """
    HHt = H_r @ H_r.transpose(-1, -2)
    combine, offsets, _ = _direction_constants(H_r.dtype, H_r.device)
    two = HHt.view(*HHt.shape[:-2], 4) @ combine  # (2b, a - c)
    return torch.cos(torch.add(offsets, torch.atan2(two[..., 0], two[..., 1]).unsqueeze(-1), alpha=0.5))


@cached_constant
def _direction_constants(dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    """``(4, 2)``: flattened ``[[a, b], [b, c]]`` -> ``(2b, a - c)``; the offsets ``(0, -π/2)``;
    ``[[1, 0], [0, 0]]``."""
    combine = torch.tensor([[0.0, 1.0], [1.0, 0.0], [1.0, 0.0], [0.0, -1.0]], dtype=dtype, device=device)
    offsets = torch.tensor([0.0, -0.5 * torch.pi], dtype=dtype, device=device)
    first = torch.tensor([[1.0, 0.0], [0.0, 0.0]], dtype=dtype, device=device)
    return combine, offsets, first


class EpipolarUpdate(NamedTuple):
    """The flow measurements reduced to their informative (epipolar) component, all ``M`` points
    in order; those not valid contribute nothing (innovation 0, H 0, noise 1)."""

    innovation: Tensor  # (..., M, 1) -wᵀh
    H: Tensor  # (..., M, 1, D) wᵀ H_x
    noise_cov: Tensor  # (..., M, 1, 1) wᵀ H_r R H_rᵀ w
    direction: Tensor  # (..., M, 2) w, unit
    valid: Tensor  # (..., M) the measurements' valid flags


def epipolar_update(measurements: FlowMeasurements, sigma_px: Tensor, *,
                    parallax_inflation: bool = False) -> EpipolarUpdate:
    """Scalar EKF measurements ``0 = wᵀ h(x, δ + r)`` of every point.

    ``H_r = ∂h/∂δ`` has rank one: moving ``δ`` along the epipolar line keeps the two
    rays consistent, so ``h`` does not change. The paper's two-dimensional update with
    noise ``H_r R H_rᵀ`` therefore has a (numerically) singular noise covariance in
    the direction orthogonal to ``w``, the dominant left singular vector of ``H_r``,
    and the filter would trust that component's curvature-driven residual
    completely (a test shows the literal 2-D update diverging on a simulated frame).
    Projecting on ``w`` keeps all the information the flow carries about the state.

    Args:
        measurements: from :func:`flow_measurements` (``h``, ``H_x``, ``H_r`` zero where not valid).
        sigma_px: ``(..., M, 2)`` 1-σ of ``(Δu, Δv)``; ``R = diag(σ²)``.
        parallax_inflation: multiply the noise by ``p² / (p² - mean σ²)`` (``p`` the parallax in px;
            the denominator at least ``10⁻⁶ p² + 10⁻³⁰``).
    Returns: all ``M`` points in order; points not valid get innovation 0, ``H`` 0 and noise 1,
        so that a stacked update adds exactly nothing for them (their NIS is 0).
    """
    m = measurements
    valid = m.valid
    H_r = m.H_r
    sigma = cast_like(sigma_px, H_r)
    _, _, first = _direction_constants(H_r.dtype, H_r.device)
    # the invalid points' H_r = 0 would make the direction's angle atan2(0, 0): no gradient there
    w = dominant_direction(torch.where(valid[..., None, None], H_r, first))  # (..., M, 2)
    spread = (w.unsqueeze(-2) @ H_r).squeeze(-2) * sigma  # (H_rᵀ w) σ
    noise = torch.linalg.vecdot(spread, spread)
    if parallax_inflation:
        p2 = torch.where(valid, m.parallax_px, 1.0).square()
        floor = torch.add(_tiny_floor(p2.dtype, p2.device), p2, alpha=1e-6)
        noise = noise * p2 / torch.sub(p2, torch.linalg.vecdot(sigma, sigma), alpha=0.5).clamp_min(floor)
    noise = torch.where(valid, noise, 1.0)
    innovation = -torch.linalg.vecdot(w, m.residual)
    H = w.unsqueeze(-2) @ m.H_x  # (..., M, 1, D)
    return EpipolarUpdate(innovation.unsqueeze(-1), H, noise[..., None, None], w, valid)


@cached_constant
def _tiny_floor(dtype: torch.dtype, device: torch.device) -> Tensor:
    return torch.tensor(1e-30, dtype=dtype, device=device)
