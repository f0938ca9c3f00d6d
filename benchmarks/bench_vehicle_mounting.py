"""The vehicle constraint on a car whose IMU is mounted off the car's axes (issue 61).

Simulates 300 s drives (``flowins.data.simulate.drive``, a 60 s GNSS outage in the middle)
whose IMU is turned ``--mount-deg PITCH YAW`` from the car's axes and sits ``--lever`` from
its non-slipping point, and runs ``ins_gnss`` on each:

* without the constraint;
* with it, the mounting taken as none (the settings' defaults);
* with it and the mounting :func:`~flowins.measurements.vehicle.fit_mounting` estimates from
  the first run's smoothed track (printed with the truth, and as the overrides a user would pass);
* with it and the true mounting.

It prints each run's filter / smoother position RMSE (m, no alignment: the fixes set the
frame), the mean horizontal error over the outage's last 20 s, and the run's time.

    python benchmarks/bench_vehicle_mounting.py [--seeds 0 1] [--mount-deg 2 3] [--lever -1 0 0]
"""
from __future__ import annotations

import argparse
import math
import time

import torch

from flowins.data.simulate.drive import AUTOMOTIVE_IMU, Drive, DriveConfig, drive_sequence
from flowins.geometry.geodesy import LocalTangentPlane
from flowins.ins.mechanization import ProcessNoise
from flowins.measurements.vehicle import VehicleSettings, fit_mounting, gyro_at
from flowins.navigation import NavigationConfig, NavigationRun, navigate
from flowins.state import STATE


def errors(result, config: DriveConfig) -> tuple[float, float, float]:
    """Filter and smoother position RMSE (m) and the outage's late horizontal error (m)."""
    f = result.frame
    shift = LocalTangentPlane(*config.origin).to_enu(f.origin_lat_deg, f.origin_lon_deg, f.origin_alt_m)
    out = []
    for track in (result.filter, result.smoother):
        t = torch.as_tensor(track.t_s, dtype=torch.float64)
        err = track.node_mean[:, STATE.p] - (Drive(config).position(t) - shift)
        out.append(err)
    rmse = [float(e.pow(2).sum(-1).mean().sqrt()) for e in out]
    t = torch.as_tensor(result.filter.t_s, dtype=torch.float64)
    t0, t1 = config.outage()
    late = (t > t1 - 20.0) & (t < t1)
    return rmse[0], rmse[1], float(out[0][late, :2].norm(dim=-1).mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--mount-deg", type=float, nargs=2, default=(2.0, 3.0), metavar=("PITCH", "YAW"))
    parser.add_argument("--lever", type=float, nargs=3, default=(-1.0, 0.0, 0.0), metavar=("FORWARD", "LEFT", "UP"))
    args = parser.parse_args()
    pitch, yaw = (math.radians(a) for a in args.mount_deg)
    e = AUTOMOTIVE_IMU
    noise = ProcessNoise(acc_noise=e.acc_noise, gyro_noise=e.gyro_noise, acc_bias_walk=e.acc_bias_walk,
                         gyro_bias_walk=e.gyro_bias_walk)
    print(f"simulated drives, 300 s, IMU turned {args.mount_deg[0]:g}° (pitch) and {args.mount_deg[1]:g}° (yaw) "
          f"from the car's axes, the non-slipping point {tuple(args.lever)} m from it; ins_gnss, "
          f"{torch.get_num_threads()} threads\n")
    print(f"{'seed':>4}  {'run':<34} {'filter':>8} {'smoother':>9} {'outage':>8} {'time':>7}")
    for seed in args.seeds:
        config = DriveConfig(seed=seed, imu_mount_pitch_rad=pitch, imu_mount_yaw_rad=yaw, imu_lever_m=tuple(args.lever))
        seq = drive_sequence(config)[0]
        run = NavigationRun(seq.imu, seq.gnss)

        def timed(settings: VehicleSettings | None):
            measurements = {} if settings is None else {"vehicle": settings}
            began = time.perf_counter()
            result = navigate(run, config=NavigationConfig(noise=noise, measurements=measurements))
            return result, time.perf_counter() - began

        plain, seconds = timed(None)
        smoothed = plain.smoother
        fit = fit_mounting(smoothed.node_mean, gyro_at(seq.imu.t_s, seq.imu.gyro_rps,
                                                       torch.as_tensor(smoothed.t_s, dtype=torch.float64)))
        rows = [("off", plain, seconds)]
        lever = dict(zip(("lever_forward_m", "lever_left_m", "lever_up_m"), fit.lever_m))
        true_lever = dict(zip(("lever_forward_m", "lever_left_m", "lever_up_m"), args.lever))
        for label, settings in (
            ("on, no mounting", VehicleSettings(mode="on")),
            ("on, the fitted mounting", VehicleSettings(mode="on", mount_pitch_rad=fit.mount_pitch_rad,
                                                        mount_yaw_rad=fit.mount_yaw_rad, **lever)),
            ("on, the true mounting", VehicleSettings(mode="on", mount_pitch_rad=pitch, mount_yaw_rad=yaw,
                                                      **true_lever)),
        ):
            rows.append((label, *timed(settings)))
        for label, result, seconds in rows:
            f, s, late = errors(result, config)
            print(f"{seed:>4}  {label:<34} {f:>6.2f} m {s:>7.2f} m {late:>6.2f} m {seconds:>6.1f}s")
        print(f"      fit on the smoothed track without the constraint ({fit.samples} samples): pitch "
              f"{math.degrees(fit.mount_pitch_rad):.2f}° (true {args.mount_deg[0]:g}°), yaw "
              f"{math.degrees(fit.mount_yaw_rad):.2f}° (true {args.mount_deg[1]:g}°), lever "
              f"({', '.join(f'{x:.2f}' for x in fit.lever_m)}) m; residual {fit.rms_before_mps:.3f} -> "
              f"{fit.rms_after_mps:.3f} m/s\n      overrides: {' '.join(fit.overrides())}")


if __name__ == "__main__":
    main()
