"""Validated, immutable sensor streams: IMU, GNSS fixes and reference poses.

Every stream holds float64 CPU tensors (copies of what it was given, detached
from any autograd graph: a stream is recorded data, not a graph node) and a
``name`` used in error messages (``"IMU"``, or the file a loader read it from).

Validation happens once, in the constructor. A bad stream raises a
``ValueError`` that names the stream, the array, the first offending row
(0-based) and what was expected. Nothing is dropped, clipped or reordered; the
only value a constructor changes is a reference quaternion, which is divided by
its norm (a rescaling of a valid rotation, not a clip: rows whose norm is zero
are rejected instead).
"""
from __future__ import annotations

from dataclasses import KW_ONLY, dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = ["GnssStream", "ImuStream", "PoseStream"]

_DTYPE = torch.float64


# ---------------------------------------------------------------------------
# Shared checks (each raises ValueError naming stream, array and 0-based row)
# ---------------------------------------------------------------------------


def as_float64(value: Any, *, stream: str, array: str) -> Tensor:
    """A float64 CPU copy of ``value`` (tensor, numpy array or nested list)."""
    if isinstance(value, Tensor):
        if value.is_complex():
            raise ValueError(f"{stream}: {array} is complex ({value.dtype}); expected real numbers")
        return value.detach().to(device="cpu", dtype=_DTYPE, copy=True)
    try:
        arr = np.array(value, dtype=np.float64, copy=True)
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"{stream}: {array} could not be converted to a float64 array ({exc}); "
            "expected numbers (a tensor, numpy array or list)"
        ) from exc
    return torch.from_numpy(arr)


def _check_rows(t_s: Tensor, *, stream: str, min_rows: int) -> int:
    """``t_s`` must be 1-D with at least ``min_rows`` rows; returns N."""
    if t_s.ndim != 1:
        raise ValueError(f"{stream}: t_s has shape {tuple(t_s.shape)}; expected a 1-D array (N,) of timestamps")
    n = t_s.shape[0]
    if n == 0:
        raise ValueError(f"{stream}: stream is empty (t_s has 0 rows); expected at least {min_rows} sample(s)")
    if n < min_rows:
        raise ValueError(f"{stream}: stream has {n} sample(s); expected at least {min_rows}")
    return n


def _check_shape(x: Tensor, expected: tuple[int, ...], *, stream: str, array: str) -> None:
    if tuple(x.shape) != expected:
        raise ValueError(
            f"{stream}: {array} has shape {tuple(x.shape)}; expected {expected} "
            f"(one row per timestamp in t_s, N={expected[0]})"
        )


def _check_finite(x: Tensor, *, stream: str, array: str, hint: str = "") -> None:
    bad = ~torch.isfinite(x)
    if not bool(bad.any()):
        return
    idx = [int(i) for i in torch.nonzero(bad)[0]]  # row-major: first row, then first column
    value = float(x[tuple(idx)])
    where = f"row {idx[0]} (0-based)" + (f", column {idx[1]}" if len(idx) > 1 else "")
    raise ValueError(
        f"{stream}: {array} has a non-finite value ({value}) at {where}; expected finite numbers{hint}"
    )


def _check_increasing(t_s: Tensor, *, stream: str, max_gap_s: float | None = None) -> None:
    """Strictly increasing timestamps, and (optionally) no step above ``max_gap_s``."""
    dt = t_s[1:] - t_s[:-1]
    bad = torch.nonzero(dt <= 0)
    if bad.numel():
        k = int(bad[0, 0]) + 1
        raise ValueError(
            f"{stream}: timestamps are not strictly increasing at row {k} (0-based): "
            f"t_s[{k - 1}]={float(t_s[k - 1])!r} s, t_s[{k}]={float(t_s[k])!r} s "
            f"(dt={float(dt[k - 1]):.6g} s); expected t_s[k] > t_s[k-1]"
        )
    if max_gap_s is not None:
        gap = torch.nonzero(dt > max_gap_s)
        if gap.numel():
            k = int(gap[0, 0]) + 1
            raise ValueError(
                f"{stream}: gap of {float(dt[k - 1]):.6g} s between rows {k - 1} and {k} (0-based; "
                f"t_s={float(t_s[k - 1])!r} s -> {float(t_s[k])!r} s) exceeds the largest allowed step"
                + gap_hint(max_gap_s)
            )


def gap_hint(max_gap_s: float) -> str:
    """The remedy for an IMU gap, as every reader words it."""
    return (f" (max_imu_gap_s={max_gap_s:g}); to bridge it, raise sequence.max_imu_gap_s in evaluate.py or "
            "train.py (read_sequence(..., max_imu_gap_s=...) in Python)")


def _set(obj: object, **fields: Any) -> None:
    """Assign converted fields on a frozen dataclass inside ``__post_init__``."""
    for key, value in fields.items():
        object.__setattr__(obj, key, value)


# ---------------------------------------------------------------------------
# Streams
# ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ImuStream:
    """Accelerometer and gyroscope samples in the IMU frame.

    Attributes:
        t_s: ``(N,)`` strictly increasing timestamps [s], N >= 2; sampling
            may be non-uniform, but no step may exceed ``max_gap_s``.
        acc_mps2: ``(N, 3)`` specific force [m/s^2].
        gyro_rps: ``(N, 3)`` angular rate [rad/s].
        name: stream name for error messages (keyword-only).
        max_gap_s: largest allowed step between consecutive timestamps [s]
            (keyword-only).
    """

    t_s: Tensor
    acc_mps2: Tensor
    gyro_rps: Tensor
    _: KW_ONLY
    name: str = "IMU"
    max_gap_s: float = 0.2

    def __post_init__(self) -> None:
        name = str(self.name)
        max_gap_s = float(self.max_gap_s)
        if not (np.isfinite(max_gap_s) and max_gap_s > 0):
            raise ValueError(f"{name}: max_gap_s={self.max_gap_s!r}; expected a finite number > 0 seconds")
        t_s = as_float64(self.t_s, stream=name, array="t_s")
        n = _check_rows(t_s, stream=name, min_rows=2)
        acc = as_float64(self.acc_mps2, stream=name, array="acc_mps2")
        gyro = as_float64(self.gyro_rps, stream=name, array="gyro_rps")
        _check_shape(acc, (n, 3), stream=name, array="acc_mps2")
        _check_shape(gyro, (n, 3), stream=name, array="gyro_rps")
        _check_finite(t_s, stream=name, array="t_s")
        _check_finite(acc, stream=name, array="acc_mps2")
        _check_finite(gyro, stream=name, array="gyro_rps")
        _check_increasing(t_s, stream=name, max_gap_s=max_gap_s)
        _set(self, t_s=t_s, acc_mps2=acc, gyro_rps=gyro, name=name, max_gap_s=max_gap_s)

    def __len__(self) -> int:
        return self.t_s.shape[0]

    @property
    def dt_s(self) -> Tensor:
        """``(N-1,)`` steps ``t_s[k] - t_s[k-1]`` [s]."""
        return self.t_s[1:] - self.t_s[:-1]

    @property
    def duration_s(self) -> float:
        """``t_s[-1] - t_s[0]`` [s]."""
        return float(self.t_s[-1] - self.t_s[0])

    @property
    def rate_hz(self) -> float:
        """Sampling rate ``1 / median(dt_s)`` [Hz] (true median, robust to a few gaps)."""
        return 1.0 / float(torch.quantile(self.dt_s, 0.5))

    def slice_time(self, t0_s: float, t1_s: float) -> ImuStream:
        """A new stream of the samples with ``t0_s <= t_s <= t1_s`` (bounds inclusive).

        Raises ``ValueError`` if ``t0_s > t1_s`` or fewer than 2 samples remain.
        """
        t0_s, t1_s = float(t0_s), float(t1_s)
        if not t0_s <= t1_s:
            raise ValueError(f"{self.name}: slice_time(t0_s={t0_s!r}, t1_s={t1_s!r}); expected t0_s <= t1_s")
        keep = (self.t_s >= t0_s) & (self.t_s <= t1_s)
        kept = int(keep.sum())
        if kept < 2:
            raise ValueError(
                f"{self.name}: slice_time(t0_s={t0_s!r}, t1_s={t1_s!r}) keeps {kept} of {len(self)} samples "
                f"(stream spans [{float(self.t_s[0])!r}, {float(self.t_s[-1])!r}] s); expected at least 2"
            )
        return ImuStream(
            self.t_s[keep],
            self.acc_mps2[keep],
            self.gyro_rps[keep],
            name=self.name,
            max_gap_s=self.max_gap_s,
        )


@dataclass(frozen=True, eq=False)
class GnssStream:
    """WGS84 position fixes with 1-sigma accuracies.

    Attributes (all ``(G,)``, G >= 1):
        t_s: strictly increasing timestamps [s].
        lat_deg: geodetic latitude in [-90, 90] [deg].
        lon_deg: longitude in [-180, 180] [deg].
        alt_m: ellipsoidal height above WGS84 [m].
        h_acc_m: horizontal 1-sigma accuracy (per axis) [m], > 0.
        v_acc_m: vertical 1-sigma accuracy [m], > 0.
        name: stream name for error messages (keyword-only).

    A missing accuracy (NaN) is an error, not a default.
    """

    t_s: Tensor
    lat_deg: Tensor
    lon_deg: Tensor
    alt_m: Tensor
    h_acc_m: Tensor
    v_acc_m: Tensor
    _: KW_ONLY
    name: str = "GNSS"

    def __post_init__(self) -> None:
        name = str(self.name)
        t_s = as_float64(self.t_s, stream=name, array="t_s")
        g = _check_rows(t_s, stream=name, min_rows=1)
        arrays = {"t_s": t_s}
        for key in ("lat_deg", "lon_deg", "alt_m", "h_acc_m", "v_acc_m"):
            arrays[key] = as_float64(getattr(self, key), stream=name, array=key)
            _check_shape(arrays[key], (g,), stream=name, array=key)
        for key, x in arrays.items():
            hint = " (a missing accuracy is an error, not a default)" if key.endswith("_acc_m") else ""
            _check_finite(x, stream=name, array=key, hint=hint)
        for key, lo, hi in (("lat_deg", -90.0, 90.0), ("lon_deg", -180.0, 180.0)):
            x = arrays[key]
            bad = torch.nonzero((x < lo) | (x > hi))
            if bad.numel():
                k = int(bad[0, 0])
                raise ValueError(
                    f"{name}: {key}={float(x[k])!r} at row {k} (0-based); expected a value in [{lo:g}, {hi:g}] degrees"
                )
        for key in ("h_acc_m", "v_acc_m"):
            x = arrays[key]
            bad = torch.nonzero(x <= 0)
            if bad.numel():
                k = int(bad[0, 0])
                raise ValueError(f"{name}: {key}={float(x[k])!r} at row {k} (0-based); expected a 1-sigma accuracy > 0 m")
        _check_increasing(t_s, stream=name)
        _set(self, name=name, **arrays)

    def __len__(self) -> int:
        return self.t_s.shape[0]

    def enu(self, origin: Any = None) -> tuple[Tensor, Tensor, Any]:
        """The fixes in a local ENU frame (:func:`flowins.geometry.geodesy.gnss_to_enu`):
        ``(pos_m (G, 3), cov_m2 (G, 3, 3), origin)``; ``origin`` the first fix when None."""
        from flowins.geometry.geodesy import gnss_to_enu

        return gnss_to_enu(self.lat_deg, self.lon_deg, self.alt_m, self.h_acc_m, self.v_acc_m, origin=origin)


@dataclass(frozen=True, eq=False)
class PoseStream:
    """Reference (ground-truth) trajectory.

    Attributes:
        t_s: ``(M,)`` strictly increasing timestamps [s], M >= 1.
        pos_m: ``(M, 3)`` positions [m] in the reference frame.
        quat_wxyz: ``(M, 4)`` orientation quaternions ``(w, x, y, z)``, or
            ``None`` when the reference has no orientation. Every row must be
            finite with non-zero norm; rows are divided by their norm (sign and
            direction are kept).
        name: stream name for error messages (keyword-only).
    """

    t_s: Tensor
    pos_m: Tensor
    quat_wxyz: Tensor | None = None
    _: KW_ONLY
    name: str = "ground truth"

    def __post_init__(self) -> None:
        name = str(self.name)
        t_s = as_float64(self.t_s, stream=name, array="t_s")
        m = _check_rows(t_s, stream=name, min_rows=1)
        pos = as_float64(self.pos_m, stream=name, array="pos_m")
        _check_shape(pos, (m, 3), stream=name, array="pos_m")
        _check_finite(t_s, stream=name, array="t_s")
        _check_finite(pos, stream=name, array="pos_m")
        quat = None
        if self.quat_wxyz is not None:
            quat = as_float64(self.quat_wxyz, stream=name, array="quat_wxyz")
            _check_shape(quat, (m, 4), stream=name, array="quat_wxyz")
            _check_finite(quat, stream=name, array="quat_wxyz")
            norm = torch.linalg.vector_norm(quat, dim=-1, keepdim=True)
            bad = torch.nonzero(norm[:, 0] == 0)
            if bad.numel():
                k = int(bad[0, 0])
                raise ValueError(
                    f"{name}: quat_wxyz row {k} (0-based) is the zero quaternion; expected a non-zero (w, x, y, z)"
                )
            quat = quat / norm
        _check_increasing(t_s, stream=name)
        _set(self, t_s=t_s, pos_m=pos, quat_wxyz=quat, name=name)

    def __len__(self) -> int:
        return self.t_s.shape[0]
