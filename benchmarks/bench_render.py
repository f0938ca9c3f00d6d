"""Render speed of the simulator's ray caster and the cost of exact flow, CPU.

Renders ``--frames`` frames along the synthetic walk (10 Hz) at 320x240 (and, with
``--large``, 683x512), prints frames/s and ms/frame (best and median of ``--repeats`` rounds: other jobs on
a shared machine inflate single rounds), the cost of ``exact_flow`` per
pair, and a reference in the same run: the same frame rendered without culling
(every facade and box tested against every pixel tile, ``max_range_m`` = inf), so
the ratio stands on this machine. Writes a sample image with its flow
visualisation to ``--out``.

    python benchmarks/bench_render.py [--frames 100] [--repeats 3] [--threads 1] [--large] [--out outputs/render_sample.png]
"""
from __future__ import annotations

import argparse
import math
import statistics
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from flowins.data.sequence import PinholeCamera
from flowins.data.simulate.render import exact_flow, render
from flowins.data.simulate.world import build_city
from flowins.data.synthetic import Walk

# camera axes in the body frame (columns): camera x = -body y, camera y = -body z, camera z = body x
R_BODY_CAM = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)


def _poses(walk: Walk, times: torch.Tensor):
    R = walk.rotation(times) @ R_BODY_CAM
    p = walk.position(times)
    return [(R[i], p[i], float(times[i])) for i in range(times.shape[0])]


def _flow_image(flow: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """HSV flow colouring (hue = direction, value = magnitude / 99th percentile); invalid black."""
    mag = np.linalg.norm(np.nan_to_num(flow), axis=-1)
    ang = np.arctan2(flow[..., 1], flow[..., 0])
    scale = max(np.percentile(mag[valid], 99) if valid.any() else 1.0, 1e-6)
    hsv = np.zeros((*flow.shape[:2], 3), np.uint8)
    hsv[..., 0] = ((np.nan_to_num(ang) + math.pi) / (2 * math.pi) * 179).astype(np.uint8)
    hsv[..., 1] = 255
    hsv[..., 2] = (np.clip(mag / scale, 0, 1) * 255).astype(np.uint8) * valid
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)


def _time_renders(city, camera, poses, **kwargs) -> tuple[float, list]:
    frames = []
    t0 = time.perf_counter()
    for pose in poses:
        frames.append(render(city, camera, *pose, **kwargs))
    return (time.perf_counter() - t0) / len(poses), frames


def _bench(
    city, walk, camera: PinholeCamera, n_frames: int, repeats: int, reference_frames: int, out: Path | None
) -> None:
    times = 10.0 + torch.arange(n_frames, dtype=torch.float64) * 0.1
    poses = _poses(walk, times)
    render(city, camera, *poses[0])  # warm-up (ray cache)
    rounds = []
    for _ in range(repeats):
        per_frame, frames = _time_renders(city, camera, poses)
        rounds.append(per_frame)
    best, median = min(rounds), statistics.median(rounds)
    print(
        f"{camera.width}x{camera.height}: {n_frames} frames x {repeats} rounds: best round {1e3 * best:.1f} ms/frame "
        f"({1 / best:.1f} frames/s), median round {1e3 * median:.1f} ms/frame ({1 / median:.1f} frames/s)"
    )
    flow_times = []
    for i in range(min(n_frames - 1, 30)):
        t0 = time.perf_counter()
        truth = exact_flow(city, camera, frames[i], poses[i], poses[i + 1], frames[i + 1])
        flow_times.append(time.perf_counter() - t0)
    print(f"  exact_flow: {1e3 * statistics.median(flow_times):.1f} ms/pair (median of {len(flow_times)})")
    reference = poses[: max(1, reference_frames)]
    ref, ref_frames = _time_renders(city, camera, reference, max_range_m=math.inf, tile=max(camera.width, camera.height))
    culled, culled_frames = _time_renders(city, camera, reference)
    same = all(torch.equal(a.depth, b.depth) for a, b in zip(ref_frames, culled_frames))
    print(
        f"  reference (no culling, one tile): {1e3 * ref:.1f} ms/frame vs {1e3 * culled:.1f} ms culled on the same "
        f"{len(reference)} frames: {ref / culled:.1f}x; identical depth maps: {same}"
    )
    if out is not None:
        i = min(n_frames - 2, n_frames // 2)
        truth = exact_flow(city, camera, frames[i], poses[i], poses[i + 1], frames[i + 1])
        panel = np.concatenate((frames[i].image.numpy(), _flow_image(truth.flow.numpy(), truth.valid.numpy())), 1)
        out.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(out), cv2.cvtColor(panel, cv2.COLOR_RGB2BGR))
        print(f"  sample frame (t = {poses[i][2]:.1f} s) and its exact flow to the next: {out}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3, help="timed rounds over the frames (best and median printed)")
    parser.add_argument("--reference-frames", type=int, default=5, help="frames rendered by the un-culled reference")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    parser.add_argument("--large", action="store_true", help="also 683x512")
    parser.add_argument("--out", type=Path, default=Path("outputs/render_sample.png"))
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    walk = Walk()
    t0 = time.perf_counter()
    city = build_city(walk, seed=0)
    print(
        f"build_city: {time.perf_counter() - t0:.2f} s, {city.n_facades} facades, {city.box_half.shape[0]} boxes "
        f"({city.n_movers} moving)"
    )
    _bench(city, walk, PinholeCamera(320, 240, 250.0, 250.0, 159.5, 119.5), args.frames, args.repeats, args.reference_frames, args.out)
    if args.large:
        large = PinholeCamera(683, 512, 534.0, 534.0, 341.0, 255.5)
        _bench(city, walk, large, max(10, args.frames // 4), args.repeats, args.reference_frames, None)


if __name__ == "__main__":
    main()
