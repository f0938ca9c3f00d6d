"""FlowNet 2.0 (Ilg et al. 2017) in plain torch, layer-compatible with NVIDIA's
``flownet2-pytorch`` checkpoints, with the paper's Monte Carlo dropout in the fusion network.

* :mod:`.correlation` — FlowNetC's correlation layer (no CUDA extension);
* :mod:`.networks` — FlowNetC, FlowNetS, FlowNetSD, FlowNetFusion;
* :mod:`.model` — the stacks FlowNet2, FlowNet2C/S/SD/CS/CSS, warping, checkpoint loading;
* :mod:`.provider` — :class:`FlowNet2Provider`, the :class:`~flowins.flow.base.FlowProvider`.
"""
from flowins.flow.flownet2.correlation import Correlation, correlation
from flowins.flow.flownet2.model import (
    VARIANTS,
    FlowNet2,
    FlowNet2C,
    FlowNet2CS,
    FlowNet2CSS,
    FlowNet2S,
    FlowNet2SD,
    brightness_error,
    build_model,
    channel_norm,
    load_checkpoint,
    normalize_pair,
    warp,
)
from flowins.flow.flownet2.networks import FlowNetC, FlowNetFusion, FlowNetS, FlowNetSD
from flowins.flow.flownet2.provider import DEFAULT_SIGMA_FLOOR_PX, FlowNet2Provider

__all__ = [
    "DEFAULT_SIGMA_FLOOR_PX",
    "VARIANTS",
    "Correlation",
    "FlowNet2",
    "FlowNet2C",
    "FlowNet2CS",
    "FlowNet2CSS",
    "FlowNet2Provider",
    "FlowNet2S",
    "FlowNet2SD",
    "FlowNetC",
    "FlowNetFusion",
    "FlowNetS",
    "FlowNetSD",
    "brightness_error",
    "build_model",
    "channel_norm",
    "correlation",
    "load_checkpoint",
    "normalize_pair",
    "warp",
]
