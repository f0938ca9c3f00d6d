"""Compare the Table I that ``python evaluate.py`` printed with the one the README shows.

``python .ci/readme_table.py README.md printed.txt``: the table is the rows from the
``#  combination`` header to the first blank line after it, compared line by line after
stripping trailing spaces. ``.ci/run`` keeps what the README's main-job command printed and
runs this on it, so the README's table is what a fresh machine measures; a default changed
without the README re-measured fails CI.
"""
import sys
from pathlib import Path

HEADER = " #  combination"


def table(path: str) -> list[str]:
    lines = [line.rstrip() for line in Path(path).read_text(errors="replace").splitlines()]
    starts = [i for i, line in enumerate(lines) if line.startswith(HEADER)]
    if not starts:
        sys.exit(f"{path}: no Table I (a line starting {HEADER!r})")
    rows = []
    for line in lines[starts[-1]:]:
        if not line.strip():
            break
        rows.append(line)
    return rows


readme, printed = table(sys.argv[1]), table(sys.argv[2])
if readme != printed:
    print(f"{sys.argv[1]}: its Table I is not what `python evaluate.py` printed ({sys.argv[2]}):", file=sys.stderr)
    for ours, theirs in zip(readme + [""] * len(printed), printed + [""] * len(readme)):
        if ours != theirs:
            print(f"  README:  {ours}\n  printed: {theirs}", file=sys.stderr)
    sys.exit(1)
print(f"{sys.argv[1]}: Table I is what `python evaluate.py` printed ({len(printed) - 2} rows)")
