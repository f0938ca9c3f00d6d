"""Noise-free IMU integration error over 60 s of walking for two simulated IMU sample models.

* increment: the simulator's samples (an integrating IMU: the constant rate and
  specific force that reproduce each interval's attitude and velocity increments);
* instantaneous: the exact rate and specific force at each interval's midpoint.

Both integrated by flowins' midpoint mechanization from the true initial state (100 Hz,
10 % timestamp jitter). Prints the largest position error. Usage:
``python benchmarks/bench_imu_sampling.py``
"""
from __future__ import annotations

import torch

from flowins.data.synthetic import Walk, WalkConfig, increment_imu, sample_times
from flowins.filter.propagation import propagate_mean
from flowins.ins.mechanization import STANDARD_GRAVITY_MPS2
from flowins.state import make_state, split


def main() -> None:
    walk = Walk(WalkConfig())
    t = sample_times(65.0, 100.0, 0.1, torch.Generator().manual_seed(11))
    x0 = make_state(p=walk.position(t[0]), v=walk.velocity(t[:1])[0], q=walk.quaternion(t[0]))
    acc_inc, gyro_inc = increment_imu(walk, t)
    acc_mid, gyro_mid = walk.imu(0.5 * (t[1:] + t[:-1]))
    for label, acc, gyro in (("increment (simulator)", acc_inc[1:], gyro_inc[1:]), ("instantaneous (midpoint)", acc_mid, gyro_mid)):
        xs = propagate_mean(x0, acc, gyro, torch.diff(t), STANDARD_GRAVITY_MPS2, "midpoint")
        err = (split(xs).p - walk.position(t[1:])).norm(dim=-1)
        print(f"{label:<26} max position error over {float(t[-1] - t[0]):.0f} s: {float(err.max()):.3g} m")


if __name__ == "__main__":
    main()
