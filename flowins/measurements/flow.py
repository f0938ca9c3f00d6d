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
(2 x 2), for all points at once, come in closed form (:func:`flow_linearisation`, the
default) or from ``torch.func.jacrev`` through the triangulation under ``vmap`` (the reference,
``jacobians="autodiff"``); both are differentiable, as training needs.

Conditioning: the world origin is moved to camera 1's centre and the triangulation
works in normalised coordinates ``K⁻¹ (u, v, 1)``; the projections are converted back
to pixels, so ``h`` is exactly the paper's.

Degenerate geometry never produces NaN or inf. A point is *degenerate* when the
triangulation's two smallest singular values meet (no baseline, or flow that only a
rotation explains: every point on the ray fits) or the solution sits at a camera
centre or behind either camera. Such points are left out of the Jacobian
computation altogether, get ``h = 0``, ``H = 0`` and ``valid = False``, and are
counted in :class:`FlowMeasurements`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor
from torch.func import jacrev, vmap

from flowins.constants import cached_constant
from flowins.geometry import quaternion as quat
from flowins.geometry.triangulation import (
    camera_matrix,
    dlt_matrix,
    project_homogeneous,
    solve_dlt,
    triangulate,
)
from flowins.state import STATE, STATE_DIM, split


@dataclass(frozen=True)
class FlowCamera:
    """Intrinsics ``K`` ``(3, 3)`` and the IMU→camera transform (``x_c = R_ci x_i + t_ci``)."""

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
    def centre_b(self) -> Tensor:
        """The camera centre in the body (IMU) frame ``(3,)``: ``-R_ciᵀ t_ci`` (kept after the
        first use unless the transform carries a gradient)."""
        if self.R_ci.requires_grad or self.t_ci.requires_grad:
            return self._centre_b()
        cached = self.__dict__.get("_centre_b_cache")
        if cached is None:
            with torch.inference_mode(False):  # a plain tensor, usable by later runs with gradients
                cached = self._centre_b()
            object.__setattr__(self, "_centre_b_cache", cached)
        return cached

    def _centre_b(self) -> Tensor:
        return -(self.R_ci.transpose(-1, -2) @ self.t_ci.unsqueeze(-1)).squeeze(-1)

    def to(self, like: Tensor) -> FlowCamera:
        """This camera in ``like``'s dtype and device (itself when it already is)."""
        if all(t.dtype == like.dtype and t.device == like.device for t in (self.K, self.R_ci, self.t_ci)):
            return self
        return FlowCamera(self.K.to(like), self.R_ci.to(like), self.t_ci.to(like))


class FlowAux(NamedTuple):
    conditioning: Tensor  # (σ₃ - σ₄) / σ₁ of the triangulation
    depth1: Tensor  # z of X̃ in camera 1 (homogeneous, X̃ of unit norm)
    depth2: Tensor  # z of X̃ in camera 2
    parallax: Tensor  # angle (rad) between the two viewing rays in the world frame


def camera_pose(q: Tensor, p: Tensor, camera: FlowCamera) -> tuple[Tensor, Tensor]:
    """``(R_wc, c_w)``: camera orientation (camera→world) and centre from the IMU pose ``(q, p)``."""
    R_wb = quat.to_matrix(q)
    R_wc = R_wb @ camera.R_ci.transpose(-1, -2)
    return R_wc, p + (R_wb @ camera.centre_b.unsqueeze(-1)).squeeze(-1)


def ray_angle(ray1: Tensor, ray2: Tensor) -> Tensor:
    """Angle (rad) between two rays ``(..., 3)`` (not necessarily unit), stable near 0 and π."""
    return torch.atan2(torch.linalg.vector_norm(torch.linalg.cross(ray1, ray2), dim=-1), (ray1 * ray2).sum(-1))


def normalise_pixels(uv: Tensor, K: Tensor) -> Tensor:
    """Pixels ``(..., 2)`` -> normalised image coordinates ``K⁻¹ (u, v, 1)`` without the 1."""
    return (uv - K[:2, 2]) / torch.diagonal(K)[:2]


def _to_pixels(xy: Tensor, K: Tensor) -> Tensor:
    return xy * torch.diagonal(K)[:2] + K[:2, 2]


def flow_residual(x: Tensor, flow_px: Tensor, uv1_px: Tensor, camera: FlowCamera) -> tuple[Tensor, FlowAux]:
    """``h(x, δ)`` ``(2,)`` for one point, and the triangulation's diagnostics.

    Args:
        x ``(26,)`` state; flow_px ``δ`` ``(2,)``; uv1_px ``(2,)`` pixel in the previous frame.
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


#: the state entries the flow model depends on (the two camera poses), in this order
POSE_FIELDS = ("p", "q", "p_prev", "q_prev")


def _relative_pose_and_derivatives(x: Tensor, camera: FlowCamera) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Camera 2 in camera 1's frame, ``P₂' = [R | t]`` ``(3, 4)`` with ``R = R₂ᵀ R₁`` and
    ``t = -R₂ᵀ d``, its derivatives ``J`` ``(6, 14)`` along the state entries of
    :data:`POSE_FIELDS` in the tangent coordinates ``(ω, t)`` of ``dR = R [ω]×`` and
    ``dt``, and the camera rotations ``R₁, R₂`` (camera→world).

    ``R_k = R(q_k) R_ciᵀ``, ``d = c₂ - c₁``, ``c_k = p_k + R(q_k) c_b`` (``c_b`` the camera
    centre in the body). :func:`~flowins.geometry.quaternion.to_matrix` normalises, so
    each ``∂R/∂x_j`` is tangent to the rotations and ``Rᵀ ∂R/∂x_j`` is skew.
    """
    s = split(x)
    # the values exactly as flow_residual forms them
    (R1, R2), (c1, c2) = camera_pose(torch.stack((s.q_prev, s.q)), torch.stack((s.p_prev, s.p)), camera)
    d = c2 - c1  # 0 when standing still
    R2t = R2.transpose(-1, -2)
    R = R2t @ R1
    t = -(R2t @ d)
    P2 = torch.cat((R, t.unsqueeze(-1)), -1)
    # ∂R_k/∂q_k = ∂R(q_k)/∂q_k R_ciᵀ, ∂c_k/∂q_k = ∂R(q_k)/∂q_k c_b; tangent order p, q, p_prev, q_prev
    R_ic = camera.R_ci.transpose(-1, -2)
    c_b = camera.centre_b
    dRb = quat.to_matrix_jacobian(torch.stack((s.q_prev, s.q)))  # (2, 4, 3, 3)
    dR = dRb @ R_ic
    dR1, dR2t = dR[0], dR[1].transpose(-1, -2)  # ∂R₁/∂q⁻, ∂R₂ᵀ/∂q
    # dR = ∂R₂ᵀ R₁ + R₂ᵀ ∂R₁ -> ω = vee(Rᵀ dR), Rᵀ ∂R₂ᵀ R₁ = R₁ᵀ R₂ ∂R₂ᵀ R₁, Rᵀ R₂ᵀ ∂R₁ = R₁ᵀ ∂R₁
    R1t = R1.transpose(-1, -2)
    vee = _vee(torch.stack((R1t @ R2 @ dR2t @ R1, R1t @ dR1)))  # (2, 4, 3): along q, along q_prev
    omega = x.new_zeros(14, 3)
    omega[3:7] = vee[0]
    omega[10:14] = vee[1]
    # dt = -(∂R₂ᵀ d + R₂ᵀ ∂d), ∂d/∂(p, q, p⁻, q⁻) = (I, ∂R(q) c_b, -I, -∂R(q⁻) c_b)
    eye = torch.eye(3, dtype=x.dtype, device=x.device)
    dRc = dRb @ c_b  # (2, 4, 3)
    dd = torch.cat((eye, dRc[1], -eye, -dRc[0]))  # (14, 3)
    dt = -(dd @ R2)  # rows: R₂ᵀ ∂d
    dt[3:7] -= dR2t @ d
    J = torch.cat((omega, dt), -1).T  # (6, 14)
    return P2, J, R, R1, R2


def _relative_camera_derivative(R: Tensor) -> Tensor:
    """``∂P₂'/∂(ω, t)`` ``(6, 3, 4)`` of ``P₂' = [R | t]`` along ``dR = R [ω]×``, ``dt``:
    ``[R [e_i]× | 0]`` and ``[0 | e_i]``."""
    generators, zero_column, translation = _camera_derivative_constants(R.dtype, R.device)
    return torch.cat((torch.cat((R @ generators, zero_column), -1), translation))


@cached_constant
def _camera_derivative_constants(dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    """``[e_i]×`` ``(3, 3, 3)``, a zero column ``(3, 3, 1)`` and ``[0 | e_i]`` ``(3, 3, 4)``."""
    eye = torch.eye(3, dtype=dtype, device=device)
    translation = torch.zeros(3, 3, 4, dtype=dtype, device=device)
    translation[:, :, 3] = eye
    return quat.skew(eye), torch.zeros(3, 3, 1, dtype=dtype, device=device), translation


def _vee(S: Tensor) -> Tensor:
    """``ω`` ``(..., 3)`` of the skew part of ``S`` ``(..., 3, 3)`` (``S = [ω]×`` for skew ``S``):
    ``½ (S₂₁ - S₁₂, S₀₂ - S₂₀, S₁₀ - S₀₁)``, gathered from the flattened matrix."""
    flat = S.flatten(-2)
    plus, minus = _VEE_INDEX
    return 0.5 * (flat[..., plus] - flat[..., minus])


#: flat positions of (S₂₁, S₀₂, S₁₀) and (S₁₂, S₂₀, S₀₁) in a row-major 3 x 3 matrix
_VEE_INDEX = (torch.tensor([7, 2, 3]), torch.tensor([5, 6, 1]))


class FlowLinearisation(NamedTuple):
    residual: Tensor  # (M, 2) h
    H_x: Tensor  # (M, 2, 26)
    H_r: Tensor  # (M, 2, 2)
    aux: FlowAux


def flow_linearisation(x: Tensor, flow_px: Tensor, uv1_px: Tensor, camera: FlowCamera) -> FlowLinearisation:
    """``h`` and its Jacobians ``H_x``, ``H_r`` for ``M`` points at once, in closed form.

    The same function as :func:`flow_residual`, differentiated by hand (no
    ``torch.func``), batched over the points ``(M, 2)``. It is computed in camera 1's
    frame, ``P₁' = [I | 0]``, ``P₂' = [R | t]`` (:func:`_relative_pose_and_derivatives`):
    the DLT matrix there is the world one times an orthogonal matrix, so its
    equilibrated singular values, the projections and ``h`` are the same, and only
    the last two rows of the DLT matrix depend on the pose and the flow. With ``A``
    the row-equilibrated DLT matrix of a point, ``A = U S Vᵀ`` and ``X̃ = v₄``, a
    perturbation ``dA`` moves the null vector by

        dX̃ = -Σ_{i<4} v_i v_iᵀ (dAᵀ A + Aᵀ dA) X̃ / (s_i² - s_4²)

    (first-order perturbation of the smallest eigenvector of ``AᵀA``), and
    ``d π(P X̃) = (dy_{1:2} - π dy_3) / y_3`` with ``y = P X̃``, ``dy = dP X̃ + P dX̃``.
    The ``6 + 2`` tangent directions (the relative pose ``(ω, t)``, then ``δ``) are
    carried at once and the pose part is mapped to the state by ``J`` ``(6, 14)``;
    ``H_x`` is zero outside :data:`POSE_FIELDS`.
    Points must be well posed (``s_3 > s_4``, in front of both cameras): screen with
    :func:`flow_measurements`, which calls this on the valid points only.
    """
    K = camera.K
    M = flow_px.shape[0]
    P2, J, R, R1, R2 = _relative_pose_and_derivatives(x, camera)
    P1 = torch.eye(3, 4, dtype=x.dtype, device=x.device)
    x1 = normalise_pixels(uv1_px, K)
    x2 = normalise_pixels(uv1_px + flow_px, K)
    A = dlt_matrix(P1, P2, x1, x2)  # (M, 4, 4)
    # the triangulation exactly as triangulate() solves it
    X, conditioning, S, Vh, As, norm = solve_dlt(A, P1)
    # ∂P₂'/∂(ω, t) (6, 3, 4): [R [e_i]× | 0] and [0 | e_i]
    dP2 = _relative_camera_derivative(R)
    dP2X = (X @ dP2.reshape(-1, 4).T).reshape(M, 6, 3)
    # Only rows 3, 4 of dA move ([I | 0] does not): along a pose tangent t, row r is
    # x₂ᵣ dP₂'[t, 2] - dP₂'[t, r]; along the flow Δu (Δv) only row 3 (4), by P₂'[2] / f.
    # With the equilibrated rows aᵣ = Aᵣ / nᵣ, eᵣ = aᵣ·dAᵣ, dᵣ = dAᵣ·X̃ and cᵣ = aᵣ·X̃,
    # d(aᵣ) = (dAᵣ - aᵣ eᵣ) / nᵣ and the null-vector right-hand side is
    #     g = Σᵣ (cᵣ / nᵣ) dAᵣ + Σᵣ ((dᵣ - 2 cᵣ eᵣ) / nᵣ) aᵣ,
    # formed from per-point scalars without building dA (M, 8, 2, 4).
    a, n = As[:, 2:], norm[:, 2:]  # (M, 2, 4), (M, 2)
    c = (a * X.unsqueeze(1)).sum(-1)  # (M, 2)
    coef = c / n
    e_all = (a @ dP2.permute(2, 0, 1).reshape(4, 18)).reshape(M, 2, 6, 3)  # aᵣ·dP₂'[t, j]
    e_pose = x2.unsqueeze(-1) * e_all[..., 2] - torch.stack((e_all[:, 0, :, 0], e_all[:, 1, :, 1]), 1)  # (M, 2, 6)
    d_pose = x2.unsqueeze(-1) * dP2X[..., 2].unsqueeze(1) - dP2X[..., :2].transpose(1, 2)  # (M, 2, 6)
    w = torch.cat((-coef, (coef * x2).sum(-1, keepdim=True)), -1)  # Σᵣ cᵣ/nᵣ dAᵣ = Σⱼ wⱼ dP₂'[t, j]
    g_pose = (w @ dP2.transpose(0, 1).reshape(3, 24)).reshape(M, 6, 4) + (
        (d_pose - 2.0 * c.unsqueeze(-1) * e_pose) / n.unsqueeze(-1)
    ).transpose(1, 2) @ a
    f = torch.stack((K[0, 0], K[1, 1]))
    row3 = P2[2] / f.unsqueeze(-1)  # (2, 4): ∂A_r/∂δ_r
    e_flow = a @ P2[2] / f  # (M, 2)
    d_flow = (X @ P2[2]).unsqueeze(-1) / f  # (M, 2)
    g_flow = coef.unsqueeze(-1) * row3 + ((d_flow - 2.0 * c * e_flow) / n).unsqueeze(-1) * a
    g = torch.cat((g_pose, g_flow), 1)  # (M, 8, 4)
    gap = (S[:, :3] ** 2 - S[:, 3:] ** 2).clamp_min(torch.finfo(A.dtype).tiny)  # (M, 3)
    V3 = Vh[:, :3]  # (M, 3, 4) rows v_i
    dX = -((g @ V3.transpose(-1, -2)) / gap.unsqueeze(1)) @ V3  # (M, T, 4)
    # camera 1: y = X̃₁:₃
    pi1 = X[:, :2] / X[:, 2:3]
    dpi1 = (dX[..., :2] - pi1.unsqueeze(1) * dX[..., 2:3]) / X[:, None, 2:3]
    # camera 2: y = P₂' X̃
    y2 = X @ P2.T  # (M, 3)
    dy2 = dX @ P2.T + torch.cat((dP2X, X.new_zeros(M, 2, 3)), 1)
    pi2 = y2[:, :2] / y2[:, 2:]
    dpi2 = (dy2[..., :2] - pi2.unsqueeze(1) * dy2[..., 2:]) / y2[:, None, 2:]
    h = f * (pi2 - pi1) - flow_px
    dh = (f * (dpi2 - dpi1)).transpose(-1, -2)  # (M, 2, 8)
    H_x = x.new_zeros(M, 2, STATE_DIM).index_copy(-1, _pose_index(x.device), dh[..., :6] @ J)
    H_r = dh[..., 6:] - torch.eye(2, dtype=x.dtype, device=x.device)
    aux = FlowAux(conditioning, X[:, 2], y2[:, 2], _parallax(R1, R2, x1, x2))
    return FlowLinearisation(h, H_x, H_r, aux)


@cached_constant
def _pose_index(device: torch.device) -> Tensor:
    return STATE.indices(*POSE_FIELDS).to(device)


class FlowMeasurements(NamedTuple):
    """Linearised flow measurements of one frame pair (``M`` points)."""

    residual: Tensor  # (M, 2) h(m, δ), px (the EKF innovation is -h)
    H_x: Tensor  # (M, 2, 26)
    H_r: Tensor  # (M, 2, 2)
    valid: Tensor  # (M,) bool: not degenerate, in front, enough parallax
    n_degenerate: int
    n_behind: int
    n_low_parallax: int = 0
    parallax_px: Tensor | None = None  # (M,) the rays' parallax angle times the focal length


def flow_measurements(
    x: Tensor,
    flow_px: Tensor,
    uv1_px: Tensor,
    camera: FlowCamera,
    *,
    min_conditioning: float = 1e-6,
    min_depth: float = 1e-9,
    min_parallax_px: float | Tensor = 0.0,
    jacobians: str = "analytic",
) -> FlowMeasurements:
    """``h``, ``H_x``, ``H_r`` of ``M`` flow points at the state ``x`` ``(26,)``.

    Args:
        flow_px ``(M, 2)``, uv1_px ``(M, 2)``.
        min_conditioning: points whose triangulation conditioning
            ``(σ₃ - σ₄) / σ₁`` is below this are degenerate.
        min_depth: points with ``z ≤ min_depth`` in either camera (``X̃`` of unit
            norm: at a camera centre or behind it) are left out as well.
        min_parallax_px: points whose parallax (the angle between the two viewing
            rays, times the focal length) is below this, a scalar or per point
            ``(M,)``, are left out: when the parallax is comparable to the flow noise
            the triangulated point, and with it ``h``, is strongly nonlinear in ``δ``.
        jacobians: ``"analytic"`` (:func:`flow_linearisation`, all points in one batch
            of closed-form derivatives) or ``"autodiff"`` (the reference: ``vmap`` of
            ``torch.func.jacrev`` of :func:`flow_residual` per point). Both are exact
            and differentiable; they agree to rounding.
    """
    if x.shape != (STATE_DIM,):
        raise ValueError(f"flow_measurements: x must be ({STATE_DIM},), got {tuple(x.shape)}")
    if flow_px.ndim != 2 or flow_px.shape[-1] != 2 or uv1_px.shape != flow_px.shape:
        raise ValueError(
            f"flow_measurements: flow_px and uv1_px must both be (M, 2); got {tuple(flow_px.shape)}, {tuple(uv1_px.shape)}"
        )
    if jacobians not in ("analytic", "autodiff"):
        raise ValueError(f"flow_measurements: jacobians must be 'analytic' or 'autodiff', got {jacobians!r}")
    camera = camera.to(x)
    flow_px, uv1_px = flow_px.to(x), uv1_px.to(x)
    M = flow_px.shape[0]
    focal = 0.5 * (camera.K[0, 0] + camera.K[1, 1])
    # without a gradient to carry, one analytic pass over all points serves both the
    # screening and the valid points (its divisions are guarded; invalid rows are zeroed)
    tracked = torch.is_grad_enabled() and any(t.requires_grad for t in (x, flow_px, uv1_px, camera.K, camera.R_ci, camera.t_ci))
    single_pass = jacobians == "analytic" and not tracked and M > 0

    with torch.no_grad():
        if single_pass:
            lin = flow_linearisation(x, flow_px, uv1_px, camera)
            h0, aux = lin.residual, lin.aux
        else:
            h0, aux = flow_residual(x.detach(), flow_px.detach(), uv1_px.detach(), camera)
        posed = torch.isfinite(h0).all(-1) & (aux.conditioning > min_conditioning)
        in_front = (aux.depth1 > min_depth) & (aux.depth2 > min_depth)
        parallax_px = focal * aux.parallax
        enough = parallax_px >= torch.as_tensor(min_parallax_px, dtype=x.dtype, device=x.device)
        posed_in_front = posed & in_front
        valid = posed_in_front & enough
        counts = torch.stack((posed & ~in_front, posed_in_front & ~enough, ~valid)).sum(-1)
    n_behind, n_low, n_invalid = counts.tolist()
    n_degenerate = n_invalid - n_behind - n_low
    if single_pass:
        keep = valid.unsqueeze(-1)
        return FlowMeasurements(
            torch.where(keep, lin.residual, 0.0),
            torch.where(keep.unsqueeze(-1), lin.H_x, 0.0),
            torch.where(keep.unsqueeze(-1), lin.H_r, 0.0),
            valid, n_degenerate, n_behind, n_low, parallax_px,
        )
    residual_out = flow_px.new_zeros(M, 2)
    H_x = flow_px.new_zeros(M, 2, STATE_DIM)
    H_r = flow_px.new_zeros(M, 2, 2)
    index = torch.nonzero(valid).squeeze(-1)
    if index.numel():
        if jacobians == "analytic":
            h_v, Hx_v, Hr_v, aux_v = flow_linearisation(x, flow_px[index], uv1_px[index], camera)
        else:
            def residual(x_, flow_, uv_):
                return flow_residual(x_, flow_, uv_, camera)[0]

            Hx_v, Hr_v = vmap(jacrev(residual, argnums=(0, 1)), in_dims=(None, 0, 0))(x, flow_px[index], uv1_px[index])
            h_v, aux_v = flow_residual(x, flow_px[index], uv1_px[index], camera)
        residual_out = residual_out.index_copy(0, index, h_v)
        # the parallax of the valid points again, now with its gradient (the noise inflation uses it)
        parallax_px = parallax_px.index_copy(0, index, focal * aux_v.parallax)
        H_x = H_x.index_copy(0, index, Hx_v)
        H_r = H_r.index_copy(0, index, Hr_v)
    return FlowMeasurements(residual_out, H_x, H_r, valid, n_degenerate, n_behind, n_low, parallax_px)


def dominant_direction(H_r: Tensor) -> Tensor:
    """The dominant left singular vector ``(..., 2)`` of ``2 x 2`` matrices, in closed form.

    The principal eigenvector of ``H_r H_rᵀ = [[a, b], [b, c]]`` is at the angle
    ``½ atan2(2b, a - c)`` (its sign, as any singular vector's, is arbitrary).
    """
    HHt = H_r @ H_r.transpose(-1, -2)
    angle = 0.5 * torch.atan2(2.0 * HHt[..., 0, 1], HHt[..., 0, 0] - HHt[..., 1, 1])
    return torch.stack((torch.cos(angle), torch.sin(angle)), dim=-1)


class EpipolarUpdate(NamedTuple):
    """The flow measurements reduced to their informative (epipolar) component."""

    innovation: Tensor  # (M, 1) -wᵀh
    H: Tensor  # (M, 1, 26) wᵀ H_x
    noise_cov: Tensor  # (M, 1, 1) wᵀ H_r R H_rᵀ w
    direction: Tensor  # (M, 2) w, unit


def epipolar_update(measurements: FlowMeasurements, sigma_px: Tensor, *, parallax_inflation: bool = False) -> EpipolarUpdate:
    """Scalar EKF measurements ``0 = wᵀ h(x, δ + r)`` of the valid points.

    ``H_r = ∂h/∂δ`` has rank one: moving ``δ`` along the epipolar line keeps the two
    rays consistent, so ``h`` does not change. The paper's two-dimensional update with
    noise ``H_r R H_rᵀ`` therefore has a (numerically) singular noise covariance in
    the direction orthogonal to ``w``, the dominant left singular vector of ``H_r``,
    and the filter would trust that component's curvature-driven residual
    completely (a test shows the literal 2-D update diverging on a simulated frame).
    Projecting on ``w`` keeps all the information the flow carries about the state.

    Args:
        sigma_px: ``(M, 2)`` 1-σ of ``(Δu, Δv)``; ``R = diag(σ²)``.
    Returns: the valid points only (``measurements.valid``), in order.
    """
    index = torch.nonzero(measurements.valid).squeeze(-1)
    H_r = measurements.H_r[index]
    w = dominant_direction(H_r)  # (m, 2)
    R = torch.diag_embed(sigma_px[index].to(H_r) ** 2)
    noise = (w.unsqueeze(-2) @ H_r @ R @ H_r.transpose(-1, -2) @ w.unsqueeze(-1))  # (m, 1, 1)
    if parallax_inflation:
        p2 = measurements.parallax_px[index].to(H_r) ** 2
        s2 = (sigma_px[index].to(H_r) ** 2).mean(-1)
        factor = p2 / (p2 - s2).clamp_min(1e-6 * p2 + 1e-30)
        noise = noise * factor.clamp_max(1e8).view(-1, 1, 1)
    innovation = -(w * measurements.residual[index]).sum(-1, keepdim=True)
    H = (w.unsqueeze(-2) @ measurements.H_x[index])  # (m, 1, 26)
    return EpipolarUpdate(innovation, H, noise, w)

