"""The printed Table I: one row per fusion combination, its filter and smoother RMSE."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class Row:
    name: str
    sources: tuple[bool, bool, bool]
    filter_rmse_m: float | None
    smoother_rmse_m: float | None
    note: str = ""
    seconds: float = 0.0
    #: standard deviations over several runs (seeds); None: one run
    filter_std_m: float | None = None
    smoother_std_m: float | None = None


def _value(mean: float | None, std: float | None) -> str:
    if mean is None:
        return "n/a"
    return f"{mean:.2f} m" if std is None else f"{mean:.2f} ± {std:.2f} m"


def format_table(rows: list[Row]) -> str:
    """The Table I analogue as fixed-width text (mean ± std where the rows have several runs)."""
    tick = lambda b: "x" if b else " "
    width = 19 if any(r.filter_std_m is not None for r in rows) else 14
    lines = [
        f"{'#':>2}  {'combination':<16} {'INS':^4} {'GNSS':^5} {'sparse':^7} {'dense':^6} "
        f"{'filter RMSE':>{width - 2}} {'smoother RMSE':>{width}}",
        "-" * (46 + 2 * width),
    ]
    for i, r in enumerate(rows, 1):
        f, s = _value(r.filter_rmse_m, r.filter_std_m), _value(r.smoother_rmse_m, r.smoother_std_m)
        g, sp, d = r.sources
        lines.append(
            f"{i:>2}  {r.name:<16} {tick(True):^4} {tick(g):^5} {tick(sp):^7} {tick(d):^6} {f:>{width - 2}} {s:>{width}}"
            + (f"   ({r.note})" if r.note else "")
        )
    return "\n".join(lines)
