"""The held-out validation of ``train.py``: in one process, and split over worker processes.

Every validation of ``python train.py experiment=mistuned`` runs its long held-out walks
(``data.select``: the 300 s walks of seeds 0, 6 and 7) under both trained methods, forward only,
as one batched filter pass (``flowins.training.unroll.sequences_errors``). With
``filter.workers=N`` on the CPU the pass is split into ``N`` parts, one worker process each.
This script builds that validation as ``train.py`` does (its config, 128 points per frame, SpyNet
in closed-form dropout, the flow from the cache or computed once), with the hand-tuned
parameters, and times it with ``filter.workers=1`` and with ``--workers`` (default: one per
core), alternating, then prints each one's seconds, the ratio and the largest RMSE difference.

    python benchmarks/bench_validation.py [--repeats 3] [--workers 2] [-- TRAIN_OVERRIDE ...]

The last line is ``RESULT one_process=<s> workers=<s> speedup=<x> rmse_difference=<m>``.
"""
from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from pathlib import Path

import hydra
import torch
from omegaconf import OmegaConf

from flowins.parallel import available_cores
from flowins.settings import flow_config, training_setup
from flowins.training.data import load_training_sequence
from flowins.training.parameters import FilterParameters
from flowins.training.unroll import sequences_errors

CONFIGS = str(Path(__file__).resolve().parents[1] / "configs")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3, help="timed pairs (one process, then the workers)")
    parser.add_argument("--workers", type=int, default=available_cores(), help="worker processes (default: the cores)")
    parser.add_argument("overrides", nargs="*", help="train.py overrides (after --)")
    args = parser.parse_args()
    if args.repeats < 1 or args.workers < 1:
        raise SystemExit(f"error: --repeats {args.repeats} --workers {args.workers}: expected counts >= 1")
    with hydra.initialize_config_dir(config_dir=CONFIGS, version_base="1.3"):
        cfg = OmegaConf.to_container(hydra.compose("train", overrides=["experiment=mistuned", "output_dir=/tmp",
                                                                       *args.overrides]), resolve=True)
    methods = list(cfg["methods"])
    data_cfg = {**cfg, "flow": flow_config(cfg, moments=bool(cfg.get("flow_moments", True)))}
    sources = cfg["data"]["select"]
    if not sources:
        raise SystemExit("error: data.select is empty: the validation timed here is the long held-out walks'")
    seqs = [load_training_sequence(s, data_cfg, methods=methods) for s in sources]
    setup = training_setup(cfg, seqs, recorded=False)
    params = FilterParameters(setup.parameters.tuned, learn=())
    with torch.no_grad():
        config = params.apply(setup.filter.navigation, training=False)
    p = float(params.value("dropout_p"))
    rows = [(seq, m) for m in methods for seq in seqs]
    seconds = sum(float(seq.imu.t_s[-1] - seq.imu.t_s[0]) for seq, _ in rows)
    print(f"validation: {len(seqs)} walks x {len(methods)} methods ({', '.join(methods)}) = {len(rows)} runs, "
          f"{seconds:.0f} s of data, {cfg['filter']['flow']['n_points']} points per frame; torch "
          f"{torch.__version__}, {torch.get_num_threads()} threads, {available_cores()} cores")

    def timed(workers: int) -> tuple[float, list[tuple[float, float]]]:
        t0 = time.perf_counter()
        errors = sequences_errors([s for s, _ in rows], [m for _, m in rows],
                                  dataclasses.replace(config, workers=workers), dropout_p=p, smoother=False)
        return time.perf_counter() - t0, errors

    timed(1)  # warm-up: constants, caches
    times: dict[int, list[float]] = {1: [], args.workers: []}
    errors: dict[int, list[tuple[float, float]]] = {}
    for r in range(args.repeats):
        for workers in (1, args.workers):
            dt, errors[workers] = timed(workers)
            times[workers].append(dt)
            print(f"  pair {r + 1}: workers={workers}: {dt:.2f} s ({seconds / dt:.1f}x real time)")
    one, many = statistics.median(times[1]), statistics.median(times[args.workers])
    difference = max(abs(a[0] - b[0]) for a, b in zip(errors[1], errors[args.workers]))
    for (seq, m), (f, _) in zip(rows, errors[args.workers]):
        print(f"  {m} {seq.name}: filter RMSE {f:.3f} m")
    print(f"median: one process {one:.2f} s, {args.workers} workers {many:.2f} s ({one / many:.2f}x); "
          f"largest filter RMSE difference {difference:.2e} m")
    print(f"RESULT one_process={one:.2f} workers={many:.2f} speedup={one / many:.2f} rmse_difference={difference:.1e}")


if __name__ == "__main__":
    main()
