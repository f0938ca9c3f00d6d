"""Table I of a run set against a reference run's, cell by cell (``benchmarks/gpu.sh``).

    python benchmarks/gpu_table.py RUN_METRICS_JSON REFERENCE_JSON

Both files are ``metrics.json`` of ``python evaluate.py`` (or the cells of one, as
``benchmarks/table1_cpu.json`` keeps them). Prints each row's filter and smoother RMSE in
both and their difference, then the largest difference over the rows with flow and over
those without (the issue's bound: 0.2 m per cell; rows without flow see the same inputs).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

ROWS = ("ins", "ins_gnss", "ins_sparse", "ins_dense", "ins_gnss_sparse", "ins_gnss_dense")


def cells(path: Path) -> dict[str, tuple[float, float]]:
    metrics = json.loads(path.read_text())
    return {row: (metrics[row]["filter_rmse_m"], metrics[row]["smoother_rmse_m"])
            for row in ROWS if isinstance(metrics.get(row), dict) and metrics[row].get("filter_rmse_m") is not None}


def main() -> None:
    if len(sys.argv) != 3:
        raise SystemExit(__doc__)
    run, reference = (cells(Path(arg)) for arg in sys.argv[1:])
    print(f"{'row':<16} {'this run (filter / smoother)':>30} {'reference':>22} {'difference':>20}")
    worst = {"with flow": 0.0, "without flow": 0.0}
    for row in ROWS:
        if row not in run or row not in reference:
            continue
        (f, s), (rf, rs) = run[row], reference[row]
        kind = "with flow" if ("sparse" in row or "dense" in row) else "without flow"
        worst[kind] = max(worst[kind], abs(f - rf), abs(s - rs))
        print(f"{row:<16} {f:>14.2f} / {s:>7.2f} m {rf:>10.2f} / {rs:>7.2f} m {f - rf:>+9.2f} / {s - rs:>+7.2f} m")
    print("largest difference: " + ", ".join(f"{k} {v:.3f} m" for k, v in worst.items()))


if __name__ == "__main__":
    main()
