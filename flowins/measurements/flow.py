"""The optical-flow measurement model of the paper (Sec. "Information Fusion").

For a flow point ``δ = (Δu, Δv)`` at pixel ``(u₁, v₁)`` of the previous frame, the
cameras ``P₁ = K [R₁ᵀ | -R₁ᵀ c₁]`` (from the augmented pose ``p⁻, q⁻``) and
``P₂ = K [R₂ᵀ | -R₂ᵀ c₂]`` (from the current pose ``p, q``), both including the
IMU→camera transform, triangulate ``X̃`` from ``(u₁, v₁)`` and ``(u₁ + Δu, v₁ + Δv)``
(:func:`flowins.geometry.triangulation.triangulate`, the paper's linear system by SVD)
and

    h(x, δ) = π(P₂ X̃) - π(P₁ X̃) - δ          (pixels, ``0 = h(x, δ + r)``)

``h`` is the reprojection inconsistency of the two rays: zero when the flow agrees
with the relative pose. Its Jacobians ``H_x = ∂h/∂x`` (2 x 26) and ``H_r = ∂h/∂δ``
(2 x 2) come from ``torch.func.jacrev`` through the SVD, for all points at once
(``vmap``).

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

from flowins.geometry import quaternion as quat
from flowins.geometry.triangulation import (
    camera_matrix,
    project_homogeneous,
    triangulate,
)
from flowins.state import STATE_DIM, split


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

    def to(self, like: Tensor) -> FlowCamera:
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
    c_b = -(camera.R_ci.transpose(-1, -2) @ camera.t_ci.unsqueeze(-1)).squeeze(-1)
    return R_wc, p + (R_wb @ c_b.unsqueeze(-1)).squeeze(-1)


def ray_angle(ray1: Tensor, ray2: Tensor) -> Tensor:
    """Angle (rad) between two rays ``(..., 3)`` (not necessarily unit), stable near 0 and π."""
    return torch.atan2(torch.linalg.cross(ray1, ray2).norm(dim=-1), (ray1 * ray2).sum(-1))


def normalise_pixels(uv: Tensor, K: Tensor) -> Tensor:
    """Pixels ``(..., 2)`` -> normalised image coordinates ``K⁻¹ (u, v, 1)`` without the 1."""
    return torch.stack(((uv[..., 0] - K[0, 2]) / K[0, 0], (uv[..., 1] - K[1, 2]) / K[1, 1]), dim=-1)


def _to_pixels(xy: Tensor, K: Tensor) -> Tensor:
    return torch.stack((K[0, 0] * xy[..., 0] + K[0, 2], K[1, 1] * xy[..., 1] + K[1, 2]), dim=-1)


def flow_residual(x: Tensor, flow_px: Tensor, uv1_px: Tensor, camera: FlowCamera) -> tuple[Tensor, FlowAux]:
    """``h(x, δ)`` ``(2,)`` for one point, and the triangulation's diagnostics.

    Args:
        x ``(26,)`` state; flow_px ``δ`` ``(2,)``; uv1_px ``(2,)`` pixel in the previous frame.
    """
    s = split(x)
    R1, c1 = camera_pose(s.q_prev, s.p_prev, camera)
    R2, c2 = camera_pose(s.q, s.p, camera)
    P1 = camera_matrix(R1, torch.zeros_like(c1))  # world origin at camera 1's centre
    P2 = camera_matrix(R2, c2 - c1)
    x1 = normalise_pixels(uv1_px, camera.K)
    x2 = normalise_pixels(uv1_px + flow_px, camera.K)
    tri = triangulate(P1, P2, x1, x2)
    y1, z1 = project_homogeneous(P1, tri.point)
    y2, z2 = project_homogeneous(P2, tri.point)
    h = _to_pixels(y2, camera.K) - _to_pixels(y1, camera.K) - flow_px
    ray1 = R1 @ torch.cat((x1, torch.ones_like(x1[..., :1])), -1)
    ray2 = R2 @ torch.cat((x2, torch.ones_like(x2[..., :1])), -1)
    parallax = ray_angle(ray1, ray2)
    return h, FlowAux(tri.conditioning, z1, z2, parallax)


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
    """
    if x.shape != (STATE_DIM,):
        raise ValueError(f"flow_measurements: x must be ({STATE_DIM},), got {tuple(x.shape)}")
    if flow_px.ndim != 2 or flow_px.shape[-1] != 2 or uv1_px.shape != flow_px.shape:
        raise ValueError(
            f"flow_measurements: flow_px and uv1_px must both be (M, 2); got {tuple(flow_px.shape)}, {tuple(uv1_px.shape)}"
        )
    camera = camera.to(x)
    flow_px, uv1_px = flow_px.to(x), uv1_px.to(x)
    M = flow_px.shape[0]

    def residual(x_, flow_, uv_):
        return flow_residual(x_, flow_, uv_, camera)

    # screening pass without gradients: which points have a well-posed triangulation?
    with torch.no_grad():
        h0, aux = vmap(residual, in_dims=(None, 0, 0))(x.detach(), flow_px.detach(), uv1_px.detach())
        finite = torch.isfinite(h0).all(-1)
        well_posed = aux.conditioning > min_conditioning
        in_front = (aux.depth1 > min_depth) & (aux.depth2 > min_depth)
        focal = 0.5 * (camera.K[0, 0] + camera.K[1, 1])
        parallax_px = focal * aux.parallax
        enough = parallax_px >= torch.as_tensor(min_parallax_px, dtype=x.dtype, device=x.device)
        valid = finite & well_posed & in_front & enough
    residual_out = flow_px.new_zeros(M, 2)
    H_x = flow_px.new_zeros(M, 2, STATE_DIM)
    H_r = flow_px.new_zeros(M, 2, 2)
    index = torch.nonzero(valid).squeeze(-1)
    if index.numel():
        jac = jacrev(lambda x_, f_, u_: residual(x_, f_, u_)[0], argnums=(0, 1))
        Hx_v, Hr_v = vmap(jac, in_dims=(None, 0, 0))(x, flow_px[index], uv1_px[index])
        h_v, aux_v = vmap(lambda f_, u_: residual(x, f_, u_))(flow_px[index], uv1_px[index])
        residual_out = residual_out.index_copy(0, index, h_v)
        # the parallax of the valid points again, now with its gradient (the noise inflation uses it)
        parallax_px = parallax_px.index_copy(0, index, focal * aux_v.parallax)
        H_x = H_x.index_copy(0, index, Hx_v)
        H_r = H_r.index_copy(0, index, Hr_v)
    n_behind = int((finite & well_posed & ~in_front).sum())
    n_low = int((finite & well_posed & in_front & ~enough).sum())
    n_degenerate = int((~valid).sum()) - n_behind - n_low
    return FlowMeasurements(residual_out, H_x, H_r, valid, n_degenerate, n_behind, n_low, parallax_px)


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
    U, _, _ = torch.linalg.svd(H_r)
    w = U[..., :, 0]  # (m, 2)
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

