"""The contract every flow provider keeps, and the input handling they share.

A *dense* provider (:class:`FlowProvider`) takes two batches of images and returns,
for every pixel of image 1, the flow ``(Δu, Δv)`` to image 2 in pixels of the
input resolution and a per-pixel 1-σ for each component::

    result = provider(image1, image2)      # FlowResult
    result.flow   # (B, 2, H, W) float32, channel 0 = Δu (right), 1 = Δv (down)
    result.sigma  # (B, 2, H, W) float32, > 0

Images may be given as ``(H, W, 3)`` / ``(B, H, W, 3)`` uint8 RGB (what
:meth:`flowins.data.CameraFrames.read` returns), ``(H, W)`` / ``(B, H, W)`` gray,
or ``(3, H, W)`` / ``(B, 3, H, W)`` float in [0, 1]; :func:`prepare_pair`
turns them into ``(B, 3, H, W)`` float32 RGB in [0, 1] and rejects anything else
with an error that says what was expected. Networks that need sizes divisible by
``2^k`` use :func:`pad_to_multiple` / :func:`unpad` (replicate padding; the flow
of the original pixels is unchanged) or :func:`resize_flow` (bilinear, with the
flow vectors rescaled by the size ratio).

A *sparse* provider (:class:`SparseFlowProvider`) returns points, their flow and
σ per pair (:class:`SparseFlowResult`).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn


@dataclass
class FlowResult:
    """Dense flow of a batch of pairs.

    ``flow`` ``(B, 2, H, W)`` px from image 1 to image 2; ``sigma`` ``(B, 2, H, W)``
    px, the 1-σ of each component; ``samples``: the Monte Carlo passes
    ``(N, B, 2, H, W)`` when a provider was asked to keep them, else ``None``.
    ``dropout_unit``, ``floor`` ``(B, 2, H, W)`` px, from a provider whose Monte Carlo
    dropout spread has a closed form (SpyNet with ``mc_mode="moments"``): the spread is
    ``sqrt(p / (1 - p)) dropout_unit`` for dropout rate ``p`` and
    ``sigma = max(spread, floor)``, so the σ at another rate needs no network pass.
    """

    flow: Tensor
    sigma: Tensor
    samples: Tensor | None = None
    dropout_unit: Tensor | None = None
    floor: Tensor | None = None

    def __post_init__(self) -> None:
        if self.flow.ndim != 4 or self.flow.shape[1] != 2 or self.sigma.shape != self.flow.shape:
            raise ValueError(
                f"FlowResult: flow and sigma must both be (B, 2, H, W); got {tuple(self.flow.shape)} and {tuple(self.sigma.shape)}"
            )

    def __getitem__(self, index: int) -> FlowResult:
        """The ``index``-th pair, keeping a batch dimension of 1."""
        samples = None if self.samples is None else self.samples[:, index : index + 1]
        one = lambda x: None if x is None else x[index : index + 1]
        return FlowResult(one(self.flow), one(self.sigma), samples, one(self.dropout_unit), one(self.floor))


@dataclass
class SparseFlowResult:
    """Sparse flow of one pair: ``points`` ``(N, 2)`` pixels ``(u, v)`` in image 1,
    ``flow`` ``(N, 2)`` px to image 2, ``sigma`` ``(N, 2)`` px; ``track_id`` ``(N,)``
    when the provider tracks features over frames."""

    points: Tensor
    flow: Tensor
    sigma: Tensor
    track_id: Tensor | None = None


def as_image_batch(image: Tensor, *, name: str) -> Tensor:
    """One image or a batch -> ``(B, 3, H, W)`` float32 RGB in [0, 1] (see module docstring)."""
    if not isinstance(image, Tensor):
        try:
            import numpy as np

            image = torch.from_numpy(np.ascontiguousarray(image))
        except TypeError as exc:
            raise ValueError(f"{name}: expected a torch tensor or numpy array, got {type(image).__name__}") from exc
    if image.numel() == 0:
        raise ValueError(f"{name}: empty image (shape {tuple(image.shape)})")
    x = image
    if x.dtype == torch.uint8:
        if x.ndim == 2:  # (H, W) gray
            x = x[None, None].expand(1, 3, *x.shape)
        elif x.ndim == 3 and x.shape[-1] in (1, 3):  # (H, W, C)
            x = x.permute(2, 0, 1)[None]
        elif x.ndim == 3:  # (B, H, W) gray
            x = x[:, None]
        elif x.ndim == 4 and x.shape[-1] in (1, 3):  # (B, H, W, C)
            x = x.permute(0, 3, 1, 2)
        else:
            raise ValueError(
                f"{name}: uint8 image of shape {tuple(image.shape)}; expected (H, W), (H, W, 3), (B, H, W) or (B, H, W, 3)"
            )
        x = x.to(torch.float32) / 255.0
    elif x.is_floating_point():
        if x.ndim == 3 and x.shape[0] in (1, 3):
            x = x[None]
        elif x.ndim == 2:
            x = x[None, None]
        if x.ndim != 4 or x.shape[1] not in (1, 3):
            raise ValueError(
                f"{name}: float image of shape {tuple(image.shape)}; expected (3, H, W) or (B, 3, H, W) "
                "(channels first, values in [0, 1])"
            )
        if not torch.isfinite(x).all():
            raise ValueError(f"{name}: float image contains NaN or inf")
        lo, hi = float(x.min()), float(x.max())
        if lo < -1e-6 or hi > 1.0 + 1e-6:
            raise ValueError(
                f"{name}: float image values span [{lo:.3g}, {hi:.3g}]; expected [0, 1] "
                "(pass uint8 images for 0-255 data)"
            )
        x = x.to(torch.float32)
    else:
        raise ValueError(f"{name}: image dtype {image.dtype}; expected uint8 (0-255) or float (0-1)")
    if x.shape[1] == 1:
        x = x.expand(-1, 3, -1, -1)
    if x.shape[-1] < 2 or x.shape[-2] < 2:
        raise ValueError(f"{name}: image of {x.shape[-1]}x{x.shape[-2]} pixels is too small")
    return x.contiguous()


def prepare_pair(image1: Tensor, image2: Tensor) -> tuple[Tensor, Tensor]:
    """Both images as ``(B, 3, H, W)`` float32 in [0, 1]; sizes and batch must agree."""
    a = as_image_batch(image1, name="image1")
    b = as_image_batch(image2, name="image2")
    if a.shape != b.shape:
        raise ValueError(
            f"image1 and image2 differ in shape: {tuple(a.shape)} vs {tuple(b.shape)} (as (B, 3, H, W)); "
            "expected two images (or batches) of the same size"
        )
    return a, b


def pad_to_multiple(x: Tensor, multiple: int) -> tuple[Tensor, tuple[int, int]]:
    """Replicate-pad ``(B, C, H, W)`` at the bottom/right to multiples of ``multiple``;
    returns the padded tensor and the original ``(H, W)``."""
    H, W = x.shape[-2:]
    pad_h, pad_w = (-H) % multiple, (-W) % multiple
    if pad_h or pad_w:
        x = F.pad(x, (0, pad_w, 0, pad_h), mode="replicate")
    return x, (H, W)


def unpad(x: Tensor, size: tuple[int, int]) -> Tensor:
    """Crop ``(..., H', W')`` back to ``size = (H, W)`` (the top-left part)."""
    return x[..., : size[0], : size[1]]


def resize_flow(flow: Tensor, size: tuple[int, int]) -> Tensor:
    """Bilinearly resize a flow field ``(B, 2, h, w)`` to ``size = (H, W)``, scaling the
    vectors: ``Δu`` by ``W / w`` and ``Δv`` by ``H / h``."""
    h, w = flow.shape[-2:]
    H, W = size
    if (h, w) == (H, W):
        return flow
    out = F.interpolate(flow, size=(H, W), mode="bilinear", align_corners=False)
    scale = torch.tensor([W / w, H / h], dtype=flow.dtype, device=flow.device).view(1, 2, 1, 1)
    return out * scale


def mc_statistics(samples: Tensor, *, floor: float = 0.0) -> tuple[Tensor, Tensor]:
    """Mean and standard deviation over the first dimension of ``(N, ...)`` samples.

    The standard deviation uses ``N - 1`` (unbiased variance) and is at least ``floor``.
    The variance is the two-pass sum of squared deviations from the mean: on the CPU,
    ``Tensor.var`` over the leading dimension runs an order of magnitude slower.
    """
    if samples.shape[0] < 2:
        raise ValueError(f"Monte Carlo statistics need at least 2 passes, got {samples.shape[0]}")
    mean = samples.mean(0)
    deviation = samples - mean
    std = ((deviation * deviation).sum(0) / (samples.shape[0] - 1)).sqrt()
    return mean, std.clamp_min(floor) if floor > 0 else std


class FlowProvider(nn.Module):
    """Base class of the dense providers: ``provider(image1, image2) -> FlowResult``.

    Subclasses implement :meth:`estimate` on prepared ``(B, 3, H, W)`` float32 RGB
    in [0, 1]; the base class validates and converts the inputs, moves them to the
    provider's device and runs without gradients unless ``requires_grad`` is set
    (training) or the caller enabled them explicitly with :attr:`differentiable`.
    """

    #: whether calls build an autograd graph (training); inference runs under no_grad
    differentiable: bool = False

    def estimate(self, image1: Tensor, image2: Tensor) -> FlowResult:  # pragma: no cover - abstract
        raise NotImplementedError

    @property
    def device(self) -> torch.device:
        for tensor in list(self.parameters()) + list(self.buffers()):
            return tensor.device
        return torch.device("cpu")

    def forward(self, image1: Tensor, image2: Tensor) -> FlowResult:
        a, b = prepare_pair(image1, image2)
        a, b = a.to(self.device), b.to(self.device)
        if self.differentiable:
            return self.estimate(a, b)
        with torch.no_grad():
            return self.estimate(a, b)


class SparseFlowProvider:
    """Base class of the sparse providers: ``provider(image1, image2) -> SparseFlowResult``."""

    def track(self, image1: Tensor, image2: Tensor) -> SparseFlowResult:  # pragma: no cover - abstract
        raise NotImplementedError

    def __call__(self, image1: Tensor, image2: Tensor) -> SparseFlowResult:
        a, b = prepare_pair(image1, image2)
        if a.shape[0] != 1:
            raise ValueError(f"sparse providers take one pair at a time, got a batch of {a.shape[0]}")
        return self.track(a, b)
