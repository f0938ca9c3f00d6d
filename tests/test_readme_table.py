"""The Table I that the README shows is the one ``benchmarks/table1_cpu.json`` records from
``python evaluate.py`` with the defaults (a default changed without the README re-measured fails here)."""
import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_readme_table_is_the_recorded_default_run():
    recorded = json.loads((ROOT / "benchmarks" / "table1_cpu.json").read_text())
    readme = (ROOT / "README.md").read_text()
    rows = re.findall(r"^ \d  (\w+) .*?([\d.]+) m +([\d.]+) m$", readme, flags=re.M)
    names = [name for name in recorded if name != "measured"]
    assert [name for name, *_ in rows] == names
    for name, filter_m, smoother_m in rows:
        assert (filter_m, smoother_m) == (f"{recorded[name]['filter_rmse_m']:.2f}",
                                          f"{recorded[name]['smoother_rmse_m']:.2f}"), name
