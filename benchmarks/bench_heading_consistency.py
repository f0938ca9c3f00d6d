"""Does the filter's heading σ cover its heading error? The multi-view track update against the
paper's two-view update, with GNSS, on a simulated walk.

Runs one row (default ``ins_gnss_sparse``) of ``python evaluate.py`` on the walk of ``--seed``
twice, with the window of ``--window`` cloned poses (``filter.tracks.window``) and with the
two-view update (``filter.tracks.window=0``), and prints for each its filter and smoother RMSE
(the table's Procrustes alignment), then the filter's heading error against its own 1-σ
(:mod:`flowins.evaluation.consistency`, after the table's alignment, so a constant turn of the
whole track is no error) every ``--every-s`` seconds, the RMS of the normalised error (about 1
for a consistent filter) and the share of nodes beyond 3 σ (0.27 % when consistent). The
walk and its tracks come from the cache ``python evaluate.py`` fills (computed here if missing).
Further arguments are Hydra overrides of both runs (e.g. ``filter.gnss_correlation_s=6``).
The last line is ``RESULT window=<rmse> two_view=<rmse> window_nees_rms=<x> two_view_nees_rms=<x>``.

    python benchmarks/bench_heading_consistency.py [--seed 3] [--sparse tracks|lk] [--row ins_gnss_sparse]
                                                   [--window 10] [--every-s 30] [OVERRIDE ...]
"""
from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from flowins.data.load import load_recording
from flowins.evaluation.consistency import track_heading_consistency
from flowins.evaluation.metrics import trajectory_errors
from flowins.flow.load import load_flow, load_tracks
from flowins.jobs.evaluate import _runs
from flowins.navigation import navigate_batch
from flowins.settings import filter_setup
from flowins.state import STATE

CONFIGS = str(Path(__file__).resolve().parents[1] / "configs")


def run(window: int, args: argparse.Namespace):
    """The row's filter and smoother RMSE and the filter's heading consistency for one update."""
    overrides = [f"sparse={args.sparse}", f"filter.tracks.window={window}", f"combinations=[{args.row}]",
                 f"sequence.seed={args.seed}", *args.overrides]
    with initialize_config_dir(config_dir=CONFIGS, version_base=None):
        cfg = OmegaConf.to_container(compose("evaluate", overrides=overrides), resolve=False)
    rec = load_recording(cfg["sequence"], quick=False, progress=True)
    if rec.truth is None:
        raise SystemExit("error: the recording has no ground truth to compare the heading with")
    flow = load_tracks(rec, cfg, progress=True) if window else load_flow("sparse", rec, cfg, progress=True)
    if isinstance(flow, str):
        raise SystemExit(f"error: no sparse input for window {window}: {flow}")
    config = dataclasses.replace(filter_setup(cfg, [rec], recorded=False).navigation, workers=1)
    result = navigate_batch(_runs(args.row, cfg, [rec], config, [{"sparse": flow}]), config=config)[0]
    track = result.filter.in_final_frame(marginal=STATE.dim)
    filtered = trajectory_errors(track.t, track.mean[:, STATE.p], rec.truth.t_s, rec.truth.pos_m, align="se3")
    smoothed = trajectory_errors(result.smoother.t, result.smoother.mean[:, STATE.p], rec.truth.t_s,
                                 rec.truth.pos_m, align="se3")
    heading = track_heading_consistency(track.t, track.mean[:, STATE.q], track.cov[:, STATE.q, STATE.q],
                                        rec.truth.t_s, rec.truth.quat_wxyz, alignment=filtered.alignment)
    return float(filtered.rmse_m), float(smoothed.rmse_m), heading


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=3, help="the simulated walk's seed")
    parser.add_argument("--sparse", default="tracks", choices=("tracks", "lk"))
    parser.add_argument("--row", default="ins_gnss_sparse", help="a sparse row of configs/method")
    parser.add_argument("--window", type=int, default=10, help="cloned poses of the multi-view update (>= 1)")
    parser.add_argument("--every-s", type=float, default=30.0, help="seconds between the printed nodes")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of both runs")
    args = parser.parse_args()
    if args.window < 1:
        raise SystemExit(f"error: --window {args.window}: the multi-view update needs at least 1 cloned pose")
    if not args.every_s > 0:
        raise SystemExit(f"error: --every-s {args.every_s}: expected seconds > 0")
    runs = {f"window {args.window}": run(args.window, args), "two-view": run(0, args)}
    print(f"{args.row} on the walk of seed {args.seed}, sparse={args.sparse}"
          + (f", {' '.join(args.overrides)}" if args.overrides else ""))
    for name, (f, s, h) in runs.items():
        print(f"  {name:10s} filter / smoother {f:.2f} / {s:.2f} m; heading error / filter's σ: RMS "
              f"{h.rms_normalised():.1f} (consistent: 1), beyond 3σ at {100 * h.share_beyond(3.0):.0f} % of the nodes "
              "(consistent: 0.3 %)")
    print(f"  {'t (s)':>6s}  " + "  ".join(f"{name + ': error, σ (°)':>26s}" for name in runs))
    t_end = min(float(h.t_s[-1]) for _, _, h in runs.values())
    t = float(runs["two-view"][2].t_s[0])
    while t <= t_end + 1e-9:
        cells = []
        for _, _, h in runs.values():
            k = min(int((h.t_s < t).sum()), len(h.t_s) - 1)
            cells.append(f"{math.degrees(float(h.error_rad[k])):+9.2f}, {math.degrees(float(h.sigma_rad[k])):6.2f} "
                         f"({abs(float(h.normalised[k])):5.1f} σ)")
        print(f"  {t:6.0f}  " + "  ".join(f"{c:>26s}" for c in cells))
        t += args.every_s
    (fw, _, hw), (f2, _, h2) = runs.values()
    print(f"RESULT window={fw:.2f} two_view={f2:.2f} window_nees_rms={hw.rms_normalised():.1f} "
          f"two_view_nees_rms={h2.rms_normalised():.1f}")


if __name__ == "__main__":
    main()
