"""FlowNet 2.0 as a :class:`~flowins.flow.base.FlowProvider`, with Monte Carlo dropout σ.

NVIDIA's pretrained weights (``FlowNet2_checkpoint.pth.tar``) are for research use
only: flowins cannot ship them or download them. Get the file from NVIDIA's
``flownet2-pytorch`` page yourself and point the config at it
(``flow.checkpoint=/path/FlowNet2_checkpoint.pth.tar``).
"""
from __future__ import annotations

import os

import torch
from torch import Tensor

from flowins.flow.base import (
    FlowProvider,
    FlowResult,
    mc_statistics,
    pad_to_multiple,
    unpad,
)
from flowins.flow.flownet2.model import (
    RGB_MAX,
    VARIANTS,
    FlowNet2,
    build_model,
    load_checkpoint,
)

#: σ (px) reported when dropout is off, and the lower bound of the Monte Carlo σ
DEFAULT_SIGMA_FLOOR_PX = 0.1
#: FlowNet2's encoders downsample 6 times
SIZE_MULTIPLE = 64

_NO_CHECKPOINT = (
    "FlowNet2Provider: no checkpoint given. NVIDIA's pretrained FlowNet2 weights are licensed for research "
    "use only, so flowins cannot ship or download them: download FlowNet2_checkpoint.pth.tar from "
    "NVIDIA/flownet2-pytorch yourself and set flow.checkpoint=/path/FlowNet2_checkpoint.pth.tar in the config "
    "(or use FlowNet2Provider.untrained(...) for random weights in tests and benchmarks)"
)


class FlowNet2Provider(FlowProvider):
    """Dense flow from FlowNet 2.0 (or one of its parts), with per-pixel σ from Monte Carlo dropout.

    ``checkpoint``: path of NVIDIA's checkpoint of ``variant`` (required unless
    ``allow_random=True``, which keeps NVIDIA's random initialisation: speed tests only).
    ``variant``: ``"FlowNet2"`` (default), ``"FlowNet2C"``, ``"FlowNet2S"``, ``"FlowNet2SD"``,
    ``"FlowNet2CS"`` or ``"FlowNet2CSS"``. ``dropout_option`` ``1``/``2``/``None``, ``p``,
    ``passes`` (``N_MC``), ``concrete``: see :class:`~flowins.flow.flownet2.model.FlowNet2`;
    dropout exists only in ``"FlowNet2"`` (its fusion network), other variants need
    ``dropout_option=None``.

    Per pair: the images (``[0, 1]``) are replicate-padded at the bottom/right to
    multiples of 64, scaled to ``[0, 255]`` (NVIDIA's ``rgb_max = 255``; the model
    subtracts the per-pair channel mean, computed on the padded images), run through
    the network and cropped back.

    ``sigma``: with dropout, the per-pixel standard deviation over the ``passes``
    (unbiased), at least ``sigma_floor``; **without dropout, the constant
    ``sigma_floor`` everywhere** (default :data:`DEFAULT_SIGMA_FLOOR_PX` = 0.1 px, a
    placeholder, not a calibrated error: set it to the flow error you expect when
    running without dropout). ``keep_samples=True`` returns the passes in
    ``FlowResult.samples``.
    """

    def __init__(
        self,
        checkpoint: str | None,
        variant: str = "FlowNet2",
        dropout_option: int | None = 2,
        p: float = 0.2,
        passes: int = 10,
        concrete: bool = False,
        device: str = "cpu",
        sigma_floor: float = DEFAULT_SIGMA_FLOOR_PX,
        seed: int | None = 0,
        *,
        allow_random: bool = False,
        chunk: int | None = 1,  # Monte Carlo passes per head batch: 1 is fastest on a CPU and needs no copies
        keep_samples: bool = False,
    ):
        super().__init__()
        if checkpoint is None and not allow_random:
            raise ValueError(_NO_CHECKPOINT)
        if variant not in VARIANTS:
            raise ValueError(f"FlowNet2Provider: unknown variant {variant!r}; expected one of {sorted(VARIANTS)}")
        if variant != "FlowNet2" and dropout_option is not None:
            raise ValueError(
                f"FlowNet2Provider: dropout_option={dropout_option} acts in FlowNet2's fusion network, which "
                f"{variant} does not have; pass dropout_option=None"
            )
        if not sigma_floor > 0:
            raise ValueError(f"FlowNet2Provider: sigma_floor={sigma_floor}; expected > 0 px")
        if variant == "FlowNet2":
            model = FlowNet2(dropout_option=dropout_option, p=p, passes=passes, concrete=concrete, chunk=chunk,
                             seed=seed)
        else:
            model = build_model(variant)
        self.checkpoint_meta: dict = {}
        if checkpoint is not None:
            self.checkpoint_meta = load_checkpoint(model, os.path.expanduser(checkpoint))
        self.model = model.eval().to(device)
        self.variant = variant
        self.dropout_option = dropout_option
        self.passes = int(passes)
        self.sigma_floor = float(sigma_floor)
        self.keep_samples = bool(keep_samples)
        self.trained = checkpoint is not None

    @classmethod
    def untrained(cls, variant: str = "FlowNet2", *, seed: int | None = 0, **kwargs) -> FlowNet2Provider:
        """A provider with NVIDIA's *random* initialisation (no checkpoint): its flow is
        meaningless; for tests and speed measurements only."""
        if seed is not None:
            torch.manual_seed(seed)
        return cls(None, variant, allow_random=True, **kwargs)

    def estimate(self, image1: Tensor, image2: Tensor) -> FlowResult:
        a, size = pad_to_multiple(image1, SIZE_MULTIPLE)
        b, _ = pad_to_multiple(image2, SIZE_MULTIPLE)
        inputs = torch.stack((a, b), dim=2) * RGB_MAX  # (B, 3, 2, H, W) in [0, 255]
        if self.dropout_option is None:
            flow = unpad(self.model(inputs), size)
            return FlowResult(flow, torch.full_like(flow, self.sigma_floor))
        samples = unpad(self.model.mc_samples(inputs, self.passes), size)
        mean, std = mc_statistics(samples, floor=self.sigma_floor)
        return FlowResult(mean, std, samples if self.keep_samples else None)

    def extra_repr(self) -> str:
        return (
            f"variant={self.variant}, trained={self.trained}, dropout_option={self.dropout_option}, "
            f"passes={self.passes}, sigma_floor={self.sigma_floor}"
        )
