"""How well a ``train.py`` run fits: every validation's parameters and the hand-tuned ones, scored
on the training sequences and on the held-out ones.

Training lowers a loss on the training sequences; the held-out RMSE is what it is selected
by. Scoring the same parameters on both tells an optimisation that has not reached the
hand-tuned values yet (worse than hand-tuned on the training sequences too) from one that
overfits (better on the training sequences, worse held out).

    python benchmarks/bench_train_fit.py outputs/DATE/TIME [--method ins_dense] [--all]
    python benchmarks/bench_train_fit.py RUN --all --sequence '{seed: 0, duration_s: 300}' --points 256
    python benchmarks/bench_train_fit.py RUN --all --hand acc_bias_walk,gyro_bias_walk,acc_scale_walk
    python benchmarks/bench_train_fit.py RUN --all --sequence '{seed: 0, duration_s: 300}' --chunks 60

``--sequence`` adds a sequence to score (a ``data.train`` entry: ``{seed: N, duration_s: S}``
or ``{path: DIR}``), such as the 300 s walk of ``evaluate.py``, which ``--points 256`` scores
with as many points per frame as ``evaluate.py`` uses: how far the parameters learned on
short walks carry. ``--chunks S`` also prints, per sequence, the RMSE of each ``S``-second
piece of the run aligned on its own (``flowins.evaluation.metrics.chunk_rmse``, the alignment
of the training loss's windows): where along a long walk the error grows. ``--hand`` sets the
named parameters to their hand-tuned values in every row but the hand-tuned one: which
learned parameters a result hinges on.

It reads the run's ``.hydra/config.yaml`` (its sequences, settings and flow, from the cache)
and ``selection.json``, and prints the filter RMSE after the Table I alignment (hard gates, as
validation runs) per sequence, for the hand-tuned parameters, the start, the chosen validation
and the last (``--all``: every validation).
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch
from omegaconf import OmegaConf

from flowins.evaluation.metrics import chunk_rmse
from flowins.settings import flow_config, training_setup
from flowins.state import STATE
from flowins.training.data import load_training_sequence
from flowins.training.parameters import NAMES, FilterParameters
from flowins.training.unroll import run_windows, track_rmse


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a train.py output folder (with .hydra/config.yaml, selection.json)")
    parser.add_argument("--method", default="ins_dense")
    parser.add_argument("--all", action="store_true", help="every validation (default: the start, the chosen, the last)")
    parser.add_argument("--sequence", action="append", default=[], metavar="SPEC",
                        help="one more sequence to score, e.g. '{seed: 0, duration_s: 300}' (repeatable)")
    parser.add_argument("--points", type=int, default=None, help="flow points per frame (default: the run's)")
    parser.add_argument("--hand", default="", metavar="NAMES",
                        help="comma-separated parameters set to their hand-tuned values in the learned rows")
    parser.add_argument("--chunks", type=float, default=None, metavar="S",
                        help="also the RMSE of each S-second piece of every run, each aligned on its own")
    args = parser.parse_args()
    if args.chunks is not None and not args.chunks > 0:
        raise SystemExit(f"error: --chunks {args.chunks}: expected a piece length in seconds > 0")
    config_file, selection_file = args.run / ".hydra" / "config.yaml", args.run / "selection.json"
    for f in (config_file, selection_file):
        if not f.is_file():
            raise SystemExit(f"error: {f}: not found; expected the output folder of a finished train.py run")
    cfg = OmegaConf.to_container(OmegaConf.load(config_file), resolve=False)
    cfg["output_dir"] = str(args.run)
    if args.points is not None:
        cfg["filter"]["flow"]["n_points"] = args.points
    extra = []
    for spec in args.sequence:
        try:
            item = OmegaConf.to_container(OmegaConf.create(spec))
        except Exception:  # not YAML: the message below says what is expected
            item = None
        if not isinstance(item, dict) or not ("seed" in item or "path" in item):
            raise SystemExit(f"error: --sequence {spec!r}: expected a mapping such as '{{seed: 0, duration_s: 300}}' "
                             "or '{path: DIR}'")
        extra.append(item)
    hand = [n for n in args.hand.split(",") if n]
    if unknown := [n for n in hand if n not in NAMES]:
        raise SystemExit(f"error: --hand {args.hand!r}: unknown parameters {unknown}; expected names from {list(NAMES)}")
    data_cfg = {**cfg, "flow": flow_config(cfg, moments=bool(cfg.get("flow_moments", True)))}
    sources = ([("train", s) for s in cfg["data"]["train"]] + [("held out", s) for s in cfg["data"]["val"]]
               + [("extra", s) for s in extra])
    seqs = [(part, load_training_sequence(s, data_cfg, methods=[args.method])) for part, s in sources]
    setup = training_setup(cfg, [seq for _, seq in seqs], recorded=any(s.get("path") for _, s in sources))
    base, tuned = setup.filter.navigation, setup.parameters.tuned
    history = json.loads(selection_file.read_text())["history"]

    pieces: dict[str, list[list[tuple[float, float, float]]]] = {}

    def scored(params: FilterParameters, label: str) -> list[float]:
        p = float(params.value("dropout_p").detach())
        config = params.apply(base, training=False)
        rmse = []
        with torch.no_grad():
            for _, seq in seqs:
                (result,) = run_windows([seq], args.method, config, [(0, seq.imu.t_s.shape[0] - 1)], dropout_p=p)
                track = result.track
                rmse.append(track_rmse(track, seq.truth))
                if args.chunks is not None:
                    pieces.setdefault(label, []).append(chunk_rmse(track.t, track.mean[:, STATE.p], seq.truth.t_s,
                                                                   seq.truth.pos_m, args.chunks))
        return rmse

    chosen = json.loads(selection_file.read_text())["chosen"]
    hand_values = {n: tuned[n] for n in hand}
    rows = {"hand-tuned": scored(FilterParameters(tuned, learn=()), "hand-tuned")}
    for entry in history if args.all else [e for e in history if e["label"] in ("start", chosen)] + history[-1:]:
        # each validation's values (a selection.json without them: log/logit coordinates)
        learned = entry["values"] if "values" in entry else FilterParameters.from_raw(entry["raw"]).values()
        rows[entry["label"]] = scored(FilterParameters({**learned, **hand_values}, learn=()), entry["label"])
    print(f"{args.method} filter RMSE (m, Table I alignment) per sequence of {args.run}")
    if hand:
        print(f"  learned rows with {', '.join(hand)} hand-tuned")
    columns = [f"{part} {i + 1}" for i, (part, _) in enumerate(seqs)]
    for column, (_, seq) in zip(columns, seqs):
        print(f"  {column}: {seq.name}")
    print(f"{'':12s}" + "".join(f"{c:>14s}" for c in columns))
    for label, values in rows.items():
        print(f"{label:12s}" + "".join(f"{v:>14.2f}" if math.isfinite(v) else f"{'diverged':>14s}" for v in values))
    for i, (column, (_, seq)) in enumerate(zip(columns, seqs)):
        if not pieces:
            break
        spans = next(iter(pieces.values()))[i]
        print(f"\n{column} ({seq.name}): RMSE (m) of each {args.chunks:g} s piece, each aligned on its own")
        print(f"{'':12s}" + "".join(f"{f'{a - spans[0][0]:.0f}-{b - spans[0][0]:.0f} s':>12s}" for a, b, _ in spans))
        for label, per_seq in pieces.items():
            print(f"{label:12s}" + "".join(f"{r:>12.2f}" if math.isfinite(r) else f"{'diverged':>12s}"
                                           for _, _, r in per_seq[i]))


if __name__ == "__main__":
    main()
