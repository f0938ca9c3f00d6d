"""The IMU checks a recording meets (consistency, saturation, noise from the still start) on a
clean set with realistic imperfections, and what the filter scores with them.

1. **Checks**: every recording of the clean set (simulated walks, car drives and drone flights;
   gyroscope biases up to 0.1 rad/s, accelerometer biases of 0.3 m/s², vibrating still starts,
   dropped samples; any real IMU files given) through ``gyro_consistency`` and
   ``find_saturation`` as they are (a refusal is a false alarm), with the gyroscope in deg/s
   (deg/s must be named) and with every axis clipped at its 99th-percentile magnitude
   (saturation must be named).
2. **A constant gyroscope bias**: a simulated walk with GNSS (2 s still start), with and without
   0.08 rad/s on one axis, through the job's IMU resolution and the filter: horizontal RMSE.
3. **Noise from a vibrating still start**: walks whose 5 s still start vibrates (accelerometer
   std 0.2-0.8 m/s²): the measured white floor against the simulator's, and the filter's RMSE
   with the measured model (``imu=auto`` on a recording that names no IMU), with ``phone``, and
   with the floor itself × 1 and × 10 (no preset below it).
4. **Mirrored accelerometer axes** (x and y swapped, z or x negated) on a walk with GNSS: the
   filter's RMSE and the run's warnings (``--sections 4``; no check looks for a mirror).

    python benchmarks/bench_imu_checks.py [/tmp/gtsam/gtsam/Data ...] [--seeds 2] [--sections 1 2 3 4] [--rate 200]

A folder holding ``KittiEquivBiasedImu.txt`` (the gtsam 4.3.0 wheel's ``gtsam/Data``) is read
as that file (t, dt, ax, ay, az, wx, wy, wz); any other folder through ``flowins.data.folder``.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

F64 = torch.float64


def _file(path: Path):
    kitti = path / "KittiEquivBiasedImu.txt"
    if kitti.is_file():
        rows = np.loadtxt(kitti, skiprows=1)[1:]
        return str(kitti), torch.tensor(rows[:, 0]), torch.tensor(rows[:, 2:5]), torch.tensor(rows[:, 5:8])
    from flowins.data.folder import read_folder

    imu = read_folder(path, check_frames=False).imu
    return str(path), imu.t_s, imu.acc_mps2, imu.gyro_rps


def _walk(seed: int, *, rate_hz: float = 100.0, vibration: float = 0.0, **imperfections):
    from flowins.data.synthetic import Imperfections, Vibration, WalkConfig, synthetic_walk_recording

    v = Vibration(vibration, vibration / 20, until_s=5.0) if vibration else Vibration()
    return synthetic_walk_recording(duration_s=120.0, seed=seed, imu_rate_hz=rate_hz, walk=WalkConfig(duration_s=120.0),
                                    vibration=v, imperfections=Imperfections(**imperfections))


def _drive(seed: int, **imperfections):
    from flowins.data.simulate.drive import DriveConfig, drive_sequence
    from flowins.data.synthetic import Imperfections

    config = DriveConfig(duration_s=120.0, outage_s=20.0, seed=seed, imperfections=Imperfections(**imperfections))
    return drive_sequence(config)[0].imu


def _flight(seed: int, bias=(0.0, 0.0, 0.0)):
    """The drone flight of bench_tracks.py (3 s on the ground, a figure of eight), its ADIS16448-like IMU."""
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_tracks import Flight

    from flowins.data.synthetic import ImuErrors, corrupt_imu, increment_imu

    t = torch.arange(0, 60 * 200 + 1, dtype=F64) / 200.0
    f_true, w_true = increment_imu(Flight(), t)
    errors = ImuErrors(acc_noise=2.0e-3, gyro_noise=1.7e-4, acc_bias_std=0.02, gyro_bias_std=2e-3,
                       acc_bias_walk=3e-3, gyro_bias_walk=1.9e-5, acc_scale_std=0.002)
    acc, gyro, _ = corrupt_imu(t, f_true, w_true, errors, torch.Generator().manual_seed(seed))
    return t, acc, gyro + torch.tensor(bias, dtype=F64)


def clean_set(paths: list[Path], seeds: int):
    """(name, t, acc, gyro) of the clean set: sound recordings, imperfect as real ones are."""
    for seed in range(seeds):
        imu = _walk(seed).imu
        yield f"walk {seed}", imu.t_s, imu.acc_mps2, imu.gyro_rps
        imu = _walk(seed, gyro_bias_rps=(0.08, 0.0, 0.0), acc_bias_mps2=(0.3, -0.3, 0.3)).imu
        yield f"walk {seed}, gyro bias 0.08 rad/s x, acc bias 0.3", imu.t_s, imu.acc_mps2, imu.gyro_rps
        imu = _walk(seed, gyro_bias_rps=(0.0, -0.1, 0.05)).imu
        yield f"walk {seed}, gyro bias (0, -0.1, 0.05) rad/s", imu.t_s, imu.acc_mps2, imu.gyro_rps
        imu = _walk(seed, rate_hz=200.0, vibration=0.8, drop_fraction=0.01, drop_run=3).imu
        yield f"walk {seed}, 200 Hz, still start vibrating 0.8 m/s², 1 % dropped", imu.t_s, imu.acc_mps2, imu.gyro_rps
        imu = _drive(seed)
        yield f"drive {seed}", imu.t_s, imu.acc_mps2, imu.gyro_rps
        imu = _drive(seed, gyro_bias_rps=(0.08, -0.05, 0.1), drop_fraction=0.02)
        yield f"drive {seed}, gyro bias (0.08, -0.05, 0.1), 2 % dropped", imu.t_s, imu.acc_mps2, imu.gyro_rps
        yield (f"drone {seed}", *_flight(seed))
        yield (f"drone {seed}, gyro bias (-0.002, 0.021, 0.077) (EuRoC's)", *_flight(seed, (-0.002, 0.021, 0.077)))
    for path in paths:
        yield _file(path)


def checks(paths: list[Path], seeds: int) -> None:
    """Section 1 (module docstring)."""
    from flowins.ins.consistency import gyro_consistency
    from flowins.ins.saturation import find_saturation

    print("1. checks on the clean set: as recorded / gyroscope in deg/s / every axis clipped at its 99th percentile")
    print(f"   {'recording':<62} {'consistency':<26} {'deg/s':<10} {'saturation':<12} {'clipped':<10} {'s':>5}")
    alarms = missed = unnamed = 0
    for name, t, acc, gyro in clean_set(paths, seeds):
        start = time.perf_counter()
        r = gyro_consistency(t, acc, gyro)
        bias = "" if r.bias_rps is None else " less " + ",".join(f"{b:.3f}" for b in r.bias_rps)
        deg = gyro_consistency(t, acc, gyro * (180.0 / math.pi))
        sat = find_saturation(t, acc, gyro)
        limit_a = acc.abs().quantile(0.99, dim=0)
        limit_g = gyro.abs().quantile(0.99, dim=0)
        clipped = find_saturation(t, acc.clamp(-limit_a, limit_a), gyro.clamp(-limit_g, limit_g))
        alarms += (not r.consistent) + bool(sat)
        missed += deg.fix != "deg/s"
        unnamed += not clipped
        print(f"   {name[-62:]:<62} {('ok' if r.consistent else 'REFUSED') + bias:<26} "
              f"{deg.fix or 'MISSED':<10} {('none' if not sat else f'FALSE {len(sat)}'):<12} "
              f"{f'{len(clipped)} axes':<10} {time.perf_counter() - start:>5.2f}")
    print(f"   false alarms on the clean set: {alarms}; deg/s not named: {missed}; clipped recordings with no axis "
          f"not named: {unnamed}")


def _score(rec, imu_model) -> float:
    return _run(rec, imu_model)[0]


def _run(rec, imu_model):
    """The filter's horizontal RMSE on a simulated walk with GNSS, and the navigation result."""
    from flowins.geometry.geodesy import LocalTangentPlane
    from flowins.navigation import NavigationConfig, NavigationRun, navigate
    from flowins.state import STATE

    result = navigate(NavigationRun(rec.imu, rec.gnss), config=NavigationConfig(noise=imu_model.process_noise()))
    f = result.frame
    shift = LocalTangentPlane(60.1699, 24.9384, 20.0).to_enu(f.origin_lat_deg, f.origin_lon_deg, f.origin_alt_m)
    t = result.filter.t_s
    truth = rec.walk.position(t) - rec.walk.position(rec.imu.t_s[:1])[0] - shift
    return float((result.filter.node_mean[:, STATE.p] - truth)[:, :2].norm(dim=-1).pow(2).mean().sqrt()), result


class _Rec:
    def __init__(self, imu, sensor=None):
        self.imu, self.sensor = imu, sensor


def _auto():
    import yaml

    root = Path(__file__).resolve().parents[1] / "configs" / "imu"
    cfg = {k: v for k, v in yaml.safe_load((root / "auto.yaml").read_text()).items() if k != "defaults"}
    for preset in ("phone", "simulated_walk"):
        cfg[preset] = yaml.safe_load((root / f"{preset}.yaml").read_text())
    return cfg


def bias_score(seeds: int) -> None:
    from flowins.data.synthetic import Imperfections, WalkConfig, synthetic_walk_recording
    from flowins.sensor import resolve_imu

    print("\n2. 120 s walk with GNSS, 2 s still start, imu=auto as for a recording that names its sensor "
          "(simulated_walk): horizontal RMSE")
    for seed in range(seeds):
        cells = []
        for bias in ((0.0, 0.0, 0.0), (0.08, 0.0, 0.0), (0.0, 0.0, 0.08)):
            rec = synthetic_walk_recording(duration_s=120.0, seed=seed, walk=WalkConfig(duration_s=120.0, stationary_s=2.0),
                                           imperfections=Imperfections(gyro_bias_rps=bias))
            model = resolve_imu(_auto(), [_Rec(rec.imu, "simulated_walk")], recorded=True)  # the checks run here
            cells.append(f"bias {bias}: {_score(rec, model):.2f} m")
        print(f"   seed {seed}: " + ", ".join(cells))


def noise_score(seeds: int, rate_hz: float) -> None:
    import dataclasses

    from flowins.data.synthetic import ImuErrors
    from flowins.ins.imu_model import still_noise_densities
    from flowins.ins.initialization import still_interval
    from flowins.sensor import resolve_imu

    truth = ImuErrors()
    print(f"\n3. vibrating still start (5 s), 120 s walk with GNSS at {rate_hz:g} Hz; simulator's white noise acc "
          f"{truth.acc_noise:g}, gyro {truth.gyro_noise:g}")
    for vibration in (0.2, 0.5, 0.8):
        for seed in range(seeds):
            rec = _walk(seed, rate_hz=rate_hz, vibration=vibration)
            imu = rec.imu
            still = still_interval(imu.t_s, imu.acc_mps2, imu.gyro_rps)
            m = still_noise_densities(imu.t_s, imu.acc_mps2, imu.gyro_rps, still.end)
            auto = resolve_imu(_auto(), [_Rec(imu)], recorded=True)
            phone = resolve_imu(_auto() | {"still_noise": False}, [_Rec(imu)], recorded=True)
            bare = [dataclasses.replace(phone, acc_noise=m.acc_noise, gyro_noise=m.gyro_noise, inflation=k)
                    for k in (1.0, 10.0)]
            print(f"   std {vibration} m/s², seed {seed}: still {still.duration_s:.1f} s ({'' if m.trusted else 'not '}"
                  f"trusted), floor acc {m.acc_noise / truth.acc_noise:.2f}× gyro {m.gyro_noise / truth.gyro_noise:.2f}× "
                  f"the truth (all variance as white: {m.acc_raw / truth.acc_noise:.1f}×, "
                  f"{m.gyro_raw / truth.gyro_noise:.1f}×); RMSE {auto.name} {_score(rec, auto):.2f} m, phone "
                  f"{_score(rec, phone):.2f} m, floor × 1 {_score(rec, bare[0]):.2f} m, × 10 {_score(rec, bare[1]):.2f} m")


def mirror_score(seeds: int) -> None:
    """Section 4: an accelerometer whose axes are mirrored (no check of its own looks for it)."""
    import dataclasses

    from flowins.data.synthetic import WalkConfig, synthetic_walk_recording
    from flowins.evaluation.run_report import run_warnings
    from flowins.sensor import resolve_imu

    print("\n4. 120 s walk with GNSS, 2 s still start, simulated_walk noise, the accelerometer's axes mirrored: "
          "horizontal RMSE and what the job warns")
    mirrors = {"as recorded": ([0, 1, 2], (1.0, 1.0, 1.0)), "x, y swapped": ([1, 0, 2], (1.0, 1.0, 1.0)),
               "z negated": ([0, 1, 2], (1.0, 1.0, -1.0)), "x negated": ([0, 1, 2], (-1.0, 1.0, 1.0))}
    for seed in range(seeds):
        clean = synthetic_walk_recording(duration_s=120.0, seed=seed, walk=WalkConfig(duration_s=120.0, stationary_s=2.0))
        for name, (order, sign) in mirrors.items():
            acc = clean.imu.acc_mps2[:, order] * torch.tensor(sign, dtype=clean.imu.acc_mps2.dtype)
            rec = dataclasses.replace(clean, imu=dataclasses.replace(clean.imu, acc_mps2=acc))
            try:
                model = resolve_imu(_auto(), [_Rec(rec.imu, "simulated_walk")], recorded=True)  # the checks run here
            except ValueError as error:
                print(f"   seed {seed}, {name}: refused: {error}")
                continue
            rmse, result = _run(rec, model)
            print(f"   seed {seed}, {name}: {rmse:.2f} m; warnings: {run_warnings(result) or 'none'}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("paths", nargs="*", type=Path, help="real IMU folders (KITTI from gtsam's wheel, flowins folders)")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--sections", type=int, nargs="+", default=[1, 2, 3], choices=[1, 2, 3, 4])
    parser.add_argument("--rate", type=float, default=200.0, help="IMU rate of section 3's walks (Hz)")
    args = parser.parse_args()
    if 1 in args.sections:
        checks(args.paths, args.seeds)
    if 2 in args.sections:
        bias_score(args.seeds)
    if 3 in args.sections:
        noise_score(args.seeds, args.rate)
    if 4 in args.sections:
        mirror_score(args.seeds)


if __name__ == "__main__":
    main()
