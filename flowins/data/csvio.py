"""Small, strict readers for the comma-separated and YAML files of recordings: the one
CSV/YAML stack of flowins.

Every reader (the flowins folder format, EuRoC, ADVIO, KITTI raw, Kalibr) goes through
these helpers, so that every bad file fails the same way: a ``ValueError`` that names the
file, the 1-based line and what was expected. Files with a header of column names are
read by :func:`read_table` (cells addressed by column name); headerless or ``#``-headed
numeric files by :func:`read_rows` / :func:`read_numeric` (by position). YAML is read
with the line of each key (:func:`load_yaml`, :func:`yaml_at`) or as a plain mapping
(:func:`read_yaml`). Nothing is skipped
except blank lines and comment/header lines that start with ``#``; nothing is
reordered or clipped.

Cells are separated by commas; whitespace around a cell is ignored (EuRoC's
ground-truth files write ``", "``), and so are Windows line endings.
"""
from __future__ import annotations

import re
from collections.abc import Iterator
from collections.abc import Sequence as Seq
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from flowins.geometry.camera import RigidTransform

__all__ = [
    "CsvRows",
    "NumericTable",
    "Table",
    "lines_for",
    "load_yaml",
    "read_table",
    "read_text",
    "rows_to_lines",
    "yaml_at",
    "yaml_line",
    "yaml_mapping",
    "yaml_number_list",
    "check_increasing",
    "read_numeric",
    "read_rows",
    "read_yaml",
    "require_file",
    "rigid_transform_from_matrix",
    "yaml_numbers",
]


def require_file(path: Path, *, what: str) -> Path:
    """``path`` if it is a file, else a ``ValueError`` saying what was expected there."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: file does not exist; expected {what}")
    return path


@dataclass(frozen=True)
class CsvRows:
    """The data rows of a CSV file: ``cells[k]`` was read from 1-based line ``lines[k]``."""

    path: Path
    cells: list[list[str]]
    lines: np.ndarray  # (N,) int64, 1-based line numbers

    def __len__(self) -> int:
        return len(self.cells)


def read_rows(path: Path, *, columns: int | tuple[int, ...], what: str, min_rows: int = 1) -> CsvRows:
    """Split every data line of ``path`` into ``columns`` cells (one count, or any of several).

    Blank lines and lines starting with ``#`` (EuRoC's header) are skipped.
    ``what`` describes the expected layout for error messages, e.g.
    ``"t [s], ax, ay, az [g]"``.
    """
    path = require_file(path, what=what)
    allowed = (columns,) if isinstance(columns, int) else tuple(columns)
    expected = " or ".join(str(c) for c in allowed)
    cells: list[list[str]] = []
    lines: list[int] = []
    with path.open("r", encoding="utf-8", errors="replace", newline="") as f:
        for number, line in enumerate(f, start=1):
            text = line.strip()
            if not text or text.startswith("#"):
                continue
            row = [c.strip() for c in text.split(",")]
            if len(row) not in allowed:
                raise ValueError(
                    f"{path}: line {number}: {len(row)} columns; expected {expected} ({what})"
                )
            cells.append(row)
            lines.append(number)
    if len(cells) < min_rows:
        raise ValueError(f"{path}: {len(cells)} data rows; expected at least {min_rows} ({what})")
    return CsvRows(path=path, cells=cells, lines=np.asarray(lines, dtype=np.int64))


@dataclass(frozen=True)
class NumericTable:
    """A numeric CSV file: first column (``int64`` nanoseconds or ``float64`` seconds) and the rest.

    ``values[k]`` (``(N, C-1)`` float64, padded with NaN where a row is shorter
    than the widest allowed layout) and ``time[k]`` come from 1-based line
    ``lines[k]``.
    """

    path: Path
    time: np.ndarray
    values: np.ndarray
    lines: np.ndarray
    columns: np.ndarray  # (N,) number of cells in each row

    def __len__(self) -> int:
        return self.time.shape[0]


def _parse_float(cell: str, *, path: Path, line: int, column: int, what: str) -> float:
    try:
        value = float(cell)
    except ValueError:
        raise ValueError(
            f"{path}: line {line}, column {column}: {cell!r} is not a number; expected {what}"
        ) from None
    if not np.isfinite(value):
        raise ValueError(f"{path}: line {line}, column {column}: {cell!r} is not a finite number; expected {what}")
    return value


def _parse_int(cell: str, *, path: Path, line: int, column: int, what: str) -> int:
    try:
        return int(cell)
    except ValueError:
        raise ValueError(
            f"{path}: line {line}, column {column}: {cell!r} is not an integer; expected {what}"
        ) from None


def read_numeric(
    path: Path,
    *,
    columns: int | tuple[int, ...],
    what: str,
    integer_time: bool = False,
    min_rows: int = 1,
) -> NumericTable:
    """Read a CSV file whose cells are all numbers; the first column is the timestamp.

    ``integer_time``: parse the first column as an exact integer (EuRoC's
    nanoseconds, ~1.4e18, are beyond float64's exact integers); otherwise as a
    float. Every other cell must be a finite float.
    """
    rows = read_rows(path, columns=columns, what=what, min_rows=min_rows)
    width = max((columns,) if isinstance(columns, int) else tuple(columns))
    n = len(rows)
    values = np.full((n, width - 1), np.nan, dtype=np.float64)
    time = np.empty(n, dtype=np.int64 if integer_time else np.float64)
    parse_time = _parse_int if integer_time else _parse_float
    count = np.empty(n, dtype=np.int64)
    for k, (row, line) in enumerate(zip(rows.cells, rows.lines.tolist())):
        time[k] = parse_time(row[0], path=rows.path, line=line, column=1, what=what)
        for j, cell in enumerate(row[1:], start=2):
            values[k, j - 2] = _parse_float(cell, path=rows.path, line=line, column=j, what=what)
        count[k] = len(row)
    return NumericTable(path=rows.path, time=time, values=values, lines=rows.lines, columns=count)


def check_increasing(
    time: np.ndarray,
    lines: np.ndarray,
    *,
    path: Path,
    unit: str,
    max_step: float | None = None,
    max_step_hint: str = "",
) -> None:
    """Timestamps must be strictly increasing (and, optionally, steps at most ``max_step``).

    Errors name the file and the 1-based lines of both samples.
    """
    if time.shape[0] < 2:
        return
    step = np.diff(time)
    bad = np.flatnonzero(step <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        raise ValueError(
            f"{path}: line {int(lines[k])}: timestamp {time[k].item()!r} {unit} is not after the previous "
            f"one ({time[k - 1].item()!r} {unit}, line {int(lines[k - 1])}); expected strictly increasing timestamps"
        )
    if max_step is not None:
        gap = np.flatnonzero(step > max_step)
        if gap.size:
            k = int(gap[0]) + 1
            raise ValueError(
                f"{path}: line {int(lines[k])}: gap of {step[k - 1].item()!r} {unit} after line {int(lines[k - 1])} "
                f"exceeds {max_step!r} {unit}{max_step_hint}"
            )


def read_yaml(path: Path, *, what: str) -> dict[str, Any]:
    """A YAML mapping. OpenCV-style ``%YAML:1.0`` directive lines (not valid YAML) are skipped."""
    path = require_file(path, what=what)
    text = path.read_text(encoding="utf-8", errors="replace")
    text = "\n".join("" if line.startswith("%YAML") else line for line in text.splitlines())
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f"{path}: not valid YAML ({exc}); expected {what}") from exc
    if not isinstance(data, dict):
        raise ValueError(f"{path}: YAML content is {type(data).__name__}; expected a mapping ({what})")
    return data


def yaml_numbers(data: dict[str, Any], key: str, *, count: int | tuple[int, ...], path: Path, what: str) -> tuple[float, ...]:
    """The list of finite numbers at ``data[key]`` (``key`` may be dotted: ``"T_BS.data"``)."""
    node: Any = data
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            raise ValueError(f"{path}: key {key!r} is missing; expected {what}")
        node = node[part]
    allowed = (count,) if isinstance(count, int) else tuple(count)
    if not isinstance(node, (list, tuple)) or len(node) not in allowed:
        expected = " or ".join(str(c) for c in allowed)
        raise ValueError(f"{path}: {key} = {node!r}; expected a list of {expected} numbers ({what})")
    out = []
    for j, value in enumerate(node):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
            raise ValueError(f"{path}: {key}[{j}] = {value!r} is not a finite number; expected {what}")
        out.append(float(value))
    return tuple(out)


def rigid_transform_from_matrix(matrix: Any, *, where: str, tolerance: float = 1e-3) -> RigidTransform:
    """A :class:`RigidTransform` from a homogeneous ``4 x 4`` matrix (nested lists or array).

    The bottom row must be ``[0, 0, 0, 1]`` and the rotation block orthonormal
    with determinant +1 to within ``tolerance`` (calibration files print about six
    digits); ``where`` names the file and key in the error.
    """
    M = np.asarray(matrix, dtype=np.float64)
    if M.shape != (4, 4):
        raise ValueError(f"{where}: matrix has shape {M.shape}; expected 4 x 4 (16 numbers, row-major)")
    if not np.allclose(M[3], [0.0, 0.0, 0.0, 1.0], atol=tolerance):
        raise ValueError(f"{where}: bottom row {M[3].tolist()}; expected [0, 0, 0, 1] (a homogeneous transform)")
    R = M[:3, :3]
    error = float(np.abs(R @ R.T - np.eye(3)).max())
    if error > tolerance or np.linalg.det(R) <= 0:
        raise ValueError(
            f"{where}: rotation block is not a rotation (|R R^T - I| = {error:.2g}, det = {np.linalg.det(R):.4g}); "
            "expected an orthonormal 3 x 3 block with determinant +1"
        )
    return RigidTransform.from_matrix(torch.from_numpy(M))


# ---------------------------------------------------------------------------
# CSV with a header of column names (cells by name; file lines in every message)
# ---------------------------------------------------------------------------



@dataclass(frozen=True)
class Table:
    """Cells of a CSV file: ``cells[r][c]`` (stripped strings) and the 1-based file line of row ``r``."""

    file: Path
    columns: tuple[str, ...]
    cells: list[list[str]]
    lines: np.ndarray  # (R,) int64

    def floats(self, column: str, *, expected: str = "a number") -> np.ndarray:
        """Column ``column`` as ``(R,)`` float64; a cell that is not a number names its line."""
        c = self.columns.index(column)
        text = [row[c] for row in self.cells]
        try:
            return np.array(text, dtype=np.float64)
        except ValueError:
            pass
        for row, cell in enumerate(text):
            try:
                float(cell)
            except ValueError:
                raise ValueError(
                    f"{self.file}: line {self.lines[row]}: column '{column}' is {cell!r}; expected {expected}"
                ) from None
        raise AssertionError("unreachable: numpy rejected a column that float() accepts")  # pragma: no cover

    def integers(self, column: str, *, expected: str = "an integer") -> np.ndarray:
        """Column ``column`` as ``(R,)`` int64 (plain decimal integers only)."""
        c = self.columns.index(column)
        out = np.empty(len(self.cells), dtype=np.int64)
        for row, cells in enumerate(self.cells):
            try:
                out[row] = int(cells[c])
            except (ValueError, OverflowError):
                raise ValueError(
                    f"{self.file}: line {self.lines[row]}: column '{column}' is {cells[c]!r}; expected {expected}"
                ) from None
        return out

    def strings(self, column: str) -> list[str]:
        c = self.columns.index(column)
        return [row[c] for row in self.cells]

    def line_of_row(self, row: int) -> int:
        return int(self.lines[row])


def read_text(file: Path) -> str:
    try:
        return file.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{file}: not UTF-8 text ({exc}); expected a CSV/YAML text file") from None


def read_table(file: Path, columns: Seq[str], *, alternatives: Seq[Seq[str]] = ()) -> Table:
    """Parse a CSV with a header row equal to ``columns`` (or one of ``alternatives``).

    Blank lines are skipped (line numbers still count them). Every data line must
    have as many comma-separated cells as the header.
    """
    accepted = [tuple(columns), *(tuple(a) for a in alternatives)]
    lines = read_text(file).splitlines()
    header_index = next((i for i, line in enumerate(lines) if line.strip()), None)
    expected_text = " or ".join(repr(",".join(a)) for a in accepted)
    if header_index is None:
        raise ValueError(f"{file}: the file is empty; expected a header row {expected_text} and data rows")
    found = tuple(cell.strip() for cell in lines[header_index].split(","))
    if found not in accepted:
        raise ValueError(
            f"{file}: line {header_index + 1}: header is {','.join(found)!r}; expected {expected_text} "
            "(column names, in this order)"
        )
    cells: list[list[str]] = []
    numbers: list[int] = []
    for i in range(header_index + 1, len(lines)):
        line = lines[i]
        if not line.strip():
            continue
        row = [cell.strip() for cell in line.split(",")]
        if len(row) != len(found):
            raise ValueError(
                f"{file}: line {i + 1}: {len(row)} comma-separated cells; expected {len(found)} "
                f"({','.join(found)})"
            )
        cells.append(row)
        numbers.append(i + 1)
    if not cells:
        raise ValueError(f"{file}: no data rows after the header (line {header_index + 1}); expected at least one")
    return Table(file=file, columns=found, cells=cells, lines=np.array(numbers, dtype=np.int64))


_ROWS_PATTERN = re.compile(r"rows (\d+) and (\d+) \(0-based;? ?")
_ROW_PATTERN = re.compile(r"row (\d+) \(0-based\)")


def rows_to_lines(message: str, table: Table) -> str:
    """Rewrite a constructor's ``row k (0-based)`` as the file's ``line N``."""

    def line(k: str) -> str:
        k_int = int(k)
        return str(table.line_of_row(k_int)) if 0 <= k_int < len(table.lines) else f"(row {k})"

    message = _ROWS_PATTERN.sub(lambda m: f"lines {line(m.group(1))} and {line(m.group(2))} (", message)
    message = _ROW_PATTERN.sub(lambda m: f"line {line(m.group(1))}", message)
    message = message.replace(" ()", "")
    if str(table.file) not in message:
        message = f"{table.file}: {message}"
    return message


@contextmanager
def lines_for(table: Table) -> Iterator[None]:
    """Re-raise a constructor's ``ValueError`` with file lines instead of 0-based rows."""
    try:
        yield
    except ValueError as exc:
        raise ValueError(rows_to_lines(str(exc), table)) from None


# ---------------------------------------------------------------------------
# YAML with the line of each key
# ---------------------------------------------------------------------------




def load_yaml(file: Path) -> tuple[Any, yaml.Node | None]:
    text = read_text(file)
    try:
        return yaml.safe_load(text), yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ValueError(f"{file}: {where}not valid YAML ({problem})") from None


def yaml_line(node: yaml.Node | None, *keys: str) -> int | None:
    """1-based line of the value at ``keys`` in a composed YAML tree (or of the deepest key found)."""
    line = None if node is None else node.start_mark.line + 1
    for key in keys:
        if not isinstance(node, yaml.MappingNode):
            break
        for k, v in node.value:
            if isinstance(k, yaml.ScalarNode) and k.value == key:
                node, line = v, k.start_mark.line + 1
                break
        else:
            break
    return line


def yaml_at(file: Path, root: yaml.Node | None, *keys: str) -> str:
    line = yaml_line(root, *keys)
    return f"{file}: line {line}: " if line is not None else f"{file}: "


def is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def yaml_number_list(value: Any, lengths: Seq[int], *, file: Path, root: yaml.Node | None, keys: Seq[str], what: str) -> list[float]:
    if value is None and 0 in lengths:
        return []
    if not isinstance(value, list) or len(value) not in lengths or not all(is_number(v) for v in value):
        sizes = " or ".join(str(n) for n in lengths)
        raise ValueError(
            f"{yaml_at(file, root, *keys)}{'.'.join(keys)} is {value!r}; expected a list of {sizes} numbers ({what})"
        )
    return [float(v) for v in value]


def yaml_mapping(value: Any, allowed: Seq[str], *, file: Path, root: yaml.Node | None, keys: Seq[str]) -> dict:
    label = ".".join(keys) if keys else "the file"
    if not isinstance(value, dict):
        raise ValueError(f"{yaml_at(file, root, *keys)}{label} is {value!r}; expected a mapping with keys {', '.join(allowed)}")
    unknown = [k for k in value if k not in allowed]
    if unknown:
        raise ValueError(
            f"{yaml_at(file, root, *keys, str(unknown[0]))}{label} has unknown key {unknown[0]!r}; "
            f"expected only {', '.join(allowed)}"
        )
    return value
