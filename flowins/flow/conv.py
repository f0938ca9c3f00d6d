"""A convolution with few output channels, evaluated in a form that is faster on a CPU.

The last layer of a flow network maps many feature channels to the 2 flow
channels with a large kernel (SpyNet: 16 -> 2, 7×7). A CPU convolution with so
few outputs leaves most of each vector register idle. Splitting the ``kh × kw``
kernel into its ``kh`` rows gives a ``1 × kw`` convolution with ``O · kh``
outputs, which vectorises well, and ``kh`` shifted additions::

    y[o, i, j] = b[o] + Σ_r  z[o, r, i + r, j],
    z[o, r]    = Σ_c  W[o, c, r, :] ⋆ x[c]   (one row of the kernel, padded by ``ph`` above and below)

The same multiply-adds in another order: the result equals ``F.conv2d`` up to
float rounding. ``benchmarks/bench_conv_rows.py`` times both on the flow networks'
last layers.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def cpu_channels_last(x: Tensor) -> Tensor:
    """``x`` ``(B, C, H, W)`` in the channels-last layout on a CPU (the layout in which
    oneDNN's convolutions run fastest there; a no-op when it is already); unchanged elsewhere."""
    return x.contiguous(memory_format=torch.channels_last) if x.device.type == "cpu" and x.ndim == 4 else x


def conv2d_rows(x: Tensor, weight: Tensor, bias: Tensor | None, padding: tuple[int, int]) -> Tensor:
    """``F.conv2d(x, weight, bias, padding=padding)`` (stride 1, no dilation, one group), by kernel rows.

    ``x`` ``(B, C, H, W)``, ``weight`` ``(O, C, kh, kw)``, ``bias`` ``(O,)`` or None.
    Returns ``(B, O, H + 2 ph - kh + 1, W + 2 pw - kw + 1)``. On the CPU the input is
    taken channels-last (the layout in which the row convolution is fast); elsewhere
    this is ``F.conv2d`` itself.
    """
    if x.ndim != 4 or weight.ndim != 4 or x.shape[1] != weight.shape[1]:
        raise ValueError(
            f"conv2d_rows: x {tuple(x.shape)} and weight {tuple(weight.shape)}; "
            "expected (B, C, H, W) and (O, C, kh, kw) with the same C"
        )
    ph, pw = (int(v) for v in padding)
    if x.device.type != "cpu":
        return F.conv2d(x, weight, bias, padding=(ph, pw))
    O, C, kh, kw = weight.shape
    rows = weight.permute(0, 2, 1, 3).reshape(O * kh, C, 1, kw)  # (o, r) x c x 1 x kw
    z = F.conv2d(cpu_channels_last(x), rows, padding=(ph, pw))
    z = z.unflatten(1, (O, kh))  # (B, O, kh, H + 2 ph, W_out)
    h_out = z.shape[-2] - kh + 1
    if h_out < 1:
        raise ValueError(f"conv2d_rows: kernel height {kh} exceeds the padded input height {z.shape[-2]}")
    y = z[:, :, 0, :h_out]
    for r in range(1, kh):
        y = y + z[:, :, r, r : r + h_out]
    return y if bias is None else y + bias.view(1, O, 1, 1)
