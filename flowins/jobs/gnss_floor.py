"""How well could any causal GNSS filter do on a recording? Its GNSS floor, and how much it depends on τ.

::

    python -m flowins.jobs.gnss_floor SEQUENCE [--correlation-s 0 10 60]

Reads ``SEQUENCE`` (a flowins folder, EuRoC or ADVIO: :func:`flowins.data.read.read_sequence`),
which must have GNSS fixes and ground truth, and prints the floor of
:mod:`flowins.evaluation.gnss_floor`: the aligned RMSE of an oracle that knows the motion
exactly and estimates, causally and by the fixes' error model, only where in the world it
started. The first row uses the correlation time ``τ`` estimated from the fixes' errors
(what ``python evaluate.py`` prints under Table I); each ``--correlation-s`` adds a row
with that ``τ``, to show how far the floor rests on the estimate. A ``ValueError`` (bad
input) prints ``error: ...`` and exits with status 2, without a traceback.
"""
from __future__ import annotations

import argparse
import sys

from flowins.data.read import read_sequence
from flowins.evaluation.gnss_floor import gnss_floor_metrics


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m flowins.jobs.gnss_floor",
        description="The GNSS floor of a recording: the RMSE after Procrustes alignment that a causal filter "
        "weighting the fixes by their error model cannot beat, even knowing the motion exactly.",
    )
    parser.add_argument("sequence", metavar="SEQUENCE", help="sequence folder with GNSS fixes and ground truth")
    parser.add_argument("--correlation-s", type=float, nargs="*", default=[], metavar="TAU",
                        help="also compute the floor with these GNSS error correlation times (s; 0: white)")
    return parser


def floor_table(sequence: str, correlation_s: list[float]) -> str:
    """The printed table: the estimated ``τ`` first, then each given one."""
    bad = [tau for tau in correlation_s if not tau >= 0.0]
    if bad:
        raise ValueError(f"--correlation-s must be >= 0 s (0: white errors), got {bad}")
    seq = read_sequence(sequence)
    missing = [name for name, stream in (("GNSS fixes", seq.gnss), ("ground truth", seq.groundtruth)) if stream is None]
    if missing:
        raise ValueError(f"{sequence}: the GNSS floor needs GNSS fixes and ground truth; this sequence has no "
                         f"{' and no '.join(missing)}")
    rows = [gnss_floor_metrics(seq.gnss, seq.groundtruth)]
    rows += [gnss_floor_metrics(seq.gnss, seq.groundtruth, correlation_s=tau) for tau in correlation_s]
    e, n, u = rows[0]["error_rms_enu_m"]
    lines = [
        f"{seq.name}: {rows[0]['fixes']} fixes with ground truth; errors {e:.1f}/{n:.1f}/{u:.1f} m RMS (E/N/U) "
        "over the fixes that pass the gate",
        f"{'τ (s)':>14}  {'floor':>9}  {'height known':>12}  {'fixes used':>11}",
    ]
    for i, row in enumerate(rows):
        tau = f"{row['correlation_s']:.1f}" + (" (est.)" if i == 0 else "")
        lines.append(f"{tau:>14}  {row['rmse_m']:7.2f} m  {row['horizontal_rmse_m']:10.2f} m  "
                     f"{row['fixes_used']:>4} of {row['fixes']}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Print the table; returns the exit status (0 ok, 2 bad input)."""
    args = _parser().parse_args(argv)
    try:
        print(floor_table(args.sequence, args.correlation_s))
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
