"""Pinhole cameras and rigid transforms (pure, batched functions).

Conventions (OpenCV): camera frame x right, y down, z forward (optical axis);
pixel ``(u, v)`` = (column, row), with the *centre* of the top-left pixel at
``(0, 0)``. A pixel grid of an image ``(H, W)`` is ``u = 0..W-1``, ``v = 0..H-1``.

A :class:`RigidTransform` ``T_ba`` maps points from frame ``a`` to frame ``b``:
``x_b = R_ba x_a + t_ba``. flowins stores the camera extrinsics as
``imu_to_camera = T_ci`` (Kalibr's ``T_cam_imu``): ``x_cam = R_ci x_imu + t_ci``.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from flowins.geometry import quaternion as quat


@dataclass(frozen=True, eq=False)
class RigidTransform:
    """``x_b = R(q) x_a + t``; ``rotation_wxyz`` ``(..., 4)``, ``translation_m`` ``(..., 3)``."""

    rotation_wxyz: Tensor
    translation_m: Tensor

    def __post_init__(self) -> None:
        q = torch.as_tensor(self.rotation_wxyz, dtype=torch.float64)
        t = torch.as_tensor(self.translation_m, dtype=torch.float64)
        if q.shape[-1:] != (4,) or t.shape[-1:] != (3,):
            raise ValueError(
                f"RigidTransform expects rotation_wxyz (..., 4) and translation_m (..., 3); got {tuple(q.shape)}, {tuple(t.shape)}"
            )
        if not (torch.isfinite(q).all() and torch.isfinite(t).all()):
            raise ValueError("RigidTransform: rotation and translation must be finite")
        norm = q.norm(dim=-1)
        if ((norm - 1.0).abs() > 1e-3).any():
            raise ValueError(
                f"RigidTransform: rotation quaternion (w, x, y, z) must have unit norm, got norm {norm.tolist()}"
            )
        object.__setattr__(self, "rotation_wxyz", q / norm.unsqueeze(-1))
        object.__setattr__(self, "translation_m", t)

    @staticmethod
    def identity() -> RigidTransform:
        return RigidTransform(torch.tensor([1.0, 0.0, 0.0, 0.0]), torch.zeros(3))

    @staticmethod
    def from_matrix(T: Tensor) -> RigidTransform:
        """From a homogeneous ``(..., 4, 4)`` matrix."""
        T = torch.as_tensor(T, dtype=torch.float64)
        return RigidTransform(quat.from_matrix(T[..., :3, :3]), T[..., :3, 3])

    @property
    def rotation_matrix(self) -> Tensor:
        return quat.to_matrix(self.rotation_wxyz)

    def matrix(self) -> Tensor:
        """Homogeneous ``(..., 4, 4)``."""
        R = self.rotation_matrix
        top = torch.cat((R, self.translation_m.unsqueeze(-1)), dim=-1)
        bottom = torch.zeros(*R.shape[:-2], 1, 4, dtype=R.dtype)
        bottom[..., 0, 3] = 1.0
        return torch.cat((top, bottom), dim=-2)

    def inverse(self) -> RigidTransform:
        q_inv = quat.conjugate(self.rotation_wxyz)
        return RigidTransform(q_inv, -quat.rotate(q_inv, self.translation_m))

    def apply(self, points: Tensor) -> Tensor:
        """``x_b`` for points ``x_a`` ``(..., 3)``."""
        q = self.rotation_wxyz.to(points)
        return quat.rotate(q, points) + self.translation_m.to(points)

    def compose(self, other: RigidTransform) -> RigidTransform:
        """``self ∘ other``: first ``other`` (a→b), then ``self`` (b→c)."""
        return RigidTransform(
            quat.multiply(self.rotation_wxyz, other.rotation_wxyz),
            quat.rotate(self.rotation_wxyz, other.translation_m) + self.translation_m,
        )


def project(points_cam: Tensor, fx: float, fy: float, cx: float, cy: float) -> Tensor:
    """Pinhole projection ``(..., 3)`` camera-frame points -> ``(..., 2)`` pixels.

    No clamping: a point with ``z <= 0`` (behind the camera) gives whatever the
    division gives; callers test ``z`` themselves.
    """
    z = points_cam[..., 2]
    return torch.stack((fx * points_cam[..., 0] / z + cx, fy * points_cam[..., 1] / z + cy), dim=-1)


def pixel_grid(height: int, width: int, *, dtype: torch.dtype = torch.float64, device=None) -> Tensor:
    """``(H, W, 2)`` pixel coordinates ``(u, v)`` of the pixel centres."""
    v, u = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device), torch.arange(width, dtype=dtype, device=device), indexing="ij"
    )
    return torch.stack((u, v), dim=-1)


def unproject(uv: Tensor, fx: float, fy: float, cx: float, cy: float) -> Tensor:
    """Pixels ``(..., 2)`` -> camera-frame ray directions ``(..., 3)`` with ``z = 1``."""
    x = (uv[..., 0] - cx) / fx
    y = (uv[..., 1] - cy) / fy
    return torch.stack((x, y, torch.ones_like(x)), dim=-1)


def distort(xy: Tensor, coefficients: tuple[float, ...]) -> Tensor:
    """OpenCV radial-tangential distortion of normalised coordinates ``(..., 2)``.

    ``coefficients = (k1, k2, p1, p2[, k3])``; an empty tuple is the identity.
    """
    if not coefficients:
        return xy
    if len(coefficients) not in (4, 5):
        raise ValueError(f"radial-tangential distortion needs (k1, k2, p1, p2[, k3]), got {coefficients}")
    k1, k2, p1, p2 = coefficients[:4]
    k3 = coefficients[4] if len(coefficients) == 5 else 0.0
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return torch.stack((xd, yd), dim=-1)


def undistort(xy_distorted: Tensor, coefficients: tuple[float, ...], iterations: int = 20) -> Tensor:
    """Inverse of :func:`distort` by fixed-point iteration (as OpenCV's ``undistortPoints``)."""
    if not coefficients:
        return xy_distorted
    xy = xy_distorted
    for _ in range(iterations):
        xy = xy + (xy_distorted - distort(xy, coefficients))
    return xy
