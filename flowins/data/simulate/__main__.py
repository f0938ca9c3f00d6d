"""``python -m flowins.data.simulate OUT --seed 0 --duration 300``: write a simulated walk."""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace

from flowins.data.simulate.scenario import SimulationConfig, simulate


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m flowins.data.simulate",
        description="Simulate the snowy city-block walk (IMU, camera frames, GNSS, ground truth, exact flow) "
        "into a folder in the flowins sequence format.",
    )
    parser.add_argument("out", help="output folder (created; reused if it already holds the same simulation)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--duration", type=float, default=300.0, help="seconds (default 300; the first 5 s are stationary)")
    parser.add_argument("--frame-rate", type=float, default=10.0, help="camera frames per second (default 10)")
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--flow-every", type=int, default=1, help="write exact flow for every n-th frame pair (0: none)")
    parser.add_argument("--motion-blur", action="store_true")
    parser.add_argument("--exposure-changes", action="store_true")
    parser.add_argument("--overwrite", action="store_true", help="replace a folder holding something else")
    args = parser.parse_args(argv)
    try:
        config = _config(args)
        start = time.perf_counter()
        sequence = simulate(args.out, config, overwrite=args.overwrite)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{sequence.describe()}\nwritten to {args.out} in {time.perf_counter() - start:.1f} s (key {config.key()})")
    return 0


def _config(args: argparse.Namespace) -> SimulationConfig:
    base = SimulationConfig()
    return replace(
        base,
        seed=args.seed,
        duration_s=args.duration,
        flow_every=args.flow_every,
        camera=replace(
            base.camera,
            rate_hz=args.frame_rate,
            width=args.width,
            height=args.height,
            motion_blur=args.motion_blur,
            exposure_changes=args.exposure_changes,
        ),
    )


if __name__ == "__main__":
    sys.exit(main())
