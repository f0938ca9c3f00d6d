"""Sparse flow: Shi–Tomasi corners tracked by pyramidal Lucas–Kanade (the paper's sparse baseline).

:class:`ShiTomasiLK` detects up to ``max_corners`` corners in image 1
(``cv2.goodFeaturesToTrack``: quality 0.01 of the best corner's min-eigenvalue,
8 px apart, 7x7 structure-tensor block, none within ``border_px`` of the edge),
tracks them to image 2 and back with ``cv2.calcOpticalFlowPyrLK`` (21x21 window,
3 pyramid levels), and keeps the points that both passes found and whose
forward–backward error ``e_fb = |x - LK_back(LK_fwd(x))|`` is below
``fb_threshold_px`` and whose end point lies inside image 2.

σ per point, the same for both components (px)::

    σ = sqrt(σ0² + (α e_fb)² + (γ e_LK)²)

with ``e_LK`` LK's own error measure: the mean absolute gray-level difference
(0–255) between the 21x21 patches around the point in image 1 and around its
match in image 2. Defaults ``σ0 = 0.1 px``, ``α = 1``, ``γ = 0.02 px`` per gray
level; with these 67 % of the component errors of the kept points lie within
±σ on the Middlebury pair of :mod:`flowins.flow.flo` (84 % within ±2σ) and 84 %
on the simulator pair (94 % within ±2σ). A heuristic, not a calibrated likelihood.

A single pair's points get track ids ``0 .. N-1``. :func:`track_sequence` runs the
tracker over consecutive frames and keeps ids across them: the end points of
pair ``k`` are handed to pair ``k + 1`` as seeds (tracked first, so a surviving
track continues from exactly where it ended), fresh corners at least
``min_distance_px`` from every seed top the set up to ``max_corners``, and a
point of pair ``k + 1`` takes the id of the pair-``k`` end point it lies within
``match_radius_px`` (0.5 px) of; any other point opens a new id.

OpenCV on CPU, not differentiable.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import NamedTuple

import cv2
import numpy as np
import torch
from torch import Tensor

from flowins.data.sequence import CameraFrames, Tracks
from flowins.flow.base import SparseFlowProvider, SparseFlowResult, prepare_pair
from flowins.flow.classical import to_gray_u8

__all__ = ["ShiTomasiLK", "TrackedSequence", "track_sequence"]


class ShiTomasiLK(SparseFlowProvider):
    """Shi–Tomasi corners + forward–backward pyramidal LK (see module docstring).

    Args:
        max_corners, quality_level, min_distance_px, block_size: ``cv2.goodFeaturesToTrack``.
        border_px: no corner closer than this to the image edge.
        win_size_px: LK window side; ``levels``: pyramid levels (OpenCV's ``maxLevel = levels - 1``).
        fb_threshold_px: largest forward–backward error kept.
        sigma0_px, fb_gain, lk_gain: σ0, α and γ of the σ model.
        max_iterations, epsilon: LK's termination criteria.
    """

    #: :func:`track_sequence` may pass ``seeds_px``
    supports_seeds = True

    def __init__(
        self,
        *,
        max_corners: int = 300,
        quality_level: float = 0.01,
        min_distance_px: float = 8.0,
        block_size: int = 7,
        border_px: int = 10,
        win_size_px: int = 21,
        levels: int = 3,
        fb_threshold_px: float = 1.0,
        sigma0_px: float = 0.1,
        fb_gain: float = 1.0,
        lk_gain: float = 0.02,
        max_iterations: int = 30,
        epsilon: float = 0.01,
    ):
        if max_corners < 1 or not 0 < quality_level < 1 or min_distance_px < 0 or block_size < 3:
            raise ValueError(
                f"ShiTomasiLK: max_corners={max_corners}, quality_level={quality_level}, "
                f"min_distance_px={min_distance_px}, block_size={block_size}; expected >= 1, in (0, 1), >= 0, >= 3"
            )
        if win_size_px < 3 or levels < 1 or fb_threshold_px <= 0 or border_px < 0:
            raise ValueError(
                f"ShiTomasiLK: win_size_px={win_size_px}, levels={levels}, fb_threshold_px={fb_threshold_px}, "
                f"border_px={border_px}; expected >= 3, >= 1, > 0, >= 0"
            )
        if sigma0_px <= 0 or fb_gain < 0 or lk_gain < 0:
            raise ValueError(
                f"ShiTomasiLK: sigma0_px={sigma0_px}, fb_gain={fb_gain}, lk_gain={lk_gain}; expected > 0, >= 0, >= 0"
            )
        self.max_corners = int(max_corners)
        self.quality_level = float(quality_level)
        self.min_distance_px = float(min_distance_px)
        self.block_size = int(block_size)
        self.border_px = int(border_px)
        self.win_size_px = int(win_size_px)
        self.levels = int(levels)
        self.fb_threshold_px = float(fb_threshold_px)
        self.sigma0_px = float(sigma0_px)
        self.fb_gain = float(fb_gain)
        self.lk_gain = float(lk_gain)
        self.criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, int(max_iterations), float(epsilon))

    def __repr__(self) -> str:
        return (
            f"ShiTomasiLK(max_corners={self.max_corners}, quality_level={self.quality_level}, "
            f"min_distance_px={self.min_distance_px}, block_size={self.block_size}, border_px={self.border_px}, "
            f"win_size_px={self.win_size_px}, levels={self.levels}, fb_threshold_px={self.fb_threshold_px})"
        )

    def detect(self, gray: np.ndarray, *, avoid_px: np.ndarray | None = None, limit: int | None = None) -> np.ndarray:
        """Corners ``(N, 2)`` float32 ``(u, v)`` of ``gray`` ``(H, W)`` uint8, none within
        ``min_distance_px`` of the points ``avoid_px`` ``(M, 2)``; at most ``limit`` (default ``max_corners``)."""
        limit = self.max_corners if limit is None else int(limit)
        h, w = gray.shape
        if limit <= 0 or h <= 2 * self.border_px or w <= 2 * self.border_px:
            return np.zeros((0, 2), np.float32)
        mask = np.zeros((h, w), np.uint8)
        mask[self.border_px : h - self.border_px, self.border_px : w - self.border_px] = 255
        if avoid_px is not None:
            radius = max(int(np.ceil(self.min_distance_px)), 1)
            for u, v in np.rint(avoid_px).astype(int):
                cv2.circle(mask, (int(u), int(v)), radius, 0, -1)
        corners = cv2.goodFeaturesToTrack(
            gray, maxCorners=limit, qualityLevel=self.quality_level, minDistance=self.min_distance_px,
            mask=mask, blockSize=self.block_size,
        )
        return np.zeros((0, 2), np.float32) if corners is None else corners.reshape(-1, 2).astype(np.float32)

    def track_gray(
        self, gray1: np.ndarray, gray2: np.ndarray, *, seeds_px: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Track one ``(H, W)`` uint8 pair -> ``points (N, 2)``, ``flow (N, 2)``, ``sigma (N, 2)`` float32.

        ``seeds_px`` ``(M, 2)``: points to track first (in this order); fresh corners
        fill up to ``max_corners``. Seeds that are lost do not appear in the output.
        """
        seeds = np.zeros((0, 2), np.float32) if seeds_px is None else np.asarray(seeds_px, np.float32).reshape(-1, 2)
        fresh = self.detect(gray1, avoid_px=seeds, limit=self.max_corners - len(seeds))
        p1 = np.concatenate([seeds, fresh]).astype(np.float32)
        empty = np.zeros((0, 2), np.float32)
        if len(p1) == 0:
            return empty, empty, empty
        lk = dict(winSize=(self.win_size_px, self.win_size_px), maxLevel=self.levels - 1, criteria=self.criteria)
        p2, ok_f, err = cv2.calcOpticalFlowPyrLK(gray1, gray2, p1.reshape(-1, 1, 2), None, **lk)
        p1b, ok_b, _ = cv2.calcOpticalFlowPyrLK(gray2, gray1, p2, None, **lk)
        p2, p1b = p2.reshape(-1, 2), p1b.reshape(-1, 2)
        e_fb = np.linalg.norm(p1b - p1, axis=-1)
        h, w = gray2.shape
        inside = (p2[:, 0] >= 0) & (p2[:, 0] <= w - 1) & (p2[:, 1] >= 0) & (p2[:, 1] <= h - 1)
        keep = (ok_f.ravel() == 1) & (ok_b.ravel() == 1) & (e_fb < self.fb_threshold_px) & inside
        keep &= np.isfinite(p2).all(-1)
        e_fb, e_lk = e_fb[keep].astype(np.float64), err.ravel()[keep].astype(np.float64)
        s = np.sqrt(self.sigma0_px**2 + (self.fb_gain * e_fb) ** 2 + (self.lk_gain * e_lk) ** 2).astype(np.float32)
        return p1[keep], (p2 - p1)[keep], np.stack([s, s], -1)

    def track(self, image1: Tensor, image2: Tensor, *, seeds_px: Tensor | None = None) -> SparseFlowResult:
        """``(1, 3, H, W)`` float RGB in [0, 1] pair -> :class:`SparseFlowResult` with ids ``0 .. N-1``."""
        seeds = None if seeds_px is None else torch.as_tensor(seeds_px).detach().cpu().numpy()
        points, flow, sigma = self.track_gray(to_gray_u8(image1)[0], to_gray_u8(image2)[0], seeds_px=seeds)
        return SparseFlowResult(
            torch.from_numpy(points), torch.from_numpy(flow), torch.from_numpy(sigma), torch.arange(len(points))
        )


class TrackedSequence(NamedTuple):
    """What :func:`track_sequence` returns: ``tracks`` (every track's pixel in every frame it
    was seen) and ``pairs``, one :class:`SparseFlowResult` per consecutive pair whose
    ``track_id`` are the ids of ``tracks``."""

    tracks: Tracks
    pairs: list[SparseFlowResult]


def _match(points: np.ndarray, previous: np.ndarray, radius: float) -> np.ndarray:
    """For each of ``points`` ``(N, 2)``: the index of the ``previous`` ``(M, 2)`` point within
    ``radius`` (nearest first, each used once), or -1."""
    out = np.full(len(points), -1, np.int64)
    if len(points) == 0 or len(previous) == 0:
        return out
    d = np.linalg.norm(points[:, None, :] - previous[None, :, :], axis=-1)
    i, j = np.nonzero(d <= radius)
    used_i, used_j = set(), set()
    for k in np.argsort(d[i, j], kind="stable"):
        if i[k] not in used_i and j[k] not in used_j:
            out[i[k]] = j[k]
            used_i.add(i[k])
            used_j.add(j[k])
    return out


def track_sequence(
    frames: CameraFrames | Sequence | Iterable,
    provider: SparseFlowProvider,
    *,
    t_s: Sequence[float] | Tensor | None = None,
    match_radius_px: float = 0.5,
    name: str = "tracks",
) -> TrackedSequence:
    """Track features through consecutive frames with ids kept across pairs (see module docstring).

    Args:
        frames: a :class:`~flowins.data.sequence.CameraFrames` (times from it) or a
            sequence of images in any form :func:`~flowins.flow.base.prepare_pair` takes.
        provider: a :class:`SparseFlowProvider`; seeds are passed when it has
            ``supports_seeds`` (otherwise ids continue only where re-detected corners
            fall within ``match_radius_px`` of a previous end point).
        t_s: frame times ``(F,)`` s; default ``frames.t_s`` or ``0, 1, 2, ...``.

    Returns:
        :class:`TrackedSequence`; its ``tracks`` rows are ``(t, track_id, u, v)`` grouped by frame,
        ready for ``tracks.csv``.
    """
    if isinstance(frames, CameraFrames):
        images: Iterable = (frames.read(i) for i in range(len(frames)))
        n_frames = len(frames)
        if t_s is None:
            t_s = frames.t_s
    else:
        images = list(frames)
        n_frames = len(images)
    if n_frames < 2:
        raise ValueError(f"track_sequence: {n_frames} frame(s); expected at least 2")
    times = torch.arange(n_frames, dtype=torch.float64) if t_s is None else torch.as_tensor(t_s, dtype=torch.float64)
    if times.shape != (n_frames,):
        raise ValueError(f"track_sequence: t_s has shape {tuple(times.shape)}; expected ({n_frames},), one per frame")

    rows_t, rows_id, rows_uv = [], [], []
    pairs: list[SparseFlowResult] = []
    ends = np.zeros((0, 2), np.float32)  # end points (frame k) of pair k-1 ...
    end_ids = np.zeros(0, np.int64)  # ... and their ids
    next_id = 0
    iterator = iter(images)
    previous = next(iterator)
    for k, current in enumerate(iterator):
        a, b = prepare_pair(previous, current)
        if a.shape[0] != 1:
            raise ValueError(f"track_sequence: frame {k} is a batch of {a.shape[0]}; expected one image per frame")
        if getattr(provider, "supports_seeds", False):
            result = provider.track(a, b, seeds_px=torch.from_numpy(ends))
        else:
            result = provider.track(a, b)
        points = result.points.numpy().astype(np.float32)
        match = _match(points, ends, match_radius_px)
        ids = np.full(len(points), -1, np.int64)
        ids[match >= 0] = end_ids[match[match >= 0]]
        fresh = ids < 0
        ids[fresh] = np.arange(next_id, next_id + int(fresh.sum()))
        next_id += int(fresh.sum())
        # frame k: every point seen there: the previous pair's end points and this pair's new points
        frame_uv = np.concatenate([ends, points[fresh]])
        frame_id = np.concatenate([end_ids, ids[fresh]])
        rows_t.append(np.full(len(frame_id), float(times[k])))
        rows_id.append(frame_id)
        rows_uv.append(frame_uv)
        pairs.append(SparseFlowResult(result.points, result.flow, result.sigma, torch.from_numpy(ids)))
        ends = (points + result.flow.numpy()).astype(np.float32)
        end_ids = ids
        previous = current
    rows_t.append(np.full(len(end_ids), float(times[n_frames - 1])))
    rows_id.append(end_ids)
    rows_uv.append(ends)
    tracks = Tracks(
        torch.from_numpy(np.concatenate(rows_t)),
        torch.from_numpy(np.concatenate(rows_id)),
        torch.from_numpy(np.concatenate(rows_uv).astype(np.float64)),
        name=name,
    )
    return TrackedSequence(tracks, pairs)
