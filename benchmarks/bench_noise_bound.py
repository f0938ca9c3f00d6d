"""How far can noise tuning go on a recording? A search on the very part it scores.

    python benchmarks/bench_noise_bound.py /tmp/kitti/recordings/kitti-seed0 --start-s 282 imu=phone

Runs ``evaluate.py sequence.path=DIR combinations=[ins_gnss]`` (the part from ``--start-s``
to ``--end-s``) again and again, each parameter of ``--params`` scaled by a factor (the
noise densities, the bias walks, the GNSS noise scale: what ``experiment=real`` learns), and
searches the factors coordinate by coordinate in log10 steps of 1, 0.5 and 0.25, keeping a
step only where the filter RMSE falls. The result is an upper bound on what any training of
those parameters can give on that part: the search is tuned on the data it is scored on,
training is not. Prints each accepted step, then

    RESULT start=<m> best=<m> change=<%> evals=<n>

A coordinate search finds a local optimum, so the bound is what the search reached, not a
proof; ``--rounds`` and ``--steps`` widen it.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import tempfile
from pathlib import Path

from flowins.jobs.cli import user_errors

PARAMS = {  # name: config key
    "acc_noise": "imu.acc_noise",
    "gyro_noise": "imu.gyro_noise",
    "acc_bias_walk": "imu.acc_bias_walk",
    "gyro_bias_walk": "imu.gyro_bias_walk",
    "acc_scale_walk": "filter.acc_scale_walk",
    "gnss_noise_scale": "filter.gnss_noise_scale",
    "vehicle_lateral_sigma_mps": "filter.measurements.vehicle.lateral_sigma_mps",
    "vehicle_vertical_sigma_mps": "filter.measurements.vehicle.vertical_sigma_mps",
}
DEFAULT = "acc_noise,gyro_noise,acc_bias_walk,gyro_bias_walk,gnss_noise_scale"


def run_once(folder: Path, out: Path, overrides: list[str], combination: str) -> tuple[dict, dict]:
    """``evaluate.py sequence.path=FOLDER combinations=[COMBINATION] OVERRIDES``; its metrics and config."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import ConfigCompositionException
    from omegaconf import OmegaConf

    from flowins.jobs.evaluate import run

    configs = Path(__file__).resolve().parents[1] / "configs"
    with initialize_config_dir(str(configs), version_base=None):
        try:
            cfg = compose("evaluate", overrides=[f"sequence.path={folder}", f"combinations=[{combination}]",
                                                 f"output_dir={out}", "plots=false", "progress=false", *overrides])
        except ConfigCompositionException as error:  # a bad override: the user's, named as hydra names it
            raise ValueError(str(error)) from error
    with open(os.devnull, "w") as quiet, contextlib.redirect_stdout(quiet):  # each run's table: not this script's output
        config = OmegaConf.to_container(cfg, resolve=True)
        run(config)
    return json.loads((out / "metrics.json").read_text()), config


def start_values(metrics: dict, config: dict, params: list[str]) -> dict[str, float]:
    """Each parameter's start: the IMU's values as the filter uses them (metrics.json's ``imu``
    block: the densities after the preset's inflation), the others from the run's config."""
    values = {}
    for name in params:
        key = PARAMS[name]
        if key.startswith("imu."):
            values[name] = float(metrics["imu"][name])
            continue
        node = config
        for part in key.split("."):
            node = node[part]
        values[name] = float(node)
    return values


def overrides_for(values: dict[str, float]) -> list[str]:
    """The values as overrides; the densities are given as used, so the preset's inflation is 1."""
    return ["imu.inflation=1", *(f"{PARAMS[p]}={values[p]:.17g}" for p in values)]


def coordinate_search(score, values: dict[str, float], params: list[str], steps: list[float], *,
                      start_score: float | None = None, rounds: int = 2, min_gain: float = 1e-3,
                      max_evals: int = 120, report=None) -> tuple[float, dict[str, float], int]:
    """Minimise ``score(values)`` over the parameters ``params`` of ``values`` (positive numbers)
    in log10 steps: for each step size of ``steps`` (largest first), up to ``rounds`` passes over
    the parameters, each trying ``x 10^step`` then ``x 10^-step`` and keeping the first trial
    that scores below ``best * (1 - min_gain)``; a pass that keeps nothing ends that step size.
    At most ``max_evals`` calls of ``score`` (the start's included unless ``start_score`` is
    given). ``report(step, name, factor, score)`` hears of each kept trial.

    Returns ``(best score, its values, calls of score)``."""
    evals = 0
    if start_score is None:
        start_score, evals = score(values), 1
    best = start_score
    for step in steps:
        for _ in range(rounds):
            moved = False
            for name in params:
                for sign in (1.0, -1.0):
                    if evals >= max_evals:
                        return best, values, evals
                    factor = 10.0 ** (sign * step)
                    trial = dict(values, **{name: values[name] * factor})
                    result = score(trial)
                    evals += 1
                    if result < best * (1.0 - min_gain):
                        best, values, moved = result, trial, True
                        if report is not None:
                            report(step, name, factor, result)
                        break
            if not moved:
                break
    return best, values, evals


@user_errors  # a bad folder, part or override: `error: ...`, exit status 2, as the jobs say it
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path, help="a recording folder (sequence.path)")
    parser.add_argument("--start-s", type=float, default=None, help="sequence.start_s of the part scored")
    parser.add_argument("--end-s", type=float, default=None, help="sequence.end_s of the part scored")
    parser.add_argument("--combination", default="ins_gnss")
    parser.add_argument("--params", default=DEFAULT, help=f"comma-separated, of {', '.join(PARAMS)} (default: what experiment=real learns)")
    parser.add_argument("--steps", default="1,0.5,0.25", help="log10 step sizes, largest first")
    parser.add_argument("--rounds", type=int, default=2, help="passes over the parameters per step size")
    parser.add_argument("--max-evals", type=int, default=120)
    parser.add_argument("--min-gain", type=float, default=1e-3, help="a step is kept when it lowers the RMSE by this fraction")
    parser.add_argument("overrides", nargs="*", help="evaluate.py overrides for every run (imu=..., filter...)")
    args = parser.parse_intermixed_args()

    params = [p.strip() for p in args.params.split(",") if p.strip()]
    unknown = [p for p in params if p not in PARAMS]
    if unknown:
        raise SystemExit(f"error: --params names {unknown}; expected some of {list(PARAMS)}")
    base = list(args.overrides)
    presets = [o.split("=", 1)[1] for o in base if o.startswith("imu=")]
    if not presets or presets[-1] == "auto":
        raise SystemExit("error: name the IMU preset among the overrides (imu=phone, imu=simulated_drive, "
                         "imu=oxts_rt3003, ...): the search writes the densities as the filter uses them, with the "
                         "preset's imu.inflation=1, which imu=auto does not have")
    if args.start_s is not None:
        base.append(f"sequence.start_s={args.start_s}")
    if args.end_s is not None:
        base.append(f"sequence.end_s={args.end_s}")

    with tempfile.TemporaryDirectory() as tmp:
        evals = 0

        def score(values: dict[str, float] | None) -> float:
            nonlocal evals
            evals += 1
            extra = overrides_for(values) if values else []
            metrics, config = run_once(args.folder, Path(tmp) / f"run{evals}", base + extra, args.combination)
            score.last = metrics, config
            return float(metrics[args.combination]["filter_rmse_m"])

        as_configured = score(None)
        values = start_values(*score.last, list(dict.fromkeys(["acc_noise", "gyro_noise", *params])))
        start_rmse = score(values)  # the same start written out as overrides: it must score the same
        if abs(start_rmse - as_configured) > 1e-6 * max(1.0, as_configured):
            raise SystemExit(f"error: the start as overrides scores {start_rmse:.6f} m, as configured "
                             f"{as_configured:.6f} m: the overrides do not reproduce the configuration")
        print(f"start: filter RMSE {start_rmse:.3f} m; " + ", ".join(f"{p} {values[p]:.4g}" for p in params), flush=True)

        def report(step: float, name: str, factor: float, rmse: float) -> None:
            print(f"  step {step:g}: {name} x{factor:.3g} -> {rmse:.3f} m", flush=True)

        best, values, _ = coordinate_search(score, values, params, [float(s) for s in args.steps.split(",")],
                                            start_score=start_rmse, rounds=args.rounds, min_gain=args.min_gain,
                                            max_evals=args.max_evals - evals, report=report)
        factors = ", ".join(f"{p} {values[p]:.4g}" for p in params)
        print(f"best: filter RMSE {best:.3f} m; {factors}")
        change = 100.0 * (best / start_rmse - 1.0) if start_rmse > 0 and math.isfinite(best) else float("nan")
        print(f"RESULT start={start_rmse:.3f} best={best:.3f} change={change:+.1f}% evals={evals}")


if __name__ == "__main__":
    main()
