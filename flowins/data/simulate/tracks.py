"""Exact sparse feature tracks of simulated landmarks.

Each landmark ``X_l`` (world) is projected into the camera at every frame, ``u = π(K,
R_wcᵀ (X_l - c_w))``; it is seen where its depth is inside ``[min_depth_m, max_depth_m]`` and
its pixel is on the image, and its track id is its index (a landmark that leaves the image
and comes back keeps its id; the gap ends its track for the filter). Optional pixel noise
``N(0, noise_px²)`` per coordinate.

:class:`RenderedTracker` follows points of a rendered scene instead (the simulated walk's
``tracks.csv``): picked on the static scene, seen while not hidden behind anything.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from flowins.data.sequence import PinholeCamera, Tracks
from flowins.geometry import quaternion as quat
from flowins.geometry.camera import RigidTransform


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


def tracks_along(t_s: Tensor, q_wb: Tensor, p_w: Tensor, imu_to_camera: RigidTransform, K: Tensor,
                 image_size: tuple[int, int], *, count: int, ahead_m: float, radius_m: float,
                 height_m: tuple[float, float], noise_px: float, generator: torch.Generator,
                 name: str = "simulated tracks") -> Tracks:
    """:func:`landmark_tracks` of a body moving through the poses ``q_wb`` ``(F, 4)`` (body→world),
    ``p_w`` ``(F, 3)`` at frame times ``t_s`` with a camera mounted as ``imu_to_camera``
    (``x_cam = R_ci x_imu + t``): ``count`` landmarks scattered within ``radius_m`` of the points
    ``ahead_m`` in front of the camera along the way."""
    R_ci = quat.to_matrix(torch.as_tensor(imu_to_camera.rotation_wxyz, dtype=p_w.dtype))
    R_wc = quat.to_matrix(q_wb) @ R_ci.T
    c_w = p_w - (R_wc @ torch.as_tensor(imu_to_camera.translation_m, dtype=p_w.dtype).unsqueeze(-1)).squeeze(-1)
    landmarks = scatter_landmarks(c_w + ahead_m * R_wc[:, :, 2], count, radius_m=radius_m, height_m=height_m,
                                  generator=generator)
    return landmark_tracks(t_s, R_wc, c_w, K, image_size, landmarks, noise_px=noise_px, generator=generator,
                           name=name)


@dataclass(frozen=True)
class TrackConfig:
    """How :class:`RenderedTracker` follows the static scene through the rendered frames."""

    #: points tracked in each frame: lost ones are replaced by fresh ones up to this count
    count: int = 200
    #: fresh points are one per free cell of this many pixels (a cell holding a tracked point is not free)
    min_distance_px: int = 8
    #: 1-σ of the pixel noise of every observation (per coordinate)
    noise_px: float = 0.3
    #: points farther than this (camera z) are neither picked nor kept
    max_depth_m: float = 40.0
    #: a point is seen where its inverse depth agrees with the render's within this fraction
    depth_tolerance: float = 0.01
    #: true pixels kept this far inside the image, so that the noisy ones stay on it
    border_px: float = 1.0

    def __post_init__(self) -> None:
        if self.count < 0 or self.min_distance_px < 1 or self.noise_px < 0 or self.max_depth_m <= 0:
            raise ValueError(f"TrackConfig: count >= 0, min_distance_px >= 1, noise_px >= 0 and max_depth_m > 0 "
                             f"expected; got {self}")


def seen_in_render(points_w: Tensor, depth: Tensor, R_wc: Tensor, p_wc: Tensor, camera: PinholeCamera, *,
                   max_depth_m: float, depth_tolerance: float, border_px: float) -> tuple[Tensor, Tensor]:
    """Pixels ``(L, 2)`` of world points ``(L, 3)`` in a rendered frame and whether each is seen
    ``(L,)``: in front of the camera and within ``max_depth_m``, at least ``border_px`` inside the
    image, and not hidden, i.e. its inverse depth equals the render's (``depth`` ``(H, W)``, camera
    ``z``, ``inf`` for sky), bilinearly sampled at its pixel, within ``depth_tolerance``."""
    from flowins.data.simulate.render import bilinear

    X_c = (points_w - p_wc) @ R_wc  # rows of R_wcᵀ (X - p)
    z = X_c[:, 2]
    front = (z > 1e-6) & (z <= max_depth_m)
    inv_z = 1.0 / torch.where(front, z, torch.ones_like(z))
    uv = torch.stack((camera.fx * X_c[:, 0] * inv_z + camera.cx, camera.fy * X_c[:, 1] * inv_z + camera.cy), -1)
    inside = ((uv[:, 0] >= border_px) & (uv[:, 0] <= camera.width - 1 - border_px)
              & (uv[:, 1] >= border_px) & (uv[:, 1] <= camera.height - 1 - border_px))
    sampled = bilinear(1.0 / depth.to(torch.float64), uv[:, 0], uv[:, 1])
    return uv, front & inside & ((sampled - inv_z).abs() <= depth_tolerance * inv_z)


def fresh_pixels(static: Tensor, taken_uv: Tensor, need: int, cell_px: int, generator: torch.Generator) -> Tensor:
    """Up to ``need`` pixels ``(n, 2)`` (integer ``(u, v)``) where ``static`` ``(H, W)`` is True, one
    per free ``cell_px`` square cell (a cell holding a pixel of ``taken_uv`` ``(L, 2)`` is not free),
    each a random pixel of its cell, the cells chosen at random."""
    H, W = static.shape
    if need <= 0:
        return torch.zeros(0, 2, dtype=torch.int64)
    cols = -(-W // cell_px)
    v, u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    cell = ((v // cell_px) * cols + u // cell_px).reshape(-1)
    n_cells = cols * -(-H // cell_px)
    priority = torch.rand(H * W, generator=generator, dtype=torch.float64)
    priority = torch.where(static.reshape(-1), priority, -1.0)
    best = torch.full((n_cells,), -1.0, dtype=torch.float64).scatter_reduce(0, cell, priority, "amax")
    taken = torch.zeros(n_cells, dtype=torch.bool)
    if taken_uv.shape[0]:
        t = taken_uv.round().to(torch.int64)
        taken[(t[:, 1] // cell_px) * cols + t[:, 0] // cell_px] = True
    winner = (priority >= 0) & (priority == best[cell]) & ~taken[cell]
    pixels = winner.nonzero().squeeze(-1)
    pixels = pixels[torch.randperm(pixels.shape[0], generator=generator)[:need]]
    return torch.stack((pixels % W, pixels // W), -1)


class RenderedTracker:
    """Tracks of static scene points through a simulation's rendered frames, as a tracker that
    never slips would give them: a point is picked at a pixel of the static scene, its world
    point (the render's hit) is followed from frame to frame while it is seen
    (:func:`seen_in_render`: in view, not hidden, within range), and a point lost is lost for good
    (its id ends). Each frame is topped up to ``count`` points with fresh ones
    (:func:`fresh_pixels`). Every observation gets ``N(0, noise_px²)`` pixel noise.

    Feed the frames in order with :meth:`add`; :meth:`tracks` gives the
    :class:`~flowins.data.sequence.Tracks`."""

    def __init__(self, camera: PinholeCamera, config: TrackConfig, generator: torch.Generator):
        self.camera, self.config, self.generator = camera, config, generator
        self.points = torch.zeros(0, 3, dtype=torch.float64)
        self.ids = torch.zeros(0, dtype=torch.int64)
        self.next_id = 0
        self.rows: list[tuple[float, Tensor, Tensor]] = []

    def add(self, t_s: float, depth: Tensor, object_id: Tensor, point_w: Tensor, R_wc: Tensor, p_wc: Tensor) -> None:
        """Frame at ``t_s`` rendered at pose ``(R_wc, p_wc)``: its ``depth`` ``(H, W)``,
        ``object_id`` ``(H, W)`` (0: static scene) and hit points ``point_w`` ``(H, W, 3)``."""
        c = self.config
        uv, seen = seen_in_render(self.points, depth, R_wc, p_wc, self.camera, max_depth_m=c.max_depth_m,
                                  depth_tolerance=c.depth_tolerance, border_px=c.border_px)
        self.points, self.ids, uv = self.points[seen], self.ids[seen], uv[seen]
        H, W = depth.shape
        inner = torch.zeros(H, W, dtype=torch.bool)
        b = math.ceil(c.border_px)
        inner[b:H - b, b:W - b] = True
        static = (object_id == 0) & (depth <= c.max_depth_m) & inner
        new = fresh_pixels(static, uv, c.count - uv.shape[0], c.min_distance_px, self.generator)
        self.points = torch.cat((self.points, point_w[new[:, 1], new[:, 0]].to(torch.float64)))
        self.ids = torch.cat((self.ids, torch.arange(self.next_id, self.next_id + new.shape[0])))
        self.next_id += new.shape[0]
        uv = torch.cat((uv, new.to(torch.float64)))
        if c.noise_px > 0:
            uv = uv + c.noise_px * torch.randn(uv.shape, generator=self.generator, dtype=torch.float64)
        self.rows.append((t_s, self.ids.clone(), uv))

    def tracks(self, name: str = "simulated tracks") -> Tracks | None:
        """Every frame's observations so far; None before any point was seen."""
        rows = [(t, i, uv) for t, i, uv in self.rows if i.numel()]
        if not rows:
            return None
        t = torch.cat([torch.full((i.shape[0],), t, dtype=torch.float64) for t, i, _ in rows])
        return Tracks(t, torch.cat([i for _, i, _ in rows]), torch.cat([uv for _, _, uv in rows]), name=name,
                      image_size=(self.camera.height, self.camera.width))
