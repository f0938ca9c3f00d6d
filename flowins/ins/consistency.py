"""Does the gyroscope agree with the accelerometer? The unit and axis check a range check can't make.

A gyroscope in deg/s on a walk stays inside any range (a walk turns slowly), and a swapped
pair of axes reads plausible values. Both show when the gyroscope's rotation is set against
the gravity direction the accelerometer sees. Over a window ``[a, b]`` of ``window_s``, the
body rotation integrated from the gyroscope, ``R_ab``, predicts the gravity direction at
``b`` from the one at ``a``: ``ĝ_b = R_abᵀ g_a`` (each ``g`` the mean specific force over
``average_s`` about its time, normalised). The check compares the angle between ``ĝ_b`` and
the seen ``g_b`` (the gyroscope's error) with the angle between ``g_a`` and ``g_b`` (the
error of predicting no rotation at all). A working gyroscope explains the tilt changes, or,
where accelerations hide them, is no worse than predicting none; a wrong unit or axis
predicts tilts that never happen. Windows where neither angle reaches ``min_change_rad``
(no tilt to judge) are left out; with fewer than ``min_windows`` left there is no verdict.

When the gyroscope fails and the same comparison with the readings × π/180 passes, the
readings are named deg/s. A swapped pair of axes is not caught on a walk: its sway is too
small a tilt for the swap to predict worse than no rotation by the margin.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from flowins.geometry import quaternion


@dataclass(frozen=True)
class GyroConsistency:
    """The gyroscope against the accelerometer (:func:`gyro_consistency`).

    Attributes:
        windows: windows with a tilt change to judge.
        gyro_error_rad: median angle between the gravity direction the gyroscope predicts and
            the one seen (nan without windows).
        still_error_rad: the same for a prediction of no rotation.
        consistent: False when the gyroscope predicts worse than no rotation by the margin;
            True otherwise, also when there is too little tilt to judge (``windows`` small).
        fix: ``"deg/s"`` when the readings × π/180 agree; None otherwise.
    """

    windows: int
    gyro_error_rad: float
    still_error_rad: float
    consistent: bool
    fix: str | None = None

    def describe(self) -> str:
        return (f"over {self.windows} windows the gravity direction the gyroscope predicts is off by "
                f"{math.degrees(self.gyro_error_rad):.1f}° (median), against {math.degrees(self.still_error_rad):.1f}° "
                "for no rotation at all")


def _gravity_directions(acc: Tensor, n_avg: int) -> Tensor:
    """``(N - n_avg + 1, 3)`` unit mean specific force over each run of ``n_avg`` samples."""
    c = torch.cat((acc.new_zeros(1, 3), torch.cumsum(acc, 0)))
    mean = (c[n_avg:] - c[:-n_avg]) / n_avg
    return mean / mean.norm(dim=-1, keepdim=True).clamp_min(1e-9)


def _angles(a: Tensor, b: Tensor) -> Tensor:
    """Angle (rad) between unit vectors ``(..., 3)`` (atan2 of cross and dot: exact near 0)."""
    return torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(-1))


def _errors(t: Tensor, acc: Tensor, gyro: Tensor, n_avg: int, n_win: int, stride: int) -> tuple[Tensor, Tensor]:
    """Per window: the gyroscope's gravity-direction error and the no-rotation one (rad)."""
    dt = torch.diff(t)
    # body orientation of every sample relative to the first (body_k -> body_0), midpoint rates
    rates = 0.5 * (gyro[1:] + gyro[:-1])
    steps = quaternion.from_rotation_vector(rates * dt.unsqueeze(-1))
    q = torch.cat((quaternion.identity(1, dtype=t.dtype), quaternion.cumulative_product(steps)))
    g = _gravity_directions(acc, n_avg)  # g[i]: samples i .. i + n_avg - 1, about i + n_avg // 2
    half = n_avg // 2
    a = torch.arange(0, g.shape[0] - n_win, stride)
    b = a + n_win
    R_a, R_b = quaternion.to_matrix(q[a + half]), quaternion.to_matrix(q[b + half])
    R_ab = R_a.transpose(-1, -2) @ R_b  # body_b -> body_a
    predicted = (R_ab.transpose(-1, -2) @ g[a].unsqueeze(-1)).squeeze(-1)
    return _angles(predicted, g[b]), _angles(g[a], g[b])


def _verdict(gyro_err: Tensor, still_err: Tensor, min_change_rad: float, min_windows: int,
             margin: float, offset_rad: float) -> tuple[int, float, float, bool]:
    keep = torch.maximum(gyro_err, still_err) >= min_change_rad
    n = int(keep.sum())
    if n == 0:
        return 0, math.nan, math.nan, True
    e_gyro, e_still = float(gyro_err[keep].median()), float(still_err[keep].median())
    return n, e_gyro, e_still, n < min_windows or e_gyro <= margin * e_still + offset_rad


def gyro_consistency(
    t_s: Tensor,
    acc_mps2: Tensor,
    gyro_rps: Tensor,
    *,
    window_s: float = 1.0,
    average_s: float = 0.5,
    min_change_rad: float = math.radians(2.0),
    min_windows: int = 10,
    margin: float = 2.0,
    offset_rad: float = math.radians(3.0),
) -> GyroConsistency:
    """Whether the gyroscope's rotation explains the accelerometer's tilt changes (module docstring).

    Args:
        t_s: ``(N,)`` increasing times (s); acc_mps2, gyro_rps: ``(N, 3)`` readings.
        window_s: the span over which a rotation predicts a tilt change.
        average_s: the span each gravity direction is averaged over (steps and vibration).
        min_change_rad: windows where neither error reaches this are not judged.
        min_windows: fewer judged windows than this give no verdict (consistent).
        margin, offset_rad: the gyroscope fails when its median error exceeds ``margin``
            times the no-rotation one plus ``offset_rad``.
    """
    t = torch.as_tensor(t_s, dtype=torch.float64)
    acc = torch.as_tensor(acc_mps2, dtype=torch.float64)
    gyro = torch.as_tensor(gyro_rps, dtype=torch.float64)
    if t.shape[0] < 2:
        return GyroConsistency(0, math.nan, math.nan, True)
    dt = float(torch.diff(t).median())
    n_avg = max(1, round(average_s / dt))
    n_win = max(1, round(window_s / dt))
    stride = max(1, n_win // 2)
    if t.shape[0] < n_avg + n_win + 1:
        return GyroConsistency(0, math.nan, math.nan, True)
    args = (min_change_rad, min_windows, margin, offset_rad)
    n, e_gyro, e_still, ok = _verdict(*_errors(t, acc, gyro, n_avg, n_win, stride), *args)
    if ok:
        return GyroConsistency(n, e_gyro, e_still, True)
    # × π/180 consistent (or too little tilt left to judge): the readings are deg/s
    fix = "deg/s" if _verdict(*_errors(t, acc, gyro * (math.pi / 180.0), n_avg, n_win, stride), *args)[3] else None
    return GyroConsistency(n, e_gyro, e_still, False, fix)
