"""Can a σ that follows the IMU beat the best constant σ of the vehicle constraint? A ceiling.

    for n in 2 3 4; do python -m flowins.data.simulate --scenario drive /tmp/dr_s$n --seed $n \\
        --duration 600 --outage 480; done
    python benchmarks/bench_adaptive_ceiling.py --search /tmp/dr_s3 --score /tmp/dr_s4 /tmp/dr_s2 \\
        imu=simulated_drive filter.measurements.vehicle.mode=on sequence.end_s=540 filter.workers=1

(drives of 600 s whose fixes stop after the first minute and come back for the last, which
``sequence.end_s=540`` leaves out: the IMU and the constraint alone for 480 s.)

``model.adaptive=[vehicle]`` learns a network that scales the constraint's σs at each update
from the IMU's last second. This script asks how much any such scaling could give, with a
form written out by hand instead of learned: on a car whose sideways slip grows with its
lateral acceleration and whose body pitches when it brakes and rides over bumps (the drive
simulator's defaults), the σs at each update are

    σ_lat = σ_lat,0 · sqrt(1 + (ā_lat / a_lat,0)²)
    σ_up  = σ_up,0  · sqrt(1 + (ā_fwd / a_fwd,0)² + (s_up / s_up,0)²)

with ``ā`` the mean specific force along the car's sideways and forward axes over the last
0.2 s and ``s_up`` the standard deviation of the vertical one over the last 0.2 s (all in g,
read from the same IMU windows the network reads). Two coordinate searches (log10 steps, as
``bench_noise_bound.py`` searches) run on ``--search``, each on the filter's KITTI drift there
(``--metric drift``, the default) or its RMSE (``--metric rmse``):

* constant: ``σ_lat,0`` and ``σ_up,0`` alone (the hand form off);
* adaptive: the two σs and the three scales, started from the constant search's best with
  the scales at ``--start-scale`` (1 g: within a few % of the constant σs, so that the
  search's first step, to 0.1 g, reaches where a car's accelerations change the σs).

Both results are then scored on each ``--score`` recording, which neither search saw: filter
and smoother RMSE and KITTI's translational drift over 100-800 m (``metrics.json``'s
``filter_drift``). The last line is ``RESULT constant_drift=<%> adaptive_drift=<%>
change=<%>`` (the mean over the scored recordings). A coordinate search finds a local
optimum, so this is a ceiling of the form that the search reached, not of every form.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_noise_bound import coordinate_search, run_once  # noqa: E402

import flowins.jobs.evaluate as evaluate_job  # noqa: E402
from flowins.jobs.cli import user_errors  # noqa: E402
from flowins.measurements.vehicle import AXES  # noqa: E402

SIGMAS = {"lat": "filter.measurements.vehicle.lateral_sigma_mps", "up": "filter.measurements.vehicle.vertical_sigma_mps"}
SCALES = ("a_lat", "a_fwd", "s_up")
LAST = 20  # samples of the window the form reads (0.2 s at 100 Hz)


def hand_form(scales: dict[str, float], forward_axis: str, up_axis: str):
    """The σ factors ``(E, 2)`` (sideways, vertical) of IMU windows ``(E, 6, S)`` (gyro, then
    specific force in g), as the module docstring writes them."""
    fwd, up = AXES[forward_axis][0], AXES[up_axis][0]
    lat = ({0, 1, 2} - {fwd, up}).pop()

    def factors(windows: torch.Tensor, steady: torch.Tensor | None = None) -> torch.Tensor:
        acc = windows[:, 3:, -LAST:]
        lateral = (acc[:, lat].mean(-1) / scales["a_lat"]) ** 2
        vertical = (acc[:, fwd].mean(-1) / scales["a_fwd"]) ** 2 + (acc[:, up].std(-1) / scales["s_up"]) ** 2
        return torch.stack(((1 + lateral).sqrt(), (1 + vertical).sqrt()), -1)

    return factors


class _Patch:
    """``evaluate.py``'s filter set-up with the hand form as the vehicle constraint's noise model."""

    def __init__(self, original) -> None:
        self.original, self.scales = original, None

    def __call__(self, *args, **kwargs):
        setup = self.original(*args, **kwargs)
        vehicle = setup.navigation.measurements.get("vehicle")
        if self.scales is None or vehicle is None:
            return setup
        model = hand_form(self.scales, vehicle.forward_axis, vehicle.up_axis)
        measurements = {**setup.navigation.measurements, "vehicle": dataclasses.replace(vehicle, noise_model=model)}
        return dataclasses.replace(setup, navigation=dataclasses.replace(setup.navigation, measurements=measurements))


PATCH = _Patch(evaluate_job.filter_setup)


def _overrides(values: dict[str, float]) -> list[str]:
    return [f"{SIGMAS[k]}={values[k]:.17g}" for k in SIGMAS]


def _run(folder: Path, out: Path, base: list[str], values: dict[str, float]) -> dict:
    PATCH.scales = {k: values[k] for k in SCALES} if all(k in values for k in SCALES) else None
    metrics, _ = run_once(folder, out, base + _overrides(values), "ins_gnss")
    return metrics["ins_gnss"]


@user_errors
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--search", type=Path, required=True, help="the recording both searches tune on")
    parser.add_argument("--score", type=Path, nargs="+", required=True, help="recordings the results are scored on")
    parser.add_argument("--steps", default="1,0.5,0.25", help="log10 step sizes, largest first")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--max-evals", type=int, default=70, help="per search")
    parser.add_argument("--start-sigma", type=float, default=1.0, help="both σs' start (m/s)")
    parser.add_argument("--start-scale", type=float, default=1.0, help="the three scales' start (g)")
    parser.add_argument("--metric", choices=("drift", "rmse"), default="drift",
                        help="what the searches minimise on --search: the filter's KITTI drift (%%) or its RMSE (m)")
    parser.add_argument("--constant", default=None, help="σ_lat,σ_up (m/s): skip the constant search, use these")
    parser.add_argument("overrides", nargs="*", help="evaluate.py overrides for every run (imu=..., filter...)")
    args = parser.parse_intermixed_args()
    base = list(args.overrides)
    evaluate_job.filter_setup = PATCH  # this process's evaluate.py runs take the hand form where it is set

    with tempfile.TemporaryDirectory() as tmp:
        count = 0

        def score(values: dict[str, float]) -> float:
            nonlocal count
            count += 1
            m = _run(args.search, Path(tmp) / f"s{count}", base, values)
            return float(m["filter_drift"]["kitti_translation_pct"] if args.metric == "drift" else m["filter_rmse_m"])

        unit = "%" if args.metric == "drift" else "m"

        def report(step, name, factor, value):
            print(f"  step {step:g}: {name} x{factor:.3g} -> {value:.3f} {unit}", flush=True)

        steps = [float(s) for s in args.steps.split(",")]
        start = {"lat": args.start_sigma, "up": args.start_sigma}
        if args.constant:
            constant = dict(zip(SIGMAS, (float(v) for v in args.constant.split(","))))
            c_best = score(constant)
        else:
            print(f"constant σs on {args.search}: start {start}", flush=True)
            c_best, constant, _ = coordinate_search(score, start, list(SIGMAS), steps, rounds=args.rounds,
                                                    max_evals=args.max_evals, report=report)
        print(f"constant: filter {args.metric} {c_best:.3f} {unit}; σ_lat {constant['lat']:.4g}, σ_up {constant['up']:.4g} m/s")
        form_start = {**constant, **{k: args.start_scale for k in SCALES}}
        print(f"hand form on {args.search}: start {form_start}", flush=True)
        a_best, adaptive, _ = coordinate_search(score, form_start, [*SIGMAS, *SCALES], steps, rounds=args.rounds,
                                                max_evals=args.max_evals, report=report)
        print(f"hand form: filter {args.metric} {a_best:.3f} {unit}; " + ", ".join(f"{k} {v:.4g}" for k, v in adaptive.items()))

        drifts = {"constant": [], "adaptive": []}
        for folder in args.score:
            for name, values in (("constant", constant), ("adaptive", adaptive)):
                count += 1
                m = _run(folder, Path(tmp) / f"s{count}", base, values)
                drift = m["filter_drift"]["kitti_translation_pct"]
                drifts[name].append(drift)
                print(f"{folder}: {name:8s} filter / smoother {m['filter_rmse_m']:.2f} / {m['smoother_rmse_m']:.2f} m, "
                      f"KITTI drift {drift:.2f} %", flush=True)
        c, a = (sum(v) / len(v) for v in (drifts["constant"], drifts["adaptive"]))
        print(f"RESULT constant_drift={c:.2f}% adaptive_drift={a:.2f}% change={100 * (a / c - 1):+.1f}%")


if __name__ == "__main__":
    main()
