"""``python -m flowins.data.simulate OUT --seed 0 --duration 300``: write a simulated walk
(``--vibration 0.5``: shaken on the ground before it sets off) or, with ``--scenario drive``,
a car drive that moves from the first sample with a GNSS outage in the middle."""
from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace

from flowins.data.simulate.drive import DriveConfig, simulate_drive
from flowins.data.simulate.scenario import SimulationConfig, simulate
from flowins.data.synthetic import Vibration, WalkConfig


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m flowins.data.simulate",
        description="Simulate the snowy city-block walk (IMU, camera frames, GNSS, ground truth, exact flow) "
        "or a car drive (IMU, GNSS with an outage, ground truth) into a folder in the flowins sequence format.",
    )
    parser.add_argument("--scenario", choices=("walk", "drive"), default="walk",
                        help="walk (default) or drive: a car at 8-15 m/s from the first sample, automotive IMU, "
                        "1 Hz GNSS with a 60 s outage in the middle, no camera")
    parser.add_argument("out", help="output folder (created; reused if it already holds the same simulation)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--duration", type=float, default=300.0,
                        help="seconds (default 300; the walk's first 5 s are stationary)")
    parser.add_argument("--vibration", type=float, default=0.0, metavar="ACC_MPS2",
                        help="walk: rotor-like vibration (50-200 Hz) on the ground before it sets off, this RMS per "
                        "accelerometer axis in the readings (and 0.08 rad/s per m/s^2 on the gyroscope)")
    parser.add_argument("--outage", type=float, default=60.0, help="drive: seconds without GNSS in the middle")
    parser.add_argument("--frame-rate", type=float, default=10.0, help="camera frames per second (default 10)")
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--flow-every", type=int, default=1, help="write exact flow for every n-th frame pair (0: none)")
    parser.add_argument("--motion-blur", action="store_true")
    parser.add_argument("--exposure-changes", action="store_true")
    parser.add_argument("--no-movers", action="store_true",
                        help="walk: no moving cars or pedestrians (the rest of the city the same)")
    parser.add_argument("--overwrite", action="store_true", help="replace a folder holding something else")
    parser.add_argument("--mount-deg", type=float, nargs=2, default=(0.0, 0.0), metavar=("PITCH", "YAW"),
                        help="drive: the IMU turned from the car's axes (degrees; its forward axis down, left)")
    parser.add_argument("--lever", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("FORWARD", "LEFT", "UP"),
                        help="drive: the car's non-slipping point (rear axle's middle) from the IMU, car axes (m)")
    drive = DriveConfig()
    parser.add_argument("--slip", type=float, default=drive.slip_per_lateral_rad, metavar="RAD_PER_MPS2",
                        help="drive: the car's nose into a turn per m/s² of lateral acceleration (0: no slip)")
    parser.add_argument("--pitch", type=float, default=drive.pitch_per_acceleration_rad, metavar="RAD_PER_MPS2",
                        help="drive: the car's nose up per m/s² of forward acceleration (0: none)")
    parser.add_argument("--slopes", type=float, default=drive.grade_scale, metavar="SCALE",
                        help="drive: the road's slopes (up to about 0.03 rad) times this (0: a flat road)")
    parser.add_argument("--bumps", type=float, default=drive.bump_height_m, metavar="M",
                        help=f"drive: bumps this high every {drive.bump_every_s:g} s (0: a smooth road)")
    args = parser.parse_args(argv)
    try:
        start = time.perf_counter()
        if args.scenario == "drive":
            pitch, yaw = (math.radians(a) for a in args.mount_deg)
            config = DriveConfig(duration_s=args.duration, seed=args.seed, outage_s=args.outage,
                                 imu_mount_pitch_rad=pitch, imu_mount_yaw_rad=yaw, imu_lever_m=tuple(args.lever),
                                 slip_per_lateral_rad=args.slip, pitch_per_acceleration_rad=args.pitch,
                                 bump_height_m=args.bumps, grade_scale=args.slopes)
            sequence = simulate_drive(args.out, config, overwrite=args.overwrite)
        else:
            config = _config(args)
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
        movers=not args.no_movers,
        vibration=Vibration(args.vibration, 0.08 * args.vibration, until_s=WalkConfig().stationary_s)
        if args.vibration else Vibration(),
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
