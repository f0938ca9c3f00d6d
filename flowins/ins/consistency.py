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

**A constant bias is not a fault.** A MEMS gyroscope reads a constant offset of up to several
°/s (EuRoC's ADIS16448: 0.077 rad/s on one axis), which over a 1 s window tilts the predicted
gravity by 4° and looks like a wrong unit. When the readings as they are fail, the check
estimates the bias and judges the readings less it: from the mean rate over the recording's
still start where it has one (:func:`~flowins.ins.initialization.still_interval`), refined by
a robust fit over every window (:func:`fit_gyro_bias`: Gauss–Newton on the gravity-direction
residuals ``ĝ_b × g_b``, Cauchy weights, so that windows whose accelerations hide gravity count
little). A constant bias cannot reproduce a scale error: a deg/s gyroscope still fails, and when
the readings × π/180 (less their own fitted bias) pass, the readings are named deg/s. A swapped
pair of axes is not caught on a walk: its sway is too small a tilt for the swap to predict
worse than no rotation by the margin (where there is flow, :mod:`flowins.flow.mounting` names
mirrored gyroscope axes).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from flowins.geometry import quaternion
from flowins.ins.initialization import still_interval


@dataclass(frozen=True)
class GyroConsistency:
    """The gyroscope against the accelerometer (:func:`gyro_consistency`).

    Attributes:
        windows: windows with a tilt change to judge.
        gyro_error_rad: median angle between the gravity direction the gyroscope (less
            ``bias_rps``) predicts and the one seen (nan without windows).
        still_error_rad: the same for a prediction of no rotation.
        consistent: False when the gyroscope predicts worse than no rotation by the margin,
            even less a constant bias; True otherwise, also when there is too little tilt to
            judge (``windows`` small).
        fix: ``"deg/s"`` when the readings × π/180 agree; None otherwise.
        bias_rps: ``(3,)`` the constant bias the verdict removed (rad/s, or in the readings'
            own unit when they fail), None when the readings pass as they are.
        bias_source: how ``bias_rps`` was found ("" when None).
    """

    windows: int
    gyro_error_rad: float
    still_error_rad: float
    consistent: bool
    fix: str | None = None
    bias_rps: tuple[float, float, float] | None = None
    bias_source: str = ""

    def describe_bias(self) -> str:
        """``"a constant bias of (x, y, z) rad/s"``; "" without one."""
        if self.bias_rps is None:
            return ""
        return "a constant bias of (" + ", ".join(f"{b:.3g}" for b in self.bias_rps) + ") rad/s"

    def describe(self) -> str:
        less = "" if self.bias_rps is None else " less " + self.describe_bias()
        return (f"over {self.windows} windows the gravity direction the gyroscope{less} predicts is off by "
                f"{math.degrees(self.gyro_error_rad):.1f}° (median), against {math.degrees(self.still_error_rad):.1f}° "
                "for no rotation at all")


@dataclass(frozen=True)
class _Windows:
    """Index arithmetic of the windows over a stream (sample counts)."""

    n_avg: int
    n_win: int
    stride: int


def _gravity_directions(acc: Tensor, n_avg: int) -> Tensor:
    """``(N - n_avg + 1, 3)`` unit mean specific force over each run of ``n_avg`` samples."""
    c = torch.cat((acc.new_zeros(1, 3), torch.cumsum(acc, 0)))
    mean = (c[n_avg:] - c[:-n_avg]) / n_avg
    return mean / mean.norm(dim=-1, keepdim=True).clamp_min(1e-9)


def _angles(a: Tensor, b: Tensor) -> Tensor:
    """Angle (rad) between unit vectors ``(..., 3)`` (atan2 of cross and dot: exact near 0)."""
    return torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(-1))


def _predictions(t: Tensor, acc: Tensor, gyro: Tensor, w: _Windows) -> tuple[Tensor, Tensor, Tensor]:
    """Per window: the gravity direction the gyroscope predicts at its end, the one seen
    there, and the one seen at its start (each ``(W, 3)``, unit)."""
    dt = torch.diff(t)
    # body orientation of every sample relative to the first (body_k -> body_0), midpoint rates
    rates = 0.5 * (gyro[1:] + gyro[:-1])
    steps = quaternion.from_rotation_vector(rates * dt.unsqueeze(-1))
    q = torch.cat((quaternion.identity(1, dtype=t.dtype), quaternion.cumulative_product(steps)))
    g = _gravity_directions(acc, w.n_avg)  # g[i]: samples i .. i + n_avg - 1, about i + n_avg // 2
    half = w.n_avg // 2
    a = torch.arange(0, g.shape[0] - w.n_win, w.stride)
    b = a + w.n_win
    R_a, R_b = quaternion.to_matrix(q[a + half]), quaternion.to_matrix(q[b + half])
    R_ab = R_a.transpose(-1, -2) @ R_b  # body_b -> body_a
    predicted = (R_ab.transpose(-1, -2) @ g[a].unsqueeze(-1)).squeeze(-1)
    return predicted, g[b], g[a]


def _errors(t: Tensor, acc: Tensor, gyro: Tensor, w: _Windows) -> tuple[Tensor, Tensor]:
    """Per window: the gyroscope's gravity-direction error and the no-rotation one (rad)."""
    predicted, seen, before = _predictions(t, acc, gyro, w)
    return _angles(predicted, seen), _angles(before, seen)


def _verdict(gyro_err: Tensor, still_err: Tensor, min_change_rad: float, min_windows: int,
             margin: float, offset_rad: float) -> tuple[int, float, float, bool]:
    keep = torch.maximum(gyro_err, still_err) >= min_change_rad
    n = int(keep.sum())
    if n == 0:
        return 0, math.nan, math.nan, True
    e_gyro, e_still = float(gyro_err[keep].median()), float(still_err[keep].median())
    return n, e_gyro, e_still, n < min_windows or e_gyro <= margin * e_still + offset_rad


def fit_gyro_bias(t: Tensor, acc: Tensor, gyro: Tensor, w: _Windows, *, start_rps: Tensor,
                  scale_rad: float = math.radians(2.0), iterations: int = 4, step_rps: float = 1e-6,
                  prior_sigma_rps: float = 1.0) -> Tensor:
    """The constant gyroscope bias ``(3,)`` (rad/s, float64) that best explains the tilt
    changes: Gauss–Newton from ``start_rps`` on the residuals ``r_k(b) = ĝ_b × g_b`` of every
    window (the small-angle rotation between predicted and seen gravity directions), with a
    forward-difference Jacobian (step ``step_rps``; float64), Cauchy weights ``1 / (1 + |r_k|² / s²)``
    (``s = scale_rad``: windows whose accelerations hide gravity count little) and a weak prior
    ``N(start_rps, prior_sigma_rps²)`` per axis (the bias about gravity's direction is not seen
    when the device never tilts; the prior keeps it at its start)."""

    def residual(bias: Tensor) -> Tensor:
        predicted, seen, _ = _predictions(t, acc, gyro - bias, w)
        return torch.linalg.cross(predicted, seen).reshape(-1)  # (3W,)

    bias = start_rps.clone()
    eye = torch.eye(3, dtype=t.dtype)
    for _ in range(iterations):
        r = residual(bias)
        J = torch.stack([(residual(bias + step_rps * eye[i]) - r) / step_rps for i in range(3)], -1)  # (3W, 3)
        per_window = r.reshape(-1, 3).pow(2).sum(-1)
        weight = (1.0 / (1.0 + per_window / scale_rad**2)).repeat_interleave(3)
        prior = (scale_rad / prior_sigma_rps) ** 2
        lhs = J.T @ (weight.unsqueeze(-1) * J) + prior * eye
        rhs = -(J.T @ (weight * r)) - prior * (bias - start_rps)
        step = torch.linalg.solve(lhs, rhs)
        bias = bias + step
        if float(step.norm()) < 1e-7:
            break
    return bias


def _still_mean(t: Tensor, acc: Tensor, gyro: Tensor, min_s: float) -> Tensor | None:
    """The mean rate over the recording's still start (at least ``min_s``), else None."""
    still = still_interval(t, acc, gyro)
    if still.end < 10 or still.duration_s < min_s or still.end >= t.shape[0]:
        return None
    return gyro[: still.end].mean(0)


def _judge(t: Tensor, acc: Tensor, gyro: Tensor, w: _Windows, args: tuple, still_min_s: float
           ) -> tuple[GyroConsistency, bool]:
    """The verdict on ``gyro`` as it is, else less a constant bias (module docstring)."""
    n, e_gyro, e_still, ok = _verdict(*_errors(t, acc, gyro, w), *args)
    if ok:
        return GyroConsistency(n, e_gyro, e_still, True), True
    start = _still_mean(t, acc, gyro, still_min_s)
    source = "the still start's mean rate, refined over every window" if start is not None else "fitted over every window"
    bias = fit_gyro_bias(t, acc, gyro, w, start_rps=gyro.new_zeros(3) if start is None else start)
    n, e_gyro, e_still, ok = _verdict(*_errors(t, acc, gyro - bias, w), *args)
    as_tuple = tuple(float(x) for x in bias)
    return GyroConsistency(n, e_gyro, e_still, ok, bias_rps=as_tuple, bias_source=source), ok


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
    still_min_s: float = 1.0,
) -> GyroConsistency:
    """Whether the gyroscope's rotation, less a constant bias, explains the accelerometer's
    tilt changes (module docstring).

    Args:
        t_s: ``(N,)`` increasing times (s); acc_mps2, gyro_rps: ``(N, 3)`` readings.
        window_s: the span over which a rotation predicts a tilt change.
        average_s: the span each gravity direction is averaged over (steps and vibration).
        min_change_rad: windows where neither error reaches this are not judged.
        min_windows: fewer judged windows than this give no verdict (consistent).
        margin, offset_rad: the gyroscope fails when its median error exceeds ``margin``
            times the no-rotation one plus ``offset_rad``.
        still_min_s: a still start at least this long gives the bias's first estimate.
    """
    t = torch.as_tensor(t_s, dtype=torch.float64)
    acc = torch.as_tensor(acc_mps2, dtype=torch.float64)
    gyro = torch.as_tensor(gyro_rps, dtype=torch.float64)
    if t.shape[0] < 2:
        return GyroConsistency(0, math.nan, math.nan, True)
    dt = float(torch.diff(t).median())
    n_avg = max(1, round(average_s / dt))
    n_win = max(1, round(window_s / dt))
    w = _Windows(n_avg, n_win, max(1, n_win // 2))
    if t.shape[0] < n_avg + n_win + 1:
        return GyroConsistency(0, math.nan, math.nan, True)
    args = (min_change_rad, min_windows, margin, offset_rad)
    result, ok = _judge(t, acc, gyro, w, args, still_min_s)
    if ok:
        return result
    # × π/180 consistent, less its own constant bias (or too little tilt left to judge): deg/s
    degrees_ok = _judge(t, acc, gyro * (math.pi / 180.0), w, args, still_min_s)[1]
    return GyroConsistency(result.windows, result.gyro_error_rad, result.still_error_rad, False,
                           "deg/s" if degrees_ok else None, result.bias_rps, result.bias_source)
