"""Peak memory and time of one training step on a 30 s window (target: < 4 GB on CPU).

Each measurement runs in a fresh process (``ru_maxrss`` only grows), on the same
window of a simulated walk (seed 1, the first training sequence of ``configs/data/simulated.yaml``),
with the training config's settings (128 points per frame, soft gates, SpyNet flow in
closed-form dropout mode, computed once and cached):

* reference: the filter over the window without gradients (inference);
* training step: the same window with the graph kept, the loss and its backward pass.

    python benchmarks/bench_train_memory.py [--window 30] [--points 128] [--method ins_gnss_dense]
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time


def measure(mode: str, window_s: float, points: int, method: str) -> dict:

    from pathlib import Path

    import hydra
    import torch
    from omegaconf import OmegaConf

    from flowins.settings import flow_config, training_setup
    from flowins.training.data import load_training_sequence
    from flowins.training.parameters import FilterParameters
    from flowins.training.unroll import run_window, window_loss

    torch.set_num_threads(2)
    configs = Path(__file__).resolve().parents[1] / "configs"
    with hydra.initialize_config_dir(config_dir=str(configs), version_base="1.3"):
        cfg = OmegaConf.to_container(hydra.compose("train", overrides=["output_dir=/tmp"]), resolve=True)
    seq = load_training_sequence({"seed": 1, "duration_s": 60.0}, {**cfg, "flow": flow_config(cfg, moments=True)},
                                 methods=[method])
    cfg["filter"]["flow"]["n_points"] = points
    setup = training_setup(cfg, [seq], recorded=False)
    base = setup.filter.navigation
    _, start, learn = setup.parameters
    params = FilterParameters(start, learn, bounds=setup.parameters.bounds)
    t = seq.imu.t_s
    i_b = min(int(torch.searchsorted(t, t[0] + window_s)), len(t) - 1)  # a window as long as the walk ends at its last sample
    baseline = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    t0 = time.perf_counter()
    if mode == "reference":
        with torch.no_grad():
            result = run_window(seq, method, params.apply(base, training=True), (0, i_b),
                                dropout_p=params.value("dropout_p"))
            loss = window_loss(result.track, seq.truth).loss
    else:
        result = run_window(seq, method, params.apply(base, training=True), (0, i_b), dropout_p=params.value("dropout_p"))
        loss = window_loss(result.track, seq.truth).loss
        loss.backward()
        assert all(torch.isfinite(p.grad).all() for p in params.parameters() if p.grad is not None)
    seconds = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    return {"mode": mode, "peak_gb": peak, "baseline_gb": baseline, "seconds": seconds, "loss": float(loss),
            "imu_samples": i_b + 1}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--window", type=float, default=30.0)
    parser.add_argument("--points", type=int, default=128)
    parser.add_argument("--method", default="ins_gnss_dense")
    parser.add_argument("--child", choices=["reference", "train"])
    args = parser.parse_args()
    if args.child:
        print(json.dumps(measure(args.child, args.window, args.points, args.method)))
        return
    rows = {}
    for mode in ("reference", "train"):
        out = subprocess.run([sys.executable, __file__, "--child", mode, "--window", str(args.window), "--points",
                              str(args.points), "--method", args.method], capture_output=True, text=True, check=True)
        rows[mode] = json.loads(out.stdout.strip().splitlines()[-1])
    ref, train = rows["reference"], rows["train"]
    print(f"{args.method}, {args.window:.0f} s window ({train['imu_samples']} IMU samples), {args.points} flow points per frame, float64, CPU")
    print(f"{'':<28}{'peak RSS':>10}{'above data':>12}{'time':>9}")
    for name, r in (("filter, no gradient", ref), ("training step (fwd + bwd)", train)):
        print(f"{name:<28}{r['peak_gb']:>8.2f} GB{r['peak_gb'] - r['baseline_gb']:>9.2f} GB{r['seconds']:>8.1f} s")
    print(f"ratio training / reference: memory above data {(train['peak_gb'] - train['baseline_gb']) / max(1e-9, ref['peak_gb'] - ref['baseline_gb']):.1f}x, "
          f"time {train['seconds'] / ref['seconds']:.1f}x; target: training peak < 4 GB -> "
          f"{'met' if train['peak_gb'] < 4.0 else 'NOT met'}")


if __name__ == "__main__":
    main()
