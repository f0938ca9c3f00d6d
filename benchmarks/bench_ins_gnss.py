"""INS + 1 Hz GNSS over a 300 s, 100 Hz synthetic stream: filter + smoother, float64.

Prints wall time, peak memory and the real-time factor of the fast path
(batched analytic Jacobians) and of the reference path (per-sample
``torch.func.jacrev``), and the ratio between them, all measured in this run.

    python benchmarks/bench_ins_gnss.py [--duration 300] [--reference-duration 300]

The reference path is slow (minutes for 300 s); ``--reference-duration`` runs it
on the first part of the stream only and the ratio is then per second of data.
"""
from __future__ import annotations

import argparse
import resource
import statistics
import time

import torch

from flowins.data.streams import GnssStream
from flowins.data.synthetic import synthetic_walk_recording
from flowins.navigation import NavigationConfig, NavigationRun, navigate


def _max_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _run(imu, gnss, jacobians: str, repeats: int = 1) -> tuple[float, float, object]:
    """Median wall time over ``repeats`` runs, process peak RSS after them (MiB) and the result."""
    config = NavigationConfig(jacobians=jacobians)
    walls = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = navigate(NavigationRun(imu, gnss), config=config)
        walls.append(time.perf_counter() - t0)
    return statistics.median(walls), _max_rss_mib(), result


def _crop_gnss(gnss: GnssStream, t_end_s: float) -> GnssStream:
    keep = gnss.t_s <= t_end_s
    return GnssStream(
        gnss.t_s[keep], gnss.lat_deg[keep], gnss.lon_deg[keep], gnss.alt_m[keep],
        gnss.h_acc_m[keep], gnss.v_acc_m[keep], name=gnss.name,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration", type=float, default=300.0, help="seconds of data (default 300)")
    parser.add_argument(
        "--reference-duration", type=float, default=60.0, help="seconds of data for the jacrev path (default 60)"
    )
    parser.add_argument("--repeats", type=int, default=3, help="timed runs of the fast path; the median is printed")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    rec = synthetic_walk_recording(duration_s=args.duration, seed=0)
    print(f"data: {args.duration:.0f} s, {len(rec.imu)} IMU samples ({rec.imu.rate_hz:.0f} Hz), {len(rec.gnss)} GNSS fixes")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, float64\n")

    # warm-up: first-call costs (pyproj transformer, torch kernels) are not per-run costs
    warm_imu = rec.imu.slice_time(0.0, 10.0)
    _run(warm_imu, _crop_gnss(rec.gnss, float(warm_imu.t_s[-1])), "analytic")
    base_mem = _max_rss_mib()
    print(f"process peak RSS after loading data: {base_mem:.0f} MiB")
    fast_wall, fast_mem, _ = _run(rec.imu, rec.gnss, "analytic", repeats=args.repeats)
    fast_rate = args.duration / fast_wall
    print(f"fast path (batched analytic Jacobians): {fast_wall:7.3f} s wall (median of {args.repeats}), process peak RSS {fast_mem:.0f} MiB, "
          f"{fast_rate:7.1f}x real time")

    ref_imu = rec.imu.slice_time(0.0, args.reference_duration)
    ref_gnss = _crop_gnss(rec.gnss, float(ref_imu.t_s[-1]))
    fast_ref_wall, _, fast_ref = _run(ref_imu, ref_gnss, "analytic")
    ref_wall, ref_mem, ref = _run(ref_imu, ref_gnss, "autodiff")
    ref_rate = args.reference_duration / ref_wall
    diff = (fast_ref.filter.node_mean - ref.filter.node_mean).abs().max().item()
    print(f"reference path (per-sample jacrev):     {ref_wall:7.3f} s wall for {args.reference_duration:.0f} s of data, "
          f"{ref_rate:7.2f}x real time")
    print(f"fast path on the same {args.reference_duration:.0f} s:              {fast_ref_wall:7.3f} s wall")
    print(f"\nspeed-up fast / reference (same data): {ref_wall / fast_ref_wall:7.1f}x")
    print(f"max |filter mean difference| between the paths: {diff:.2e}")
    print(f"target: >= 200x real time on 300 s -> {'met' if fast_rate >= 200 else 'NOT met'} ({fast_rate:.0f}x)")


if __name__ == "__main__":
    main()
