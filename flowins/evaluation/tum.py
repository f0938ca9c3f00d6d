"""TUM trajectory files, as read by the ``evo`` tool.

One pose per line, space separated::

    timestamp tx ty tz qx qy qz qw

Note the TUM order puts the scalar part ``qw`` *last*; flowins quaternions are
scalar first ``(w, x, y, z)``, and these functions convert. Lines starting with
``#`` and blank lines are comments.
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import torch
from torch import Tensor

from flowins.data.streams import as_float64

TUM_HEADER = "timestamp tx ty tz qx qy qz qw"
_NUM_FIELDS = 8


def _rows(x, name: str, shape_tail: tuple[int, ...]) -> Tensor:
    """``x`` as float64 ``(N, *shape_tail)`` (:func:`flowins.data.streams.as_float64`)."""
    x = as_float64(x, stream="TUM track", array=name)
    if x.ndim != 1 + len(shape_tail) or tuple(x.shape[1:]) != shape_tail:
        expected = "(N" + "".join(f", {d}" for d in shape_tail) + ")"
        raise ValueError(f"{name} must have shape {expected}, got {tuple(x.shape)}")
    return x


def write_tum(
    path: str | os.PathLike,
    t_s: Tensor,
    pos_m: Tensor,
    quat_wxyz: Tensor,
    *,
    header: str | None = TUM_HEADER,
) -> Path:
    """Write poses to a TUM trajectory file and return its path.

    Args:
        path: output file (its parent directory is created if missing).
        t_s: ``(N,)`` time stamps (s), written with ``%.9f`` (ns resolution).
        pos_m: ``(N, 3)`` positions (m), written with shortest exact repr.
        quat_wxyz: ``(N, 4)`` orientations (w, x, y, z), written as ``qx qy qz qw``.
        header: text of a leading ``# ...`` comment line; ``None`` for none.

    Raises:
        ValueError: shapes disagree or a value is NaN/inf (naming argument and row).
    """
    t = _rows(t_s, "t_s", ())
    p = _rows(pos_m, "pos_m", (3,))
    q = _rows(quat_wxyz, "quat_wxyz", (4,))
    if not (t.shape[0] == p.shape[0] == q.shape[0]):
        raise ValueError(
            f"t_s, pos_m and quat_wxyz must have the same number of rows, got {t.shape[0]}, {p.shape[0]}, {q.shape[0]}"
        )
    for name, x in (("t_s", t.unsqueeze(-1)), ("pos_m", p), ("quat_wxyz", q)):
        bad = ~torch.isfinite(x).all(dim=-1)
        if bool(bad.any()):
            row = int(bad.nonzero()[0, 0])
            raise ValueError(f"{name} contains NaN or inf; first bad row is {name}[{row}] = {x[row].tolist()}")
    if header is not None and "\n" in header:
        raise ValueError("header must be a single line (no newline characters)")

    lines = [] if header is None else [f"# {header}"]
    for ti, pi, qi in zip(t.tolist(), p.tolist(), q.tolist()):
        w, x, y, z = qi
        values = (*pi, x, y, z, w)
        lines.append(f"{ti:.9f} " + " ".join(repr(v) for v in values))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


def read_tum(path: str | os.PathLike) -> tuple[Tensor, Tensor, Tensor]:
    """Read a TUM trajectory file.

    Returns:
        ``(t_s (N,), pos_m (N, 3), quat_wxyz (N, 4))`` as float64 tensors, with the
        quaternion reordered to scalar first.

    Raises:
        ValueError: a line that is not 8 finite numbers (naming the file and the
            1-based line number), or a file without any pose.
    """
    path = Path(path)
    rows: list[list[float]] = []
    with path.open() as f:
        for line_no, line in enumerate(f, start=1):
            text = line.strip()
            if not text or text.startswith("#"):
                continue
            fields = text.split()
            if len(fields) != _NUM_FIELDS:
                raise ValueError(
                    f"{path}, line {line_no}: expected {_NUM_FIELDS} numbers '{TUM_HEADER}', "
                    f"got {len(fields)} fields: {text!r}"
                )
            try:
                values = [float(v) for v in fields]
            except ValueError:
                raise ValueError(
                    f"{path}, line {line_no}: expected {_NUM_FIELDS} numbers '{TUM_HEADER}', "
                    f"got a non-numeric field: {text!r}"
                ) from None
            if not all(math.isfinite(v) for v in values):
                raise ValueError(f"{path}, line {line_no}: expected {_NUM_FIELDS} finite numbers, got NaN or inf: {text!r}")
            rows.append(values)
    if not rows:
        raise ValueError(f"{path}: no poses found (only blank or '#' comment lines)")
    data = torch.tensor(rows, dtype=torch.float64)
    t_s = data[:, 0].clone()
    pos_m = data[:, 1:4].clone()
    quat_wxyz = torch.cat((data[:, 7:8], data[:, 4:7]), dim=-1)
    return t_s, pos_m, quat_wxyz
