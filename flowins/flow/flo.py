"""Middlebury ``.flo`` flow files.

``.flo`` (Baker et al., the Middlebury flow benchmark), little-endian::

    float32  202021.25            magic ("PIEH" in ASCII)
    int32    width, height
    float32  (height, width, 2)   row-major, (Δu, Δv) interleaved per pixel

Values above 1e9 mark unknown flow by the benchmark's convention; :func:`read_flo`
returns them as they are.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["FLO_MAGIC", "read_flo", "write_flo"]

FLO_MAGIC = np.float32(202021.25)
_MAX_SIDE = 1 << 20  # a sanity bound on width and height


def write_flo(path: str | Path, flow) -> Path:
    """Write ``flow`` ``(H, W, 2)`` (numpy or torch, any float dtype; stored as float32) to ``path``."""
    arr = flow.detach().cpu().numpy() if hasattr(flow, "detach") else np.asarray(flow)
    if arr.ndim != 3 or arr.shape[-1] != 2:
        raise ValueError(
            f"write_flo({path}): flow of shape {arr.shape}; expected (H, W, 2) "
            "(for a (2, H, W) tensor pass flow.permute(1, 2, 0))"
        )
    if not np.issubdtype(arr.dtype, np.floating):
        raise ValueError(f"write_flo({path}): flow dtype {arr.dtype}; expected a float array")
    h, w = arr.shape[:2]
    path = Path(path)
    with open(path, "wb") as out:
        out.write(FLO_MAGIC.astype("<f4").tobytes())
        out.write(np.array([w, h], dtype="<i4").tobytes())
        out.write(np.ascontiguousarray(arr, dtype="<f4").tobytes())
    return path


def read_flo(path: str | Path) -> np.ndarray:
    """Read a ``.flo`` file -> ``(H, W, 2)`` float32; ``ValueError`` naming the file on a bad
    magic number, an implausible size, or a file shorter or longer than its header says."""
    path = Path(path)
    data = path.read_bytes()
    if len(data) < 12:
        raise ValueError(f"read_flo({path}): {len(data)} bytes; a .flo file has a 12-byte header (magic, width, height)")
    magic = np.frombuffer(data, "<f4", 1, 0)[0]
    if magic != FLO_MAGIC:
        raise ValueError(
            f"read_flo({path}): magic number {float(magic)!r} (bytes {data[:4]!r}); expected 202021.25 (b'PIEH'): "
            "not a Middlebury .flo file (or written big-endian)"
        )
    w, h = (int(x) for x in np.frombuffer(data, "<i4", 2, 4))
    if not (0 < w <= _MAX_SIDE and 0 < h <= _MAX_SIDE):
        raise ValueError(f"read_flo({path}): header says width={w}, height={h}; expected positive sizes up to {_MAX_SIDE}")
    expected = 12 + 8 * w * h
    if len(data) != expected:
        what = "truncated" if len(data) < expected else "has trailing bytes"
        raise ValueError(
            f"read_flo({path}): file {what}: {len(data)} bytes, expected {expected} "
            f"(12-byte header + {h} x {w} x 2 float32)"
        )
    return np.frombuffer(data, "<f4", 2 * w * h, 12).reshape(h, w, 2).astype(np.float32)
