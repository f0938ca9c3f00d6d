"""The RTS smoother where updates lie far apart: the nodes' transitions to their key formed as
products (one per node) against applied to the nodes' columns one distance at a time (the sum of
the distances), in one process.

Filters the default simulated walk (cached by ``python evaluate.py``) with the IMU alone
(``--fixes-every-s 0``: one key node, at the end) or with every n-th second's GNSS fix, then
times :func:`flowins.filter.smoother.rts_smooth` on that track both ways (median of
``--repeats``) and prints the largest difference of the smoothed means and covariances::

    python benchmarks/bench_smoother_gaps.py [--fixes-every-s 0] [--quick] [--repeats 3]

The last line is ``RESULT products=<s> applications=<s> speedup=<x>``.
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from flowins.data.load import load_recording
from flowins.data.streams import GnssStream
from flowins.filter import smoother
from flowins.navigation import NavigationRun, navigate
from flowins.settings import filter_setup

CONFIGS = str(Path(__file__).resolve().parents[1] / "configs")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--fixes-every-s", type=float, default=0.0, help="0: no GNSS (one key at the end)")
    parser.add_argument("--quick", action="store_true", help="the 60 s walk")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    with initialize_config_dir(CONFIGS, version_base=None):
        cfg = OmegaConf.to_container(compose("evaluate"), resolve=False)
    rec = load_recording(cfg["sequence"], quick=args.quick, progress=False)
    gnss = None
    if args.fixes_every_s > 0:
        g = rec.gnss
        keep = torch.zeros(len(g), dtype=torch.bool)
        keep[:: max(1, round(args.fixes_every_s / float(g.t_s[1] - g.t_s[0])))] = True
        gnss = GnssStream(g.t_s[keep], g.lat_deg[keep], g.lon_deg[keep], g.alt_m[keep], g.h_acc_m[keep],
                          g.v_acc_m[keep], name=g.name)
    config = filter_setup(cfg, [rec], recorded=False).navigation
    with torch.inference_mode():
        track = navigate(NavigationRun(rec.imu, gnss), config=config).filter
    keys = int(track.key_nodes().sum())
    print(f"{rec.name}: {track.node_mean.shape[0]} nodes, {keys} key nodes "
          f"({'no GNSS' if gnss is None else f'a fix every {args.fixes_every_s:g} s'})")

    def timed(products_above: float):
        smoother._PRODUCTS_ABOVE = products_above
        times, out = [], None
        for _ in range(args.repeats):
            start = time.perf_counter()
            with torch.inference_mode():
                out = smoother.rts_smooth(track)
            times.append(time.perf_counter() - start)
        return statistics.median(times), out

    fast, a = timed(1.0)
    slow, b = timed(float("inf"))
    smoother._PRODUCTS_ABOVE = 1.0
    mean_diff = float((a.node_mean - b.node_mean).abs().max())
    cov_diff = float(((a.node_cov - b.node_cov).abs() / b.node_cov.abs().amax((-2, -1), keepdim=True)).max())
    print(f"products:     {fast:7.3f} s (median of {args.repeats})")
    print(f"applications: {slow:7.3f} s")
    print(f"largest difference: means {mean_diff:.2e}, covariances {cov_diff:.2e} of each node's largest entry")
    print(f"RESULT products={fast:.3f}s applications={slow:.3f}s speedup={slow / fast:.1f}x")


if __name__ == "__main__":
    main()
