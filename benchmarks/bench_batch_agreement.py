"""How far a run in a batch is from the same run alone, next to how far rounding alone moves it.

Runs ``ins_gnss_dense`` on the quick simulated walks of ``--seeds`` (default 0 1; walks and
dense flow cached by ``python evaluate.py quick=true sequence.seeds=[0,1]``, computed here if
missing) in one batched pass (:func:`flowins.navigation.navigate_batch`) and the last seed's
walk alone with one and with two threads, and prints the largest difference of the filter
means between them and the filter RMSE of each.

    python benchmarks/bench_batch_agreement.py [--seeds 0 1]
"""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from flowins.data.load import load_recording
from flowins.evaluation.metrics import trajectory_errors
from flowins.flow.load import load_flow
from flowins.measurements.flow import FlowCamera
from flowins.navigation import NavigationRun, navigate, navigate_batch
from flowins.settings import filter_setup
from flowins.state import STATE

CONFIGS = str(Path(__file__).resolve().parents[1] / "configs")


def rmse(result, rec) -> float:
    track = result.filter.in_final_frame()
    return trajectory_errors(track.t, track.mean[:, STATE.p], rec.truth.t_s, rec.truth.pos_m, align="se3").rmse_m


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    args = parser.parse_args()
    with initialize_config_dir(config_dir=CONFIGS, version_base=None):
        cfg = OmegaConf.to_container(compose("evaluate"), resolve=False)
    recs = [load_recording({**cfg["sequence"], "seed": seed}, quick=True, progress=True) for seed in args.seeds]
    runs = [NavigationRun(rec.imu, rec.gnss, flow=load_flow("dense", rec, cfg, progress=True),
                          camera=FlowCamera.from_sequence(rec.sequence), start_gnss=rec.gnss) for rec in recs]
    # the batch in this process (filter.workers would give each seed a process of its own)
    config = dataclasses.replace(filter_setup(cfg, recs, recorded=False).navigation, workers=1)
    rec, run = recs[-1], runs[-1]

    def alone(threads: int):
        before = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            return navigate(run, config=config)
        finally:
            torch.set_num_threads(before)

    batched = navigate_batch(runs, config=config)[-1]
    one, two = alone(1), alone(2)
    print(f"ins_gnss_dense, quick walk of seed {args.seeds[-1]} ({float(rec.imu.duration_s):.0f} s); batch: seeds {args.seeds}")
    for label, result in (("alone, 2 threads", two), ("alone, 1 thread", one), ("in the batch", batched)):
        print(f"  {label:<17} filter RMSE {rmse(result, rec):.6f} m")
    for label, a, b in (("batch vs alone (2 threads)", batched, two), ("1 vs 2 threads, alone", one, two)):
        difference = (a.filter.node_mean[:, STATE.p] - b.filter.node_mean[:, STATE.p]).norm(dim=-1)
        print(f"  {label:<27} largest position difference {float(difference.max()):.2e} m")


if __name__ == "__main__":
    main()
