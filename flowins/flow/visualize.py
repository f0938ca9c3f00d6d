"""Pictures of flow: the Middlebury colour wheel and the paper's Fig. 2 panel.

:func:`flow_to_rgb` is the colour coding of Baker et al. (the Middlebury flow
benchmark, ``colorcode.cpp``): hue from the direction, saturation from the
magnitude normalised by ``max_magnitude`` (white = no motion). The wheel has 55
colours in six ramps, RY = 15 (red -> yellow), YG = 6, GC = 4, CB = 11, BM = 13,
MR = 6; the angle ``atan2(-Δv, -Δu) / π ∈ [-1, 1]`` indexes it linearly
(``-1`` and ``1`` both land on red), so with image axes (``Δv`` down) motion to the
right is red, down is yellow-orange, left is cyan-blue and up is violet.
Magnitudes beyond the normaliser are darkened to 75 %.

:func:`flow_panel` writes Fig. 2 of the paper: frame 1, frame 2, horizontal and
vertical flow (diverging colour maps, symmetric limits) and the uncertainty,
each with a colour bar labelled with its quantity in px, as a PNG (matplotlib,
Agg backend); :func:`flow_panel_figure` returns the same figure unsaved.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["COLOR_WHEEL", "color_wheel", "flow_panel", "flow_panel_figure", "flow_to_rgb"]

_RAMPS = (("RY", 15), ("YG", 6), ("GC", 4), ("CB", 11), ("BM", 13), ("MR", 6))


def color_wheel() -> np.ndarray:
    """The 55 Middlebury wheel colours ``(55, 3)`` float64 in 0..255 (Baker et al.)."""
    rows = []
    for name, n in _RAMPS:
        up = np.floor(255.0 * np.arange(n) / n)  # 0 -> 255 (exclusive)
        down, full, zero = 255.0 - up, np.full(n, 255.0), np.zeros(n)
        r, g, b = {
            "RY": (full, up, zero),
            "YG": (down, full, zero),
            "GC": (zero, full, up),
            "CB": (zero, down, full),
            "BM": (up, zero, full),
            "MR": (full, zero, down),
        }[name]
        rows.append(np.stack([r, g, b], -1))
    return np.concatenate(rows)


COLOR_WHEEL = color_wheel()


def _as_hw2(flow, *, name: str) -> np.ndarray:
    """``(2, H, W)`` or ``(1, 2, H, W)`` (numpy or torch) -> ``(H, W, 2)`` float64."""
    arr = flow.detach().cpu().numpy() if hasattr(flow, "detach") else np.asarray(flow)
    if arr.ndim == 4 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim != 3 or arr.shape[0] != 2:
        raise ValueError(f"{name}: shape {arr.shape}; expected (2, H, W) or (1, 2, H, W) (channel 0 = Δu, 1 = Δv)")
    return np.moveaxis(arr.astype(np.float64), 0, -1)


def flow_to_rgb(flow, max_magnitude: float | None = None) -> np.ndarray:
    """Flow ``(2, H, W)`` / ``(1, 2, H, W)`` px -> ``(H, W, 3)`` uint8 RGB on the Middlebury wheel.

    ``max_magnitude``: the magnitude drawn fully saturated; default the largest
    finite magnitude in ``flow``. Non-finite flow is drawn black.
    """
    uv = _as_hw2(flow, name="flow_to_rgb")
    finite = np.isfinite(uv).all(-1)
    uv = np.where(finite[..., None], uv, 0.0)
    rad = np.hypot(uv[..., 0], uv[..., 1])
    if max_magnitude is None:
        max_magnitude = float(rad.max()) if rad.size else 0.0
    elif not max_magnitude > 0:
        raise ValueError(f"flow_to_rgb: max_magnitude={max_magnitude}; expected > 0 (or None for the flow's maximum)")
    scale = 1.0 / max(max_magnitude, np.finfo(np.float64).eps)
    u, v, rad = uv[..., 0] * scale, uv[..., 1] * scale, rad * scale
    n = len(COLOR_WHEEL)
    fk = (np.arctan2(-v, -u) / np.pi + 1.0) / 2.0 * (n - 1)  # 0 .. n-1
    k0 = np.floor(fk).astype(np.int64)
    k1 = (k0 + 1) % n
    f = (fk - k0)[..., None]
    col = ((1.0 - f) * COLOR_WHEEL[k0] + f * COLOR_WHEEL[k1]) / 255.0
    inside = (rad <= 1.0)[..., None]
    col = np.where(inside, 1.0 - rad[..., None] * (1.0 - col), col * 0.75)
    out = np.floor(255.0 * col).astype(np.uint8)
    out[~finite] = 0
    return out


def _as_rgb_image(image, *, name: str) -> np.ndarray:
    """``(H, W, 3)`` uint8, ``(3, H, W)`` / ``(1, 3, H, W)`` float in [0, 1], or ``(H, W)`` gray -> something imshow draws."""
    arr = image.detach().cpu().numpy() if hasattr(image, "detach") else np.asarray(image)
    if arr.ndim == 4 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim == 3 and arr.shape[0] in (1, 3) and arr.shape[-1] not in (1, 3):
        arr = np.moveaxis(arr, 0, -1)
    if arr.ndim == 3 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    if arr.ndim == 2:
        arr = np.stack([arr] * 3, -1)
    if arr.ndim != 3 or arr.shape[-1] != 3:
        raise ValueError(f"{name}: shape {arr.shape}; expected (H, W, 3) uint8 or (3, H, W) float in [0, 1]")
    return arr if arr.dtype == np.uint8 else np.clip(arr.astype(np.float64), 0.0, 1.0)


def flow_panel_figure(
    image1,
    image2,
    flow,
    sigma,
    *,
    title: str | None = None,
    flow_limit_px: float | None = None,
    sigma_limit_px: float | None = None,
    sigma_mode: str = "magnitude",
    panel_width_in: float = 2.4,
    dpi: int = 100,
):
    """The paper's Fig. 2 for one pair as a ``matplotlib.figure.Figure`` on an Agg canvas.

    Panels: frame 1, frame 2, horizontal flow ``Δu``, vertical flow ``Δv`` (both on
    ``[-flow_limit_px, flow_limit_px]``, default the 99th percentile of ``|flow|``),
    and the uncertainty: ``sigma_mode="magnitude"`` draws ``|σ| = sqrt(σu² + σv²)`` in one
    panel, ``"components"`` draws ``σu`` and ``σv`` in two (on ``[0, sigma_limit_px]``,
    default the 99th percentile). Images as ``(H, W, 3)`` uint8 or ``(3, H, W)``
    float; ``flow`` and ``sigma`` ``(2, H, W)`` or ``(1, 2, H, W)`` px. Each colour
    bar is labelled with its quantity and unit (``Δu [px]``, ``Δv [px]``,
    ``|σ| [px]`` or ``σu [px]`` and ``σv [px]``), above the bar.

    The figure is ``panel_width_in`` inches per panel wide (``dpi`` pixels per
    inch), each panel the images' aspect plus room for the titles and colour bar;
    its size in pixels does not depend on the data.
    """
    from matplotlib.backends.backend_agg import (
        FigureCanvasAgg,  # no pyplot: the global backend is left alone
    )
    from matplotlib.figure import Figure

    if sigma_mode not in ("magnitude", "components"):
        raise ValueError(f"flow_panel: sigma_mode={sigma_mode!r}; expected 'magnitude' or 'components'")
    a = _as_rgb_image(image1, name="flow_panel image1")
    b = _as_rgb_image(image2, name="flow_panel image2")
    uv = _as_hw2(flow, name="flow_panel flow")
    s = _as_hw2(sigma, name="flow_panel sigma")
    h, w = uv.shape[:2]
    for label, arr in (("image1", a), ("image2", b), ("sigma", s)):
        if arr.shape[:2] != (h, w):
            raise ValueError(f"flow_panel: {label} is {arr.shape[:2]} pixels, flow is {(h, w)}; expected the same size")

    def limit(x: np.ndarray, given: float | None) -> float:
        if given is not None:
            return float(given)
        x = np.abs(x[np.isfinite(x)])
        return max(float(np.percentile(x, 99)) if x.size else 0.0, 1e-3)

    flow_lim = limit(uv, flow_limit_px)
    # (panel title, colour-bar label, data)
    if sigma_mode == "magnitude":
        sig_panels = [("uncertainty |σ| (px)", "|σ| [px]", np.hypot(s[..., 0], s[..., 1]))]
    else:
        sig_panels = [("uncertainty σu (px)", "σu [px]", s[..., 0]), ("uncertainty σv (px)", "σv [px]", s[..., 1])]
    sig_lim = limit(np.stack([p for _, _, p in sig_panels]), sigma_limit_px)

    # (panel title, image, (colour map, low, high, colour-bar label) or None for a picture)
    panels = [("frame #1", a, None), ("frame #2", b, None)]
    panels += [("horizontal flow Δu (px)", uv[..., 0], ("RdBu_r", -flow_lim, flow_lim, "Δu [px]"))]
    panels += [("vertical flow Δv (px)", uv[..., 1], ("RdBu_r", -flow_lim, flow_lim, "Δv [px]"))]
    panels += [(label, arr, ("magma", 0.0, sig_lim, unit)) for label, unit, arr in sig_panels]

    n = len(panels)
    image_h_in = panel_width_in * h / w
    height_in = image_h_in + 0.9 + (0.35 if title else 0.0)  # titles above, colour bars below
    fig = Figure(figsize=(panel_width_in * n, height_in), dpi=dpi)
    FigureCanvasAgg(fig)
    top = 1.0 - (0.35 + (0.35 if title else 0.0)) / height_in
    bottom = 0.55 / height_in
    for i, (label, data, cmap) in enumerate(panels):
        ax = fig.add_axes((i / n + 0.01, bottom, 1.0 / n - 0.02, top - bottom))
        if cmap is None:
            ax.imshow(data, interpolation="nearest")
        else:
            name, lo, hi, bar_label = cmap
            im = ax.imshow(np.where(np.isfinite(data), data, np.nan), cmap=name, vmin=lo, vmax=hi, interpolation="nearest")
            # bar 0.25 .. 0.37 in from the bottom, ticks below it, its label in the 0.18 in above it
            cax = fig.add_axes((i / n + 0.03, 0.25 / height_in, 1.0 / n - 0.06, 0.12 / height_in))
            bar = fig.colorbar(im, cax=cax, orientation="horizontal")
            cax.tick_params(labelsize=7)
            cax.xaxis.set_label_position("top")
            bar.set_label(bar_label, fontsize=7, labelpad=2.5)
        ax.set_title(label, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title, fontsize=9, y=1.0 - 0.08 / height_in, va="top")
    return fig


def flow_panel(
    image1,
    image2,
    flow,
    sigma,
    path: str | Path,
    *,
    title: str | None = None,
    flow_limit_px: float | None = None,
    sigma_limit_px: float | None = None,
    sigma_mode: str = "magnitude",
    panel_width_in: float = 2.4,
    dpi: int = 100,
) -> Path:
    """Write :func:`flow_panel_figure` (the paper's Fig. 2 for one pair) as a PNG at ``path``; returns the path.

    The arguments other than ``path`` are those of :func:`flow_panel_figure`.
    """
    fig = flow_panel_figure(
        image1,
        image2,
        flow,
        sigma,
        title=title,
        flow_limit_px=flow_limit_px,
        sigma_limit_px=sigma_limit_px,
        sigma_mode=sigma_mode,
        panel_width_in=panel_width_in,
        dpi=dpi,
    )
    path = Path(path)
    fig.savefig(path, format="png", dpi=dpi)
    return path
