"""What a trained adaptive-noise network sets: its σ factors over recordings.

``model.adaptive=[vehicle]`` learns a network that multiplies the vehicle constraint's σs at
each update by a factor within ``10^±model.adaptive_decades`` (docs/training.md). A network that
adapts spreads its factors with the road; one that learned only a level sets the same factor
everywhere, and one pinned at its bound says the bound, not the data, set it. For each
recording this prints the checkpoint's learned constant σs times the factors' 10th, 50th and
90th percentiles at a 1 Hz update rate (the constraint's default), laterally and vertically,
and how many updates sit within 1 % of a bound::

    python benchmarks/bench_adaptive_factors.py RUN/checkpoints/best.ckpt /tmp/drv_s2 /tmp/kitti/recordings/kitti-seed0 \
        [--rate-hz 1] [--start-s 10] [--end-s 0] [--forward-axis x --up-axis z]

A network that also sets the mounting's angles (``model.adaptive_angles_rad``) has them
printed too: the pitch and yaw offsets' 10th, 50th and 90th percentiles, and each one's slope
(rad per g) and correlation against the mean specific force of the last 0.2 s along the car's
forward axis (pitch) and left axis (yaw), the car's axes as ``--forward-axis`` / ``--up-axis``
name them (the drive simulator's car: a yaw of +0.049 rad per g of lateral force, its
``slip_per_lateral_rad``, and a pitch of −0.098 rad per g of forward force). A network that
reads the car's acceleration (``model.adaptive_compensate_gravity``) has its angles taken at the
recording's reference orientation, and its slopes against the acceleration; without a
reference orientation its angles are not printed.

``--start-s`` / ``--end-s`` crop each recording (seconds after its first IMU sample; end 0: to
its end).
"""
from __future__ import annotations

import argparse
import math

import torch

from flowins.data.folder.reading import read_folder
from flowins.evaluation.metrics import associate, interpolate_quaternions
from flowins.measurements.adaptive_noise import acceleration_g, imu_windows, recent_force_g, steady_window
from flowins.measurements.vehicle import VehicleSettings
from flowins.training.parameters import FilterParameters


def summary(network, sigmas: torch.Tensor, t_s: torch.Tensor, acc: torch.Tensor, gyro: torch.Tensor,
            times: torch.Tensor, steady: torch.Tensor | None = None) -> tuple[torch.Tensor, int]:
    """The σs ``sigmas`` ``(2,)`` times the network's factors at the update times ``times`` ``(E,)``:
    their 10th, 50th and 90th percentiles ``(3, 2)``, and the updates with a factor within 1 % of
    a bound."""
    with torch.no_grad():
        f, _ = network.split(imu_windows(t_s, acc, gyro, times), steady)
    levels = torch.tensor([0.1, 0.5, 0.9], dtype=f.dtype)
    log_bound = float(network.decades) * math.log(10.0)
    pinned = ((f.log().abs() - log_bound).abs() < math.log(1.01)).any(-1).sum()
    return torch.quantile(f, levels, dim=0) * sigmas, int(pinned)


def angle_summary(network, windows: torch.Tensor, steady: torch.Tensor, C_cb: torch.Tensor,
                  q: torch.Tensor | None = None) -> list[str]:
    """For the pitch and the yaw offsets at ``windows (E, 6, S)``: a line with their 10th, 50th and
    90th percentiles and their least-squares slope and correlation against the recent mean
    specific force along the car's forward (pitch) and left (yaw) axes (``C_cb``'s rows). A
    network that reads the car's acceleration (``compensates_gravity``) takes it at the
    attitudes ``q (E, 4)`` (the recording's reference), and the slopes are against it."""
    reading, reads = recent_force_g(windows), "force"  # what the linear path reads, in g
    if network.compensates_gravity:
        if q is None:
            return ["  angles: the network reads the car's acceleration, which needs an attitude; the recording "
                    "has no reference orientation"]
        reading, reads = acceleration_g(reading, q), "acceleration"
    with torch.no_grad():
        _, angles = network(windows, steady, reading if network.compensates_gravity else None)
    along = reading @ C_cb.T  # (E, 3) in g along the car's axes
    levels = torch.tensor([0.1, 0.5, 0.9], dtype=angles.dtype)
    lines = []
    for name, column, axis in (("pitch", 0, 0), ("yaw", 1, 1)):
        y, x = angles[:, column], along[:, axis]
        design = torch.stack((x, torch.ones_like(x)), -1)
        slope = float(torch.linalg.lstsq(design, y.unsqueeze(-1)).solution[0, 0])
        corr = float(torch.corrcoef(torch.stack((x, y)))[0, 1]) if float(y.std()) > 0 else float("nan")
        q10 = " / ".join(f"{v:+.4f}" for v in torch.quantile(y, levels).tolist())
        lines.append(f"  {name:>5} offset p10 / p50 / p90 {q10} rad; {slope:+.4f} rad per g of "
                     f"{'forward' if axis == 0 else 'lateral'} {reads}, correlation {corr:+.3f}")
    return lines


def reference_attitudes(recording, times: torch.Tensor) -> torch.Tensor | None:
    """``(E, 4)``: the recording's reference orientation at ``times (E,)`` (slerp), None without
    one or where a time lies outside it."""
    truth = recording.groundtruth
    if truth is None or truth.quat_wxyz is None or len(truth.t_s) < 2:
        return None
    association = associate(truth.t_s, times, max_dt_s=1.0)
    if len(association.ref_index) != len(times):
        return None
    return interpolate_quaternions(truth.quat_wxyz, association)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint")
    parser.add_argument("recordings", nargs="+")
    parser.add_argument("--rate-hz", type=float, default=1.0)
    parser.add_argument("--start-s", type=float, default=10.0)
    parser.add_argument("--end-s", type=float, default=0.0)
    parser.add_argument("--forward-axis", default="x", help="the IMU axis along the car's forward direction")
    parser.add_argument("--up-axis", default="z", help="the IMU axis along the car's up direction")
    args = parser.parse_args()
    params = FilterParameters.from_checkpoint(args.checkpoint)
    if "vehicle" not in params.adaptive:
        raise SystemExit(f"error: {args.checkpoint}: no adaptive vehicle noise in it (train with model.adaptive=[vehicle])")
    network = params.adaptive["vehicle"]
    values = params.values()
    sigmas = torch.tensor([values["vehicle_lateral_sigma_mps"], values["vehicle_vertical_sigma_mps"]], dtype=torch.float64)
    bound = 10.0 ** float(network.decades)
    car = VehicleSettings(forward_axis=args.forward_axis, up_axis=args.up_axis,
                          mount_pitch_rad=values["vehicle_mount_pitch_rad"], mount_yaw_rad=values["vehicle_mount_yaw_rad"])
    C_cb = car.vehicle_from_imu(sigmas)
    steady = steady_window(C_cb[2])
    print(f"{args.checkpoint}: constant σs {sigmas[0]:.3f} / {sigmas[1]:.3f} m/s, factors within "
          f"[{1 / bound:.3g}, {bound:.3g}]")
    print(f"{'recording':<40} {'updates':>7}  {'lateral σ p10 / p50 / p90 (m/s)':>32}  {'vertical σ p10 / p50 / p90':>28}  at a bound")
    for path in args.recordings:
        recording = read_folder(path, check_frames=False)
        imu = recording.imu
        t0 = float(imu.t_s[0])
        end = float(imu.t_s[-1]) if args.end_s <= 0 else t0 + args.end_s
        times = torch.arange(t0 + args.start_s, end, 1.0 / args.rate_hz, dtype=torch.float64)
        if not len(times):
            raise SystemExit(f"error: {path}: no update between --start-s and --end-s")
        q, pinned = summary(network, sigmas, imu.t_s, imu.acc_mps2, imu.gyro_rps, times, steady)
        lat = " / ".join(f"{v:.3f}" for v in q[:, 0].tolist())
        up = " / ".join(f"{v:.3f}" for v in q[:, 1].tolist())
        print(f"{path:<40} {len(times):>7}  {lat:>32}  {up:>28}  {pinned:>5} of {len(times)}")
        if network.angles:
            windows = imu_windows(imu.t_s, imu.acc_mps2, imu.gyro_rps, times)
            print("\n".join(angle_summary(network, windows, steady, C_cb, reference_attitudes(recording, times))))


if __name__ == "__main__":
    main()
