"""The camera mounting check (``flowins.flow.mounting``) on the clean set and on wrong calibrations.

Recordings: the simulated walk (``WalkConfig``: turns, sway, 100 Hz IMU, the simulator's
camera at 10 Hz, exact tracks of random landmarks with 0.3 px noise) and the drone flight
of ``bench_tracks.py`` (200 Hz ADIS16448-like IMU, 752x480 camera at 20 Hz looking 30°
down), each with and without EuRoC's constant gyroscope bias (-0.002, 0.021, 0.077) rad/s;
with ``--rendered`` also the job's own simulated walk (rendered frames, its ``sparse.tracker``
flow, read through the job's loaders, cached). Each runs with the true ``imu_to_camera``
rotation (a warning is a false alarm) and with wrong ones: identity, and the truth turned
90° about the camera's x, y and z axes (each must be named, its suggestion within 5° of the
truth); and with the true rotation but the gyroscope's x and y columns swapped, or its z
negated (the axes mirrored: each must be named so). Prints per case the angle between the
configured and the fitted rotation, the suggestion's error against the truth, the test
statistic, whether the axes were called mirrored, and the time::

    python benchmarks/bench_mounting.py [--seeds 2] [--duration 60] [--rendered]
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch

from flowins.data.simulate.scenario import CameraConfig
from flowins.data.simulate.tracks import tracks_along
from flowins.data.synthetic import ImuErrors, Walk, WalkConfig, corrupt_imu, increment_imu
from flowins.flow.mounting import check_mounting
from flowins.flow.pairs import track_pairs
from flowins.geometry import quaternion as quat

F64 = torch.float64
EUROC_BIAS = (-0.002, 0.021, 0.077)


def _walk(seed: int, duration_s: float):
    g = torch.Generator().manual_seed(seed)
    walk = Walk(WalkConfig(duration_s=duration_s))
    t = torch.arange(0, int(duration_s * 100) + 1, dtype=F64) / 100
    _, gyro, _ = corrupt_imu(t, *increment_imu(walk, t), ImuErrors(), g)
    config = CameraConfig()
    pin = config.intrinsics()
    t_cam = torch.arange(0, int(duration_s * 10) + 1, dtype=F64) / 10
    tracks = tracks_along(t_cam, walk.quaternion(t_cam), walk.position(t_cam), config.imu_to_camera(), pin.K,
                          (pin.height, pin.width), count=3000, ahead_m=10.0, radius_m=10.0, height_m=(0.0, 8.0),
                          noise_px=0.3, generator=g)
    return t, gyro, track_pairs(tracks, sigma_px=0.3), pin.K, quat.to_matrix(config.imu_to_camera().rotation_wxyz)


def _flight(seed: int, duration_s: float):
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_tracks import recording

    _, imu, tracks, cam, _ = recording(duration_s, seed)
    return imu.t_s, imu.gyro_rps, track_pairs(tracks, sigma_px=0.3), cam.K, cam.R_ci


def _rendered(duration_s: float):
    """The job's simulated walk, its sparse flow as the job computes it."""
    from hydra import compose, initialize_config_dir

    from flowins.data.load import load_recording
    from flowins.flow.load import load_flow

    with initialize_config_dir(config_dir=str(Path(__file__).resolve().parents[1] / "configs"), version_base=None):
        cfg = compose("evaluate", overrides=["output_dir=unused", f"sequence.quick_duration_s={duration_s}"])
    rec = load_recording(cfg["sequence"], quick=True, progress=False)
    pairs = load_flow("sparse", rec, cfg, progress=False)
    return (rec.imu.t_s, rec.imu.gyro_rps, pairs, rec.sequence.camera.K,
            quat.to_matrix(rec.sequence.imu_to_camera.rotation_wxyz))


def _turn(axis: int, degrees: float) -> torch.Tensor:
    v = torch.zeros(3, dtype=F64)
    v[axis] = math.radians(degrees)
    return quat.to_matrix(quat.from_rotation_vector(v))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of each recording")
    parser.add_argument("--rendered", action="store_true", help="also the job's rendered walk with its sparse flow")
    args = parser.parse_args()
    recordings = []
    for seed in range(args.seeds):
        recordings.append((f"walk {seed}", lambda s=seed: _walk(s, args.duration)))
        recordings.append((f"drone {seed}", lambda s=seed: _flight(s, args.duration)))
    if args.rendered:
        recordings.append(("rendered walk, LK flow", lambda: _rendered(args.duration)))
    print(f"{'recording':<40} {'configured':<18} {'warned':<7} {'angle°':>7} {'sugg. err°':>10} {'δᵀHδ':>10} "
          f"{'mirrored':<9} {'pairs':>6} {'s':>5}")
    alarms = missed = far = unmirrored = 0
    for name, make in recordings:
        t, gyro, pairs, K, R_true = make()
        for bias in (None, EUROC_BIAS):
            label = name if bias is None else f"{name}, EuRoC gyro bias"
            g = gyro if bias is None else gyro + torch.tensor(bias, dtype=F64)
            cases = {"true": (R_true, g), "identity": (torch.eye(3, dtype=F64), g)}
            cases.update({f"90° about {'xyz'[a]}": (_turn(a, 90.0) @ R_true, g) for a in range(3)})
            cases["gyro x, y swapped"] = (R_true, g[:, [1, 0, 2]])
            cases["gyro z negated"] = (R_true, g * torch.tensor([1.0, 1.0, -1.0], dtype=F64))
            for case, (configured, readings) in cases.items():
                t0 = time.perf_counter()
                result = check_mounting(t, readings, pairs, K, quat.from_matrix(configured))
                seconds = time.perf_counter() - t0
                error = math.degrees(float(quat.angle_between(torch.tensor(result.suggested_wxyz, dtype=F64),
                                                              quat.from_matrix(R_true))))
                if case == "true":
                    alarms += result.warn
                elif case.startswith("gyro"):
                    unmirrored += not result.mirrored
                else:
                    missed += not result.warn
                    far += result.warn and error > 5.0
                    alarms += result.mirrored
                print(f"{label:<40} {case:<18} {str(result.warn):<7} {math.degrees(result.angle_rad):7.2f} "
                      f"{error:10.2f} {result.significance:10.3g} {str(result.mirrored):<9} {result.pairs:6d} "
                      f"{seconds:5.1f}" + (f"  ({result.reason})" if result.reason else ""))
    print(f"\nfalse alarms (a true mounting warned, or proper axes called mirrored): {alarms}; wrong mountings not "
          f"named: {missed}; named with a suggestion over 5° from the truth: {far}; mirrored axes not named: "
          f"{unmirrored}")


if __name__ == "__main__":
    main()
