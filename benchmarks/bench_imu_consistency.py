"""The gyroscope consistency check (flowins/ins/consistency.py) on real and simulated IMU files.

For each recording it prints the check's verdict on the readings as they are and on the same
readings with the gyroscope in deg/s (× 180/π) and with its x and y axes swapped: no false
alarm on the clean ones, deg/s named on every converted one (the swap is not claimed).

    python benchmarks/bench_imu_consistency.py ~/.cache/flowins/simulated/*/ /tmp/gtsam/gtsam/Data --drives 4
    python benchmarks/bench_imu_consistency.py DIR ...     # flowins folders (imu.csv) or EuRoC/KITTI folders

A folder holding ``KittiEquivBiasedImu.txt`` (the gtsam 4.3.0 wheel's ``gtsam/Data``) is read
as that file (t, dt, ax, ay, az, wx, wy, wz); any other folder through ``flowins.data.load``.
"""
from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch


def _readings(path: Path) -> tuple[str, torch.Tensor, torch.Tensor, torch.Tensor]:
    kitti = path / "KittiEquivBiasedImu.txt"
    if kitti.is_file():
        rows = np.loadtxt(kitti, skiprows=1)[1:]
        return str(kitti), torch.tensor(rows[:, 0]), torch.tensor(rows[:, 2:5]), torch.tensor(rows[:, 5:8])
    from flowins.data.folder import read_folder

    imu = read_folder(path, check_frames=False).imu
    return str(path), imu.t_s, imu.acc_mps2, imu.gyro_rps


def _drive(seed: int) -> tuple[str, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A simulated car drive's IMU (flowins.data.simulate.drive, 300 s)."""
    import dataclasses

    from flowins.data.simulate.drive import DriveConfig, drive_sequence

    imu = drive_sequence(dataclasses.replace(DriveConfig(), seed=seed))[0].imu
    return f"simulated drive, seed {seed}", imu.t_s, imu.acc_mps2, imu.gyro_rps


def main() -> None:
    from flowins.ins.consistency import gyro_consistency

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("paths", nargs="*", type=Path, help="recording folders")
    parser.add_argument("--drives", type=int, default=0, help="also this many simulated car drives (seeds 0, 1, ...)")
    args = parser.parse_args()
    print(f"{'recording':<60} {'s':>6}  {'clean':<22} {'deg/s':<22} {'x<->y':<22} {'time':>6}")
    alarms = missed = 0
    for path in [*args.paths, *(f"drive:{seed}" for seed in range(args.drives))]:
        try:
            name, t, acc, gyro = _drive(int(path[6:])) if isinstance(path, str) else _readings(path)
        except (ValueError, OSError) as exc:
            print(f"{str(path):<60} skipped: {exc}")
            continue
        start = time.perf_counter()
        cells = []
        for label, g in (("clean", gyro), ("deg/s", gyro * (180.0 / math.pi)), ("swap", gyro[:, [1, 0, 2]])):
            r = gyro_consistency(t, acc, g)
            verdict = "ok" if r.consistent else f"FAIL{' ' + r.fix if r.fix else ''}"
            cells.append(f"{verdict} {math.degrees(r.gyro_error_rad):.1f}/{math.degrees(r.still_error_rad):.1f}°")
            alarms += label == "clean" and not r.consistent
            missed += label == "deg/s" and r.fix != "deg/s"
        elapsed = (time.perf_counter() - start) / 3
        print(f"{name[-60:]:<60} {float(t[-1] - t[0]):>6.0f}  {cells[0]:<22} {cells[1]:<22} {cells[2]:<22} "
              f"{elapsed:>5.2f}s")
    print(f"\nfalse alarms on clean readings: {alarms}; deg/s not named: {missed}  "
          "(cells: verdict, median gyroscope / no-rotation gravity-direction error)")


if __name__ == "__main__":
    main()
