"""Exact sparse feature tracks of simulated landmarks.

Each landmark ``X_l`` (world) is projected into the camera at every frame, ``u = π(K,
R_wcᵀ (X_l - c_w))``; it is seen where its depth is inside ``[min_depth_m, max_depth_m]`` and
its pixel is on the image, and its track id is its index (a landmark that leaves the image
and comes back keeps its id; the gap ends its track for the filter). Optional pixel noise
``N(0, noise_px²)`` per coordinate.
"""
from __future__ import annotations

import torch
from torch import Tensor

from flowins.data.sequence import Tracks


def scatter_landmarks(centres_m: Tensor, count: int, *, radius_m: float, height_m: tuple[float, float],
                      generator: torch.Generator) -> Tensor:
    """``count`` landmarks ``(count, 3)`` uniform within ``radius_m`` (horizontally) of points
    drawn from ``centres_m`` ``(K, 3)``, at heights in ``height_m``."""
    pick = torch.randint(centres_m.shape[0], (count,), generator=generator)
    angle = 2 * torch.pi * torch.rand(count, generator=generator, dtype=centres_m.dtype)
    r = radius_m * torch.rand(count, generator=generator, dtype=centres_m.dtype).sqrt()
    z = height_m[0] + (height_m[1] - height_m[0]) * torch.rand(count, generator=generator, dtype=centres_m.dtype)
    xy = centres_m[pick, :2] + torch.stack((r * torch.cos(angle), r * torch.sin(angle)), -1)
    return torch.cat((xy, z.unsqueeze(-1)), -1)


def landmark_tracks(t_s: Tensor, R_wc: Tensor, c_w: Tensor, K: Tensor, image_size: tuple[int, int],
                    landmarks: Tensor, *, min_depth_m: float = 0.5, max_depth_m: float = 40.0,
                    noise_px: float = 0.0, generator: torch.Generator | None = None,
                    name: str = "simulated tracks") -> Tracks:
    """The :class:`~flowins.data.sequence.Tracks` of ``landmarks`` ``(L, 3)`` seen by a camera at
    frame times ``t_s`` ``(F,)`` with orientations (camera→world) ``R_wc`` ``(F, 3, 3)``, centres
    ``c_w`` ``(F, 3)``, intrinsics ``K`` and ``image_size`` ``(H, W)``."""
    H, W = image_size
    X_c = (R_wc.transpose(-1, -2).unsqueeze(1) @ (landmarks.unsqueeze(0) - c_w.unsqueeze(1)).unsqueeze(-1)).squeeze(-1)
    z = X_c[..., 2]
    safe = torch.where(z > 0, z, torch.ones_like(z))
    f = torch.stack((K[0, 0], K[1, 1]))
    uv = f * X_c[..., :2] / safe.unsqueeze(-1) + K[:2, 2]
    if noise_px > 0:
        uv = uv + noise_px * torch.randn(uv.shape, generator=generator, dtype=uv.dtype)
    seen = (z >= min_depth_m) & (z <= max_depth_m) & (uv[..., 0] >= 0) & (uv[..., 0] <= W - 1)
    seen &= (uv[..., 1] >= 0) & (uv[..., 1] <= H - 1)
    frame, landmark = torch.nonzero(seen, as_tuple=True)  # row-major: grouped by frame
    return Tracks(t_s[frame], landmark, uv[frame, landmark], name=name, image_size=(H, W))
