"""flowins' relative pose error against evo's on one shared case.

    pip download --no-deps evo -d /tmp/evo && (cd /tmp/evo && unzip -o evo-*.whl 'evo/*')
    PYTHONPATH=/tmp/evo python benchmarks/bench_drift_evo.py

A wandering 3-D walk (600 poses at 10 Hz, its attitude turning) as the truth, and an
estimate that is 3 % long, walks off in position, drifts in yaw and carries attitude noise.
For the translation part and the rotation angle, with evo's pairs (non-overlapping) and with
all pairs, it prints evo's RMSE and flowins' (:func:`flowins.evaluation.drift.rpe`), their
pair counts and the relative difference. evo is read from wherever Python finds it (only its
``evo.core`` modules are used, which need NumPy and SciPy); flowins does not depend on it.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

from flowins.evaluation.drift import rpe
from flowins.geometry import quaternion


def euler_wxyz(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    cr, sr, cp, sp = np.cos(roll / 2), np.sin(roll / 2), np.cos(pitch / 2), np.sin(pitch / 2)
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    return np.stack([cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                     cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy], -1)


def shared_case(seed: int, n: int = 600):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.1
    yaw = np.cumsum(rng.normal(0.0, 0.02, n))
    pitch, roll = 0.1 * np.sin(0.05 * t), 0.05 * np.cos(0.03 * t)
    q_ref = euler_wxyz(roll, pitch, yaw)
    p_ref = np.cumsum(np.stack([np.cos(yaw), np.sin(yaw), 0.1 * np.sin(0.1 * t)], -1) * 0.14, 0)
    q_est = euler_wxyz(roll + rng.normal(0, 0.01, n), pitch + rng.normal(0, 0.01, n),
                       yaw + 0.002 * t + rng.normal(0, 0.01, n))
    p_est = 1.03 * p_ref + np.cumsum(rng.normal(0.0, 0.01, (n, 3)), 0)
    return t, p_ref, q_ref, p_est, q_est


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--delta", type=int, default=50, help="pair span in samples")
    args = parser.parse_args()
    try:
        from evo.core import metrics, trajectory
    except ImportError:
        print("error: evo is not importable: pip install evo, or put its wheel's evo/ folder on PYTHONPATH "
              "(see this script's docstring)", file=sys.stderr)
        return 2
    t, p_ref, q_ref, p_est, q_est = shared_case(args.seed)
    ref = trajectory.PoseTrajectory3D(p_ref, q_ref, t)
    est = trajectory.PoseTrajectory3D(p_est, q_est, t)
    as_t = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    R_ref, R_est = quaternion.to_matrix(as_t(q_ref)), quaternion.to_matrix(as_t(q_est))
    print(f"{'relation':<22}{'pairs':<10}{'evo RMSE':>18}{'flowins RMSE':>18}{'relative difference':>22}")
    worst = 0.0
    for relation in (metrics.PoseRelation.translation_part, metrics.PoseRelation.rotation_angle_rad):
        for all_pairs in (False, True):
            metric = metrics.RPE(relation, delta=args.delta, delta_unit=metrics.Unit.frames, all_pairs=all_pairs)
            metric.process_data((ref, est))
            theirs = metric.get_all_statistics()["rmse"]
            ours = rpe(as_t(t), R_ref, as_t(p_ref), R_est, as_t(p_est), delta=args.delta, unit="f",
                       all_pairs=all_pairs)
            mine = ours.translation_rmse_m if relation == metrics.PoseRelation.translation_part else ours.rotation_rmse_rad
            diff = abs(mine - theirs) / abs(theirs)
            worst = max(worst, diff)
            pairs = f"{ours.pairs}/{len(metric.error)}" + (" all" if all_pairs else "")
            print(f"{relation.name:<22}{pairs:<10}{theirs:>18.12f}{mine:>18.12f}{diff:>22.2e}")
    print(f"largest relative difference: {worst:.2e} (pairs: flowins/evo)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
