"""A snowy city block around the synthetic walk: facades, ground, parked and moving boxes.

The walk of :class:`~flowins.data.synthetic.Walk` follows a closed loop (a Fourier
curve) on a sidewalk. :func:`build_city` lines that loop with

* **facades**: vertical planar quads (polyline chords of ``segment_m`` along offset
  curves of the loop). The block's own buildings stand ``inner_offset_m`` to the
  inside of the path; across a street the outer buildings stand ``outer_offset_m``
  to the outside. Buildings are 5-10 storeys of 3 m with a per-building style
  (wall colour, window grid, window colour, doors and shop windows at street
  level, bricks). Occasional alleys between buildings are closed by two side walls
  and a back wall, so one never looks "through" a facade.
* **ground**: the plane ``z = 0``, near-white snow with a faint texture, greyer slush
  on the road, tyre tracks along the lanes and foot marks on the sidewalks;
* **boxes**: parked cars (static, object id 0) along both curbs, and movers
  (object ids ``1..M``): cars driving along the road and box-shaped pedestrians on
  the sidewalks. A mover's pose is closed-form in time (:meth:`City.mover_pose`):
  it moves along an offset curve of the loop at a constant curve-parameter rate.

Frames and conventions
----------------------
World: local ENU (x east, y north, z up), the walk's frame (origin at the start of
the walk, on the ground). A box's body frame: origin at the centre of its bottom
face, x forward (direction of travel), y left, z up; its pose is
``x_world = Rz(yaw) x_body + (x, y, 0)``.

Dtypes: geometry (facade endpoints and heights, box poses) is float64; textures and
colours are float32 in [0, 1] (the renderer converts to uint8 at the end).
Appearance depends only on the surface point (and its fixed normal), never on the
viewer, so brightness constancy holds exactly up to sampling.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch
from torch import Tensor

from flowins.data.synthetic import Walk

STOREY_M = 3.0
_SUN_XY = (0.55, -0.83)  # horizontal direction the diffuse light comes from (overcast sky)
_PALETTE = (
    (0.80, 0.65, 0.40),  # ochre
    (0.88, 0.80, 0.55),  # pale yellow
    (0.80, 0.55, 0.45),  # salmon
    (0.62, 0.62, 0.60),  # grey
    (0.60, 0.30, 0.22),  # brick red
    (0.60, 0.66, 0.72),  # blue-grey
    (0.86, 0.84, 0.78),  # off-white
    (0.55, 0.62, 0.55),  # green-grey
)
_CAR_COLOURS = ((0.7, 0.1, 0.1), (0.1, 0.2, 0.55), (0.15, 0.15, 0.15), (0.75, 0.75, 0.78), (0.9, 0.9, 0.9), (0.2, 0.4, 0.25))
_CAR = 0
_PEDESTRIAN = 1


@dataclass(frozen=True)
class CityConfig:
    """Layout of the city; distances in metres, positive offsets outward (away from the block)."""

    inner_offset_m: float = -3.5  # block facades: 3.5 m to the inside of the path
    outer_offset_m: float = 18.0  # facades across the street
    curb_offset_m: float = 2.5  # sidewalk / road boundary on the walk's side
    far_curb_offset_m: float = 15.5  # road / sidewalk boundary on the far side
    segment_m: float = 5.0  # facade chord length
    building_length_m: tuple[float, float] = (12.0, 36.0)
    storeys: tuple[int, int] = (5, 10)
    alley_probability: float = 0.2
    alley_width_m: tuple[float, float] = (2.5, 4.0)
    alley_depth_m: float = 8.0
    parked_gap_m: tuple[float, float] = (0.8, 14.0)
    n_moving_cars: int = 4
    car_speed_mps: tuple[float, float] = (6.0, 11.0)
    n_pedestrians: int = 8
    pedestrian_speed_mps: tuple[float, float] = (1.0, 1.6)
    #: False: the movers are drawn (the rest of the city stays as it is with them) and left out
    movers: bool = True
    ground_resolution_m: float = 0.1
    ground_margin_m: float = 30.0

    def __post_init__(self) -> None:
        if not self.inner_offset_m < 0 < self.curb_offset_m < self.far_curb_offset_m < self.outer_offset_m:
            raise ValueError(
                "CityConfig: expected inner_offset_m < 0 < curb_offset_m < far_curb_offset_m < outer_offset_m, got "
                f"{self.inner_offset_m}, {self.curb_offset_m}, {self.far_curb_offset_m}, {self.outer_offset_m}"
            )
        if self.segment_m <= 0 or self.building_length_m[0] <= 0 or self.building_length_m[0] > self.building_length_m[1]:
            raise ValueError(f"CityConfig: bad segment_m={self.segment_m} or building_length_m={self.building_length_m}")


@dataclass(frozen=True, eq=False)
class City:
    """All geometry and appearance of the world (see the module docstring for frames).

    Facades ``(F, ...)``: endpoints ``facade_a``, ``facade_b`` ``(F, 2)`` float64 on the
    ground, front normal ``facade_normal`` ``(F, 2)`` (only the front side is drawn),
    ``facade_height`` ``(F,)`` m, ``facade_s0`` ``(F,)`` texture coordinate at ``a``
    (``s`` grows towards ``b``), ``facade_columns`` ``(F,)`` number of window columns
    of the building (windows at ``0 <= floor(s / spacing) < columns``),
    ``facade_building`` ``(F,)`` int64 index into the building styles.

    Buildings ``(NB, ...)``: ``building_rgb``, ``window_rgb`` ``(NB, 3)``,
    ``window_spacing`` ``(NB,)`` m, ``window_size`` ``(NB, 2)`` (width, height) m,
    ``window_sill`` ``(NB,)`` m above the storey floor, ``door_rate`` ``(NB,)``,
    ``brick`` ``(NB,)`` bool.

    Boxes ``(B, ...)``: ``box_half`` ``(B, 3)`` half extents (length, width, height);
    ``box_xy``, ``box_yaw`` the static pose (ignored for movers), ``box_object_id``
    ``(B,)`` int64 (0 static, ``k`` mover ``k``), ``box_kind`` (0 car, 1 pedestrian),
    ``box_rgb`` ``(B, 3)``. Movers are the last ``M`` boxes, in order ``k = 1..M``;
    ``mover_offset_m``, ``mover_s0``, ``mover_rate`` ``(M,)`` define their poses.

    Ground: ``ground_lum`` ``(Hg, Wg)`` float32 luminance raster, texel ``(0, 0)``
    centred at ``ground_origin`` ``(2,)``, ``ground_resolution_m`` per texel.
    ``noise``: ``(256, 256)`` float32 smooth value noise in [0, 1] (wraps).

    Derived (for fast texturing): ``facade_table`` ``(17, F)`` and ``box_table``
    ``(B, 11)``, the per-object attributes gathered once per pixel.
    """

    walk: Walk
    outward_sign: float
    facade_a: Tensor
    facade_b: Tensor
    facade_normal: Tensor
    facade_height: Tensor
    facade_s0: Tensor
    facade_columns: Tensor
    facade_building: Tensor
    building_rgb: Tensor
    window_rgb: Tensor
    window_spacing: Tensor
    window_size: Tensor
    window_sill: Tensor
    door_rate: Tensor
    brick: Tensor
    box_half: Tensor
    box_xy: Tensor
    box_yaw: Tensor
    box_object_id: Tensor
    box_kind: Tensor
    box_rgb: Tensor
    mover_offset_m: Tensor
    mover_s0: Tensor
    mover_rate: Tensor
    ground_lum: Tensor
    ground_origin: Tensor
    ground_resolution_m: float
    noise: Tensor
    seed: int
    facade_table: Tensor  # (17, F) per-facade texturing attributes, planar (derived, see _facade_table)
    box_table: Tensor  # (B, 11) per-box texturing attributes (derived, see _box_table)

    @property
    def n_movers(self) -> int:
        return int(self.mover_s0.shape[0])

    @property
    def n_facades(self) -> int:
        return int(self.facade_a.shape[0])

    def mover_pose(self, t_s: float | Tensor) -> tuple[Tensor, Tensor]:
        """Poses of the movers at time ``t_s``: ``xy`` ``(M, 2)`` and ``yaw`` ``(M,)`` (float64).

        Mover ``k`` (object id ``k``) moves along the loop's offset curve at
        ``mover_offset_m[k-1]``: curve parameter ``s(t) = s0 + rate t``; it faces its
        direction of travel.
        """
        t = torch.as_tensor(t_s, dtype=torch.float64)
        s = self.mover_s0 + self.mover_rate * t
        xy, tangent = loop_point(self.walk, s, self.mover_offset_m, self.outward_sign)
        yaw = torch.atan2(tangent[..., 1], tangent[..., 0]) + torch.where(self.mover_rate < 0, math.pi, 0.0)
        return xy, yaw

    def box_poses(self, t_s: float | Tensor) -> tuple[Tensor, Tensor]:
        """Poses of all boxes at time ``t_s``: ``xy`` ``(B, 2)``, ``yaw`` ``(B,)``."""
        m = self.n_movers
        if m == 0:
            return self.box_xy, self.box_yaw
        xy, yaw = self.mover_pose(t_s)
        return torch.cat((self.box_xy[:-m], xy)), torch.cat((self.box_yaw[:-m], yaw))

    def canyon(self, positions_m: Tensor) -> Tensor:
        """How enclosed each position ``(G, 3)`` is, in [0, 1] ``(G,)``.

        The mean over eight horizontal azimuths of the elevation angle of the top of
        the first facade hit (0 where none is hit within 200 m), divided by 60°.
        """
        p = torch.as_tensor(positions_m, dtype=torch.float64).reshape(-1, 3)
        az = torch.arange(8, dtype=torch.float64) * (math.pi / 4)
        d = torch.stack((az.cos(), az.sin()), -1)  # (8, 2)
        rel = self.facade_a[None] - p[:, None, :2]  # (G, F, 2)
        e = self.facade_b - self.facade_a  # (F, 2)
        den = d[:, 0, None] * e[None, :, 1] - d[:, 1, None] * e[None, :, 0]  # (8, F)
        lam = (rel[:, None, :, 0] * e[None, None, :, 1] - rel[:, None, :, 1] * e[None, None, :, 0]) / den
        mu = (rel[:, None, :, 0] * d[None, :, None, 1] - rel[:, None, :, 1] * d[None, :, None, 0]) / den
        hit = (lam > 0) & (lam < 200.0) & (mu >= 0) & (mu <= 1)
        lam = torch.where(hit, lam, torch.inf)
        dist, idx = lam.min(-1)  # (G, 8)
        top = self.facade_height[idx] - p[:, 2:3]
        elevation = torch.where(torch.isfinite(dist), torch.atan2(top.clamp_min(0.0), dist), 0.0)
        return (elevation.mean(-1) / math.radians(60.0)).clamp(0.0, 1.0)


# --------------------------------------------------------------------------- the loop


def loop_orientation(walk: Walk) -> float:
    """+1 if the walk's loop runs counter-clockwise (its inside on the left), else -1."""
    s = torch.linspace(0, 2 * math.pi, 2001, dtype=torch.float64)
    c = walk._curve(s)
    area = 0.5 * (c[:-1, 0] * c[1:, 1] - c[1:, 0] * c[:-1, 1]).sum()
    return 1.0 if float(area) > 0 else -1.0


def loop_point(walk: Walk, s: Tensor, offset_m: Tensor | float, outward_sign: float) -> tuple[Tensor, Tensor]:
    """Points of the loop's offset curve at curve parameters ``s`` ``(...)``.

    ``xy = scale (c(s) - c(0)) + offset n_out(s)`` (the walk's horizontal path for
    offset 0; ``n_out`` the unit outward normal), and the unit tangent ``(..., 2)``
    (direction of increasing ``s``, a central difference with step 1e-5: its error,
    ~1e-10, is far below anything visible; the pose stays a smooth closed form).
    """
    s = torch.as_tensor(s, dtype=torch.float64)
    n = s.numel()
    flat = s.reshape(-1)
    both = walk._curve(torch.cat((flat, flat + 1e-5, flat - 1e-5, flat.new_zeros(1))))  # one evaluation
    c = both[:n].reshape(*s.shape, 2)
    dc = (both[n : 2 * n] - both[2 * n : 3 * n]).reshape(*s.shape, 2)
    origin = both[3 * n]
    tangent = dc / dc.norm(dim=-1, keepdim=True)
    normal = outward_sign * torch.stack((tangent[..., 1], -tangent[..., 0]), -1)
    offset = torch.as_tensor(offset_m, dtype=torch.float64)
    xy = walk.scale * (c - origin) + offset.unsqueeze(-1) * normal
    return xy, tangent


def _offset_curve(walk: Walk, offset_m: float, sign: float, n: int = 8001) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Dense samples of an offset curve: curve parameters, ``xy`` ``(n, 2)`` and arc length ``(n,)``."""
    s = torch.linspace(0, 2 * math.pi, n, dtype=torch.float64)
    xy, _ = loop_point(walk, s, offset_m, sign)
    xy = xy.numpy()
    arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))))
    return s.numpy(), xy, arc


def _at_arc(xy: np.ndarray, arc: np.ndarray, a: np.ndarray) -> np.ndarray:
    a = np.mod(a, arc[-1])
    return np.stack((np.interp(a, arc, xy[:, 0]), np.interp(a, arc, xy[:, 1])), -1)


# --------------------------------------------------------------------------- building the city


class _Builder:
    """Accumulates facades and building styles (plain lists; turned into tensors at the end)."""

    def __init__(self, gen: torch.Generator):
        self.gen = gen
        self.quads: list[tuple] = []  # (a, b, normal, height, s0, columns, building)
        self.styles: list[tuple] = []

    def uniform(self, lo: float, hi: float) -> float:
        return lo + (hi - lo) * float(torch.rand((), generator=self.gen, dtype=torch.float64))

    def integer(self, lo: int, hi: int) -> int:
        return int(torch.randint(lo, hi + 1, (), generator=self.gen))

    def style(self) -> int:
        base = torch.tensor(_PALETTE[self.integer(0, len(_PALETTE) - 1)])
        base = (base * (1 + 0.08 * (2 * torch.rand(3, generator=self.gen) - 1))).clamp(0, 1)
        window = torch.tensor((0.16, 0.2, 0.26)) * (1 + 0.3 * (2 * torch.rand(3, generator=self.gen) - 1))
        spacing = self.uniform(2.4, 3.6)
        size = (self.uniform(0.40, 0.62) * spacing, self.uniform(1.3, 1.8))
        sill = self.uniform(0.7, 1.0)
        door_rate = self.uniform(0.1, 0.35)
        brick = self.uniform(0, 1) < 0.3
        self.styles.append((base.tolist(), window.tolist(), spacing, size, sill, door_rate, brick))
        return len(self.styles) - 1

    def quad(self, a, b, front, height: float, s0: float, columns: int, building: int) -> None:
        """A facade from ``a`` to ``b`` whose front faces the point ``front``."""
        a, b, front = np.asarray(a, float), np.asarray(b, float), np.asarray(front, float)
        e = b - a
        n = np.array((-e[1], e[0])) / np.linalg.norm(e)
        if np.dot(front - a, n) < 0:
            n = -n
        self.quads.append((a, b, n, height, s0, columns, building))

    def street_side(self, walk: Walk, sign: float, offset_m: float, config: CityConfig) -> None:
        """Buildings along one offset curve, facing the walk's path, with alleys."""
        _, xy, arc = _offset_curve(walk, offset_m, sign)
        _, path_xy, path_arc = _offset_curve(walk, 0.0, sign)
        total = arc[-1]
        lengths, gaps = [], []
        while sum(lengths) + sum(gaps) < total:
            lengths.append(self.uniform(*config.building_length_m))
            gaps.append(self.uniform(*config.alley_width_m) if self.uniform(0, 1) < config.alley_probability else 0.0)
        k = total / (sum(lengths) + sum(gaps))
        lengths, gaps = [length * k for length in lengths], [g * k for g in gaps]
        back_sign = 1.0 if offset_m > 0 else -1.0  # away from the street, in units of the outward normal
        start = 0.0
        ends = []
        for length, gap in zip(lengths, gaps):
            building = self.style()
            height = STOREY_M * self.integer(*config.storeys)
            n_seg = max(1, round(length / config.segment_m))
            pts = _at_arc(xy, arc, np.linspace(start, start + length, n_seg + 1))
            front = _at_arc(path_xy, path_arc, np.linspace(start, start + length, n_seg + 1) * path_arc[-1] / total)
            chord = np.linalg.norm(np.diff(pts, axis=0), axis=1)
            s_cum = np.concatenate(([0.0], np.cumsum(chord)))
            spacing = self.styles[building][2]
            columns = int(s_cum[-1] // spacing)
            margin = 0.5 * (s_cum[-1] - columns * spacing)
            for j in range(n_seg):
                self.quad(pts[j], pts[j + 1], 0.5 * (front[j] + front[j + 1]), height, s_cum[j] - margin, columns, building)
            ends.append((pts[0], pts[-1], pts[1] - pts[0], pts[-1] - pts[-2], height, building, gap))
            start += length + gap
        # alleys: side walls of the two neighbours and a back wall
        for i, (_, end, _, t_end, height, building, gap) in enumerate(ends):
            if gap <= 0:
                continue
            nxt = ends[(i + 1) % len(ends)]
            begin, t_begin, height_next, building_next = nxt[0], nxt[2], nxt[4], nxt[5]
            depth = config.alley_depth_m
            back_e = self._back(t_end, sign * back_sign) * depth
            back_b = self._back(t_begin, sign * back_sign) * depth
            centre = 0.5 * (end + begin)
            cos_turn = np.dot(t_end, t_begin) / (np.linalg.norm(t_end) * np.linalg.norm(t_begin))
            if cos_turn < math.cos(math.radians(15.0)):  # a tight bend: the side walls would cross; close the gap
                self.quad(end, begin, centre - back_e, height, 0.0, 0, building)
                continue
            self.quad(end, end + back_e, begin, height, 0.0, 0, building)
            self.quad(begin, begin + back_b, end, height_next, 0.0, 0, building_next)
            wall = self.style()
            a, b = end + back_e, begin + back_b
            length = float(np.linalg.norm(b - a))
            spacing = self.styles[wall][2]
            columns = int(length // spacing)
            self.quad(a, b, centre, STOREY_M * self.integer(*config.storeys), -0.5 * (length - columns * spacing), columns, wall)

    @staticmethod
    def _back(tangent: np.ndarray, sign: float) -> np.ndarray:
        t = tangent / np.linalg.norm(tangent)
        return sign * np.array((t[1], -t[0]))  # right normal x orientation (+1 counter-clockwise) = outward


def _value_noise(gen: torch.Generator, size: int = 256) -> Tensor:
    """``(size, size)`` smooth, tileable value noise in [0, 1]: two octaves of blurred white noise."""
    out = torch.zeros(size, size)
    for sigma, weight in ((1.0, 0.6), (3.0, 0.4)):
        white = torch.rand(1, 1, size, size, generator=gen)
        r = int(3 * sigma)
        x = torch.arange(-r, r + 1, dtype=torch.float32)
        k = torch.exp(-0.5 * (x / sigma) ** 2)
        k = k / k.sum()
        padded = torch.nn.functional.pad(white, (r, r, r, r), mode="circular")
        blurred = torch.nn.functional.conv2d(padded, k.view(1, 1, 1, -1))
        blurred = torch.nn.functional.conv2d(blurred, k.view(1, 1, -1, 1))
        b = blurred[0, 0]
        out += weight * (b - b.min()) / (b.max() - b.min())
    return (out - out.min()) / (out.max() - out.min())


def _ground(walk: Walk, sign: float, config: CityConfig, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """Snow luminance raster: sidewalks, slushy road, tyre tracks and foot marks."""
    res = config.ground_resolution_m
    _, outer, _ = _offset_curve(walk, config.outer_offset_m, sign, 4001)
    lo = outer.min(0) - config.ground_margin_m
    hi = outer.max(0) + config.ground_margin_m
    w, h = (np.ceil((hi - lo) / res).astype(int) + 1).tolist()
    shift = 4  # sub-pixel drawing precision: coordinates in 1/16 texel

    def to_px(xy: np.ndarray) -> np.ndarray:
        return np.round((xy - lo) / res * (1 << shift)).astype(np.int32).reshape(-1, 1, 2)

    road = np.zeros((h, w), np.uint8)
    _, near_curb, _ = _offset_curve(walk, config.curb_offset_m, sign, 4001)
    _, far_curb, _ = _offset_curve(walk, config.far_curb_offset_m, sign, 4001)
    cv2.fillPoly(road, [to_px(far_curb)], 255, cv2.LINE_AA, shift)
    cv2.fillPoly(road, [to_px(near_curb)], 0, cv2.LINE_AA, shift)
    tracks = np.zeros((h, w), np.uint8)
    centre = 0.5 * (config.curb_offset_m + config.far_curb_offset_m)
    rng = np.random.default_rng(int(torch.randint(0, 2**31, (), generator=gen)))
    for lane in (centre - 1.8, centre + 1.8, centre - 1.8 + 0.4, centre + 1.8 - 0.3):
        for wheel in (-0.78, 0.78):
            s = torch.linspace(0, 2 * math.pi, 4001, dtype=torch.float64)
            wobble = 0.15 * torch.sin(s * rng.integers(5, 30) + rng.uniform(0, 6.3))
            xy, _ = loop_point(walk, s, lane + wheel + wobble, sign)
            cv2.polylines(tracks, [to_px(xy.numpy())], True, int(rng.integers(90, 200)), max(1, round(0.25 / res)), cv2.LINE_AA, shift)
    marks = np.zeros((h, w), np.uint8)
    for offset_range in ((config.inner_offset_m + 0.3, config.curb_offset_m - 0.2), (config.far_curb_offset_m + 0.2, config.outer_offset_m - 0.3)):
        n = 6000
        s = torch.as_tensor(rng.uniform(0, 2 * math.pi, n))
        off = torch.as_tensor(rng.uniform(*offset_range, n))
        xy, tangent = loop_point(walk, s, off, sign)
        angle = np.degrees(np.arctan2(tangent[:, 1].numpy(), tangent[:, 0].numpy())) + rng.normal(0, 15, n)
        for (x, y), a, v in zip(((xy.numpy() - lo) / res * (1 << shift)).astype(np.int64), angle, rng.integers(60, 160, n)):
            axes = (int(0.14 / res * (1 << shift)), int(0.05 / res * (1 << shift)))
            cv2.ellipse(marks, (int(x), int(y)), axes, float(a), 0, 360, int(v), -1, cv2.LINE_AA, shift)
    noise = rng.standard_normal((h // 8 + 2, w // 8 + 2)).astype(np.float32)
    noise = cv2.resize(cv2.GaussianBlur(noise, (0, 0), 1.5), (w, h), interpolation=cv2.INTER_CUBIC)
    lum = 0.95 - 0.07 * road / 255.0 - 0.11 * tracks / 255.0 - 0.06 * marks / 255.0 + 0.012 * noise
    lum = cv2.GaussianBlur(lum.astype(np.float32), (0, 0), 0.7)
    return torch.from_numpy(np.ascontiguousarray(lum)), torch.tensor(lo, dtype=torch.float64)


@dataclass
class _Boxes:
    """The city's boxes as they are built: static ones first (parked cars), then movers."""

    half: list = field(default_factory=list)  # (half length, half width, half height) m
    xy: list = field(default_factory=list)  # static boxes' centres
    yaw: list = field(default_factory=list)
    kind: list = field(default_factory=list)
    rgb: list = field(default_factory=list)
    mover_offset: list = field(default_factory=list)  # movers: the offset curve they follow, m
    mover_s0: list = field(default_factory=list)  # their phase at t = 0, rad
    mover_rate: list = field(default_factory=list)  # and its rate, rad/s


def _park_cars(boxes: _Boxes, builder: _Builder, walk: Walk, sign: float, config: CityConfig) -> None:
    """Parked cars along both curbs (static boxes)."""
    for offset in (config.curb_offset_m + 1.1, config.far_curb_offset_m - 1.1):
        _, curb_xy, arc = _offset_curve(walk, offset, sign)
        position = builder.uniform(0.0, 10.0)
        while position < arc[-1] - 6.0:
            length = builder.uniform(4.1, 4.8)
            centre = position + 0.5 * length
            p0, p1 = _at_arc(curb_xy, arc, np.array([centre - 0.5, centre + 0.5]))
            yaw = math.atan2(p1[1] - p0[1], p1[0] - p0[0]) + (math.pi if builder.uniform(0, 1) < 0.3 else 0.0)
            boxes.half.append((0.5 * length, 0.5 * builder.uniform(1.7, 1.9), 0.5 * builder.uniform(1.4, 1.65)))
            boxes.xy.append(0.5 * (p0 + p1))
            boxes.yaw.append(yaw)
            boxes.kind.append(_CAR)
            boxes.rgb.append(_CAR_COLOURS[builder.integer(0, len(_CAR_COLOURS) - 1)])
            position += length + builder.uniform(*config.parked_gap_m)


def _add_movers(boxes: _Boxes, builder: _Builder, walk: Walk, sign: float, config: CityConfig,
                gen: torch.Generator) -> None:
    """Moving boxes: cars in the two lanes around the road's centre, pedestrians on the sidewalks."""
    centre = 0.5 * (config.curb_offset_m + config.far_curb_offset_m)
    lane_speed = (builder.uniform(*config.car_speed_mps), builder.uniform(*config.car_speed_mps))
    for i in range(config.n_moving_cars):
        lane = i % 2  # right-hand traffic: forward (+s) on the outer lane
        offset = centre + (1.8 if lane == 0 else -1.8)
        perimeter = _offset_curve(walk, offset, sign, 2001)[2][-1]
        boxes.mover_offset.append(offset)
        boxes.mover_s0.append(2 * math.pi * (i + builder.uniform(0.0, 0.5)) / config.n_moving_cars)
        boxes.mover_rate.append((1 if lane == 0 else -1) * 2 * math.pi * lane_speed[lane] / perimeter)
        boxes.half.append((0.5 * builder.uniform(4.1, 4.8), 0.5 * builder.uniform(1.7, 1.9), 0.5 * builder.uniform(1.4, 1.65)))
        boxes.kind.append(_CAR)
        boxes.rgb.append(_CAR_COLOURS[builder.integer(0, len(_CAR_COLOURS) - 1)])
    sidewalks = ((config.inner_offset_m + 1.0, -1.0), (1.0, config.curb_offset_m - 0.4), (config.far_curb_offset_m + 0.5, config.outer_offset_m - 1.0))
    for i in range(config.n_pedestrians):
        lo, hi = sidewalks[i % len(sidewalks)]
        offset = builder.uniform(lo, hi)
        perimeter = _offset_curve(walk, offset, sign, 2001)[2][-1]
        direction = 1 if builder.uniform(0, 1) < 0.5 else -1
        boxes.mover_offset.append(offset)
        boxes.mover_s0.append(builder.uniform(0, 2 * math.pi))
        boxes.mover_rate.append(direction * 2 * math.pi * builder.uniform(*config.pedestrian_speed_mps) / perimeter)
        boxes.half.append((0.25, 0.25, 0.5 * builder.uniform(1.6, 1.9)))
        boxes.kind.append(_PEDESTRIAN)
        boxes.rgb.append(tuple(torch.rand(3, generator=gen).mul(0.7).add(0.1).tolist()))


def build_city(walk: Walk, *, seed: int = 0, config: CityConfig = CityConfig()) -> City:
    """The city around ``walk``, deterministic in ``seed`` (a ``torch.Generator``)."""
    gen = torch.Generator().manual_seed(seed)
    sign = loop_orientation(walk)
    builder = _Builder(gen)
    builder.street_side(walk, sign, config.inner_offset_m, config)
    builder.street_side(walk, sign, config.outer_offset_m, config)
    a, b, n, height, s0, columns, building = zip(*builder.quads)
    base, window, spacing, size, sill, door_rate, brick = zip(*builder.styles)

    boxes = _Boxes()
    _park_cars(boxes, builder, walk, sign, config)
    _add_movers(boxes, builder, walk, sign, config, gen)
    half, xy_list, yaw_list, kind, rgb = boxes.half, boxes.xy, boxes.yaw, boxes.kind, boxes.rgb
    mover_offset, mover_s0, mover_rate = boxes.mover_offset, boxes.mover_s0, boxes.mover_rate
    n_static = len(xy_list)
    if not config.movers:  # drawn above all the same, so the ground's texture below is the same
        half, kind, rgb = half[:n_static], kind[:n_static], rgb[:n_static]
        mover_offset, mover_s0, mover_rate = [], [], []
    n_movers = len(mover_s0)
    xy_list += [np.zeros(2)] * n_movers
    yaw_list += [0.0] * n_movers

    ground_lum, ground_origin = _ground(walk, sign, config, gen)
    f64 = {"dtype": torch.float64}
    fields = dict(
        walk=walk,
        outward_sign=sign,
        facade_a=torch.tensor(np.stack(a), **f64),
        facade_b=torch.tensor(np.stack(b), **f64),
        facade_normal=torch.tensor(np.stack(n), **f64),
        facade_height=torch.tensor(height, **f64),
        facade_s0=torch.tensor(s0, dtype=torch.float32),
        facade_columns=torch.tensor(columns, dtype=torch.int64),
        facade_building=torch.tensor(building, dtype=torch.int64),
        building_rgb=torch.tensor(base, dtype=torch.float32),
        window_rgb=torch.tensor(window, dtype=torch.float32),
        window_spacing=torch.tensor(spacing, dtype=torch.float32),
        window_size=torch.tensor(size, dtype=torch.float32),
        window_sill=torch.tensor(sill, dtype=torch.float32),
        door_rate=torch.tensor(door_rate, dtype=torch.float32),
        brick=torch.tensor(brick, dtype=torch.bool),
        box_half=torch.tensor(half, **f64),
        box_xy=torch.tensor(np.stack(xy_list), **f64),
        box_yaw=torch.tensor(yaw_list, **f64),
        box_object_id=torch.cat((torch.zeros(n_static, dtype=torch.int64), torch.arange(1, n_movers + 1))),
        box_kind=torch.tensor(kind, dtype=torch.int64),
        box_rgb=torch.tensor(rgb, dtype=torch.float32),
        mover_offset_m=torch.tensor(mover_offset, **f64),
        mover_s0=torch.tensor(mover_s0, **f64),
        mover_rate=torch.tensor(mover_rate, **f64),
        ground_lum=ground_lum,
        ground_origin=ground_origin,
        ground_resolution_m=config.ground_resolution_m,
        noise=_value_noise(gen),
        seed=seed,
    )
    fields["facade_table"] = _facade_table(fields)
    fields["box_table"] = _box_table(fields)
    return City(**fields)


# --------------------------------------------------------------------------- appearance (float32, [0, 1])


def sample_noise(noise: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """Bilinear sample of the tileable ``noise`` ``(n, n)`` at texel coordinates ``(u, v)``
    (float32, wraps; texel ``(i, j)`` is ``noise[j, i]``)."""
    n = noise.shape[0]
    padded = torch.cat((noise, noise[:1]), 0)
    padded = torch.cat((padded, padded[:, :1]), 1).reshape(-1)  # (n + 1)^2: neighbours never wrap
    u = u - n * torch.floor(u * (1.0 / n))
    v = v - n * torch.floor(v * (1.0 / n))
    i0, j0 = torch.floor(u), torch.floor(v)
    fu, fv = u - i0, v - j0
    # a coordinate a hair below a multiple of n wraps to n itself in float32: texel 0 again
    i0, j0 = torch.remainder(i0, n), torch.remainder(j0, n)
    idx = torch.addcmul(i0, j0, torch.tensor(float(n + 1))).to(torch.int64)  # exact in float32 below 2^24

    def at(offset: int) -> Tensor:
        return padded.index_select(0, idx + offset if offset else idx)

    top = torch.lerp(at(0), at(1), fu)
    bottom = torch.lerp(at(n + 1), at(n + 2), fu)
    return torch.lerp(top, bottom, fv)


def _hash01(a: Tensor, b: Tensor, c: Tensor) -> Tensor:
    """Deterministic pseudo-random value in [0, 1) from three float32 tensors holding
    integers (the classic ``fract(sin(k) * 43758.5453)`` shader hash)."""
    k = torch.sin(a * 12.9898 + b * 78.233 + c * 37.719) * 43758.5453
    return k - torch.floor(k)


def _shade(normal_xy: Tensor) -> Tensor:
    sun = torch.tensor(_SUN_XY, dtype=normal_xy.dtype)
    return (0.82 + 0.18 * (normal_xy @ sun)).to(torch.float32)


# columns of City.facade_table; the two colours are shaded by the facade's orientation
_S0, _SPACING, _HALF_WW, _WH, _SILL, _HEIGHT, _COLUMNS, _DOOR, _BRICK, _BUILDING, _SHADE = range(11)
_WALL_RGB, _WINDOW_RGB = 11, 14
_FRAME_RGB = torch.tensor((0.88, 0.88, 0.85))
_DOOR_RGB = torch.tensor((0.30, 0.18, 0.10))
_LIT_RGB = torch.tensor((0.95, 0.82, 0.5))


def _facade_table(city_fields: dict) -> Tensor:
    """Per-facade texturing attributes ``(17, F)`` float32, planar (one row per attribute),
    so texturing gathers once per pixel and reads contiguous rows."""
    b = city_fields["facade_building"]
    shade = _shade(city_fields["facade_normal"])
    scalars = torch.stack(
        (
            city_fields["facade_s0"],
            city_fields["window_spacing"][b],
            0.5 * city_fields["window_size"][b, 0],
            city_fields["window_size"][b, 1],
            city_fields["window_sill"][b],
            city_fields["facade_height"].to(torch.float32),
            city_fields["facade_columns"].to(torch.float32),
            city_fields["door_rate"][b],
            city_fields["brick"][b].to(torch.float32),
            b.to(torch.float32),
            shade,
        ),
        -1,
    )
    wall = city_fields["building_rgb"][b] * shade[:, None]
    window = city_fields["window_rgb"][b] * shade[:, None]
    return torch.cat((scalars, wall, window), -1).T.contiguous()


_HALF = torch.tensor(0.5)


def _ramp(d: Tensor, inv_width: Tensor) -> Tensor:
    """Fraction of a pixel footprint (``1 / inv_width`` wide) on the inside of an edge at
    signed distance ``d`` (positive inside): a box-filtered step."""
    return torch.addcmul(_HALF, d, inv_width).clamp_(0, 1)


def _band(z: Tensor, lo: Tensor | float, hi: Tensor | float, inv_width: Tensor) -> Tensor:
    """Box-filtered indicator of ``lo < z < hi``."""
    return _ramp(torch.minimum(z - lo, hi - z), inv_width)


def facade_colour(
    city: City, facade: Tensor, s_m: Tensor, z_m: Tensor, footprint_s: Tensor | None = None, footprint_z: Tensor | None = None
) -> Tensor:
    """Colour ``(N, 3)`` of facade points: facade index ``(N,)``, distance ``s_m`` from its
    endpoint ``a`` along the facade and height ``z_m`` (float32).

    A window grid (columns of ``spacing``, one row per storey above the ground
    storey, with frames), doors and shop windows in the ground storey, cornices
    between storeys, a parapet band, bricks on some buildings and value-noise grain.
    ``footprint_s``, ``footprint_z`` ``(N,)``: the pixel's extent on the facade (m);
    edges are box-filtered over it and the brick pattern fades where it would alias
    (default: 1 mm, i.e. hard edges). The colour is a coverage-weighted sum of the
    materials (wall, frame, glass, lit glass, shop window, door).
    """
    fs = footprint_s.clamp_min(1e-3) if footprint_s is not None else torch.full_like(s_m, 1e-3)
    fz = footprint_z.clamp_min(1e-3) if footprint_z is not None else torch.full_like(s_m, 1e-3)
    ifs, ifz = 1.0 / fs, 1.0 / fz
    attr = city.facade_table.index_select(1, facade)  # (17, N)
    s = s_m + attr[_S0]
    z = z_m
    spacing = attr[_SPACING]
    column = torch.floor(s / spacing)
    xs = -(s - (column + 0.5) * spacing).abs()  # minus the distance from the column's centre line
    storey = torch.floor(z * (1.0 / STOREY_M))
    zs = z - storey * STOREY_M
    half_ww, wh, sill, height = attr[_HALF_WW], attr[_WH], attr[_SILL], attr[_HEIGHT]
    in_grid = (column >= 0) & (column < attr[_COLUMNS]) & (z < height - 1.0)
    upper = (in_grid & (storey >= 1)).to(torch.float32)
    ground = (in_grid & (storey == 0)).to(torch.float32)
    rnd = _hash01(attr[_BUILDING], column, storey)
    window = upper * _ramp(xs + half_ww, ifs) * _band(zs, sill, sill + wh, ifz)
    frame = upper * _ramp(xs + (half_ww + 0.12), ifs) * _band(zs, sill - 0.15, sill + wh + 0.1, ifz)
    is_door = ground * (rnd < attr[_DOOR])
    door = is_door * _ramp(xs + 0.65, ifs) * _ramp(2.3 - zs, ifz)
    shop = (ground - is_door) * _ramp(xs + 0.42 * spacing, ifs) * _band(zs, 0.7, 2.5, ifz)
    cornice = torch.maximum((storey >= 1) * _ramp(0.2 - zs, ifz), _ramp(z - (height - 0.5), ifz))

    grain = sample_noise(city.noise, s * 6.0, z * 6.0) - 0.5
    courses = z * (1.0 / 0.075)
    row = torch.floor(courses)
    half_bond = torch.frac(row * 0.5) * 0.5  # alternate courses shift by half a brick (0.125 m)
    mortar = ((courses - row) < 0.18) | (torch.frac(s * 4.0 + half_bond) < 0.08)
    brick = attr[_BRICK] * (1.0 - torch.maximum(fs, fz) * (1.0 / 0.03)).clamp_(0, 1)  # fades before it aliases
    lit = (rnd > 0.92).to(torch.float32)
    # coverage weights (frame contains window; door and shop are disjoint, in the ground storey)
    w_wall = 1.0 - frame - door - shop
    w_frame = frame - window
    shade = attr[_SHADE]
    c_wall = w_wall * (0.92 + 0.25 * grain) * (1.0 - 0.18 * brick * mortar) * (1 - 0.25 * cornice)
    c_window = window * (1 - lit) * (0.6 + 0.8 * rnd) + shop * 1.3
    c_frame = w_frame * shade
    c_door = door * (1.0 + 0.4 * grain) * shade
    c_lit = window * lit * shade
    offset = shade * (
        w_wall * 0.25 * cornice + window * (1 - lit) * 0.12 * (zs - sill) / wh + w_frame * 0.1 * grain + shop * 0.15 * (rnd + grain)
    )
    colour = attr[_WALL_RGB : _WALL_RGB + 3] * c_wall
    colour.addcmul_(attr[_WINDOW_RGB : _WINDOW_RGB + 3], c_window)
    colour.addcmul_(c_frame, _FRAME_RGB[:, None])
    colour.addcmul_(c_door, _DOOR_RGB[:, None])
    colour.addcmul_(c_lit, _LIT_RGB[:, None])
    colour += offset
    return colour.clamp_(0, 1).T  # (N, 3) view of the planar (3, N) result


def ground_colour(city: City, xy: Tensor) -> Tensor:
    """Colour ``(N, 3)`` of ground points ``xy`` ``(N, 2)`` (float32 or float64, world metres)."""
    h, w = city.ground_lum.shape
    x, y = xy[:, 0].to(torch.float32), xy[:, 1].to(torch.float32)
    scale = 1.0 / city.ground_resolution_m
    u = ((x - float(city.ground_origin[0])) * scale).clamp_(0, w - 1.001)
    v = ((y - float(city.ground_origin[1])) * scale).clamp_(0, h - 1.001)
    u0, v0 = u.floor(), v.floor()
    fu, fv = u - u0, v - v0
    idx = v0.to(torch.int64) * w + u0.to(torch.int64)
    flat = city.ground_lum.reshape(-1)

    def at(i: Tensor) -> Tensor:
        return flat.index_select(0, i)

    lum = torch.lerp(torch.lerp(at(idx), at(idx + 1), fu), torch.lerp(at(idx + w), at(idx + w + 1), fu), fv)
    lum = lum + 0.02 * (sample_noise(city.noise, x * 40.0, y * 40.0) - 0.5)
    return (lum.unsqueeze(-1) * torch.tensor((0.95, 0.97, 1.0))).clamp_(0, 1)


def _box_table(city_fields: dict) -> Tensor:
    """Per-box texturing attributes ``(B, 11)`` float32: half extents, colour, kind and the
    shade of the faces +x, -x, +y, -y (by the static yaw; movers' shades are fixed in
    their body frame, so a mover's appearance stays constant as it turns)."""
    yaw = city_fields["box_yaw"]
    c, s = yaw.cos(), yaw.sin()
    normals = torch.stack((torch.stack((c, s), -1), torch.stack((-c, -s), -1), torch.stack((-s, c), -1), torch.stack((s, -c), -1)), 1)
    shade = _shade(normals.reshape(-1, 2)).reshape(-1, 4)
    return torch.cat(
        (
            city_fields["box_half"].to(torch.float32),
            city_fields["box_rgb"],
            city_fields["box_kind"].to(torch.float32).unsqueeze(-1),
            shade,
        ),
        -1,
    )


def box_colour(city: City, box: Tensor, local: Tensor) -> Tensor:
    """Colour ``(N, 3)`` of box points: box index ``(N,)``, point in the box frame ``(N, 3)``.

    Cars: body colour, a dark glass cabin, wheels, lights, snow on the roof;
    pedestrians: head, jacket (the box colour), dark trousers; value-noise grain.
    """
    attr = city.box_table.index_select(0, box)
    hx, hy, hz = attr[:, 0], attr[:, 1], attr[:, 2]
    p = local.to(torch.float32)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    ax, ay = x.abs(), y.abs()
    rx, ry, rz = ax / hx, ay / hy, (z - hz).abs() / hz
    top = (rz >= rx) & (rz >= ry) & (z > hz)
    side = ~top & (ry >= rx)  # the long faces (normal ±y)
    end = ~top & ~side  # front / back (normal ±x)
    height = 2 * hz
    grain = (sample_noise(city.noise, (x + y) * 8.0 + 31.0, z * 8.0) - 0.5).unsqueeze(-1)
    colour = attr[:, 3:6] * (0.92 + 0.3 * grain)
    car = attr[:, 6] == _CAR
    ped = ~car
    glass = car & ~top & (z > 0.58 * height) & ((side & (rx < 0.62)) | (end & (ry < 0.82)))
    wheel = car & side & (z < 0.38 * height) & ((ax - 0.68 * hx).abs() < 0.36)
    light = car & end & (z > 0.42 * height) & (z < 0.55 * height) & (ry > 0.62)
    head = ped & (z > height - 0.27)
    legs = ped & (z < 0.85)
    for mask, rgb, amount in (
        (glass, (0.12, 0.15, 0.2), 0.15),
        (wheel, (0.06, 0.06, 0.06), 0.05),
        (car & top, (0.93, 0.95, 0.98), 0.1),
        (head, (0.85, 0.68, 0.55), 0.1),
        (legs, (0.12, 0.12, 0.16), 0.1),
    ):
        colour = torch.where(mask.unsqueeze(-1), torch.tensor(rgb) + amount * grain, colour)
    front_light = torch.where((x > 0).unsqueeze(-1), torch.tensor((0.95, 0.95, 0.85)), torch.tensor((0.8, 0.1, 0.1)))
    colour = torch.where(light.unsqueeze(-1), front_light, colour)
    shade = torch.where(
        top, 1.0, torch.where(side, torch.where(y > 0, attr[:, 9], attr[:, 10]), torch.where(x > 0, attr[:, 7], attr[:, 8]))
    )
    return (colour * shade.unsqueeze(-1)).clamp_(0, 1)


def sky_colour(direction_w: Tensor) -> Tensor:
    """Overcast sky ``(N, 3)`` for world ray directions ``(N, 3)`` (any length)."""
    x, y, z = direction_w.to(torch.float32).unbind(-1)
    elevation = (z * torch.rsqrt(x * x + y * y + z * z)).clamp_(0, 1).sqrt_().unsqueeze(-1)
    horizon = torch.tensor((0.84, 0.86, 0.89))
    zenith = torch.tensor((0.60, 0.68, 0.80))
    return torch.addcmul(horizon, elevation, zenith - horizon)
