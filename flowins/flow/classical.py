"""Classical dense flow: OpenCV's DIS (Kroeger et al. 2016) with a heuristic uncertainty.

:class:`DISProvider` runs ``cv2.DISOpticalFlow`` on the gray images of each pair of
the batch, once forward (image 1 -> image 2, the flow it returns) and once
backward (image 2 -> image 1), and turns two cues into a per-pixel, per-component
1-σ in pixels:

* **forward-backward residual** — a correct flow and its reverse cancel:
  ``r(x) = f(x) + b(x + f(x))`` with ``b`` sampled bilinearly (border pixels
  replicated where ``x + f(x)`` leaves the image). Occlusions, moving-object
  boundaries and outright failures give large ``|r|``.
* **texture** — where the image has little gradient energy the flow is not
  observable (the aperture problem), however consistent the two directions are:
  a uniform pair gives ``f = b = 0`` and ``r = 0``, a *confident zero* unless
  the texture term says otherwise. The gradient energy is the smaller eigenvalue
  ``λ_min(x)`` of the structure tensor ``J = mean_W [I_u², I_u I_v; I_u I_v, I_v²]``
  over a ``window x window`` box around ``x``, with ``I`` the gray image in [0, 1]
  and ``I_u, I_v`` its derivatives per pixel (3x3 Sobel / 8); ``(intensity/px)²``.

Both enter in quadrature with a floor::

    σ_c(x) = sqrt(σ0² + (α r_c(x))² + σ_tex(x)²),   σ_tex(x) = β / sqrt(λ_min(x) + ε),   c ∈ {u, v}

Defaults ``σ0 = 0.1 px``, ``α = 2``, ``β = 0.004``, ``ε = 1e-8``, ``window = 9``.
``β / sqrt(λ_min)`` is the Lucas–Kanade standard deviation ``σ_I / sqrt(N λ_min)``
for image noise ``σ_I = 0.036`` (≈ 9 gray levels, a stand-in for model error as
much as sensor noise) over an ``N = 81`` pixel window: ~0.08 px on a well
textured patch (``|∇I| ≈ 0.05`` per px), 4 px on the simulator's snow
(``λ_min ≈ 1e-6``), ``β / sqrt(ε) = 40 px`` on a uniform image. ``α = 2``
because the residual of a pair of equally wrong flows is about twice either's
error only where they disagree; inside a consistently wrong region it is ~0.
Chosen by a small grid search on the two reference pairs of
:mod:`flowins.flow.flo` (preset ``medium``): 69 % of the component errors lie
within ±σ on the Middlebury pair (86 % within ±2σ), 97 % on the simulator pair
(σ is conservative there). Heuristics, not a calibrated likelihood: the errors
are heavy-tailed (occlusions, discontinuities) and the cues miss some of them.

Not differentiable (OpenCV, CPU, numpy in between): ``differentiable`` stays
``False`` and no gradient reaches the images.
"""
from __future__ import annotations

import cv2
import numpy as np
import torch
from torch import Tensor

from flowins.flow.base import FlowProvider, FlowResult

__all__ = ["DIS_PRESETS", "DISProvider", "fb_residual", "min_eigenvalue", "to_gray_u8"]

#: the presets of ``cv2.DISOpticalFlow_create`` by name
DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


def to_gray_u8(images: Tensor) -> np.ndarray:
    """``(B, 3, H, W)`` float RGB in [0, 1] -> ``(B, H, W)`` uint8 gray (ITU-R 601 luma, OpenCV's weights)."""
    if images.ndim != 4 or images.shape[1] != 3:
        raise ValueError(f"to_gray_u8: expected (B, 3, H, W) RGB, got {tuple(images.shape)}")
    rgb = (images.detach().to("cpu", torch.float32) * 255.0).round_().clamp_(0, 255).to(torch.uint8)
    rgb = rgb.permute(0, 2, 3, 1).numpy()
    return np.stack([cv2.cvtColor(np.ascontiguousarray(x), cv2.COLOR_RGB2GRAY) for x in rgb])


def min_eigenvalue(gray: np.ndarray, window: int) -> np.ndarray:
    """Smaller eigenvalue ``(H, W)`` float32 of the structure tensor of ``gray`` ``(H, W)``.

    ``gray`` uint8 (scaled to [0, 1]) or float in [0, 1]; derivatives per pixel by
    the 3x3 Sobel divided by 8; the tensor's entries are box means over
    ``window x window`` pixels (reflected at the border)::

        λ_min = (a + c) / 2 - sqrt(((a - c) / 2)² + b²),   J = [[a, b], [b, c]]
    """
    if gray.ndim != 2:
        raise ValueError(f"min_eigenvalue: expected an (H, W) gray image, got shape {gray.shape}")
    if window < 1:
        raise ValueError(f"min_eigenvalue: window={window}; expected >= 1")
    g = gray.astype(np.float32) / 255.0 if gray.dtype == np.uint8 else gray.astype(np.float32)
    iu = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 8.0, borderType=cv2.BORDER_REFLECT101)
    iv = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 8.0, borderType=cv2.BORDER_REFLECT101)
    box = dict(ksize=(window, window), normalize=True, borderType=cv2.BORDER_REFLECT101)
    a = cv2.boxFilter(iu * iu, -1, **box)
    b = cv2.boxFilter(iu * iv, -1, **box)
    c = cv2.boxFilter(iv * iv, -1, **box)
    lam = 0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b)
    return np.maximum(lam, 0.0)


def fb_residual(forward: np.ndarray, backward: np.ndarray) -> np.ndarray:
    """``r(x) = f(x) + b(x + f(x))`` ``(H, W, 2)`` for flows ``(H, W, 2)`` (b bilinear, border replicated)."""
    if forward.shape != backward.shape or forward.ndim != 3 or forward.shape[-1] != 2:
        raise ValueError(f"fb_residual: expected two (H, W, 2) flows, got {forward.shape} and {backward.shape}")
    h, w = forward.shape[:2]
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    map_u = u + forward[..., 0]
    map_v = v + forward[..., 1]
    b_at = cv2.remap(backward.astype(np.float32), map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return forward + b_at


class DISProvider(FlowProvider):
    """Dense Inverse Search flow with forward–backward + texture uncertainty (see module docstring).

    Args:
        preset: ``"ultrafast"``, ``"fast"`` or ``"medium"`` (OpenCV's presets).
        sigma0_px: σ0, the floor of σ.
        fb_gain: α, multiplies the forward–backward residual (0 skips the backward pass).
        texture_gain: β, in px · intensity/px (intensity in [0, 1]).
        texture_eps: ε added to ``λ_min``; sets the largest texture σ, ``β / sqrt(ε)``.
        texture_window_px: side of the structure tensor's box window.
    """

    differentiable = False

    def __init__(
        self,
        preset: str = "medium",
        *,
        sigma0_px: float = 0.1,
        fb_gain: float = 2.0,
        texture_gain: float = 0.004,
        texture_eps: float = 1e-8,
        texture_window_px: int = 9,
    ):
        super().__init__()
        if preset not in DIS_PRESETS:
            raise ValueError(f"DISProvider: preset={preset!r}; expected one of {sorted(DIS_PRESETS)}")
        if sigma0_px <= 0:
            raise ValueError(f"DISProvider: sigma0_px={sigma0_px}; expected > 0 (σ must be positive)")
        if fb_gain < 0 or texture_gain < 0 or texture_eps <= 0:
            raise ValueError(
                f"DISProvider: fb_gain={fb_gain}, texture_gain={texture_gain}, texture_eps={texture_eps}; "
                "expected fb_gain >= 0, texture_gain >= 0, texture_eps > 0"
            )
        if texture_window_px < 1:
            raise ValueError(f"DISProvider: texture_window_px={texture_window_px}; expected >= 1")
        self.preset = preset
        self.sigma0_px = float(sigma0_px)
        self.fb_gain = float(fb_gain)
        self.texture_gain = float(texture_gain)
        self.texture_eps = float(texture_eps)
        self.texture_window_px = int(texture_window_px)

    def extra_repr(self) -> str:
        return (
            f"preset={self.preset!r}, sigma0_px={self.sigma0_px}, fb_gain={self.fb_gain}, "
            f"texture_gain={self.texture_gain}, texture_eps={self.texture_eps}, texture_window_px={self.texture_window_px}"
        )

    def flow_and_sigma(self, gray1: np.ndarray, gray2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One pair of ``(H, W)`` uint8 gray images -> flow and σ, each ``(H, W, 2)`` float32 px."""
        dis = cv2.DISOpticalFlow_create(DIS_PRESETS[self.preset])  # cheap (~0.1 ms); no state kept between calls
        forward = dis.calc(gray1, gray2, None)
        var = np.full(forward.shape, self.sigma0_px**2, np.float32)
        if self.fb_gain > 0:
            backward = dis.calc(gray2, gray1, None)
            var += (self.fb_gain * fb_residual(forward, backward)) ** 2
        if self.texture_gain > 0:
            lam = min_eigenvalue(gray1, self.texture_window_px)
            var += (self.texture_gain**2 / (lam + self.texture_eps))[..., None]
        return forward, np.sqrt(var)

    def estimate(self, image1: Tensor, image2: Tensor) -> FlowResult:
        """``(B, 3, H, W)`` float RGB in [0, 1] -> :class:`FlowResult` ``(B, 2, H, W)`` (pairs run one by one)."""
        g1, g2 = to_gray_u8(image1), to_gray_u8(image2)
        flows, sigmas = zip(*(self.flow_and_sigma(a, b) for a, b in zip(g1, g2)))
        flow = torch.from_numpy(np.stack(flows)).permute(0, 3, 1, 2).contiguous()
        sigma = torch.from_numpy(np.stack(sigmas)).permute(0, 3, 1, 2).contiguous()
        return FlowResult(flow.to(image1.device), sigma.to(image1.device))
