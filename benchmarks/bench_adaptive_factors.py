"""What a trained adaptive-noise network sets: its σ factors over recordings.

``model.adaptive=[vehicle]`` learns a network that multiplies the vehicle constraint's σs at
each update by a factor within ``10^±model.adaptive_decades`` (docs/training.md). A network that
adapts spreads its factors with the road; one that learned only a level sets the same factor
everywhere, and one pinned at its bound says the bound, not the data, set it. For each
recording this prints the checkpoint's learned constant σs times the factors' 10th, 50th and
90th percentiles at a 1 Hz update rate (the constraint's default), laterally and vertically,
and how many updates sit within 1 % of a bound::

    python benchmarks/bench_adaptive_factors.py RUN/checkpoints/best.ckpt /tmp/drv_s2 /tmp/kitti/recordings/kitti-seed0 \
        [--rate-hz 1] [--start-s 10] [--end-s 0]

``--start-s`` / ``--end-s`` crop each recording (seconds after its first IMU sample; end 0: to
its end).
"""
from __future__ import annotations

import argparse
import math

import torch

from flowins.data.folder.reading import read_folder
from flowins.measurements.adaptive_noise import imu_windows
from flowins.training.parameters import FilterParameters


def summary(network, sigmas: torch.Tensor, t_s: torch.Tensor, acc: torch.Tensor, gyro: torch.Tensor,
            times: torch.Tensor) -> tuple[torch.Tensor, int]:
    """The σs ``sigmas`` ``(2,)`` times the network's factors at the update times ``times`` ``(E,)``:
    their 10th, 50th and 90th percentiles ``(3, 2)``, and the updates with a factor within 1 % of
    a bound."""
    with torch.no_grad():
        f = network(imu_windows(t_s, acc, gyro, times))
    levels = torch.tensor([0.1, 0.5, 0.9], dtype=f.dtype)
    log_bound = float(network.decades) * math.log(10.0)
    pinned = ((f.log().abs() - log_bound).abs() < math.log(1.01)).any(-1).sum()
    return torch.quantile(f, levels, dim=0) * sigmas, int(pinned)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint")
    parser.add_argument("recordings", nargs="+")
    parser.add_argument("--rate-hz", type=float, default=1.0)
    parser.add_argument("--start-s", type=float, default=10.0)
    parser.add_argument("--end-s", type=float, default=0.0)
    args = parser.parse_args()
    params = FilterParameters.from_checkpoint(args.checkpoint)
    if "vehicle" not in params.adaptive:
        raise SystemExit(f"error: {args.checkpoint}: no adaptive vehicle noise in it (train with model.adaptive=[vehicle])")
    network = params.adaptive["vehicle"]
    values = params.values()
    sigmas = torch.tensor([values["vehicle_lateral_sigma_mps"], values["vehicle_vertical_sigma_mps"]], dtype=torch.float64)
    bound = 10.0 ** float(network.decades)
    print(f"{args.checkpoint}: constant σs {sigmas[0]:.3f} / {sigmas[1]:.3f} m/s, factors within "
          f"[{1 / bound:.3g}, {bound:.3g}]")
    print(f"{'recording':<40} {'updates':>7}  {'lateral σ p10 / p50 / p90 (m/s)':>32}  {'vertical σ p10 / p50 / p90':>28}  at a bound")
    for path in args.recordings:
        imu = read_folder(path, check_frames=False).imu
        t0 = float(imu.t_s[0])
        end = float(imu.t_s[-1]) if args.end_s <= 0 else t0 + args.end_s
        times = torch.arange(t0 + args.start_s, end, 1.0 / args.rate_hz, dtype=torch.float64)
        if not len(times):
            raise SystemExit(f"error: {path}: no update between --start-s and --end-s")
        q, pinned = summary(network, sigmas, imu.t_s, imu.acc_mps2, imu.gyro_rps, times)
        lat = " / ".join(f"{v:.3f}" for v in q[:, 0].tolist())
        up = " / ".join(f"{v:.3f}" for v in q[:, 1].tolist())
        print(f"{path:<40} {len(times):>7}  {lat:>32}  {up:>28}  {pinned:>5} of {len(times)}")


if __name__ == "__main__":
    main()
