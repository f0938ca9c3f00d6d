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


def format_table(rows: list[Row]) -> str:
    """The Table I analogue as fixed-width text."""
    tick = lambda b: "x" if b else " "
    lines = [
        f"{'#':>2}  {'combination':<16} {'INS':^4} {'GNSS':^5} {'sparse':^7} {'dense':^6} {'filter RMSE':>12} {'smoother RMSE':>14}",
        "-" * 74,
    ]
    for i, r in enumerate(rows, 1):
        f = "n/a" if r.filter_rmse_m is None else f"{r.filter_rmse_m:.2f} m"
        s = "n/a" if r.smoother_rmse_m is None else f"{r.smoother_rmse_m:.2f} m"
        g, sp, d = r.sources
        lines.append(
            f"{i:>2}  {r.name:<16} {tick(True):^4} {tick(g):^5} {tick(sp):^7} {tick(d):^6} {f:>12} {s:>14}"
            + (f"   ({r.note})" if r.note else "")
        )
    return "\n".join(lines)
