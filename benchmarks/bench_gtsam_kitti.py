"""GTSAM side by side: iSAM2 with IMU preintegration and GPS factors on a flowins recording.

The recordings of ``bench_real_kitti.py`` (the real KITTI IMU, fixes made from its reference
track) are run through a factor graph built the way GTSAM's own KITTI example builds it: a
pose, a velocity and an IMU bias at every GNSS fix, the IMU preintegrated between fixes
(``ImuFactor``), a bias random walk between consecutive biases, and a ``GPSFactor`` per fix,
solved incrementally with iSAM2. The causal estimate at a reference time is the prediction
from the newest solved state (before the next fix arrives); the smoothed one, the prediction
from the fully solved state of the fix before it. Both are scored as ``evaluate.py`` scores
flowins (SE(3) Procrustes alignment to the reference, RMSE), over a grid of IMU noise
scales, with flowins' ``ins_gnss`` row on the same recording beside them.

GTSAM is not a flowins dependency: ``pip install gtsam==4.3.0`` (or the wheel the KITTI files
come from) in the same environment. The starting pose (roll and pitch from the first second's
specific force, yaw from the course between the first two fixes) is given to both filters alike.

    python benchmarks/bench_real_kitti.py /tmp/gtsam/gtsam/Data --out /tmp/kitti --seeds 0
    python benchmarks/bench_gtsam_kitti.py /tmp/kitti/recordings/kitti-seed0 [evaluate.py overrides ...]
"""
from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

# the KittiEquivBiasedImu_metadata.txt figures (the GTSAM example's noise)
ACC_SIGMA, GYRO_SIGMA, ACC_BIAS_SIGMA, GYRO_BIAS_SIGMA = 0.01, 0.000175, 0.000167, 2.91e-6


def _rmse(t_est: np.ndarray, p_est: np.ndarray, truth) -> float:
    from flowins.evaluation import trajectory_errors

    return trajectory_errors(torch.from_numpy(t_est), torch.from_numpy(p_est), truth.t_s, truth.pos_m,
                             max_dt_s=0.06, align="se3").rmse_m


def _predictions(pim, state, bias, t_imu, acc, gyro, rows, t_start: float, refs: np.ndarray) -> list:
    """Positions predicted from ``state`` at each of ``refs`` (increasing), integrating the
    IMU ``rows`` (from ``t_start``) into ``pim`` on the way; a reference time is taken at the
    first sample at or after it."""
    out, j, t_prev = [], 0, t_start
    for r in rows:
        dt = t_imu[r] - t_prev
        if dt > 0:
            pim.integrateMeasurement(acc[r], gyro[r], dt)
        t_prev = t_imu[r]
        while j < len(refs) and refs[j] <= t_prev:
            out.append(pim.predict(state, bias).pose().translation())
            j += 1
    return out


def run_gtsam(seq, enu: np.ndarray, sigma_m: np.ndarray, *, imu_scale: float) -> tuple[float, float]:
    """(causal RMSE, smoothed RMSE) of iSAM2 on ``seq`` with the IMU noise × ``imu_scale``."""
    import gtsam
    from gtsam.symbol_shorthand import B, V, X

    t_imu = seq.imu.t_s.numpy()
    acc, gyro = seq.imu.acc_mps2.numpy(), seq.imu.gyro_rps.numpy()
    t_fix = seq.gnss.t_s.numpy()
    truth = seq.groundtruth
    t_ref = truth.t_s.numpy()
    params = gtsam.PreintegrationParams.MakeSharedU(9.80665)
    params.setAccelerometerCovariance(np.eye(3) * (imu_scale * ACC_SIGMA) ** 2)
    params.setGyroscopeCovariance(np.eye(3) * (imu_scale * GYRO_SIGMA) ** 2)
    params.setIntegrationCovariance(np.eye(3) * 1e-8)
    # the start: roll and pitch from the first second's mean specific force, yaw from the first two fixes
    f = acc[t_imu <= t_imu[0] + 1.0].mean(0)
    roll, pitch = math.atan2(f[1], f[2]), math.atan2(-f[0], math.hypot(f[1], f[2]))
    d = enu[1] - enu[0]
    yaw = math.atan2(d[1], d[0])
    v0 = d / (t_fix[1] - t_fix[0])
    pose0 = gtsam.Pose3(gtsam.Rot3.Ypr(yaw, pitch, roll), gtsam.Point3(*enu[0]))
    bias0 = gtsam.imuBias.ConstantBias()
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(X(0), pose0, gtsam.noiseModel.Diagonal.Sigmas(
        np.array([0.05, 0.05, 0.3, *(sigma_m[0],) * 3]))))
    graph.add(gtsam.PriorFactorVector(V(0), v0, gtsam.noiseModel.Isotropic.Sigma(3, 2.0)))
    graph.add(gtsam.PriorFactorConstantBias(B(0), bias0, gtsam.noiseModel.Diagonal.Sigmas(
        np.array([0.1, 0.1, 0.1, 0.01, 0.01, 0.01]))))
    values.insert(X(0), pose0)
    values.insert(V(0), v0)
    values.insert(B(0), bias0)
    isam = gtsam.ISAM2()
    isam.update(graph, values)
    state, bias = gtsam.NavState(pose0, v0), bias0
    causal_t, causal_p, segments = [], [], []  # segments: (key, IMU rows, reference times) for the smoother
    row = int(np.searchsorted(t_imu, t_fix[0]))
    for k in range(1, len(t_fix) + 1):
        t_end = t_fix[k] if k < len(t_fix) else t_imu[-1]
        pim = gtsam.PreintegratedImuMeasurements(params, bias)
        refs = t_ref[(t_ref > (t_fix[k - 1])) & (t_ref <= t_end)]
        first_row = row
        row = int(np.searchsorted(t_imu, t_end, side="right"))
        predicted = _predictions(pim, state, bias, t_imu, acc, gyro, range(first_row, row), t_fix[k - 1], refs)
        causal_t += list(refs[: len(predicted)])
        causal_p += predicted
        segments.append((k - 1, first_row, row, refs))
        if k == len(t_fix):
            break
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(gtsam.ImuFactor(X(k - 1), V(k - 1), X(k), V(k), B(k - 1), pim))
        dt_k = t_fix[k] - t_fix[k - 1]
        graph.add(gtsam.BetweenFactorConstantBias(B(k - 1), B(k), gtsam.imuBias.ConstantBias(),
                                                  gtsam.noiseModel.Diagonal.Sigmas(math.sqrt(dt_k) * np.array(
                                                      [*(ACC_BIAS_SIGMA,) * 3, *(GYRO_BIAS_SIGMA,) * 3]) * imu_scale)))
        graph.add(gtsam.GPSFactor(X(k), gtsam.Point3(*enu[k]), gtsam.noiseModel.Isotropic.Sigma(3, sigma_m[k])))
        predicted = pim.predict(state, bias)
        values.insert(X(k), predicted.pose())
        values.insert(V(k), predicted.velocity())
        values.insert(B(k), bias)
        isam.update(graph, values)
        estimate = isam.calculateEstimate()
        state = gtsam.NavState(estimate.atPose3(X(k)), estimate.atVector(V(k)))
        bias = estimate.atConstantBias(B(k))
    final = isam.calculateEstimate()
    smooth_t, smooth_p = [], []
    for key, first_row, last_row, refs in segments:
        b = final.atConstantBias(B(key))
        s = gtsam.NavState(final.atPose3(X(key)), final.atVector(V(key)))
        pim = gtsam.PreintegratedImuMeasurements(params, b)
        predicted = _predictions(pim, s, b, t_imu, acc, gyro, range(first_row, last_row), t_fix[key], refs)
        smooth_t += list(refs[: len(predicted)])
        smooth_p += predicted
    return (_rmse(np.array(causal_t), np.array(causal_p), truth), _rmse(np.array(smooth_t), np.array(smooth_p), truth))


def run_flowins(folder: Path, overrides: list[str]) -> tuple[float, float]:
    out = Path(tempfile.mkdtemp(prefix="flowins-gtsam-"))
    cmd = [sys.executable, "evaluate.py", f"sequence.path={folder}", "combinations=[ins_gnss]", "plots=false",
           "progress=false", f"hydra.run.dir={out}", *overrides]
    subprocess.run(cmd, check=True, capture_output=True, cwd=Path(__file__).resolve().parents[1])
    m = json.loads((out / "metrics.json").read_text())["ins_gnss"]
    return m["filter_rmse_m"], m["smoother_rmse_m"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("recording", type=Path, help="a recording folder written by bench_real_kitti.py")
    parser.add_argument("--scales", type=float, nargs="+", default=[1.0, 3.0, 10.0, 30.0],
                        help="IMU noise scales of GTSAM's grid (× the KITTI metadata's sigmas)")
    parser.add_argument("overrides", nargs="*", help="evaluate.py overrides for the flowins row")
    args = parser.parse_args()
    try:
        import gtsam  # noqa: F401
    except ImportError:
        raise SystemExit("error: gtsam is not installed: pip install gtsam==4.3.0 (not a flowins dependency)") from None
    from flowins.data.folder import read_folder
    from flowins.geometry.geodesy import LocalTangentPlane

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_real_kitti import ORIGIN

    seq = read_folder(args.recording, check_frames=False)
    if seq.gnss is None or seq.groundtruth is None:
        raise SystemExit(f"error: {args.recording}: needs gnss.csv and groundtruth.csv (bench_real_kitti.py writes both)")
    g = seq.gnss
    enu = LocalTangentPlane(*ORIGIN).to_enu(g.lat_deg, g.lon_deg, g.alt_m).numpy()
    sigma = g.h_acc_m.numpy()
    print(f"{args.recording.name}: {len(g.t_s)} fixes over {float(g.t_s[-1] - g.t_s[0]):.0f} s\n")
    print(f"{'':<34} {'causal':>9} {'smoothed':>9} {'time':>7}")
    best = None
    for scale in args.scales:
        t = time.perf_counter()
        causal, smooth = run_gtsam(seq, enu, sigma, imu_scale=scale)
        print(f"{'GTSAM iSAM2, IMU noise x' + format(scale, 'g'):<34} {causal:>7.2f} m {smooth:>7.2f} m "
              f"{time.perf_counter() - t:>6.1f}s")
        best = min(best or (causal, smooth, scale), (causal, smooth, scale))
    t = time.perf_counter()
    filt, smooth = run_flowins(args.recording, args.overrides)
    label = "flowins ins_gnss" + (f" ({' '.join(args.overrides)})" if args.overrides else "")
    print(f"{label[:34]:<34} {filt:>7.2f} m {smooth:>7.2f} m {time.perf_counter() - t:>6.1f}s")
    print(f"\nbest GTSAM (causal): x{best[2]:g}, {best[0]:.2f} / {best[1]:.2f} m; flowins {filt:.2f} / {smooth:.2f} m "
          f"(filter/smoother, SE(3)-aligned RMSE against the reference)")


if __name__ == "__main__":
    main()
