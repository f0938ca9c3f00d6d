"""What a recording's start and platform do, on simulated recordings with known truth.

Prints three measurements (no targets; docs/data.md, docs/initialization.md and docs/model.md
quote them):

1. **Noise from the still start**: the white-noise densities measured over the still start of
   simulated walks (``flowins.ins.imu_model.still_noise_densities``) against the densities the
   simulator drew the noise with.
2. **Ground-truth start on a still IMU**: INS alone over a 20 s tilted walk (5 s still, gyroscope
   bias σ 0.01 rad/s, ground truth at 20 Hz with 2 mm / 2 mrad of its own noise), started still,
   from the ground truth, and from the ground truth without the still start's bias and
   zero-velocity updates (``filter.init.still.min_s`` beyond the walk); SE(3)-aligned RMSE.
3. **Vehicle constraint through an outage**: a 240 s simulated car drive with a 60 s GNSS outage,
   the mean horizontal error over the outage's last 20 s and the run time, without and with
   ``filter.measurements.vehicle.mode=on``.

    python benchmarks/bench_recording_checks.py [--seeds 0 1 2 3 4 5 6 7]
"""
from __future__ import annotations

import argparse
import time

import torch


def still_noise(seeds: list[int]) -> None:
    from flowins.data.synthetic import ImuErrors, WalkConfig, synthetic_walk_recording
    from flowins.ins.imu_model import still_noise_densities
    from flowins.ins.initialization import still_interval

    truth = ImuErrors()
    print(f"1. noise from the still start (simulator: acc {truth.acc_noise:g} m/s²/√Hz, gyro {truth.gyro_noise:g} "
          "rad/s/√Hz)")
    worst = 0.0
    for seed in seeds:
        imu = synthetic_walk_recording(duration_s=20.0, seed=seed, walk=WalkConfig(duration_s=20.0)).imu
        still = still_interval(imu.t_s, imu.acc_mps2, imu.gyro_rps)
        m = still_noise_densities(imu.t_s, imu.acc_mps2, imu.gyro_rps, still.end)
        errors = (m.acc_noise / truth.acc_noise - 1, m.gyro_noise / truth.gyro_noise - 1)
        worst = max(worst, *(abs(e) for e in errors))
        print(f"   seed {seed}: still {still.duration_s:.2f} s, acc {m.acc_noise:.4g} ({100 * errors[0]:+.1f} %), "
              f"gyro {m.gyro_noise:.4g} ({100 * errors[1]:+.1f} %)")
    print(f"   largest error: {100 * worst:.1f} %")


def groundtruth_start(seeds: list[int]) -> None:
    from flowins.data.synthetic import WalkConfig, noisy_truth, synthetic_walk_recording
    from flowins.evaluation import trajectory_errors
    from flowins.navigation import NavigationConfig, NavigationRun, navigate
    from flowins.start import StartSettings, StillSettings
    from flowins.state import STATE

    print("\n2. INS alone, 20 s walk with a 5 s still start: SE(3)-aligned RMSE")
    starts = {"still": StartSettings(mode="still"), "ground truth": StartSettings(mode="groundtruth"),
              "ground truth, no still calibration": StartSettings(mode="groundtruth", still=StillSettings(min_s=1e3))}
    for seed in seeds[:2]:
        rec = synthetic_walk_recording(duration_s=20.0, seed=seed, truth_rate_hz=20.0, walk=WalkConfig(duration_s=20.0))
        truth = noisy_truth(rec.truth, position_sigma_m=0.002, attitude_sigma_rad=0.002,
                            generator=torch.Generator().manual_seed(100 + seed))
        cells = []
        for label, settings in starts.items():
            track = navigate(NavigationRun(rec.imu, truth=truth), config=NavigationConfig(start=settings)).filter
            rmse = trajectory_errors(track.t, track.mean[:, STATE.p], rec.truth.t_s, rec.truth.pos_m,
                                     align="se3").rmse_m
            cells.append(f"{label} {rmse:.2f} m")
        print(f"   seed {seed}: " + ", ".join(cells))


def vehicle_outage() -> None:
    from flowins.data.simulate.drive import AUTOMOTIVE_IMU, Drive, DriveConfig, drive_sequence
    from flowins.geometry.geodesy import LocalTangentPlane
    from flowins.ins.mechanization import ProcessNoise
    from flowins.measurements.vehicle import VehicleSettings
    from flowins.navigation import NavigationConfig, NavigationRun, navigate
    from flowins.state import STATE

    config = DriveConfig(duration_s=240.0, outage_s=60.0)
    seq = drive_sequence(config)[0]
    e = AUTOMOTIVE_IMU
    noise = ProcessNoise(acc_noise=e.acc_noise, gyro_noise=e.gyro_noise, acc_bias_walk=e.acc_bias_walk,
                         gyro_bias_walk=e.gyro_bias_walk)
    t0, t1 = config.outage()
    print(f"\n3. simulated car drive, {config.duration_s:.0f} s, GNSS outage {t0:.0f}-{t1:.0f} s: mean horizontal "
          "error over the outage's last 20 s")
    for label, settings in (("off", VehicleSettings(mode="off")), ("on", VehicleSettings(mode="on"))):
        start = time.perf_counter()
        result = navigate(NavigationRun(seq.imu, seq.gnss),
                          config=NavigationConfig(noise=noise, measurements={"vehicle": settings}))
        seconds = time.perf_counter() - start
        f = result.frame
        shift = LocalTangentPlane(*config.origin).to_enu(f.origin_lat_deg, f.origin_lon_deg, f.origin_alt_m)
        t = result.filter.t_s
        err = result.filter.node_mean[:, STATE.p] - (Drive(config).position(t) - shift)
        late = (t > t1 - 20.0) & (t < t1)
        print(f"   vehicle constraint {label}: {float(err[late, :2].norm(dim=-1).mean()):.2f} m ({seconds:.1f} s)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(8)))
    args = parser.parse_args()
    still_noise(args.seeds)
    groundtruth_start(args.seeds)
    vehicle_outage()


if __name__ == "__main__":
    main()
