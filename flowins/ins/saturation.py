"""Saturation (clipping) in an IMU recording: an axis that sticks at its range.

A sensor driven past its range reports its limit: the readings of a clipped axis stop at
one value ``M`` and stay there while the motion lasts. For each sensor, axis and side
(max and min) the extreme reading ``M`` of the axis is saturation when

(a) at least ``min_count`` readings equal ``M`` exactly: the extreme is a limit the axis
    returns to, not one noisy peak;
(b) at least one run of ``min_run`` consecutive readings sits at ``M``: the signal stays
    at the limit while it lasts (a clipped peak is a plateau, not a spike);
(c) the readings pile up at ``M`` instead of thinning out toward it:
    ``#{x = M} > pile_up · #{M - δ <= x < M}`` (mirrored on the min side; ``pile_up`` = 2), with
    ``δ = max(0.005 |M - median(x)|, 1.5 q)`` and ``q`` the axis' quantisation step, the
    smallest positive difference between its sorted distinct values (a real sensor's
    16-bit LSB; for unquantised readings ``q`` is tiny and the 0.5 % term rules: float readings repeat only at a clip).

(c) is what tells a clip from a quantised sensor. A still, quantised gyroscope reads a
few levels of noise: its top level repeats and forms runs, so (a) and (b) hold, but the
level below it is read more often (a distribution thins out toward its tail). A clipped
signal gathers every reading that would have gone beyond the limit at the limit, so the
limit holds more readings than the band just below it. The band is at least 1.5 LSB
wide, so it holds the level below ``M`` on a quantised axis.

A constant axis (one distinct value, e.g. a gyroscope that reads exactly 0) is not
saturation: its one value is both extremes and there is no distribution below it that
the value could pile up against, so a clip cannot be told from a dead or disconnected
channel. It is left to a check for dead axes; here it gives no finding.

Example: the simulated walk's accelerometer clipped at ±12 m/s² names its z axis (+)
only; the walk's vertical bounce carries z above 12 m/s² at every step.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

_UNITS = {"accelerometer": "m/s²", "gyroscope": "rad/s"}


@dataclass(frozen=True)
class Saturation:
    """An axis that sticks at one extreme value (:func:`find_saturation`).

    Attributes:
        sensor: ``"accelerometer"`` or ``"gyroscope"``.
        axis: ``"x"``, ``"y"`` or ``"z"``.
        value: the reading the axis sticks at (m/s² or rad/s), signed.
        count: readings exactly at ``value``.
        longest_run: longest run of consecutive readings at ``value``.
        first_row: 0-based row of the first reading at ``value``.
        first_t_s: its time (s).
        last_t_s: time of the last reading at ``value`` (s).
        readings: rows of the recording (for the fraction ``count / readings``).
    """

    sensor: str
    axis: str
    value: float
    count: int
    longest_run: int
    first_row: int
    first_t_s: float
    last_t_s: float
    readings: int

    def describe(self) -> str:
        """One line, e.g. ``accelerometer z sticks at +12 m/s² in 2071 readings (18.3 %),
        longest run 45, from t = 3.21 s to 280.4 s``."""
        share = 100.0 * self.count / self.readings
        return (f"{self.sensor} {self.axis} sticks at {self.value:+.6g} {_UNITS[self.sensor]} in {self.count} readings "
                f"({share:.1f} %), longest run {self.longest_run}, "
                f"from t = {self.first_t_s:.4g} s to {self.last_t_s:.4g} s")


def _as_rows(values: Any, name: str, columns: int | None, n: int | None) -> Tensor:
    """``values`` as float64 ``(N,)`` (``columns`` None) or ``(N, columns)``; ValueError naming ``name``."""
    x = torch.as_tensor(values, dtype=torch.float64)
    expected = (n if n is not None else x.shape[0] if x.ndim else -1,) + (() if columns is None else (columns,))
    if tuple(x.shape) != expected:
        want = "(N,)" if columns is None else f"(N, {columns})"
        raise ValueError(f"find_saturation: {name} has shape {tuple(x.shape)}; expected {want}"
                         + (f" with N = {n} (the rows of t_s)" if n is not None else ""))
    bad = ~(torch.isfinite(x) if columns is None else torch.isfinite(x).all(-1))
    if bool(bad.any()):
        row = int(bad.nonzero()[0, 0])
        raise ValueError(f"find_saturation: {name} row {row} is not finite: {x[row].tolist()}")
    return x


def _longest_run(at: Tensor) -> int:
    """Longest run of consecutive True in the boolean ``(N,)`` ``at``."""
    padded = torch.cat((at.new_zeros(1), at, at.new_zeros(1))).to(torch.int8)
    edges = torch.diff(padded)
    starts, ends = (edges == 1).nonzero()[:, 0], (edges == -1).nonzero()[:, 0]
    return int((ends - starts).max()) if starts.numel() else 0


def quantisation_step(x: Tensor) -> float:
    """The smallest positive difference between the sorted distinct values of ``x`` ``(N,)``
    (a quantised sensor's LSB); 0.0 when ``x`` holds fewer than two distinct values."""
    levels = torch.unique(x)
    return float(torch.diff(levels).min()) if levels.numel() > 1 else 0.0


def find_saturation(t_s: Any, acc_mps2: Any, gyro_rps: Any, *, min_count: int = 5,
                    min_run: int = 2, pile_up: float = 2.0) -> list[Saturation]:
    """The saturated axes of an IMU recording (criterion in the module docstring).

    Args:
        t_s: ``(N,)`` sample times (s).
        acc_mps2: ``(N, 3)`` accelerometer readings (m/s²).
        gyro_rps: ``(N, 3)`` gyroscope readings (rad/s). Tensors or arrays, read as float64.
        min_count: readings at the extreme needed (criterion a), >= 1.
        min_run: consecutive readings at the extreme needed (criterion b), >= 1.
        pile_up: the extreme holds more than this many times the readings of the band below
            it (criterion c): a sensor's own low-pass filter can leave a few more readings
            at a noise extreme than next to it, a clip leaves tens of times more.

    Returns:
        The findings, accelerometer before gyroscope, x, y, z, max before min; empty when
        ``N < min_count``. A constant axis gives none.
    """
    if isinstance(min_count, bool) or not isinstance(min_count, int) or min_count < 1:
        raise ValueError(f"find_saturation: min_count={min_count!r}; expected an integer >= 1")
    if isinstance(min_run, bool) or not isinstance(min_run, int) or min_run < 1:
        raise ValueError(f"find_saturation: min_run={min_run!r}; expected an integer >= 1")
    t = _as_rows(t_s, "t_s", None, None)
    n = t.shape[0]
    streams = (("accelerometer", _as_rows(acc_mps2, "acc_mps2", 3, n)),
               ("gyroscope", _as_rows(gyro_rps, "gyro_rps", 3, n)))
    if n < min_count:
        return []
    found = []
    for sensor, readings in streams:
        for k, axis in enumerate("xyz"):
            x = readings[:, k]
            q = quantisation_step(x)
            if q == 0.0:  # a constant axis: no distribution to pile up against
                continue
            median = x.median()
            for sign in (1.0, -1.0):  # max side, then min side as the max of -x
                y = sign * x
                top = y.max()
                at = y == top
                count = int(at.sum())
                if count < min_count:
                    continue
                delta = max(0.005 * float((top - sign * median).abs()), 1.5 * q)
                below = int(((y >= top - delta) & (y < top)).sum())
                if count <= pile_up * below:
                    continue
                run = _longest_run(at)
                if run < min_run:
                    continue
                rows = at.nonzero()[:, 0]
                first, last = int(rows[0]), int(rows[-1])
                found.append(Saturation(sensor=sensor, axis=axis, value=float(x[first]), count=count,
                                        longest_run=run, first_row=first, first_t_s=float(t[first]),
                                        last_t_s=float(t[last]), readings=n))
    return found


__all__ = ["Saturation", "find_saturation", "quantisation_step"]
