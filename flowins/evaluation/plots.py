"""Figures of evaluated trajectories (Agg canvas, written to PNG, nothing shown).

:func:`plot_trajectory` follows Fig. 5 of Meronen et al. (2020): one top-view
panel per track (e.g. filter and smoother) side by side, the track as points
coloured by time (viridis, purple at the start to yellow at the end), ground
truth as a red line, GNSS fixes as magenta ``+`` markers, each with an unfilled
outline of its accuracy radius. Magenta is at least 0.9 (RGB distance, channels
in [0, 1]) from every viridis colour and 1.0 from the red of the ground truth,
so fixes never read as part of the track. The circles have no fill, so hundreds
of overlapping fixes do not add up to an opaque blob; their outline alpha falls
as ``1 / G`` beyond 50 fixes (:func:`accuracy_outline_alpha`), so a dense run of
fixes draws a band of about the ink of 50 outlines.

:func:`trajectory_figure` builds that figure and returns it (for inspection or
further drawing); :func:`plot_trajectory` builds it and writes the PNG.
Figures are built on a ``matplotlib.figure.Figure`` with an explicit Agg canvas,
never through ``pyplot``: no global backend switch, no figure registry to leak.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PatchCollection
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Circle
from torch import Tensor

GNSS_COLOR = "magenta"
"""Colour of the GNSS fixes and their accuracy outlines: far from viridis (track) and red (truth)."""
_OUTLINE_ALPHA = 0.5  # outline alpha of each fix up to _OUTLINE_FULL_COUNT fixes
_OUTLINE_FULL_COUNT = 50
_OUTLINE_MIN_ALPHA = 0.05


def _to_numpy(x, name: str, shape_tail: tuple[int, ...]) -> np.ndarray:
    """Float64 ``(N, *shape_tail)`` array, or ``ValueError`` naming ``name`` and the first non-finite row."""
    a = torch.as_tensor(x).detach().to(device="cpu", dtype=torch.float64).numpy()
    if a.ndim != 1 + len(shape_tail) or tuple(a.shape[1:]) != shape_tail:
        expected = "(N" + "".join(f", {d}" for d in shape_tail) + ")"
        raise ValueError(f"{name} must have shape {expected}, got {tuple(a.shape)}")
    if a.shape[0] == 0:
        raise ValueError(f"{name} is empty")
    bad = ~np.isfinite(a.reshape(a.shape[0], -1)).all(axis=-1)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{name} contains NaN or inf; first bad row is {row}: {a[row].tolist()} (refusing to plot it)")
    return a


def _figure(figsize_in: tuple[float, float], dpi: int) -> Figure:
    """A constrained-layout ``Figure`` with its own Agg canvas (``fig.canvas.buffer_rgba()`` after ``draw``)."""
    fig = Figure(figsize=figsize_in, dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path: str | os.PathLike, dpi: int) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, format="png")
    return path


def accuracy_outline_alpha(count: int) -> float:
    """Alpha of each GNSS accuracy outline when ``count`` fixes are drawn.

    ``0.5`` up to 50 fixes, then ``0.5 * 50 / count`` (never below ``0.05``): the
    ink of a dense run of coinciding outlines stays about that of 50 outlines.
    """
    if count <= _OUTLINE_FULL_COUNT:
        return _OUTLINE_ALPHA
    return max(_OUTLINE_ALPHA * _OUTLINE_FULL_COUNT / count, _OUTLINE_MIN_ALPHA)


def trajectory_figure(
    *,
    ground_truth_m: Tensor | None,
    tracks: dict[str, tuple[Tensor, Tensor]],
    gnss_m: Tensor | None = None,
    gnss_radius_m: Tensor | None = None,
    title: str = "",
    panel_size_in: tuple[float, float] = (5.0, 4.5),
    dpi: int = 120,
) -> Figure:
    """Top view (East, North) of each track next to the ground truth, as a ``Figure`` on an Agg canvas.

    Each panel shows, bottom to top: the accuracy circles of the GNSS fixes
    (magenta outlines, no fill, alpha from :func:`accuracy_outline_alpha`), the
    fixes (magenta ``+``), the ground truth (red line) and the track (points
    coloured by time, viridis, one time scale for all panels). The legend names
    the ground truth, the GNSS fixes and the track (by its name in ``tracks``).

    Args:
        ground_truth_m: ``(M, 3)`` ground-truth positions (m) drawn as a red line, or ``None``.
        tracks: name → ``(t_s (N,), pos_m (N, 3))``; one panel per entry, in order.
        gnss_m: ``(G, 3)`` GNSS fix positions (m), or ``None``.
        gnss_radius_m: ``(G,)`` accuracy radius of each fix (m), drawn as an unfilled circle.
        title: figure title.
        panel_size_in: ``(width, height)`` of one panel in inches; the figure is
            ``(width * len(tracks), height)`` inches, i.e. that times ``dpi`` pixels.
        dpi: resolution of the figure's canvas.

    Raises:
        ValueError: no tracks, shapes that disagree, NaN/inf anywhere (named), or
            a radius without fixes.
    """
    if not tracks:
        raise ValueError("tracks is empty: give at least one name -> (t_s, pos_m)")
    data = {}
    for name, value in tracks.items():
        if not (isinstance(value, (tuple, list)) and len(value) == 2):
            raise ValueError(f"tracks[{name!r}] must be a tuple (t_s (N,), pos_m (N, 3))")
        t = _to_numpy(value[0], f"tracks[{name!r}] t_s", ())
        p = _to_numpy(value[1], f"tracks[{name!r}] pos_m", (3,))
        if t.shape[0] != p.shape[0]:
            raise ValueError(f"tracks[{name!r}]: t_s has {t.shape[0]} samples but pos_m has {p.shape[0]} rows")
        data[name] = (t, p)
    gt = None if ground_truth_m is None else _to_numpy(ground_truth_m, "ground_truth_m", (3,))
    if gnss_radius_m is not None and gnss_m is None:
        raise ValueError("gnss_radius_m given without gnss_m")
    gnss = None if gnss_m is None else _to_numpy(gnss_m, "gnss_m", (3,))
    radius = None
    if gnss_radius_m is not None:
        radius = _to_numpy(gnss_radius_m, "gnss_radius_m", ())
        if radius.shape[0] != gnss.shape[0]:
            raise ValueError(f"gnss_radius_m has {radius.shape[0]} entries but gnss_m has {gnss.shape[0]} rows")
        if (radius < 0).any():
            row = int(np.flatnonzero(radius < 0)[0])
            raise ValueError(f"gnss_radius_m must be >= 0; row {row} is {radius[row]}")

    # One colour scale for all panels, so equal colours mean equal times.
    t_min = min(float(t.min()) for t, _ in data.values())
    t_max = max(float(t.max()) for t, _ in data.values())
    norm = Normalize(vmin=t_min, vmax=t_max if t_max > t_min else t_min + 1.0)
    cmap = colormaps["viridis"]

    width_in, height_in = panel_size_in
    fig = _figure((width_in * len(data), height_in), dpi)
    axes = fig.subplots(1, len(data), squeeze=False)[0]
    for ax, (name, (t, p)) in zip(axes, data.items()):
        if gnss is not None:
            if radius is not None:
                circles = [Circle((e, n), r) for (e, n), r in zip(gnss[:, :2], radius)]
                ax.add_collection(
                    PatchCollection(
                        circles,
                        facecolor="none",
                        edgecolor=GNSS_COLOR,
                        linewidth=0.6,
                        alpha=accuracy_outline_alpha(len(circles)),
                        zorder=1,
                    )
                )
            ax.scatter(gnss[:, 0], gnss[:, 1], s=16, marker="+", linewidths=0.8, color=GNSS_COLOR, zorder=2, label="GNSS")
        if gt is not None:
            ax.plot(gt[:, 0], gt[:, 1], color="red", linewidth=1.2, zorder=3, label="ground truth")
        points = ax.scatter(p[:, 0], p[:, 1], c=t, cmap=cmap, norm=norm, s=3, zorder=4, rasterized=True, label=name)
        colorbar = fig.colorbar(points, ax=ax, shrink=0.9)
        colorbar.set_label("time [s]")
        ax.set_title(name)
        ax.set_xlabel("East [m]")
        ax.set_ylabel("North [m]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.autoscale_view()
        ax.legend(loc="best", fontsize="small")
    if title:
        fig.suptitle(title)
    return fig


def plot_trajectory(
    path: str | os.PathLike,
    *,
    ground_truth_m: Tensor | None,
    tracks: dict[str, tuple[Tensor, Tensor]],
    gnss_m: Tensor | None = None,
    gnss_radius_m: Tensor | None = None,
    title: str = "",
    panel_size_in: tuple[float, float] = (5.0, 4.5),
    dpi: int = 120,
) -> Path:
    """:func:`trajectory_figure` written as a PNG at ``path`` (parent folders made); returns the path.

    The arguments are those of :func:`trajectory_figure`; the PNG is
    ``(width * len(tracks), height) * dpi`` pixels for ``panel_size_in = (width, height)``.
    """
    fig = trajectory_figure(
        ground_truth_m=ground_truth_m,
        tracks=tracks,
        gnss_m=gnss_m,
        gnss_radius_m=gnss_radius_m,
        title=title,
        panel_size_in=panel_size_in,
        dpi=dpi,
    )
    return _save(fig, path, dpi)


def errors_figure(
    *,
    series: dict[str, tuple[Tensor, Tensor]],
    title: str = "",
    figsize_in: tuple[float, float] = (8.0, 3.5),
    dpi: int = 120,
) -> Figure:
    """Position error (m) against time (s), one line per series, labelled by its name.

    Args:
        series: name → ``(t_s (K,), errors_m (K,))``, e.g. ``TrajectoryErrors.t_s, .errors_m``.
        title: axes title.
        figsize_in: figure size (inches).
        dpi: resolution.
    """
    if not series:
        raise ValueError("series is empty: give at least one name -> (t_s, errors_m)")
    fig = _figure(figsize_in, dpi)
    ax = fig.subplots()
    for name, value in series.items():
        if not (isinstance(value, (tuple, list)) and len(value) == 2):
            raise ValueError(f"series[{name!r}] must be a tuple (t_s (K,), errors_m (K,))")
        t = _to_numpy(value[0], f"series[{name!r}] t_s", ())
        e = _to_numpy(value[1], f"series[{name!r}] errors_m", ())
        if t.shape[0] != e.shape[0]:
            raise ValueError(f"series[{name!r}]: t_s has {t.shape[0]} samples but errors_m has {e.shape[0]}")
        ax.plot(t, e, linewidth=1.0, label=name)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("position error [m]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    if title:
        ax.set_title(title)
    return fig


def plot_errors(
    path: str | os.PathLike,
    *,
    series: dict[str, tuple[Tensor, Tensor]],
    title: str = "",
    figsize_in: tuple[float, float] = (8.0, 3.5),
    dpi: int = 120,
) -> Path:
    """:func:`errors_figure` written as a PNG at ``path`` (parent folders made; ``figsize_in``
    times ``dpi`` pixels); returns the path."""
    return _save(errors_figure(series=series, title=title, figsize_in=figsize_in, dpi=dpi), path, dpi)
