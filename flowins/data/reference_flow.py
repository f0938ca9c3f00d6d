"""Reference flow pairs with exact ground truth (data for checking flow providers), shared
by the flow tests and ``benchmarks/bench_flow.py`` (:class:`FlowPair`: flow ``(H, W, 2)`` from image 1 to
image 2 and the mask of pixels where it is known), and the end-point error.

* :func:`middlebury_pair`: the Middlebury 2014 *Motorcycle* stereo pair shipped
  with scikit-image (``skimage.data.stereo_motorcycle``), as flow left -> right
  ``(-d, 0)``; pixels whose disparity is unknown, whose match falls outside the
  right image, or that the right camera does not see (a z-buffer over each row)
  are masked out.
* :func:`simulator_pair`: two frames 0.1 s apart of the simulated city walk with
  :func:`flowins.data.simulate.render.exact_flow`; the mask is ``valid & static``.

Both are cached per process (``functools.lru_cache``); each call returns fresh copies.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

__all__ = ["FlowPair", "endpoint_error", "middlebury_pair", "simulator_pair"]


class FlowPair(NamedTuple):
    """Two images ``(H, W, 3)`` uint8 RGB, the true flow ``(H, W, 2)`` float32 px from
    image 1 to image 2 and ``mask`` ``(H, W)`` bool where it is known."""

    image1: np.ndarray
    image2: np.ndarray
    flow: np.ndarray
    mask: np.ndarray
    name: str


def endpoint_error(flow: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Per-pixel ``|flow - truth|`` of two ``(..., 2)`` flows; the masked entries only when ``mask`` is given."""
    flow, truth = np.asarray(flow), np.asarray(truth)
    if flow.shape != truth.shape or flow.shape[-1] != 2:
        raise ValueError(f"endpoint_error: flows of shapes {flow.shape} and {truth.shape}; expected equal (..., 2)")
    err = np.linalg.norm(flow.astype(np.float64) - truth, axis=-1)
    return err if mask is None else err[mask]


def _copied(cached):
    """Cache a function returning a :class:`FlowPair` per process; callers get fresh copies."""
    cached = functools.lru_cache(maxsize=4)(cached)

    @functools.wraps(cached.__wrapped__)
    def wrapper(*args, **kwargs) -> FlowPair:
        pair = cached(*args, **kwargs)
        return FlowPair(*(a.copy() for a in pair[:4]), pair.name)

    wrapper.cache_clear = cached.cache_clear
    return wrapper


@_copied
def middlebury_pair(scale: int = 4) -> FlowPair:
    """The Motorcycle stereo pair downscaled by ``scale`` (area average) with flow ``(-d / scale, 0)``.

    Disparity conventions checked by warping: the left pixel ``(u, v)`` is seen at
    ``(u - d, v)`` in the right image (warping with ``-d`` leaves a mean gray error
    of 7 levels, with ``+d`` 45). A coarse pixel keeps its flow only when all
    ``scale x scale`` fine pixels are valid.
    """
    import cv2
    from skimage.data import stereo_motorcycle

    if scale < 1:
        raise ValueError(f"middlebury_pair: scale={scale}; expected an integer >= 1")
    left, right, disp = stereo_motorcycle()
    h, w = disp.shape
    known = np.isfinite(disp)
    d = np.where(known, disp, 0.0).astype(np.float32)
    # visibility in the right image: per row, the largest disparity landing on each right pixel wins
    target = np.rint(np.arange(w)[None, :] - d).astype(np.int64)
    inside = known & (target >= 0) & (target <= w - 1)
    zbuf = np.full((h, w), -np.inf, np.float32)
    rows = np.broadcast_to(np.arange(h)[:, None], (h, w))
    np.maximum.at(zbuf, (rows[inside], target[inside]), d[inside])
    seen = np.zeros_like(known)
    seen[inside] = d[inside] >= zbuf[rows[inside], target[inside]] - 1.0
    valid = known & inside & seen

    hs, ws = h // scale, w // scale
    crop = (slice(0, hs * scale), slice(0, ws * scale))

    def down(x: np.ndarray) -> np.ndarray:
        return cv2.resize(np.ascontiguousarray(x[crop]), (ws, hs), interpolation=cv2.INTER_AREA)

    frac = down(valid.astype(np.float32))
    mean_d = down(np.where(valid, d, 0.0).astype(np.float32)) / np.maximum(frac, 1e-6)
    mask = frac > 1.0 - 1e-4
    flow = np.zeros((hs, ws, 2), np.float32)
    flow[..., 0] = np.where(mask, -mean_d / scale, 0.0)
    return FlowPair(down(left), down(right), flow, mask, f"middlebury-motorcycle/{scale}")


@_copied
def simulator_pair(t1_s: float = 60.0, t2_s: float = 60.1, *, seed: int = 0) -> FlowPair:
    """Frames of the simulated walk (default configuration, 320 x 240) at ``t1_s`` and ``t2_s``
    with their exact flow; ``mask`` is ``valid & static`` (a few seconds: builds the city)."""
    import torch

    from flowins.data.simulate.render import exact_flow, render
    from flowins.data.simulate.scenario import CameraConfig, CameraTrajectory
    from flowins.data.simulate.world import build_city
    from flowins.data.synthetic import Walk, WalkConfig

    walk = Walk(WalkConfig())
    city = build_city(walk, seed=seed)
    config = CameraConfig()
    camera = config.intrinsics()
    R, p = CameraTrajectory(walk, config.imu_to_camera()).pose(torch.tensor([t1_s, t2_s], dtype=torch.float64))
    r1 = render(city, camera, R[0], p[0], t1_s)
    r2 = render(city, camera, R[1], p[1], t2_s)
    truth = exact_flow(city, camera, r1, (R[0], p[0], t1_s), (R[1], p[1], t2_s), r2)
    mask = (truth.valid & truth.static).numpy()
    flow = np.where(mask[..., None], truth.flow.numpy(), 0.0).astype(np.float32)
    return FlowPair(r1.image.numpy(), r2.image.numpy(), flow, mask, f"simulator/t={t1_s:g}-{t2_s:g}s")
