"""The four networks of FlowNet 2.0 (Ilg et al. 2017) with NVIDIA's module names.

Module and parameter names and shapes are those of NVIDIA's ``flownet2-pytorch``
(``networks/FlowNetC.py``, ``FlowNetS.py``, ``FlowNetSD.py``, ``FlowNetFusion.py``,
``submodules.py``), so that their checkpoints load with ``strict=True``:

* ``conv(...)`` is ``Sequential(Conv2d, LeakyReLU(0.1))`` (keys ``<name>.0.weight``,
  ``<name>.0.bias``), or ``Sequential(Conv2d(bias=False), BatchNorm2d, LeakyReLU)``
  with ``batch_norm=True``; padding ``(k-1)//2``;
* ``i_conv(...)`` the same without the activation;
* ``deconv(...)`` is ``Sequential(ConvTranspose2d(4, stride 2, padding 1), LeakyReLU(0.1))``;
* ``predict_flow(c)`` a bare ``Conv2d(c, 2, 3, padding=1)`` (keys ``<name>.weight``);
* the flow upsamplers ``upsampled_flow*`` are ``ConvTranspose2d(2, 2, 4, 2, 1)``,
  **without bias in FlowNetS** and with bias in FlowNetC, FlowNetSD and FlowNetFusion.

Each ``forward(x)`` returns the finest flow of the network (``flow2`` at 1/4 of
the input resolution for C, S and SD, ``flow0`` at full resolution for the
fusion network), in units of ``pixels / div_flow`` as NVIDIA's; with
``all_scales=True`` C, S and SD return ``(flow2, flow3, flow4, flow5, flow6)`` as
NVIDIA's do in training mode. Inputs must have ``H, W`` divisible by 64 (C, S,
SD) or 4 (fusion).

:class:`FlowNetFusion` also exposes the two Monte Carlo dropout positions of the
paper's Fig. 3 (``fig:architecture_fusion``), see :meth:`FlowNetFusion.forward`
and :meth:`FlowNetFusion.mc_samples`.
"""
from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.nn import init
from torch.nn.utils.fusion import fuse_conv_bn_weights

from flowins.flow.conv import conv2d_rows, cpu_channels_last
from flowins.flow.flownet2.correlation import Correlation
from flowins.flow.mc_dropout import mc_samples as _mc_samples


def conv(batch_norm: bool, in_planes: int, out_planes: int, kernel_size: int = 3, stride: int = 1) -> nn.Sequential:
    """Convolution + LeakyReLU(0.1) (+ BatchNorm in between when ``batch_norm``)."""
    pad = (kernel_size - 1) // 2
    if batch_norm:
        return nn.Sequential(
            nn.Conv2d(in_planes, out_planes, kernel_size, stride=stride, padding=pad, bias=False),
            nn.BatchNorm2d(out_planes),
            nn.LeakyReLU(0.1, inplace=True),
        )
    return nn.Sequential(
        nn.Conv2d(in_planes, out_planes, kernel_size, stride=stride, padding=pad, bias=True),
        nn.LeakyReLU(0.1, inplace=True),
    )


def i_conv(batch_norm: bool, in_planes: int, out_planes: int, kernel_size: int = 3, stride: int = 1) -> nn.Sequential:
    """Convolution without activation (+ BatchNorm when ``batch_norm``)."""
    layers: list[nn.Module] = [
        nn.Conv2d(in_planes, out_planes, kernel_size, stride=stride, padding=(kernel_size - 1) // 2, bias=True)
    ]
    if batch_norm:
        layers.append(nn.BatchNorm2d(out_planes))
    return nn.Sequential(*layers)


def predict_flow(in_planes: int) -> nn.Conv2d:
    """3x3 convolution to the 2 flow channels."""
    return nn.Conv2d(in_planes, 2, kernel_size=3, stride=1, padding=1, bias=True)


def deconv(in_planes: int, out_planes: int) -> nn.Sequential:
    """x2 transposed convolution + LeakyReLU(0.1)."""
    return nn.Sequential(
        nn.ConvTranspose2d(in_planes, out_planes, kernel_size=4, stride=2, padding=1, bias=True),
        nn.LeakyReLU(0.1, inplace=True),
    )


def upsample_flow(bias: bool) -> nn.ConvTranspose2d:
    """The learned x2 upsampling of a flow estimate, ``ConvTranspose2d(2, 2, 4, 2, 1)``."""
    return nn.ConvTranspose2d(2, 2, 4, 2, 1, bias=bias)


def init_weights(module: nn.Module) -> None:
    """NVIDIA's initialisation: Xavier-uniform weights, U(0, 1) biases for every
    (transposed) convolution below ``module``."""
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
            if m.bias is not None:
                init.uniform_(m.bias)
            init.xavier_uniform_(m.weight)


class _Decoder(nn.Module):
    """The refinement shared by FlowNetC and FlowNetS: from ``conv6`` up to ``flow2``
    (``deconv5..2``, ``predict_flow6..2``, ``upsampled_flow6_to_5..3_to_2``).

    Not a module of NVIDIA's: its members are attributes of the network itself,
    so this is a mixin holding only the ``forward`` of the decoder.
    """

    def _build_decoder(self, *, upsample_bias: bool) -> None:
        self.deconv5 = deconv(1024, 512)
        self.deconv4 = deconv(1026, 256)
        self.deconv3 = deconv(770, 128)
        self.deconv2 = deconv(386, 64)
        self.predict_flow6 = predict_flow(1024)
        self.predict_flow5 = predict_flow(1026)
        self.predict_flow4 = predict_flow(770)
        self.predict_flow3 = predict_flow(386)
        self.predict_flow2 = predict_flow(194)
        self.upsampled_flow6_to_5 = upsample_flow(upsample_bias)
        self.upsampled_flow5_to_4 = upsample_flow(upsample_bias)
        self.upsampled_flow4_to_3 = upsample_flow(upsample_bias)
        self.upsampled_flow3_to_2 = upsample_flow(upsample_bias)

    def _decode(self, out_conv2: Tensor, out_conv3: Tensor, out_conv4: Tensor, out_conv5: Tensor, out_conv6: Tensor):
        flow6 = self.predict_flow6(out_conv6)
        concat5 = torch.cat((out_conv5, self.deconv5(out_conv6), self.upsampled_flow6_to_5(flow6)), 1)
        flow5 = self.predict_flow5(concat5)
        concat4 = torch.cat((out_conv4, self.deconv4(concat5), self.upsampled_flow5_to_4(flow5)), 1)
        flow4 = self.predict_flow4(concat4)
        concat3 = torch.cat((out_conv3, self.deconv3(concat4), self.upsampled_flow4_to_3(flow4)), 1)
        flow3 = self.predict_flow3(concat3)
        concat2 = torch.cat((out_conv2, self.deconv2(concat3), self.upsampled_flow3_to_2(flow3)), 1)
        flow2 = self.predict_flow2(concat2)
        return flow2, flow3, flow4, flow5, flow6


class FlowNetC(_Decoder, nn.Module):
    """FlowNetC: a siamese encoder (``conv1..3`` shared by both images), the
    correlation of the two ``conv3`` maps (441 channels, LeakyReLU) concatenated
    after ``conv_redir(conv3a)`` (32 channels), then ``conv3_1..conv6_1`` and the decoder.

    ``x`` ``(B, 6, H, W)``: image 1 in channels 0-2, image 2 in 3-5 (normalised).
    """

    def __init__(self, *, batch_norm: bool = False, div_flow: float = 20.0):
        super().__init__()
        self.batchNorm = batch_norm
        self.div_flow = div_flow
        self.conv1 = conv(batch_norm, 3, 64, kernel_size=7, stride=2)
        self.conv2 = conv(batch_norm, 64, 128, kernel_size=5, stride=2)
        self.conv3 = conv(batch_norm, 128, 256, kernel_size=5, stride=2)
        self.conv_redir = conv(batch_norm, 256, 32, kernel_size=1, stride=1)
        self.corr = Correlation(pad_size=20, kernel_size=1, max_displacement=20, stride1=1, stride2=2, corr_multiply=1)
        self.corr_activation = nn.LeakyReLU(0.1, inplace=True)
        self.conv3_1 = conv(batch_norm, 473, 256)
        self.conv4 = conv(batch_norm, 256, 512, stride=2)
        self.conv4_1 = conv(batch_norm, 512, 512)
        self.conv5 = conv(batch_norm, 512, 512, stride=2)
        self.conv5_1 = conv(batch_norm, 512, 512)
        self.conv6 = conv(batch_norm, 512, 1024, stride=2)
        self.conv6_1 = conv(batch_norm, 1024, 1024)
        self._build_decoder(upsample_bias=True)
        init_weights(self)

    def forward(self, x: Tensor, *, all_scales: bool = False):
        # the two streams share conv1..3: run them as one batch
        B = x.shape[0]
        both = torch.cat((x[:, 0:3], x[:, 3:6]), 0)
        out_conv2_both = self.conv2(self.conv1(both))
        out_conv3_both = self.conv3(out_conv2_both)
        out_conv2a = out_conv2_both[:B]
        out_conv3a, out_conv3b = out_conv3_both[:B], out_conv3_both[B:]
        out_corr = self.corr_activation(self.corr(out_conv3a, out_conv3b))
        in_conv3_1 = torch.cat((self.conv_redir(out_conv3a), out_corr), 1)
        out_conv3_1 = self.conv3_1(in_conv3_1)
        out_conv4 = self.conv4_1(self.conv4(out_conv3_1))
        out_conv5 = self.conv5_1(self.conv5(out_conv4))
        out_conv6 = self.conv6_1(self.conv6(out_conv5))
        flows = self._decode(out_conv2a, out_conv3_1, out_conv4, out_conv5, out_conv6)
        return flows if all_scales else flows[0]


class FlowNetS(_Decoder, nn.Module):
    """FlowNetS: one encoder ``conv1..conv6_1`` on the stacked inputs, then the decoder.

    ``x`` ``(B, input_channels, H, W)``: 12 channels inside FlowNet2 (image 1, image 2,
    warped image 2, flow / div_flow, brightness error), 6 for the stand-alone FlowNet2S.
    """

    def __init__(self, *, input_channels: int = 12, batch_norm: bool = False):
        super().__init__()
        self.batchNorm = batch_norm
        self.conv1 = conv(batch_norm, input_channels, 64, kernel_size=7, stride=2)
        self.conv2 = conv(batch_norm, 64, 128, kernel_size=5, stride=2)
        self.conv3 = conv(batch_norm, 128, 256, kernel_size=5, stride=2)
        self.conv3_1 = conv(batch_norm, 256, 256)
        self.conv4 = conv(batch_norm, 256, 512, stride=2)
        self.conv4_1 = conv(batch_norm, 512, 512)
        self.conv5 = conv(batch_norm, 512, 512, stride=2)
        self.conv5_1 = conv(batch_norm, 512, 512)
        self.conv6 = conv(batch_norm, 512, 1024, stride=2)
        self.conv6_1 = conv(batch_norm, 1024, 1024)
        self._build_decoder(upsample_bias=False)
        init_weights(self)

    def forward(self, x: Tensor, *, all_scales: bool = False):
        out_conv2 = self.conv2(self.conv1(x))
        out_conv3 = self.conv3_1(self.conv3(out_conv2))
        out_conv4 = self.conv4_1(self.conv4(out_conv3))
        out_conv5 = self.conv5_1(self.conv5(out_conv4))
        out_conv6 = self.conv6_1(self.conv6(out_conv5))
        flows = self._decode(out_conv2, out_conv3, out_conv4, out_conv5, out_conv6)
        return flows if all_scales else flows[0]


class FlowNetSD(nn.Module):
    """FlowNetSD (small displacements): stride-1 ``conv0``, 3x3 kernels throughout,
    and an ``inter_conv`` between every concatenation and its flow prediction.

    ``x`` ``(B, 6, H, W)``: image 1 and image 2 (normalised).
    """

    def __init__(self, *, batch_norm: bool = False):
        super().__init__()
        self.batchNorm = batch_norm
        self.conv0 = conv(batch_norm, 6, 64)
        self.conv1 = conv(batch_norm, 64, 64, stride=2)
        self.conv1_1 = conv(batch_norm, 64, 128)
        self.conv2 = conv(batch_norm, 128, 128, stride=2)
        self.conv2_1 = conv(batch_norm, 128, 128)
        self.conv3 = conv(batch_norm, 128, 256, stride=2)
        self.conv3_1 = conv(batch_norm, 256, 256)
        self.conv4 = conv(batch_norm, 256, 512, stride=2)
        self.conv4_1 = conv(batch_norm, 512, 512)
        self.conv5 = conv(batch_norm, 512, 512, stride=2)
        self.conv5_1 = conv(batch_norm, 512, 512)
        self.conv6 = conv(batch_norm, 512, 1024, stride=2)
        self.conv6_1 = conv(batch_norm, 1024, 1024)
        self.deconv5 = deconv(1024, 512)
        self.deconv4 = deconv(1026, 256)
        self.deconv3 = deconv(770, 128)
        self.deconv2 = deconv(386, 64)
        self.inter_conv5 = i_conv(batch_norm, 1026, 512)
        self.inter_conv4 = i_conv(batch_norm, 770, 256)
        self.inter_conv3 = i_conv(batch_norm, 386, 128)
        self.inter_conv2 = i_conv(batch_norm, 194, 64)
        self.predict_flow6 = predict_flow(1024)
        self.predict_flow5 = predict_flow(512)
        self.predict_flow4 = predict_flow(256)
        self.predict_flow3 = predict_flow(128)
        self.predict_flow2 = predict_flow(64)
        self.upsampled_flow6_to_5 = upsample_flow(True)
        self.upsampled_flow5_to_4 = upsample_flow(True)
        self.upsampled_flow4_to_3 = upsample_flow(True)
        self.upsampled_flow3_to_2 = upsample_flow(True)
        init_weights(self)

    def forward(self, x: Tensor, *, all_scales: bool = False):
        out_conv0 = self.conv0(x)
        out_conv1 = self.conv1_1(self.conv1(out_conv0))
        out_conv2 = self.conv2_1(self.conv2(out_conv1))
        out_conv3 = self.conv3_1(self.conv3(out_conv2))
        out_conv4 = self.conv4_1(self.conv4(out_conv3))
        out_conv5 = self.conv5_1(self.conv5(out_conv4))
        out_conv6 = self.conv6_1(self.conv6(out_conv5))

        flow6 = self.predict_flow6(out_conv6)
        concat5 = torch.cat((out_conv5, self.deconv5(out_conv6), self.upsampled_flow6_to_5(flow6)), 1)
        flow5 = self.predict_flow5(self.inter_conv5(concat5))
        concat4 = torch.cat((out_conv4, self.deconv4(concat5), self.upsampled_flow5_to_4(flow5)), 1)
        flow4 = self.predict_flow4(self.inter_conv4(concat4))
        concat3 = torch.cat((out_conv3, self.deconv3(concat4), self.upsampled_flow4_to_3(flow4)), 1)
        flow3 = self.predict_flow3(self.inter_conv3(concat3))
        concat2 = torch.cat((out_conv2, self.deconv2(concat3), self.upsampled_flow3_to_2(flow3)), 1)
        flow2 = self.predict_flow2(self.inter_conv2(concat2))
        flows = (flow2, flow3, flow4, flow5, flow6)
        return flows if all_scales else flows[0]


#: where Monte Carlo dropout acts in the fusion network (paper, Fig. 3)
DROPOUT_OPTIONS = (None, 1, 2)


class HeadWeights(NamedTuple):
    """The fusion network's linear head: ``inter_conv0`` (3×3, 82 -> 16), ``predict_flow0``
    (3×3, 16 -> 2), and their composition (5×5, 82 -> 2)."""

    conv0: Tensor
    bias0: Tensor
    conv1: Tensor
    bias1: Tensor
    composite: Tensor
    composite_bias: Tensor


def compose_convs(w1: Tensor, b1: Tensor, w2: Tensor, b2: Tensor) -> tuple[Tensor, Tensor]:
    """The one convolution that two stride-1 convolutions without padding make.

    ``y = w2 ⋆ (w1 ⋆ x + b1) + b2`` with ``w1`` ``(M, C, k1, k1)``, ``w2`` ``(O, M, k2, k2)``
    is ``w ⋆ x + b`` with ``w[o, c, u + d] = Σ_m w2[o, m, u] w1[m, c, d]`` (kernel
    ``k1 + k2 - 1``) and ``b = b2 + Σ_{m,u} w2[o, m, u] b1[m]``; formed in float64.
    With zero padding the two agree except where ``w1 ⋆ x`` would be read outside the image.
    """
    k2 = w2.shape[-1]
    a, c = w1.double(), w2.double()
    w = a.new_zeros(c.shape[0], a.shape[1], a.shape[-2] + k2 - 1, a.shape[-1] + k2 - 1)
    for i in range(c.shape[-2]):
        for j in range(k2):
            w[:, :, i : i + a.shape[-2], j : j + a.shape[-1]] += torch.einsum("om,mcuv->ocuv", c[:, :, i, j], a)
    b = b2.double() + torch.einsum("omuv,m->o", c, b1.double())
    return w.to(w1.dtype), b.to(b1.dtype)


def two_conv_rows(
    scaled: Tensor, keep: Tensor, r0: int, r1: int, w1: Tensor, b1: Tensor, w2: Tensor, b2: Tensor
) -> Tensor:
    """Rows ``[r0, r1)`` of ``conv(conv(scaled * keep, w1, b1), w2, b2)`` (3×3 kernels, zero
    padding 1 each), from rows ``[r0 - 2, r1 + 2)`` of the input only: rows beyond the
    image are the convs' own zero padding (of the input for the first, of its output
    for the second). ``(B, O, r1 - r0, W)``."""
    H = scaled.shape[-2]
    i0, i1 = max(r0 - 1, 0), min(r1 + 1, H)  # rows of the first conv's output that they need
    a, b = max(i0 - 1, 0), min(i1 + 1, H)  # rows of the input that those need
    x = F.pad(scaled[:, :, a:b] * keep[:, :, a:b], (0, 0, int(i0 == 0), int(i1 == H)))
    inter = F.pad(F.conv2d(x, w1, b1, padding=(0, 1)), (0, 0, int(r0 == 0), int(r1 == H)))
    return conv2d_rows(inter, w2, b2, (0, 1))


#: output rows per strip of :meth:`FlowNetFusion.head_strips` (at 512 px wide, 32 rows of the
#: 82-channel features are 5 MiB: they stay in the cache between the mask and the convs)
HEAD_STRIP_ROWS = 32


class FlowNetFusion(nn.Module):
    """The fusion network (paper Fig. 3): 11 input channels at full resolution ->
    ``flow0`` ``(B, 2, H, W)`` in pixels.

    Graph (NVIDIA's ``FlowNetFusion.forward``; ``N = H x W``)::

        out_conv0 = conv0(x)                                   64 x N
        out_conv1 = conv1_1(conv1(out_conv0))                 128 x N/2
        out_conv2 = conv2_1(conv2(out_conv1))                 128 x N/4
        ---------------- dropout option #1: on out_conv1 and out_conv2 ----------------
        concat1 = [out_conv1, deconv1(out_conv2), up(predict_flow2(out_conv2))]   162 x N/2
        concat0 = [out_conv0, deconv0(concat1), up(predict_flow1(inter_conv1(concat1)))]  82 x N
        ---------------- dropout option #2: on concat0 ----------------
        flow0 = predict_flow0(inter_conv0(concat0))             2 x N

    In the figure the dashed line of option #1 cuts the three arrows that leave
    the encoder ``out_conv1 -> concat1``, ``out_conv2 -> deconv1`` and
    ``out_conv2 -> predict_flow2``; the skip ``out_conv0 -> concat0`` goes around
    it (bypasses the dropout). Option #2 cuts the single arrow
    ``concat0 -> inter_conv0``, which every branch passes.
    """

    def __init__(self, *, batch_norm: bool = False):
        super().__init__()
        self.batchNorm = batch_norm
        self.conv0 = conv(batch_norm, 11, 64)
        self.conv1 = conv(batch_norm, 64, 64, stride=2)
        self.conv1_1 = conv(batch_norm, 64, 128)
        self.conv2 = conv(batch_norm, 128, 128, stride=2)
        self.conv2_1 = conv(batch_norm, 128, 128)
        self.deconv1 = deconv(128, 32)
        self.deconv0 = deconv(162, 16)
        self.inter_conv1 = i_conv(batch_norm, 162, 32)
        self.inter_conv0 = i_conv(batch_norm, 82, 16)
        self.predict_flow2 = predict_flow(128)
        self.predict_flow1 = predict_flow(32)
        self.predict_flow0 = predict_flow(16)
        self.upsampled_flow2_to_1 = upsample_flow(True)
        self.upsampled_flow1_to_0 = upsample_flow(True)
        init_weights(self)

    # -- the three parts, split at the two dropout positions --
    def encode(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``x`` ``(B, 11, H, W)`` -> ``out_conv0, out_conv1, out_conv2``."""
        out_conv0 = self.conv0(x)
        out_conv1 = self.conv1_1(self.conv1(out_conv0))
        out_conv2 = self.conv2_1(self.conv2(out_conv1))
        return out_conv0, out_conv1, out_conv2

    def refine(self, out_conv0: Tensor, out_conv1: Tensor, out_conv2: Tensor) -> Tensor:
        """Encoder outputs -> ``concat0`` ``(B, 82, H, W)``."""
        flow2_up = self.upsampled_flow2_to_1(self.predict_flow2(out_conv2))
        concat1 = torch.cat((out_conv1, self.deconv1(out_conv2), flow2_up), 1)
        flow1_up = self.upsampled_flow1_to_0(self.predict_flow1(self.inter_conv1(concat1)))
        # channels-last on a CPU: the head's convs run about twice as fast, and a dropout
        # of concat0 (option #2) draws its mask in the same memory order
        return cpu_channels_last(torch.cat((out_conv0, self.deconv0(concat1), flow1_up), 1))

    def linear_head(self) -> HeadWeights | None:
        """The head ``inter_conv0 -> predict_flow0`` as weights: both convs (a BatchNorm in
        eval mode folded into the first) and their composition, one 5×5 conv 82 -> 2
        (:func:`compose_convs`); None while a BatchNorm trains (batch statistics)."""
        conv0, flow = self.inter_conv0[0], self.predict_flow0
        w1, b1 = conv0.weight, conv0.bias
        if self.batchNorm:
            bn = self.inter_conv0[1]
            if bn.training:
                return None
            w1, b1 = fuse_conv_bn_weights(w1, b1, bn.running_mean, bn.running_var, bn.eps, bn.weight, bn.bias)
        return HeadWeights(w1, b1, flow.weight, flow.bias, *compose_convs(w1, b1, flow.weight, flow.bias))

    def head_strips(
        self, scaled: Tensor, keep: Tensor, weights: HeadWeights | None = None, rows: int = HEAD_STRIP_ROWS
    ) -> Tensor:
        """``head(scaled * keep)`` (a dropout pass of option #2), ``rows`` output rows at a time.

        The head is two 3×3 convs without an activation between them, i.e. one 5×5
        conv 82 -> 2 (a third of the multiply-adds, run by kernel rows) everywhere but on
        the image's outermost ring of pixels, where the first conv's output is zero
        padding for the second; the ring is computed by the two convs themselves
        (:func:`two_conv_rows`). Output rows ``[r0, r1)`` depend on input rows
        ``[r0 - 2, r1 + 2)`` only, so each strip multiplies just those rows by the mask
        and convolves them at once, while they are still in the cache.
        """
        w = self.linear_head() if weights is None else weights
        if w is None:
            return self.head(scaled * keep)
        H, W = scaled.shape[-2:]
        strips = []
        for r0 in range(0, H, rows):
            r1 = min(r0 + rows, H)
            a, b = max(r0 - 2, 0), min(r1 + 2, H)
            x = F.pad(scaled[:, :, a:b] * keep[:, :, a:b], (0, 0, a - (r0 - 2), (r1 + 2) - b))
            strips.append(conv2d_rows(x, w.composite, w.composite_bias, (0, 2)))
        out = torch.cat(strips, dim=2)
        convs = (w.conv0, w.bias0, w.conv1, w.bias1)
        out[:, :, :1] = two_conv_rows(scaled, keep, 0, 1, *convs)
        out[:, :, H - 1 :] = two_conv_rows(scaled, keep, H - 1, H, *convs)
        convs_t = (w.conv0.mT, w.bias0, w.conv1.mT, w.bias1)  # columns: the same on the transposed image
        out[..., :1] = two_conv_rows(scaled.mT, keep.mT, 0, 1, *convs_t).mT
        out[..., W - 1 :] = two_conv_rows(scaled.mT, keep.mT, W - 1, W, *convs_t).mT
        return out

    def head(self, concat0: Tensor) -> Tensor:
        """``concat0`` ``(B, 82, H, W)`` -> ``flow0`` ``(B, 2, H, W)`` (``predict_flow0`` by
        kernel rows, :func:`~flowins.flow.conv.conv2d_rows`: the same map, faster on a CPU)."""
        out = self.inter_conv0(cpu_channels_last(concat0))
        return conv2d_rows(out, self.predict_flow0.weight, self.predict_flow0.bias, self.predict_flow0.padding)

    def forward(self, x: Tensor, *, dropout: Callable[[Tensor], Tensor] | None = None, option: int | None = None) -> Tensor:
        """One pass; ``dropout`` (e.g. :class:`~flowins.flow.mc_dropout.MCDropout`) acts at
        ``option`` 1 or 2 (class docstring); ``option=None`` is NVIDIA's forward."""
        _check_option(option, dropout)
        out_conv0, out_conv1, out_conv2 = self.encode(x)
        if option == 1:
            packed, shapes = _pack(out_conv1, out_conv2)
            out_conv1, out_conv2 = _unpack(dropout(packed), shapes)
        concat0 = self.refine(out_conv0, out_conv1, out_conv2)
        if option == 2:
            concat0 = dropout(concat0)
        return self.head(concat0)

    def mc_samples(
        self, x: Tensor, *, dropout: nn.Module, option: int, passes: int, chunk: int | None = None
    ) -> Tensor:
        """``(passes, B, 2, H, W)`` flows of ``passes`` dropout passes, computing
        everything upstream of the dropout **once** (:func:`flowins.flow.mc_dropout.mc_samples`).

        Option 2: the head ``inter_conv0 -> predict_flow0`` runs ``passes`` times (on a CPU,
        with :class:`~flowins.flow.mc_dropout.MCDropout` one pass at a time, strip by strip:
        :meth:`head_strips`).
        Option 1: ``refine`` + ``head`` run ``passes`` times; ``out_conv1`` and
        ``out_conv2`` are dropped (packed into one tensor, element-wise dropout),
        ``out_conv0`` is passed as context (it bypasses the dropout).
        """
        _check_option(option, dropout)
        if option is None:
            raise ValueError("FlowNetFusion.mc_samples: option=None has no dropout; expected 1 or 2")
        out_conv0, out_conv1, out_conv2 = self.encode(x)
        if option == 2:
            concat0 = self.refine(out_conv0, out_conv1, out_conv2)
            weights = self.linear_head() if concat0.device.type == "cpu" else None  # a CPU gain
            strips = functools.partial(self.head_strips, weights=weights) if weights is not None else None
            return _mc_samples(self.head, concat0, dropout, passes, chunk=chunk, masked_head=strips)
        packed, shapes = _pack(out_conv1, out_conv2)

        def downstream(dropped: Tensor, conv0: Tensor) -> Tensor:
            c1, c2 = _unpack(dropped, shapes)
            return self.head(self.refine(conv0, c1, c2))

        return _mc_samples(downstream, packed, dropout, passes, context=(out_conv0,), chunk=chunk)


def _check_option(option: int | None, dropout) -> None:
    if option not in DROPOUT_OPTIONS:
        raise ValueError(f"dropout option {option!r}; expected one of {DROPOUT_OPTIONS} (paper Fig. 3)")
    if option is not None and dropout is None:
        raise ValueError(f"dropout option {option} needs a dropout module")


def _pack(*tensors: Tensor) -> tuple[Tensor, list[torch.Size]]:
    """Flatten ``(B, ...)`` tensors into one ``(B, sum of sizes)`` (for one element-wise dropout)."""
    return torch.cat([t.flatten(1) for t in tensors], 1), [t.shape[1:] for t in tensors]


def _unpack(packed: Tensor, shapes: list[torch.Size]) -> list[Tensor]:
    sizes = [int(torch.Size(s).numel()) for s in shapes]
    return [part.reshape(packed.shape[0], *s) for part, s in zip(torch.split(packed, sizes, 1), shapes)]
