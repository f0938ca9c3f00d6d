"""FlowNet 2.0 stacks (NVIDIA ``models.py``) in plain torch, with Monte Carlo dropout.

Inputs follow NVIDIA's convention: ``inputs`` ``(B, 3, 2, H, W)`` (RGB, the two
frames on dim 2) with values in ``[0, rgb_max]`` (``rgb_max = 255``), ``H, W``
multiples of 64. :func:`normalize_pair` subtracts the per-pair channel mean
(over both frames and all pixels) and divides by ``rgb_max``, then stacks the
frames on the channel axis, ``(B, 6, H, W)``.

FlowNet2 (Ilg et al. 2017, Fig. 2)::

    flow_c   = up_bilinear_x4(FlowNetC(x) · div_flow)
    flow_s1  = up_bilinear_x4(FlowNetS_1([x, warp(x2, flow_c), flow_c / div_flow, |x1 - warp(x2, flow_c)|]) · div_flow)
    flow_s2  = up_nearest_x4(FlowNetS_2([x, warp(x2, flow_s1), flow_s1 / div_flow, |x1 - warp|]) · div_flow)
    flow_sd  = up_nearest_x4(FlowNetSD(x) / div_flow)          # "/": as NVIDIA's code
    flow     = FlowNetFusion([x1, flow_sd, flow_s2, |flow_sd|, |flow_s2|,
                              |x1 - warp(x2, flow_sd)|, |x1 - warp(x2, flow_s2)|])   # pixels

``warp`` is NVIDIA's ``Resample2d`` (bilinear, coordinates clamped to the image)
as ``F.grid_sample(..., padding_mode="border", align_corners=True)``, which gives
the same values; ``|·|`` is ``ChannelNorm`` (the L2 norm over channels); the
bilinear x4 upsampling is ``nn.Upsample(scale_factor=4, mode="bilinear")`` as
PyTorch >= 0.4 runs it (``align_corners=False``).

Module and parameter names equal NVIDIA's (``flownetc``, ``flownets_1``,
``flownets_2``, ``flownets_d``, ``flownetfusion``; FlowNet2C/S/SD subclass their
network, so their keys have no prefix), so :func:`load_checkpoint` reads
``FlowNet2_checkpoint.pth.tar`` and the other NVIDIA files with a strict check.

Monte Carlo dropout (paper Sec. "Uncertainty Quantification", Fig. 3) acts in
the fusion network only (:class:`~flowins.flow.flownet2.networks.FlowNetFusion`),
so :meth:`FlowNet2.mc_samples` runs the four upstream networks and the part of
the fusion network before the dropout once and only the downstream part
``passes`` times. The pretrained weights were trained without dropout; applying
it at test time is what the paper did.
"""
from __future__ import annotations

import os
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from flowins.flow.flownet2.networks import (
    DROPOUT_OPTIONS,
    FlowNetC,
    FlowNetFusion,
    FlowNetS,
    FlowNetSD,
)
from flowins.flow.mc_dropout import ConcreteDropout, MCDropout
from flowins.serialization import load_tensors

#: NVIDIA's defaults: images in [0, 255], flows predicted in units of 1/20 pixel
RGB_MAX = 255.0
DIV_FLOW = 20.0


# --------------------------------------------------------------------------- ops
def normalize_pair(inputs: Tensor, rgb_max: float = RGB_MAX) -> Tensor:
    """``(B, 3, 2, H, W)`` in ``[0, rgb_max]`` -> ``(B, 6, H, W)``: minus the per-pair
    channel mean (both frames, all pixels), over ``rgb_max``, frames stacked on channels."""
    if inputs.ndim != 5 or inputs.shape[1] != 3 or inputs.shape[2] != 2:
        raise ValueError(
            f"FlowNet2 input of shape {tuple(inputs.shape)}; expected (B, 3, 2, H, W): RGB, two frames on dim 2"
        )
    rgb_mean = inputs.reshape(*inputs.shape[:2], -1).mean(-1).reshape(*inputs.shape[:2], 1, 1, 1)
    x = (inputs - rgb_mean) / rgb_max
    return torch.cat((x[:, :, 0], x[:, :, 1]), dim=1)


def channel_norm(x: Tensor) -> Tensor:
    """``ChannelNorm``: ``(B, C, H, W)`` -> ``(B, 1, H, W)``, the L2 norm over channels
    (gradient 0 where the norm is 0)."""
    return torch.linalg.vector_norm(x, ord=2, dim=1, keepdim=True)


def warp(image: Tensor, flow: Tensor) -> Tensor:
    """``Resample2d``: ``out[b, c, y, x] = image[b, c, y + flow_v, x + flow_u]`` (bilinear,
    sample positions clamped to the image); ``image`` ``(B, C, H, W)``, ``flow`` ``(B, 2, H, W)`` px."""
    B, _, H, W = image.shape
    ys = torch.arange(H, dtype=flow.dtype, device=flow.device).view(1, H, 1)
    xs = torch.arange(W, dtype=flow.dtype, device=flow.device).view(1, 1, W)
    gx = (xs + flow[:, 0]) * (2.0 / max(W - 1, 1)) - 1.0
    gy = (ys + flow[:, 1]) * (2.0 / max(H - 1, 1)) - 1.0
    grid = torch.stack((gx, gy), dim=-1)
    return F.grid_sample(image, grid.to(image.dtype), mode="bilinear", padding_mode="border", align_corners=True)


def brightness_error(image1: Tensor, image2: Tensor, flow: Tensor) -> Tensor:
    """``|image1 - warp(image2, flow)|`` over channels, ``(B, 1, H, W)``."""
    return channel_norm(image1 - warp(image2, flow))


def upsample4(flow: Tensor, mode: str) -> Tensor:
    """``nn.Upsample(scale_factor=4, mode)`` (values not rescaled, as NVIDIA's)."""
    if mode == "nearest":
        return F.interpolate(flow, scale_factor=4, mode="nearest")
    return F.interpolate(flow, scale_factor=4, mode="bilinear", align_corners=False)


def _warp_stage_input(x: Tensor, flow: Tensor, div_flow: float) -> Tensor:
    """The 12 input channels of a stacked FlowNetS: images, warped image 2, flow / div_flow,
    brightness error."""
    warped = warp(x[:, 3:], flow)
    error = channel_norm(x[:, :3] - warped)
    return torch.cat((x, warped, flow / div_flow, error), dim=1)


def _check_size(x: Tensor, multiple: int = 64) -> None:
    H, W = x.shape[-2:]
    if H % multiple or W % multiple:
        raise ValueError(
            f"FlowNet2 input of {W}x{H} pixels; expected width and height divisible by {multiple} "
            "(pad with flowins.flow.base.pad_to_multiple)"
        )


# ------------------------------------------------------------------ single nets
class FlowNet2C(FlowNetC):
    """FlowNetC alone (NVIDIA ``FlowNet2C``): ``inputs`` ``(B, 3, 2, H, W)`` -> flow ``(B, 2, H, W)`` px."""

    def __init__(self, *, rgb_max: float = RGB_MAX, div_flow: float = DIV_FLOW, batch_norm: bool = False):
        super().__init__(batch_norm=batch_norm, div_flow=div_flow)
        self.rgb_max = rgb_max

    def forward(self, inputs: Tensor) -> Tensor:
        _check_size(inputs)
        return upsample4(super().forward(normalize_pair(inputs, self.rgb_max)) * self.div_flow, "bilinear")


class FlowNet2S(FlowNetS):
    """FlowNetS alone on the two images (NVIDIA ``FlowNet2S``, 6 input channels)."""

    def __init__(self, *, rgb_max: float = RGB_MAX, div_flow: float = DIV_FLOW, batch_norm: bool = False):
        super().__init__(input_channels=6, batch_norm=batch_norm)
        self.rgb_max = rgb_max
        self.div_flow = div_flow

    def forward(self, inputs: Tensor) -> Tensor:
        _check_size(inputs)
        return upsample4(super().forward(normalize_pair(inputs, self.rgb_max)) * self.div_flow, "bilinear")


class FlowNet2SD(FlowNetSD):
    """FlowNetSD alone (NVIDIA ``FlowNet2SD``)."""

    def __init__(self, *, rgb_max: float = RGB_MAX, div_flow: float = DIV_FLOW, batch_norm: bool = False):
        super().__init__(batch_norm=batch_norm)
        self.rgb_max = rgb_max
        self.div_flow = div_flow

    def forward(self, inputs: Tensor) -> Tensor:
        _check_size(inputs)
        return upsample4(super().forward(normalize_pair(inputs, self.rgb_max)) * self.div_flow, "bilinear")


# ----------------------------------------------------------------------- stacks
class FlowNet2CS(nn.Module):
    """FlowNetC followed by one warped FlowNetS (NVIDIA ``FlowNet2CS``)."""

    #: how many FlowNetS follow FlowNetC
    n_stacked = 1

    def __init__(self, *, rgb_max: float = RGB_MAX, div_flow: float = DIV_FLOW, batch_norm: bool = False):
        super().__init__()
        self.batchNorm = batch_norm
        self.div_flow = div_flow
        self.rgb_max = rgb_max
        self.flownetc = FlowNetC(batch_norm=batch_norm, div_flow=div_flow)
        self.flownets_1 = FlowNetS(batch_norm=batch_norm)
        if self.n_stacked >= 2:
            self.flownets_2 = FlowNetS(batch_norm=batch_norm)

    def _css(self, x: Tensor) -> Tensor:
        """Normalised ``x`` ``(B, 6, H, W)`` -> flow of the last stacked net, px, full resolution."""
        flow = upsample4(self.flownetc(x) * self.div_flow, "bilinear")
        flow = upsample4(self.flownets_1(_warp_stage_input(x, flow, self.div_flow)) * self.div_flow, "bilinear")
        if self.n_stacked >= 2:
            flow = upsample4(self.flownets_2(_warp_stage_input(x, flow, self.div_flow)) * self.div_flow, "nearest")
        return flow

    def forward(self, inputs: Tensor) -> Tensor:
        """``inputs`` ``(B, 3, 2, H, W)`` in ``[0, rgb_max]`` -> flow ``(B, 2, H, W)`` px."""
        _check_size(inputs)
        return self._css(normalize_pair(inputs, self.rgb_max))


class FlowNet2CSS(FlowNet2CS):
    """FlowNetC followed by two warped FlowNetS (NVIDIA ``FlowNet2CSS``)."""

    n_stacked = 2


class FlowNet2(FlowNet2CSS):
    """The full FlowNet 2.0 (NVIDIA ``FlowNet2``): FlowNet-CSS, FlowNet-SD and the fusion network,
    with optional Monte Carlo dropout in the fusion network.

    ``dropout_option``: ``None`` (NVIDIA's deterministic network), ``1`` or ``2``
    (paper Fig. 3, see :class:`~flowins.flow.flownet2.networks.FlowNetFusion`); ``p``
    the dropout rate; ``passes`` the default ``N_MC`` (paper: 10); ``concrete=True``
    uses :class:`~flowins.flow.mc_dropout.ConcreteDropout` (learnable rate; its
    ``mc_dropout.p_logit`` is the one parameter not in NVIDIA's checkpoints);
    ``chunk`` bounds how many passes run as one batch.

    ``forward(inputs)`` is one pass (stochastic when dropout is on);
    :meth:`mc_samples` the ``passes`` samples with the upstream computed once.
    """

    n_stacked = 2

    def __init__(
        self,
        *,
        rgb_max: float = RGB_MAX,
        div_flow: float = DIV_FLOW,
        batch_norm: bool = False,
        dropout_option: int | None = None,
        p: float = 0.2,
        passes: int = 10,
        concrete: bool = False,
        chunk: int | None = None,
        seed: int | None = None,
    ):
        if dropout_option not in DROPOUT_OPTIONS:
            raise ValueError(f"FlowNet2: dropout_option={dropout_option!r}; expected one of {DROPOUT_OPTIONS}")
        if dropout_option is not None and passes < 2:
            raise ValueError(f"FlowNet2: passes={passes}; Monte Carlo dropout needs at least 2")
        super().__init__(rgb_max=rgb_max, div_flow=div_flow, batch_norm=batch_norm)
        self.flownets_d = FlowNetSD(batch_norm=batch_norm)
        self.flownetfusion = FlowNetFusion(batch_norm=batch_norm)
        self.dropout_option = dropout_option
        self.passes = int(passes)
        self.chunk = chunk
        if dropout_option is None:
            self.mc_dropout = None
        else:
            self.mc_dropout = ConcreteDropout(p, seed=seed) if concrete else MCDropout(p, seed=seed)

    def fusion_input(self, inputs: Tensor) -> Tensor:
        """Everything upstream of the fusion network: ``(B, 3, 2, H, W)`` -> ``(B, 11, H, W)``
        ``[x1, flow_sd, flow_s2, |flow_sd|, |flow_s2|, err_sd, err_s2]`` (class docstring)."""
        _check_size(inputs)
        x = normalize_pair(inputs, self.rgb_max)
        flow_s2 = self._css(x)
        flow_sd = upsample4(self.flownets_d(x) / self.div_flow, "nearest")  # NVIDIA divides here
        x1, x2 = x[:, :3], x[:, 3:]
        return torch.cat(
            (
                x1,
                flow_sd,
                flow_s2,
                channel_norm(flow_sd),
                channel_norm(flow_s2),
                brightness_error(x1, x2, flow_sd),
                brightness_error(x1, x2, flow_s2),
            ),
            dim=1,
        )

    def forward(self, inputs: Tensor) -> Tensor:
        """One pass: ``(B, 3, 2, H, W)`` in ``[0, rgb_max]`` -> flow ``(B, 2, H, W)`` px
        (a dropout sample when ``dropout_option`` is set)."""
        return self.flownetfusion(self.fusion_input(inputs), dropout=self.mc_dropout, option=self.dropout_option)

    def mc_samples(self, inputs: Tensor, passes: int | None = None, *, chunk: int | None = None) -> Tensor:
        """``(N, B, 2, H, W)`` dropout samples, upstream of the dropout computed once."""
        if self.dropout_option is None:
            raise ValueError("FlowNet2.mc_samples: dropout is off (dropout_option=None); build with 1 or 2")
        return self.flownetfusion.mc_samples(
            self.fusion_input(inputs),
            dropout=self.mc_dropout,
            option=self.dropout_option,
            passes=self.passes if passes is None else int(passes),
            chunk=self.chunk if chunk is None else chunk,
        )

    def mc_samples_naive(self, inputs: Tensor, passes: int | None = None) -> Tensor:
        """``(N, B, 2, H, W)`` from ``N`` complete forward passes (the reference the
        run-once path must equal; for tests and benchmarks)."""
        n = self.passes if passes is None else int(passes)
        return torch.stack([self(inputs) for _ in range(n)])


#: NVIDIA's model names -> classes
VARIANTS: dict[str, type[nn.Module]] = {
    "FlowNet2": FlowNet2,
    "FlowNet2C": FlowNet2C,
    "FlowNet2S": FlowNet2S,
    "FlowNet2SD": FlowNet2SD,
    "FlowNet2CS": FlowNet2CS,
    "FlowNet2CSS": FlowNet2CSS,
}


def build_model(variant: str = "FlowNet2", **kwargs: Any) -> nn.Module:
    """The network called ``variant`` (a key of :data:`VARIANTS`), with random (NVIDIA-initialised) weights."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown FlowNet2 variant {variant!r}; expected one of {sorted(VARIANTS)}")
    return VARIANTS[variant](**kwargs)


# ------------------------------------------------------------------ checkpoints
#: key prefixes that flowins adds to NVIDIA's networks (not in their checkpoints)
EXTRA_PREFIXES = ("mc_dropout.",)
_SHOW = 20


def guess_variant(keys) -> str | None:
    """Which NVIDIA model a state dict's keys belong to, from its top-level names."""
    keys = set(keys)
    tops = {k.split(".", 1)[0] for k in keys}
    if "flownetfusion" in tops:
        return "FlowNet2"
    if "flownets_2" in tops:
        return "FlowNet2CSS"
    if "flownets_1" in tops:
        return "FlowNet2CS"
    if "conv_redir" in tops:
        return "FlowNet2C"
    if "inter_conv2" in tops:
        return "FlowNet2SD"
    if "conv3_1" in tops:
        return "FlowNet2S"
    return None


def _read_state_dict(path: str | os.PathLike, map_location) -> tuple[dict, dict]:
    path = os.fspath(path)
    ckpt = load_tensors(path, argument="flow.checkpoint (FlowNet2)", map_location=map_location,
                        expected="NVIDIA's FlowNet 2.0 checkpoint (e.g. FlowNet2_checkpoint.pth.tar)")
    if isinstance(ckpt, dict) and "state_dict" in ckpt:
        sd, meta = ckpt["state_dict"], {k: v for k, v in ckpt.items() if k != "state_dict"}
    elif isinstance(ckpt, dict) and ckpt and all(isinstance(v, Tensor) for v in ckpt.values()):
        sd, meta = ckpt, {}
    else:
        raise ValueError(
            f"FlowNet2 checkpoint {path!r}: expected NVIDIA's layout, a dict with a 'state_dict' entry "
            f"(or a bare state dict); got {type(ckpt).__name__}"
            + (f" with keys {sorted(ckpt)[:10]}" if isinstance(ckpt, dict) else "")
        )
    if sd and all(k.startswith("module.") for k in sd):  # saved from nn.DataParallel
        sd = {k[len("module.") :]: v for k, v in sd.items()}
    return dict(sd), meta


def load_checkpoint(model: nn.Module, path: str | os.PathLike, *, map_location: str | torch.device = "cpu") -> dict:
    """Load NVIDIA's checkpoint file (e.g. ``FlowNet2_checkpoint.pth.tar``) into ``model``.

    Accepts ``{'state_dict': ..., 'epoch': ..., 'best_EPE': ...}`` or a bare state dict,
    with or without DataParallel's ``module.`` prefix. Before loading, every key and
    shape is compared with ``model``'s (its flowins-only keys, :data:`EXTRA_PREFIXES`,
    excepted); any missing key, unexpected key or shape mismatch raises a
    ``ValueError`` naming the file, the expected architecture and the first 20 of each.
    The file is read with ``weights_only=True`` (:func:`flowins.serialization.load_tensors`):
    tensors and plain values only, so no checkpoint can run code.
    Returns the checkpoint's other entries (``epoch``, ``best_EPE``, ...).
    """
    sd, meta = _read_state_dict(path, map_location)
    expected = {k: v.shape for k, v in model.state_dict().items() if not k.startswith(EXTRA_PREFIXES)}
    missing = [k for k in expected if k not in sd]
    unexpected = [k for k in sd if k not in expected]
    mismatched = [
        f"{k}: checkpoint {tuple(sd[k].shape)} vs model {tuple(expected[k])}"
        for k in expected
        if k in sd and tuple(sd[k].shape) != tuple(expected[k])
    ]
    if missing or unexpected or mismatched:
        arch = type(model).__name__
        guess = guess_variant(sd)
        lines = [
            f"FlowNet2 checkpoint {os.fspath(path)!r} does not match the expected architecture {arch} "
            f"({len(expected)} tensors)"
            + (f"; its keys look like NVIDIA's {guess}" if guess and guess != arch else ""),
        ]
        for title, items in (("missing keys", missing), ("unexpected keys", unexpected), ("shape mismatches", mismatched)):
            if items:
                more = f" (first {_SHOW})" if len(items) > _SHOW else ""
                lines.append(f"{len(items)} {title}{more}: " + ", ".join(items[:_SHOW]))
        raise ValueError("\n".join(lines))
    has_extra = any(k.startswith(EXTRA_PREFIXES) for k in model.state_dict())
    result = model.load_state_dict(sd, strict=not has_extra)
    leftover = [k for k in result.missing_keys if not k.startswith(EXTRA_PREFIXES)]
    if leftover or result.unexpected_keys:  # pragma: no cover - guarded by the check above
        raise ValueError(f"FlowNet2 checkpoint {os.fspath(path)!r}: load_state_dict left {leftover + result.unexpected_keys}")
    return meta
