"""The printed Table I: one row per fusion combination, its filter and smoother RMSE."""
from __future__ import annotations

from dataclasses import dataclass


#: the table's source columns: (config key of a method, heading); the INS column is always ticked
COLUMNS: tuple[tuple[str, str], ...] = (("gnss", "GNSS"), ("sparse", "sparse"), ("dense", "dense"))


@dataclass
class Row:
    """One combination: its name, the sources it fuses (names of :data:`COLUMNS` and of any
    other measurement), its RMSE (mean and standard deviation over several runs)."""

    name: str
    sources: frozenset[str]
    filter_rmse_m: float | None
    smoother_rmse_m: float | None
    note: str = ""
    seconds: float = 0.0
    #: standard deviations over several runs (seeds); None: one run
    filter_std_m: float | None = None
    smoother_std_m: float | None = None
    #: how the filter started (:meth:`flowins.start.Start.describe`), "" if unknown
    start: str = ""


def _value(mean: float | None, std: float | None) -> str:
    if mean is None:
        return "n/a"
    return f"{mean:.2f} m" if std is None else f"{mean:.2f} ± {std:.2f} m"


def format_table(rows: list[Row]) -> str:
    """The Table I analogue as fixed-width text (mean ± std where the rows have several runs)."""
    tick = lambda b: "x" if b else " "
    width = 19 if any(r.filter_std_m is not None for r in rows) else 14
    known = {key for key, _ in COLUMNS}
    columns = [("ins", "INS"), *COLUMNS, *((key, key) for key in sorted(set().union(*(r.sources for r in rows)) - known))]
    widths = [max(len(heading) + 1, 4) for _, heading in columns]
    head = " ".join(f"{heading:^{w}}" for (_, heading), w in zip(columns, widths))
    lines = [
        f"{'#':>2}  {'combination':<16} {head} {'filter RMSE':>{width - 2}} {'smoother RMSE':>{width}}",
        "-" * (24 + sum(widths) + len(widths) + 2 * width - 4),
    ]
    for i, r in enumerate(rows, 1):
        f, s = _value(r.filter_rmse_m, r.filter_std_m), _value(r.smoother_rmse_m, r.smoother_std_m)
        ticks = " ".join(f"{tick(key == 'ins' or key in r.sources):^{w}}" for (key, _), w in zip(columns, widths))
        lines.append(
            f"{i:>2}  {r.name:<16} {ticks} {f:>{width - 2}} {s:>{width}}" + (f"   ({r.note})" if r.note else "")
        )
    return "\n".join(lines)
