"""Does a still start make up a heading? The filter's heading σ over a walk's still start, with
the zero-velocity updates blind to the heading (``filter.init.still.zupt_keeps_heading=true``,
the default) and with the plain update (``false``).

Runs one row (default ``ins``) of ``python evaluate.py`` on the walk of ``--seed`` both ways,
with the yaw free at the start (σ ``--yaw-sigma-rad``, default π: without GNSS the start would
give it only the reference σ), and prints the heading σ (:mod:`flowins.evaluation.consistency`'s
linearised ``g P_q gᵀ``) and how far the heading estimate has turned from where it started, at
``--times`` seconds, then the row's filter and smoother RMSE. Nothing in a still IMU observes the
heading, so a consistent filter keeps the σ it started with. The walk comes from the cache
``python evaluate.py`` fills. Further arguments are Hydra overrides of both runs. The last line
is ``RESULT kept_sigma_deg=<x> plain_sigma_deg=<x>`` at the last time::

    python benchmarks/bench_still_heading.py [--seed 0] [--row ins] [--yaw-sigma-rad 3.14159]
                                             [--times 1 2 5 10 30] [OVERRIDE ...]
"""
from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from flowins.data.load import load_recording
from flowins.evaluation.consistency import heading_consistency, heading_error
from flowins.evaluation.metrics import trajectory_errors
from flowins.jobs.evaluate import _runs
from flowins.navigation import navigate_batch
from flowins.settings import filter_setup
from flowins.state import STATE

CONFIGS = str(Path(__file__).resolve().parents[1] / "configs")


def run(keeps: bool, args: argparse.Namespace):
    """Times, heading σ and turn since the start (rad) of the row's filter track; its filter and
    smoother RMSE."""
    overrides = [f"combinations=[{args.row}]", f"sequence.seed={args.seed}",
                 f"filter.init.still.zupt_keeps_heading={str(keeps).lower()}",
                 f"filter.initial.yaw_rad={args.yaw_sigma_rad}", f"filter.initial.reference_yaw_rad={args.yaw_sigma_rad}",
                 *args.overrides]
    with initialize_config_dir(config_dir=CONFIGS, version_base=None):
        cfg = OmegaConf.to_container(compose("evaluate", overrides=overrides), resolve=False)
    rec = load_recording(cfg["sequence"], quick=False, progress=True)
    if rec.truth is None:
        raise SystemExit("error: the recording has no ground truth for the RMSE")
    config = dataclasses.replace(filter_setup(cfg, [rec], recorded=False).navigation, workers=1)
    result = navigate_batch(_runs(args.row, cfg, [rec], config, [{}]), config=config)[0]
    track = result.filter.in_final_frame(marginal=STATE.dim)
    q = track.mean[:, STATE.q]
    sigma = heading_consistency(q, track.cov[:, STATE.q, STATE.q], q).sigma_rad
    turned = heading_error(q, q[:1].expand_as(q))
    filtered = trajectory_errors(track.t, track.mean[:, STATE.p], rec.truth.t_s, rec.truth.pos_m, align="se3")
    smoothed = trajectory_errors(result.smoother.t, result.smoother.mean[:, STATE.p], rec.truth.t_s,
                                 rec.truth.pos_m, align="se3")
    return track.t, sigma, turned, float(filtered.rmse_m), float(smoothed.rmse_m), result.start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=0, help="the simulated walk's seed")
    parser.add_argument("--row", default="ins", help="a row of configs/method")
    parser.add_argument("--yaw-sigma-rad", type=float, default=math.pi, help="the free yaw's σ at the start")
    parser.add_argument("--times", type=float, nargs="+", default=[1.0, 2.0, 5.0, 10.0, 30.0],
                        help="seconds after the start at which to print")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of both runs")
    args = parser.parse_args()
    if not args.yaw_sigma_rad > 0:
        raise SystemExit(f"error: --yaw-sigma-rad {args.yaw_sigma_rad}: expected a σ > 0")
    runs = {"blind (default)": run(True, args), "plain": run(False, args)}
    start = runs["plain"][5]
    print(f"{args.row} on the walk of seed {args.seed}, yaw σ {math.degrees(args.yaw_sigma_rad):.1f}° at the start "
          f"({start.mode} start at {start.t_s:.2f} s, {len(start.zupt_times_s)} zero-velocity updates)")
    print(f"  {'t (s)':>6s}  " + "  ".join(f"{name + ': σ, turned (°)':>30s}" for name in runs))
    for t in args.times:
        cells = []
        for t_s, sigma, turned, *_ in runs.values():
            k = max(int((t_s <= start.t_s + t).sum()) - 1, 0)
            cells.append(f"{math.degrees(float(sigma[k])):7.2f}, {math.degrees(float(turned[k])):+7.2f}")
        print(f"  {t:6.1f}  " + "  ".join(f"{c:>30s}" for c in cells))
    for name, (*_, f, s, _) in runs.items():
        print(f"  {name}: filter / smoother RMSE {f:.2f} / {s:.2f} m")
    last = [math.degrees(float(r[1][max(int((r[0] <= start.t_s + args.times[-1]).sum()) - 1, 0)])) for r in runs.values()]
    print(f"RESULT kept_sigma_deg={last[0]:.2f} plain_sigma_deg={last[1]:.2f}")


if __name__ == "__main__":
    torch.set_grad_enabled(False)
    main()
