"""Vectorised ray casting of a :class:`~flowins.data.simulate.world.City`, and exact optical flow.

One ray per pixel centre (OpenCV conventions of :mod:`flowins.geometry.camera`; the
ray direction has camera ``z = 1``, so its parameter at a hit *is* the depth).

How it stays fast (no Python loop over pixels or objects):

1. **Cull** facades that face away, lie beyond ``max_range_m`` or whose quad
   (clipped at the near plane) projects outside the image; likewise boxes.
2. **Bin** the image into ``tile x tile`` pixel tiles; a (tile, object) pair is kept
   when the object's projected bounding rectangle overlaps the tile.
3. **Occlusion prune**: a facade *covers* a tile when all four corner rays of the
   tile hit it (facade quads map convexly to the image, so then every ray of the
   tile does); facades whose nearest point is farther than a covering facade's
   farthest hit in that tile are dropped from the tile.
4. **Intersect** each kept pair on the tile's pixels: facades are vertical, so a
   ray meets one where its horizontal projection meets the 2D segment, plus a
   height check; boxes by the slab test in the box frame; the ground analytically.
   The nearest hit per pixel is a ``scatter_reduce(amin)`` of a key that packs the
   float32 depth's bits above the object's index.

Per-pixel work is float32 in camera-centred coordinates (world coordinates are
subtracted in float64 first). A hit point is the float64 camera centre plus the
float32 camera-centred offset ``depth * ray`` (relative error ~1e-7: it reprojects
into its own pixel to ~1e-5 px), so :func:`exact_flow` is consistent with the
images to far better than 1e-3 px. Textures are box-filtered over the pixel's
footprint on facades (no supersampling: geometric edges stay aliased).
"""
from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from flowins.data.sequence import PinholeCamera
from flowins.data.simulate.world import (
    City,
    box_colour,
    facade_colour,
    ground_colour,
    sky_colour,
)
from flowins.geometry.camera import pixel_grid, project, unproject

__all__ = ["FlowTruth", "Render", "exact_flow", "render"]

Pose = tuple[Tensor, Tensor, float]  # (R_wc (3, 3), p_wc (3,), t_s)

_NEAR_M = 0.05
_INDEX_BITS = 16  # object index packed below the depth's float32 bits
_NO_HIT_KEY = (0x7F800000 << _INDEX_BITS) | ((1 << _INDEX_BITS) - 1)  # +inf depth
_QUAD_EDGES = torch.tensor(((0, 1), (1, 2), (2, 3), (3, 0)))
_BOX_CORNERS = torch.tensor(
    [[sx, sy, sz] for sx in (-1.0, 1.0) for sy in (-1.0, 1.0) for sz in (0.0, 2.0)], dtype=torch.float64
)
_BOX_EDGES = torch.tensor([(i, j) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1])

SKY, GROUND, FACADE, BOX = 0, 1, 2, 3


class Render(NamedTuple):
    """One rendered frame.

    ``image`` ``(H, W, 3)`` uint8 RGB; ``depth`` ``(H, W)`` float32 camera-frame ``z`` of
    the hit (``inf`` for sky); ``object_id`` ``(H, W)`` int32 (-1 sky, 0 static scene,
    ``k > 0`` mover ``k``); ``point`` ``(H, W, 3)`` float64 hit point in the hit
    object's frame (world for the static scene, the mover's body frame for movers;
    NaN for sky).
    """

    image: Tensor
    depth: Tensor
    object_id: Tensor
    point: Tensor


class FlowTruth(NamedTuple):
    """Exact flow from frame 1 to frame 2.

    ``flow`` ``(H, W, 2)`` float32 px (NaN where the point is behind camera 2);
    ``valid`` ``(H, W)`` bool: a scene point, in front of camera 2, inside image 2 and
    not occluded there; ``static`` ``(H, W)``: ``object_id == 0``; ``sky`` ``(H, W)``:
    sky pixels, whose flow is the rotation-only flow of points at infinity (never
    ``valid``); ``depth`` ``(H, W)`` float32: frame 1's depth.
    """

    flow: Tensor
    valid: Tensor
    static: Tensor
    sky: Tensor
    depth: Tensor


class _Rays(NamedTuple):
    """Pixel rays of a camera in tile order: ``(T, S*S, ...)`` with ``T`` tiles of ``S x S``."""

    xy: Tensor  # (2, T, S*S) float32: camera-frame rays (x, y, 1)
    corners: Tensor  # (T, 4, 3) float64 rays through the tiles' outer pixel corners
    rects: Tensor  # (T, 4) u_lo, u_hi, v_lo, v_hi of the tiles' pixel areas
    tiles_yx: tuple[int, int]
    tile: int


@functools.lru_cache(maxsize=8)
def _rays(camera: PinholeCamera, tile: int) -> _Rays:
    h, w = camera.size
    ty, tx = -(-h // tile), -(-w // tile)
    uv = pixel_grid(ty * tile, tx * tile)  # (Hp, Wp, 2) float64
    uv = uv.view(ty, tile, tx, tile, 2).permute(0, 2, 1, 3, 4).reshape(ty * tx, tile * tile, 2)
    dirs64 = unproject(uv, camera.fx, camera.fy, camera.cx, camera.cy)
    u0 = torch.arange(tx, dtype=torch.float64) * tile - 0.5
    v0 = torch.arange(ty, dtype=torch.float64) * tile - 0.5
    v_lo, u_lo = torch.meshgrid(v0, u0, indexing="ij")
    rects = torch.stack((u_lo, u_lo + tile, v_lo, v_lo + tile), -1).reshape(-1, 4)
    corner_uv = torch.stack(
        (rects[:, [0, 1, 1, 0]], rects[:, [2, 2, 3, 3]]), -1
    )  # (T, 4, 2)
    corners = unproject(corner_uv, camera.fx, camera.fy, camera.cx, camera.cy)
    return _Rays(dirs64[..., :2].permute(2, 0, 1).to(torch.float32).contiguous(), corners, rects, (ty, tx), tile)


def _untile(x: Tensor, rays: _Rays, size: tuple[int, int]) -> Tensor:
    """``(T * S * S, ...)`` in tile order -> ``(H, W, ...)``."""
    (ty, tx), s = rays.tiles_yx, rays.tile
    rest = x.shape[1:]
    x = x.reshape(ty, tx, s, s, *rest).transpose(1, 2).reshape(ty * s, tx * s, *rest)
    return x[: size[0], : size[1]]


def _screen_rects(corners_cam: Tensor, edges: Tensor, camera: PinholeCamera) -> tuple[Tensor, Tensor]:
    """Bounding pixel rectangles ``(N, 4)`` (u_lo, u_hi, v_lo, v_hi) of convex polytopes
    given by camera-frame vertices ``(N, C, 3)`` and their edges ``(E, 2)``, clipped at the
    near plane, and whether each is visible at all ``(N,)``."""
    z = corners_cam[..., 2]
    front = z > _NEAR_M
    p, q = corners_cam[:, edges[:, 0]], corners_cam[:, edges[:, 1]]  # (N, E, 3)
    zp, zq = p[..., 2], q[..., 2]
    crossing = (zp > _NEAR_M) != (zq > _NEAR_M)
    a = ((_NEAR_M - zp) / torch.where(crossing, zq - zp, 1.0)).unsqueeze(-1)
    cut = p + a * (q - p)
    pts = torch.cat((corners_cam, cut), 1)
    ok = torch.cat((front, crossing), 1)
    safe = torch.where(ok.unsqueeze(-1), pts, torch.tensor((0.0, 0.0, 1.0), dtype=pts.dtype))
    uv = project(safe, camera.fx, camera.fy, camera.cx, camera.cy)
    big = torch.tensor(torch.inf, dtype=uv.dtype)
    lo = torch.where(ok.unsqueeze(-1), uv, big).amin(1)
    hi = torch.where(ok.unsqueeze(-1), uv, -big).amax(1)
    rect = torch.stack((lo[:, 0], hi[:, 0], lo[:, 1], hi[:, 1]), -1)
    visible = ok.any(1) & (rect[:, 1] >= -0.5) & (rect[:, 0] <= camera.width - 0.5)
    visible &= (rect[:, 3] >= -0.5) & (rect[:, 2] <= camera.height - 0.5)
    return rect, visible


def _tile_pairs(rects: Tensor, tiles: Tensor) -> tuple[Tensor, Tensor]:
    """(tile, object) index pairs whose rectangles overlap."""
    overlap = (
        (tiles[:, None, 0] <= rects[None, :, 1])
        & (tiles[:, None, 1] >= rects[None, :, 0])
        & (tiles[:, None, 2] <= rects[None, :, 3])
        & (tiles[:, None, 3] >= rects[None, :, 2])
    )
    pairs = overlap.nonzero()
    return pairs[:, 0], pairs[:, 1]


def _pack(depth: Tensor, index: Tensor) -> Tensor:
    """int64 key ordering by (depth, index); ``depth`` float32 >= 0 or inf."""
    return (depth.view(torch.int32).to(torch.int64) << _INDEX_BITS) | index


def _unpack(key: Tensor) -> tuple[Tensor, Tensor]:
    depth = (key >> _INDEX_BITS).to(torch.int32).view(torch.float32)
    return depth, key & ((1 << _INDEX_BITS) - 1)


def _nearest(n_pixels: int, tile_px: Tensor, s2: int, key: Tensor) -> Tensor:
    """Per-pixel minimum key over pairs: ``key`` ``(Np, S*S)`` of pairs on tiles ``tile_px``."""
    out = torch.full((n_pixels,), _NO_HIT_KEY, dtype=torch.int64)
    if key.numel():
        idx = (tile_px.unsqueeze(-1) * s2 + torch.arange(s2)).reshape(-1)
        out.scatter_reduce_(0, idx, key.reshape(-1), "amin")
    return out


def _facade_hits(city: City, camera: PinholeCamera, rays: _Rays, R: Tensor, p: Tensor, dirs_w: Tensor, max_range_m: float) -> Tensor:
    """Per-pixel key (depth, facade index) of the nearest facade hit ``(T * S * S,)``;
    ``dirs_w`` ``(3, T, S*S)`` float32 world ray directions (planar)."""
    n_tiles, s2 = dirs_w.shape[1], dirs_w.shape[2]
    rel_a = city.facade_a - p[:2]
    rel_b = city.facade_b - p[:2]
    e = rel_b - rel_a
    length2 = (e * e).sum(-1)
    foot = (-(rel_a * e).sum(-1) / length2).clamp(0, 1)
    dist = (rel_a + foot.unsqueeze(-1) * e).norm(dim=-1)  # horizontal distance camera -> segment
    facing = -(rel_a * city.facade_normal).sum(-1) > 0
    keep = (facing & (dist < max_range_m)).nonzero().squeeze(-1)
    if keep.numel() == 0:
        return torch.full((n_tiles * s2,), _NO_HIT_KEY, dtype=torch.int64)
    ra, rb, h = rel_a[keep], rel_b[keep], city.facade_height[keep]
    lo = torch.zeros_like(h) - p[2]
    hi = h - p[2]
    quad = torch.stack(
        (
            torch.cat((ra, lo[:, None]), -1),
            torch.cat((rb, lo[:, None]), -1),
            torch.cat((rb, hi[:, None]), -1),
            torch.cat((ra, hi[:, None]), -1),
        ),
        1,
    )  # (F, 4, 3) world, camera-centred
    rect, visible = _screen_rects(quad @ R, _QUAD_EDGES, camera)
    keep, ra, e, lo, hi, rect, dist = (x[visible] for x in (keep, ra, e[keep], lo, hi, rect, dist[keep]))
    tile_p, obj_p = _tile_pairs(rect, rays.rects)
    if tile_p.numel() == 0:
        return torch.full((n_tiles * s2,), _NO_HIT_KEY, dtype=torch.int64)

    # occlusion pruning with the tiles' corner rays (float64, few)
    cd = (rays.corners[tile_p] @ R.T)  # (Np, 4, 3) world directions
    a_p, e_p = ra[obj_p].unsqueeze(1), e[obj_p].unsqueeze(1)
    den = cd[..., 0] * e_p[..., 1] - cd[..., 1] * e_p[..., 0]
    lam = (a_p[..., 0] * e_p[..., 1] - a_p[..., 1] * e_p[..., 0]) / den
    mu = (a_p[..., 0] * cd[..., 1] - a_p[..., 1] * cd[..., 0]) / den
    zc = lam * cd[..., 2]
    covers = ((lam > 0) & (mu >= 0) & (mu <= 1) & (zc >= lo[obj_p, None]) & (zc <= hi[obj_p, None])).all(-1)
    far = torch.where(covers, (lam * cd[..., :2].norm(dim=-1)).amax(-1), torch.inf)
    cover_dist = torch.full((n_tiles,), torch.inf, dtype=far.dtype).scatter_reduce_(0, tile_p, far, "amin")
    needed = dist[obj_p] <= cover_dist[tile_p]
    tile_p, obj_p = tile_p[needed], obj_p[needed]

    # per-pixel intersection, float32
    table = torch.stack((ra[:, 0], ra[:, 1], e[:, 0], e[:, 1], lo, hi), -1).to(torch.float32).index_select(0, obj_p)
    ax, ay, ex, ey, z_lo, z_hi = (table[:, i, None] for i in range(6))
    dx, dy, dz = dirs_w.index_select(1, tile_p)  # (Np, S*S) each
    inv = 1.0 / (dx * ey - dy * ex)
    lam = (ax * ey - ay * ex) * inv
    mu = (ax * dy - ay * dx) * inv
    z = lam * dz
    hit = (lam > 0) & (mu >= 0) & (mu <= 1) & (z >= z_lo) & (z <= z_hi)
    key = _pack(torch.where(hit, lam, torch.inf), keep.index_select(0, obj_p).unsqueeze(-1))
    return _nearest(n_tiles * s2, tile_p, s2, key)


def _box_hits(
    city: City, camera: PinholeCamera, rays: _Rays, R: Tensor, p: Tensor, dirs_w: Tensor, box_xy: Tensor, box_yaw: Tensor, max_range_m: float
) -> Tensor:
    """Per-pixel key (depth, box index) of the nearest box hit ``(T * S * S,)``."""
    n_tiles, s2 = dirs_w.shape[1], dirs_w.shape[2]
    rel = box_xy - p[:2]
    keep = (rel.norm(dim=-1) < max_range_m).nonzero().squeeze(-1)
    if keep.numel() == 0:
        return torch.full((n_tiles * s2,), _NO_HIT_KEY, dtype=torch.int64)
    half = city.box_half[keep]
    c, s = box_yaw[keep].cos(), box_yaw[keep].sin()
    local = _BOX_CORNERS * half.unsqueeze(1)  # (B, 8, 3)
    world = torch.stack(
        (c[:, None] * local[..., 0] - s[:, None] * local[..., 1] + rel[keep, 0, None],
         s[:, None] * local[..., 0] + c[:, None] * local[..., 1] + rel[keep, 1, None],
         local[..., 2] - p[2]),
        -1,
    )
    rect, visible = _screen_rects(world @ R, _BOX_EDGES, camera)
    keep, half, c, s = keep[visible], half[visible], c[visible], s[visible]
    tile_p, obj_p = _tile_pairs(rect[visible], rays.rects)
    if tile_p.numel() == 0:
        return torch.full((n_tiles * s2,), _NO_HIT_KEY, dtype=torch.int64)
    # camera centre in each box frame, then float32 per pair
    o = -rel[keep]
    ox, oy = c * o[:, 0] + s * o[:, 1], -s * o[:, 0] + c * o[:, 1]
    table = torch.stack((c, s, ox, oy, p[2].expand_as(ox), half[:, 0], half[:, 1], half[:, 2]), -1)
    cp, sp, ox, oy, oz, hx, hy, hz = (x.unsqueeze(-1) for x in table.to(torch.float32).index_select(0, obj_p).unbind(-1))
    dx, dy, dz = dirs_w.index_select(1, tile_p)
    lx, ly = cp * dx + sp * dy, -sp * dx + cp * dy
    t_lo, t_hi = None, None
    for d, orig, lo, hi in ((lx, ox, -hx, hx), (ly, oy, -hy, hy), (dz, oz, torch.zeros_like(hz), 2 * hz)):
        inv = 1.0 / d
        t1, t2 = (lo - orig) * inv, (hi - orig) * inv
        near, far = torch.minimum(t1, t2), torch.maximum(t1, t2)
        t_lo = near if t_lo is None else torch.maximum(t_lo, near)
        t_hi = far if t_hi is None else torch.minimum(t_hi, far)
    hit = (t_hi >= t_lo) & (t_lo > 0)
    lam = torch.where(hit, t_lo, torch.inf)
    key = _pack(lam, keep.index_select(0, obj_p).unsqueeze(-1))
    return _nearest(n_tiles * s2, tile_p, s2, key)


def _cast(
    city: City, camera: PinholeCamera, R_wc: Tensor, p_wc: Tensor, t_s: float, *, tile: int, max_range_m: float
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Colour ``(H, W, 3)`` float32 in [0, 1] and the Render's depth, object id and point."""
    R = torch.as_tensor(R_wc, dtype=torch.float64)
    p = torch.as_tensor(p_wc, dtype=torch.float64)
    if R.shape != (3, 3) or p.shape != (3,):
        raise ValueError(f"render: expected R_wc (3, 3) and p_wc (3,), got {tuple(R.shape)}, {tuple(p.shape)}")
    rays = _rays(camera, tile)
    R32 = R.to(torch.float32)
    x_c, y_c = rays.xy  # (T, S*S) each, camera-frame ray (x, y, 1)
    dirs_w = torch.addcmul(torch.addcmul(R32[:, 2, None, None], x_c, R32[:, 0, None, None]), y_c, R32[:, 1, None, None])
    n = x_c.numel()
    box_xy, box_yaw = city.box_poses(t_s)

    depth_f, facade = _unpack(_facade_hits(city, camera, rays, R, p, dirs_w, max_range_m))
    depth_b, box = _unpack(_box_hits(city, camera, rays, R, p, dirs_w, box_xy, box_yaw, max_range_m))
    dz = dirs_w[2].reshape(-1)
    depth_g = torch.where(dz < 0, -float(p[2]) / dz, torch.inf)
    depth_g = torch.where(depth_g < max_range_m * 3, depth_g, torch.inf)
    kind = torch.where(depth_f < depth_g, FACADE, GROUND)
    depth = torch.minimum(depth_f, depth_g)
    kind = torch.where(depth_b < depth, BOX, kind)
    depth = torch.minimum(depth_b, depth)
    kind = torch.where(torch.isfinite(depth), kind, SKY)

    # hit points: camera-centred offsets in float32 (relative error ~6e-8), the camera centre in float64
    offset = dirs_w.reshape(3, -1) * depth  # (3, P)
    object_id = torch.zeros(n, dtype=torch.int32)
    colour = torch.empty(n, 3)

    def take(x: Tensor, idx: Tensor) -> Tensor:
        return x.index_select(0, idx)

    def take_t(x: Tensor, idx: Tensor) -> Tensor:  # columns of a planar (C, P) tensor as (N, C)
        return x.index_select(1, idx).T

    sky = (kind == SKY).nonzero().squeeze(-1)
    colour.index_copy_(0, sky, sky_colour(take_t(dirs_w.reshape(3, -1), sky)))
    object_id.index_fill_(0, sky, -1)

    ground = (kind == GROUND).nonzero().squeeze(-1)
    colour.index_copy_(0, ground, ground_colour(city, take_t(offset[:2], ground) + p[:2].to(torch.float32)))

    fac = (kind == FACADE).nonzero().squeeze(-1)
    fi = take(facade, fac)
    e = city.facade_b - city.facade_a
    u = (e / e.norm(dim=-1, keepdim=True))
    s0 = ((p[:2] - city.facade_a) * u).sum(-1).to(torch.float32)  # camera's coordinate along each facade
    off = take_t(offset, fac)
    u_f = take(u.to(torch.float32), fi)
    s_m = take(s0, fi) + off[:, 0] * u_f[:, 0] + off[:, 1] * u_f[:, 1]
    # the pixel's footprint on the facade, for box-filtered texture edges
    r = torch.sqrt(off[:, 0] * off[:, 0] + off[:, 1] * off[:, 1] + off[:, 2] * off[:, 2])  # (rows of a planar tensor)
    n_f = take(city.facade_normal.to(torch.float32), fi)
    cos_incidence = ((off[:, 0] * n_f[:, 0] + off[:, 1] * n_f[:, 1]).abs() / r).clamp_(min=0.1)
    pixel = r * (1.0 / camera.fx)
    colour.index_copy_(0, fac, facade_colour(city, fi, s_m, off[:, 2] + float(p[2]), pixel / cos_incidence, pixel))

    bx = (kind == BOX).nonzero().squeeze(-1)
    bi = take(box, bx)
    off = take_t(offset, bx).to(torch.float64)
    c, s = take(box_yaw, bi).cos(), take(box_yaw, bi).sin()
    rel = off[:, :2] + (p[:2] - take(box_xy, bi))
    local = torch.stack((c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], off[:, 2] + p[2]), -1)
    colour.index_copy_(0, bx, box_colour(city, bi, local))
    oid = take(city.box_object_id, bi)
    object_id.index_copy_(0, bx, oid.to(torch.int32))

    point = torch.empty(n, 3, dtype=torch.float64)
    point.copy_(offset.T)
    point += p
    point.index_fill_(0, sky, torch.nan)
    moving = (oid > 0).nonzero().squeeze(-1)
    point.index_copy_(0, take(bx, moving), take(local, moving))

    depth = torch.where(kind == SKY, torch.inf, depth)
    size = camera.size
    return (
        _untile(colour, rays, size),
        _untile(depth, rays, size).contiguous(),
        _untile(object_id, rays, size).contiguous(),
        _untile(point, rays, size).contiguous(),
    )


def render(
    city: City,
    camera: PinholeCamera,
    R_wc: Tensor,
    p_wc: Tensor,
    t_s: float,
    *,
    exposure: float = 1.0,
    motion_blur: Sequence[Pose] = (),
    tile: int = 16,
    max_range_m: float = 150.0,
) -> Render:
    """Ray-cast ``city`` through ``camera`` at pose ``(R_wc, p_wc)`` and time ``t_s``.

    ``R_wc`` ``(3, 3)`` maps camera-frame vectors to world, ``p_wc`` ``(3,)`` is the
    camera centre in world. ``exposure``: a gain on the linear colour before
    quantisation. ``motion_blur``: extra sub-frame poses ``(R_wc, p_wc, t_s)``; the
    image is the mean over the main pose and these (depth, ids and points are the
    main pose's). Facades and boxes beyond ``max_range_m`` (horizontal distance) are
    not drawn (the default, 150 m, changes no pixel along the default walk: the
    block's own facades hide everything farther); the ground is drawn to three
    times that. ``tile``: the binning tile size in pixels (a speed knob only: the
    result does not depend on it).
    """
    colour, depth, object_id, point = _cast(city, camera, R_wc, p_wc, t_s, tile=tile, max_range_m=max_range_m)
    if motion_blur:
        for R, p, t in motion_blur:
            colour = colour + _cast(city, camera, R, p, t, tile=tile, max_range_m=max_range_m)[0]
        colour = colour / (1 + len(motion_blur))
    image = (colour * (255.0 * exposure)).round_().clamp_(0, 255).to(torch.uint8)
    return Render(image, depth, object_id, point)


def bilinear(image: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """Bilinear sample of ``image`` ``(H, W)`` at pixels ``(u, v)`` (clamped into ``[0, W-1] x [0, H-1]``)."""
    h, w = image.shape
    u = u.clamp(0, w - 1)
    v = v.clamp(0, h - 1)
    u0 = u.floor().clamp_(max=w - 2)
    v0 = v.floor().clamp_(max=h - 2)
    fu, fv = u - u0, v - v0
    i = (v0 * w + u0).to(torch.int64)
    flat = image.reshape(-1).to(u.dtype)

    def at(k: Tensor) -> Tensor:
        return flat.index_select(0, k)

    return torch.lerp(torch.lerp(at(i), at(i + 1), fu), torch.lerp(at(i + w), at(i + w + 1), fu), fv)


def exact_flow(
    city: City,
    camera: PinholeCamera,
    render1: Render,
    pose1: Pose,
    pose2: Pose,
    render2: Render,
    *,
    depth_tolerance: float = 0.01,
) -> FlowTruth:
    """Exact optical flow from ``render1`` (at ``pose1``) to frame 2 (``pose2``, ``render2``).

    Each pixel's hit point (frame 1) is moved to time ``t2`` (static points stay;
    a mover's body-frame point goes with the mover's pose at ``t2``), projected
    into camera 2 (float64), minus the pixel. Occlusion: the point's inverse depth
    in camera 2 must agree with ``render2``'s inverse depth, bilinearly sampled
    (exact on planes), within ``depth_tolerance`` (relative); "inside" means within
    ``[0, W-1] x [0, H-1]`` (the pixel centres' hull). Sky pixels get the
    rotation-only flow of points at infinity.
    """
    R1 = torch.as_tensor(pose1[0], dtype=torch.float64)  # frame 1's points are already in their own frames
    R2, p2, t2 = pose2
    R2, p2 = torch.as_tensor(R2, dtype=torch.float64), torch.as_tensor(p2, dtype=torch.float64)
    h, w = camera.size
    if render1.depth.shape != (h, w) or render2.depth.shape != (h, w):
        raise ValueError(f"exact_flow: renders of {tuple(render1.depth.shape)}, {tuple(render2.depth.shape)}; camera is {(h, w)}")
    oid = render1.object_id.reshape(-1)
    world = render1.point.reshape(-1, 3).T.contiguous()  # (3, P) planar
    v1, u1 = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    u1, v1 = u1.reshape(-1), v1.reshape(-1)

    movers = (oid > 0).nonzero().squeeze(-1)
    if movers.numel():
        xy, yaw = city.mover_pose(t2)
        k = oid.index_select(0, movers).to(torch.int64) - 1
        c, s = yaw.index_select(0, k).cos(), yaw.index_select(0, k).sin()
        xm, ym = world[0].index_select(0, movers), world[1].index_select(0, movers)
        world[0].index_copy_(0, movers, c * xm - s * ym + xy[:, 0].index_select(0, k))
        world[1].index_copy_(0, movers, s * xm + c * ym + xy[:, 1].index_select(0, k))
    sky_idx = (oid < 0).nonzero().squeeze(-1)
    if sky_idx.numel():  # points at infinity: camera 2 sees the direction R2^T R1 d, so place them at p2 + R1 d
        us, vs = u1.index_select(0, sky_idx), v1.index_select(0, sky_idx)
        d = torch.stack(((us - camera.cx) / camera.fx, (vs - camera.cy) / camera.fy, torch.ones_like(us)))
        world.index_copy_(1, sky_idx, R1 @ d + p2[:, None])
    cam2 = R2.T @ (world - p2[:, None])  # (3, P)
    z2 = cam2[2]
    front = z2 > 1e-9
    inv_z2 = 1.0 / torch.where(front, z2, 1.0)
    u2 = camera.fx * cam2[0] * inv_z2 + camera.cx
    v2 = camera.fy * cam2[1] * inv_z2 + camera.cy
    flow = torch.stack((u2 - u1, v2 - v1), -1)
    flow = torch.where(front.unsqueeze(-1), flow, torch.nan).reshape(h, w, 2)
    inside = (u2 >= 0) & (u2 <= w - 1) & (v2 >= 0) & (v2 <= h - 1)
    sampled = bilinear(1.0 / render2.depth.to(torch.float64), u2, v2)  # inverse depth: 0 for sky
    visible = (sampled - inv_z2).abs() <= depth_tolerance * inv_z2
    sky = (oid < 0).reshape(h, w)
    valid = (front & inside & visible).reshape(h, w) & ~sky
    return FlowTruth(flow.to(torch.float32), valid, (oid == 0).reshape(h, w), sky, render1.depth)
