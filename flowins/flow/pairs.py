"""Flow over a whole recording: one set of flow points per frame pair, cached on disk.

This is the stage between the flow providers and the measurement model
(``frames -> flow points per pair -> filter``):

* :func:`dense_pairs` runs a dense provider (SpyNet, FlowNet 2.0, DIS) on the pairs
  ``(k, k + step)`` and keeps the field on a grid of candidate pixels
  (:func:`flowins.flow.points.grid_candidates`); the filter picks its
  points among them at its current state.
* :func:`sparse_pairs` runs the paper's sparse baseline (Shi–Tomasi + Lucas–Kanade)
  on the same pairs.
* :func:`track_pairs` turns a sequence's precomputed ``tracks.csv`` into pairs.

:class:`FlowPairs` saves to and loads from one ``.npz`` file, so the expensive
network passes run once per recording and provider setting.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from flowins.progress import Progress, progress as track_progress
from flowins.cache import content_key, library_versions, source_digest
from flowins.flow.base import FlowResult, resize_flow
from flowins.flow.points import FlowPoints, grid_candidates

FORMAT_VERSION = 1
_REQUIRED = ("uv1_px", "flow_px", "sigma_px")
_OPTIONAL = ("dropout_unit_px", "floor_px")  # the dropout moments, when the provider gives them


@dataclass
class FlowPairs:
    """Flow points of ``P`` frame pairs: pair ``k`` goes from ``t1_s[k]`` to ``t2_s[k]``."""

    t1_s: Tensor  # (P,) float64
    t2_s: Tensor  # (P,)
    points: list[FlowPoints]
    kind: str  # "dense" | "sparse"
    description: str = ""

    def __post_init__(self) -> None:
        if self.t1_s.shape != self.t2_s.shape or self.t1_s.ndim != 1 or len(self.points) != self.t1_s.shape[0]:
            raise ValueError(
                f"FlowPairs: t1 {tuple(self.t1_s.shape)}, t2 {tuple(self.t2_s.shape)} and {len(self.points)} point sets "
                "must all have one entry per pair"
            )
        if bool((self.t2_s <= self.t1_s).any()):
            k = int(torch.nonzero(self.t2_s <= self.t1_s)[0])
            raise ValueError(f"FlowPairs: pair {k} ends at {float(self.t2_s[k])} s, not after its start {float(self.t1_s[k])} s")

    def __len__(self) -> int:
        return len(self.points)

    def undistorted(self, camera) -> FlowPairs:
        """The points in the ideal pinhole image of ``camera`` (a
        :class:`~flowins.data.sequence.PinholeCamera`): both ends of every flow vector
        are undistorted (radial-tangential); ``σ`` is kept. Without distortion, ``self``."""
        if not any(camera.distortion):
            return self
        points = []
        for p in self.points:
            uv1 = ideal_pixels(p.uv1_px, camera)
            points.append(FlowPoints(uv1, ideal_pixels(p.uv1_px + p.flow_px, camera) - uv1, *p[2:]))
        return FlowPairs(self.t1_s, self.t2_s, points, self.kind, self.description)

    def at_dropout_rate(self, p: float | Tensor) -> FlowPairs:
        """The pairs with every point's σ at dropout rate ``p`` (:meth:`FlowPoints.at_dropout_rate`)."""
        return FlowPairs(self.t1_s, self.t2_s, [pts.at_dropout_rate(p) for pts in self.points], self.kind,
                         self.description)

    def select(self, keep: Tensor) -> FlowPairs:
        """The pairs where the bool mask ``keep`` ``(P,)`` is true."""
        index = torch.nonzero(keep).squeeze(-1).tolist()
        return FlowPairs(self.t1_s[keep], self.t2_s[keep], [self.points[i] for i in index], self.kind, self.description)

    def save(self, path: str | Path) -> None:
        """One ``.npz``: times, per-pair counts and the concatenated points."""
        counts = np.array([len(p) for p in self.points], np.int64)
        cat = lambda field: (
            np.concatenate([getattr(p, field).detach().cpu().numpy() for p in self.points]) if self.points
            else np.zeros((0, 2))
        ).astype(np.float32)
        optional = [f for f in _OPTIONAL if self.points and all(getattr(p, f) is not None for p in self.points)]
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.partial.npz")  # one per process: no two write one file
        np.savez_compressed(
            tmp, version=FORMAT_VERSION, t1_s=self.t1_s.cpu().numpy(), t2_s=self.t2_s.cpu().numpy(), counts=counts,
            **{f: cat(f) for f in (*_REQUIRED, *optional)},
            kind=self.kind, description=self.description,
        )
        tmp.replace(path)

    @classmethod
    def load(cls, path: str | Path) -> FlowPairs:
        path = Path(path)
        with np.load(path, allow_pickle=False) as z:
            if "version" not in z or int(z["version"]) != FORMAT_VERSION:
                raise ValueError(f"{path}: not a flowins flow-pairs file of format version {FORMAT_VERSION}")
            counts = z["counts"]
            edges = np.concatenate(([0], np.cumsum(counts)))
            # in row order whatever order the file holds (a file written from column-major points)
            arrays = {k: torch.from_numpy(np.ascontiguousarray(z[k])).double() for k in (*_REQUIRED, *_OPTIONAL) if k in z}
            points = [
                FlowPoints(**{k: a[edges[i] : edges[i + 1]] for k, a in arrays.items()})
                for i in range(len(counts))
            ]
            return cls(torch.from_numpy(z["t1_s"]), torch.from_numpy(z["t2_s"]), points, str(z["kind"]), str(z["description"]))


def pair_indices(n_frames: int, step: int) -> list[tuple[int, int]]:
    """``(k, k + step)`` for ``k = 0, step, 2 step, ...``: consecutive pairs that chain."""
    if step < 1:
        raise ValueError(f"frame step must be >= 1, got {step}")
    if n_frames < step + 1:
        raise ValueError(f"{n_frames} frame(s) make no pair with step {step}")
    return [(k, k + step) for k in range(0, n_frames - step, step)]


#: the code that turns frames into flow pairs: part of every cache key
def ideal_pixels(uv_px: Tensor, camera) -> Tensor:
    """Pixels ``(..., 2)`` of ``camera``'s raw image (a :class:`~flowins.data.sequence.PinholeCamera`)
    in its ideal pinhole image: the radial-tangential distortion removed."""
    from flowins.geometry.camera import undistort

    f = torch.tensor([camera.fx, camera.fy], dtype=torch.float64)
    c = torch.tensor([camera.cx, camera.cy], dtype=torch.float64)
    return undistort((uv_px - c) / f, tuple(camera.distortion)) * f + c


FLOW_CODE = ("flowins.flow", "flowins.data.sequence")


def cache_key(**parts: Any) -> str:
    """A short content key of what produces a :class:`FlowPairs`: ``parts`` (the
    recording's content key, the provider's settings and its ``nn.Module`` for its
    weights, ...), the file format, flowins' flow code and the numeric libraries' versions."""
    return content_key({"format": FORMAT_VERSION, "code": source_digest(*FLOW_CODE), "libraries": library_versions(),
                        **parts})


def cached(path: Path | None, compute: Callable[[], FlowPairs]) -> FlowPairs:
    """``FlowPairs.load(path)`` if it exists, else ``compute()`` and save it there."""
    if path is not None and path.is_file():
        return FlowPairs.load(path)
    pairs = compute()
    if path is not None:
        pairs.save(path)
    return pairs


def read_frame(frames, index: int) -> Tensor:
    """Frame ``index`` of ``frames`` as a ``(H, W, 3)`` uint8 tensor (readers may return numpy)."""
    image = frames.read(index)
    return image if isinstance(image, Tensor) else torch.from_numpy(np.ascontiguousarray(image))


def run_provider(provider: Callable, first: Tensor, second: Tensor, scale: float = 1.0) -> FlowResult:
    """``provider`` on ``(B, H, W, 3)`` uint8 images resized by ``scale``; the
    :class:`~flowins.flow.base.FlowResult` (flow, σ and its parts) at full size."""
    if scale == 1.0:
        return provider(first, second)

    H, W = first.shape[1:3]
    size = (max(8, round(H * scale)), max(8, round(W * scale)))

    def shrink(images: Tensor) -> Tensor:
        x = images.permute(0, 3, 1, 2).float() / 255.0
        return F.interpolate(x, size=size, mode="area")

    result = provider(shrink(first), shrink(second))
    grow = lambda x: None if x is None else resize_flow(x, (H, W)).abs()
    return FlowResult(resize_flow(result.flow, (H, W)), grow(result.sigma), None, grow(result.dropout_unit),
                      grow(result.floor))


#: frame pairs between two returns of freed heap memory to the system in the flow loops
RELEASE_EVERY = 64


@functools.cache
def _malloc_trim():
    """glibc's ``malloc_trim``, or None on other C libraries (macOS, Windows, musl)."""
    name = ctypes.util.find_library("c")
    try:
        trim = getattr(ctypes.CDLL(name), "malloc_trim") if name else None
    except (OSError, AttributeError):
        return None
    return trim


def release_freed_memory() -> None:
    """Hand heap memory that is free but still held by the C allocator back to the system.

    The flow loops keep a few kB of points per pair while every pair allocates and frees
    megabytes of images and pyramids; glibc raises its mmap threshold after such frees,
    so the temporaries come from the heap and the small survivors pin it: the first
    ``python evaluate.py`` peaked at 7.3 GB, almost all of it the sparse pass's heap.
    ``malloc_trim(0)`` every :data:`RELEASE_EVERY` pairs keeps it flat (1.65 GB peak; a
    no-op on other C libraries).
    """
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


def dense_pairs(
    frames,
    provider: Callable,
    *,
    step: int = 1,
    stride_px: int = 8,
    border_px: int = 8,
    batch_size: int = 4,
    input_scale: float = 1.0,
    progress: bool = True,
    description: str = "",
) -> FlowPairs:
    """Run a dense provider on the pairs ``(k, k + step)`` of ``frames`` and keep grid candidates.

    Args:
        frames: a :class:`~flowins.data.sequence.CameraFrames` (``read(i)`` -> ``(H, W, 3)`` uint8, ``t_s``).
        provider: ``provider(image1, image2) -> FlowResult`` (a :class:`~flowins.flow.base.FlowProvider`
            or :class:`~flowins.flow.classical.DISProvider`).
        step: frame step of a pair (1: consecutive frames).
        stride_px, border_px: candidate grid (:func:`grid_candidates`).
        batch_size: pairs per provider call.
        input_scale: the provider sees the images resized by this factor (area
            interpolation); its flow and σ are resized back and scaled by ``1 / input_scale``
            (:func:`~flowins.flow.base.resize_flow`), so points and flow are always in
            pixels of the recording.
    """
    if not 0.0 < input_scale <= 1.0:
        raise ValueError(f"dense_pairs: input_scale must be in (0, 1], got {input_scale}")
    pairs = pair_indices(len(frames), step)
    t = torch.as_tensor(frames.t_s, dtype=torch.float64)
    points: list[FlowPoints] = []
    cache: dict[int, Tensor] = {}
    bar = Progress(total=len(pairs), description=f"dense flow ({description or type(provider).__name__})",
                   unit="pair", enabled=progress)
    for start in range(0, len(pairs), batch_size):
        chunk = pairs[start : start + batch_size]
        need = sorted({i for pair in chunk for i in pair})
        cache = {i: cache[i] if i in cache else read_frame(frames, i) for i in need}
        first = torch.stack([cache[a] for a, _ in chunk])
        second = torch.stack([cache[b] for _, b in chunk])
        result = run_provider(provider, first, second, input_scale)
        for j in range(len(chunk)):
            item = lambda x: None if x is None else x[j].to("cpu", torch.float64)  # pairs are data: on the CPU
            points.append(grid_candidates(item(result.flow), item(result.sigma), stride_px=stride_px,
                                          border_px=border_px, dropout_unit_px=item(result.dropout_unit),
                                          floor_px=item(result.floor)))
        cache = {chunk[-1][1]: cache[chunk[-1][1]]}
        bar.update(len(chunk))
        if (start // batch_size) % max(1, RELEASE_EVERY // batch_size) == 0:
            release_freed_memory()
    bar.close()
    index = torch.tensor(pairs)
    return FlowPairs(t[index[:, 0]], t[index[:, 1]], points, "dense", description)


def sparse_pairs(
    frames, tracker: Callable, *, step: int = 1, progress: bool = True, description: str = ""
) -> FlowPairs:
    """Run a sparse provider (``tracker(image1, image2) -> SparseFlowResult``) on the pairs ``(k, k + step)``."""
    pairs = pair_indices(len(frames), step)
    t = torch.as_tensor(frames.t_s, dtype=torch.float64)
    points = []
    previous: tuple[int, Tensor] | None = None
    for k, (a, b) in enumerate(track_progress(pairs, description=f"sparse flow ({description or type(tracker).__name__})",
                                              unit="pair", enabled=progress)):
        if k % RELEASE_EVERY == 0:
            release_freed_memory()
        image1 = previous[1] if previous is not None and previous[0] == a else read_frame(frames, a)
        image2 = read_frame(frames, b)
        result = tracker(image1, image2)
        points.append(FlowPoints(result.points.double(), result.flow.double(), result.sigma.double()))
        previous = (b, image2)
    index = torch.tensor(pairs)
    return FlowPairs(t[index[:, 0]], t[index[:, 1]], points, "sparse", description)


def track_pairs(tracks, *, sigma_px: float = 0.5, step: int = 1) -> FlowPairs:
    """Pairs from precomputed tracks (:class:`~flowins.data.sequence.Tracks`): for consecutive
    track times ``(k, k + step)``, every id seen at both gives a flow point with 1-σ ``sigma_px``."""
    if sigma_px <= 0:
        raise ValueError(f"track_pairs: sigma_px must be > 0, got {sigma_px}")
    times = torch.unique(tracks.t_s)
    index = pair_indices(times.shape[0], step)
    points = []
    for a, b in index:
        in_a, in_b = tracks.t_s == times[a], tracks.t_s == times[b]
        ids_a, ids_b = tracks.track_id[in_a], tracks.track_id[in_b]
        common, ia, ib = np.intersect1d(ids_a.numpy(), ids_b.numpy(), return_indices=True)
        uv_a = tracks.uv_px[in_a][torch.from_numpy(ia)]
        uv_b = tracks.uv_px[in_b][torch.from_numpy(ib)]
        points.append(FlowPoints(uv_a, uv_b - uv_a, torch.full_like(uv_a, sigma_px)))
    idx = torch.tensor(index)
    return FlowPairs(times[idx[:, 0]], times[idx[:, 1]], points, "sparse", f"{tracks.name} (precomputed tracks)")
