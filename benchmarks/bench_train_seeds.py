"""Does ``train.py experiment=mistuned`` end well whatever the order of its walks? Several seeds.

    python benchmarks/bench_train_seeds.py --out /tmp/seeds --seeds 0 1 2 3 4 --heldout 8 9 10 \\
        [--jobs 2] [--reuse] [-- TRAIN_OVERRIDE ...]

Each seed is one ``python train.py experiment=mistuned seed=S`` (the seed draws the order of
the four training walks; ``best.ckpt`` is chosen on the 300 s walks of seeds 0, 6 and 7) in
``OUT/train/seed_S``. Each run's ``best.ckpt``, and the hand-tuned parameters, are then scored
on 300 s walks that neither training nor selection sees (``--heldout``; ``python evaluate.py
'sequence.seeds=[8,9,10]' 'combinations=[ins_dense]' flow.mc_mode=moments
[model.checkpoint=...]``, 256 points per frame as Table I) in ``OUT/score/...``.

It prints the filter RMSE of every run on every held-out walk beside hand-tuning's, and the
criteria of issue 62: every run's mean at or below hand-tuning's mean, the runs' means within
1.3x of each other (largest / smallest), and no run more than 20 % above hand-tuning on any
single walk. The last line is ``RESULT runs=N at_or_below=K spread=X worst_walk=+Y%``.

``--jobs 2`` runs two trainings at once, each with one thread (on 2 cores about as fast in all
as one after the other with two; the thread count changes the rounding, and from a 10x start
the outcome with it); ``--threads N`` sets the threads per process instead (``--threads 1 --
trainer=ddp``: one run at a time, its two processes one thread each). ``--reuse`` keeps the runs and scores already in ``OUT`` that were
made with the same overrides, held-out walks and checkpoint. A run takes about
20 min on a 2-core CPU; the held-out walks' flow is computed once (about 10 min a walk) and
cached. Arguments after ``--`` go to every ``train.py`` run.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
EXPERIMENT = "experiment=mistuned"
ARGUMENTS = "bench_arguments.json"  # what a finished run or score was made with (--reuse keeps only its own)


def train(seed: int, out: Path, threads: int, overrides: list[str], reuse: bool) -> Path:
    """``train.py experiment=mistuned seed=SEED`` in ``out/train/seed_SEED``; its ``best.ckpt``."""
    run = out / "train" / f"seed_{seed}"
    best = run / "checkpoints" / "best.ckpt"
    if reuse and best.exists() and _same_arguments(run, {"overrides": overrides}):
        return best
    run.mkdir(parents=True, exist_ok=True)
    (run / ARGUMENTS).unlink(missing_ok=True)  # written again once the run has finished
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    with open(run / "stdout.log", "w") as log:
        code = subprocess.call([sys.executable, "train.py", EXPERIMENT, f"seed={seed}", "progress=false",
                                f"hydra.run.dir={run}", *overrides], cwd=REPO, env=env, stdout=log,
                               stderr=subprocess.STDOUT)
    if code != 0 or not best.exists():
        raise SystemExit(f"error: train.py seed={seed} stopped with status {code}: see {run / 'stdout.log'}")
    (run / ARGUMENTS).write_text(json.dumps({"overrides": overrides}))
    return best


def score(label: str, checkpoint: Path | None, heldout: list[int], out: Path, reuse: bool) -> dict[int, float]:
    """``{walk seed: ins_dense filter RMSE (m)}`` of ``evaluate.py`` on the held-out walks."""
    where = out / "score" / label
    metrics = where / "metrics.json"
    arguments = {"heldout": heldout, "checkpoint": None if checkpoint is None else str(checkpoint)}
    if not (reuse and metrics.exists() and _same_arguments(where, arguments)):
        where.mkdir(parents=True, exist_ok=True)
        (where / ARGUMENTS).unlink(missing_ok=True)
        args = [sys.executable, "evaluate.py", f"sequence.seeds=[{','.join(map(str, heldout))}]",
                "combinations=[ins_dense]", "flow.mc_mode=moments", "progress=false", f"hydra.run.dir={where}"]
        if checkpoint is not None:
            args.append(f"model.checkpoint={checkpoint}")
        with open(where / "stdout.log", "w") as log:
            code = subprocess.call(args, cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
        if code != 0:
            raise SystemExit(f"error: evaluate.py for {label} stopped with status {code}: see {where / 'stdout.log'}")
        (where / ARGUMENTS).write_text(json.dumps(arguments))
    per_seed = json.loads(metrics.read_text())["ins_dense"]["per_seed"]
    return {int(s): float(v["filter_rmse_m"]) for s, v in per_seed.items()}


def _same_arguments(folder: Path, arguments: dict) -> bool:
    """Whether ``folder``'s finished run was made with ``arguments`` (what ``--reuse`` may keep)."""
    path = folder / ARGUMENTS
    return path.exists() and json.loads(path.read_text()) == json.loads(json.dumps(arguments))


def criteria(runs: dict[int, dict[int, float]], hand: dict[int, float]) -> dict:
    """Issue 62's criteria from each run's RMSE per held-out walk (``runs[seed][walk]``) and
    hand-tuning's (``hand[walk]``): each run's mean and its ratio to hand-tuning's mean, how
    many are at or below it, the spread (largest / smallest run mean), the worst single walk
    (its RMSE / hand-tuning's on that walk, the largest over runs and walks), whether all
    three hold (every run at or below, spread <= 1.3, worst walk <= 1.2), and the runs' means'
    mean, sample standard deviation and median (``runs_mean``, ``runs_std``, ``runs_median``)."""
    walks = sorted(hand)
    hand_mean = sum(hand[w] for w in walks) / len(walks)
    means = {s: sum(r[w] for w in walks) / len(walks) for s, r in runs.items()}
    worst = max((r[w] / hand[w], s, w) for s, r in runs.items() for w in walks)
    spread = max(means.values()) / min(means.values())
    below = sum(m <= hand_mean for m in means.values())
    values = list(means.values())
    return {"hand_mean": hand_mean, "means": means, "ratios": {s: m / hand_mean for s, m in means.items()},
            "runs_mean": statistics.mean(values), "runs_std": statistics.stdev(values) if len(values) > 1 else 0.0,
            "runs_median": statistics.median(values),
            "at_or_below": below, "spread": spread, "worst_walk": {"ratio": worst[0], "run": worst[1], "walk": worst[2]},
            "met": below == len(runs) and spread <= 1.3 and worst[0] <= 1.2}


def table(runs: dict[int, dict[int, float]], hand: dict[int, float], result: dict) -> str:
    walks = sorted(hand)
    lines = [f"{'ins_dense filter RMSE':<22}" + "".join(f"{'walk ' + str(w):>10}" for w in walks)
             + f"{'mean':>10}{'/ hand':>9}"]
    lines.append(f"{'hand-tuned':<22}" + "".join(f"{hand[w]:>8.2f} m" for w in walks) + f"{result['hand_mean']:>8.2f} m")
    for s, r in sorted(runs.items()):
        lines.append(f"{'seed ' + str(s):<22}" + "".join(f"{r[w]:>8.2f} m" for w in walks)
                     + f"{result['means'][s]:>8.2f} m{result['ratios'][s]:>8.2f}x")
    worst = result["worst_walk"]
    lines += ["", f"the runs' means: {result['runs_mean']:.2f} ± {result['runs_std']:.2f} m (mean ± std over "
              f"{len(runs)} runs; median {result['runs_median']:.2f} m), hand-tuning {result['hand_mean']:.2f} m",
              f"runs at or below hand-tuning on the mean: {result['at_or_below']} of {len(runs)}",
              f"spread of the runs' means (largest / smallest): {result['spread']:.2f}x (issue 62: <= 1.3x)",
              f"worst single walk: {100 * (worst['ratio'] - 1):+.1f} % against hand-tuning (seed {worst['run']}, "
              f"walk {worst['walk']}; issue 62: <= +20 %)",
              f"RESULT runs={len(runs)} at_or_below={result['at_or_below']} spread={result['spread']:.2f} "
              f"worst_walk={100 * (worst['ratio'] - 1):+.1f}%"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    overrides = argv[argv.index("--") + 1:] if "--" in argv else []
    ours = argv[: argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--heldout", type=int, nargs="+", default=[8, 9, 10])
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--threads", type=int, default=None,
                        help="threads per training process (default: the cores / --jobs; 1 with trainer=ddp's two "
                             "processes on two cores)")
    parser.add_argument("--reuse", action="store_true", help="keep the runs and scores in --out made with the same arguments")
    args = parser.parse_args(ours)
    if args.jobs < 1:
        parser.error(f"--jobs {args.jobs}: expected 1 or more")
    if args.threads is not None and args.threads < 1:
        parser.error(f"--threads {args.threads}: expected 1 or more")
    threads = args.threads or max(1, (os.cpu_count() or 1) // args.jobs)
    with ThreadPoolExecutor(args.jobs) as pool:
        best = dict(zip(args.seeds, pool.map(lambda s: train(s, args.out, threads, overrides, args.reuse), args.seeds)))
    hand = score("hand-tuned", None, args.heldout, args.out, args.reuse)
    runs = {s: score(f"seed_{s}", ckpt, args.heldout, args.out, args.reuse) for s, ckpt in best.items()}
    result = criteria(runs, hand)
    print(table(runs, hand, result))
    (args.out / "result.json").write_text(json.dumps({"runs": runs, "hand": hand, **result}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
