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

``--no-grad-reference`` times instead, in one process, the validation as it runs (in
``torch.inference_mode``) against the same batch under ``torch.no_grad`` alone (autograd's
bookkeeping of views and in-place operations kept), alternating; its last line is
``RESULT no_grad=<s> inference=<s> speedup=<x> rmse_difference=<m>``.
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
from flowins.training.unroll import run_windows, sequences_errors, track_rmse

CONFIGS = str(Path(__file__).resolve().parents[1] / "configs")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3, help="timed pairs (one process, then the workers)")
    parser.add_argument("--workers", type=int, default=available_cores(), help="worker processes (default: the cores)")
    parser.add_argument("--no-grad-reference", action="store_true",
                        help="one process: inference mode against torch.no_grad alone")
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

    def timed_no_grad() -> tuple[float, list[tuple[float, float]]]:
        """The one-process validation's batch under torch.no_grad alone (the reference)."""
        t0 = time.perf_counter()
        with torch.no_grad():
            results = run_windows([s for s, _ in rows], [m for _, m in rows], dataclasses.replace(config, workers=1),
                                  [(0, s.imu.t_s.shape[0] - 1) for s, _ in rows], dropout_p=p)
            errors = [(track_rmse(r.track, s.truth), float("nan")) for (s, _), r in zip(rows, results)]
        return time.perf_counter() - t0, errors

    ways = {"no_grad": timed_no_grad, "inference": lambda: timed(1)} if args.no_grad_reference else \
        {"one_process": lambda: timed(1), "workers": lambda: timed(args.workers)}
    first, second = ways
    ways[first]()  # warm-up: constants, caches
    times: dict[str, list[float]] = {way: [] for way in ways}
    errors: dict[str, list[tuple[float, float]]] = {}
    for r in range(args.repeats):
        for way, run in ways.items():
            dt, errors[way] = run()
            times[way].append(dt)
            print(f"  pair {r + 1}: {way}: {dt:.2f} s ({seconds / dt:.1f}x real time)")
    a, b = statistics.median(times[first]), statistics.median(times[second])
    difference = max(abs(x[0] - y[0]) for x, y in zip(errors[first], errors[second]))
    for (seq, m), (f, _) in zip(rows, errors[second]):
        print(f"  {m} {seq.name}: filter RMSE {f:.3f} m")
    print(f"median: {first} {a:.2f} s, {second} {b:.2f} s ({a / b:.2f}x); largest filter RMSE difference "
          f"{difference:.2e} m")
    print(f"RESULT {first}={a:.2f} {second}={b:.2f} speedup={a / b:.2f} rmse_difference={difference:.1e}")


if __name__ == "__main__":
    main()
