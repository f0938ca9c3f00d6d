"""Small, strict readers for the comma-separated (and YAML) files of recorded datasets.

The dataset readers (:mod:`flowins.data.euroc`, :mod:`flowins.data.advio`) share
these helpers so that every bad file fails the same way: a ``ValueError`` that
names the file, the 1-based line and what was expected. Nothing is skipped
except blank lines and comment/header lines that start with ``#``; nothing is
reordered or clipped.

Cells are separated by commas; whitespace around a cell is ignored (EuRoC's
ground-truth files write ``", "``), and so are Windows line endings.
"""
from __future__ import annotations

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
