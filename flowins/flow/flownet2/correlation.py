"""FlowNetC's correlation layer in plain torch (replaces NVIDIA's ``correlation_cuda``).

For two feature maps ``f1, f2`` ``(B, C, H, W)`` the layer compares a patch of
``f1`` around every output position with patches of ``f2`` displaced by
``(dx, dy) = (tx·stride2, ty·stride2)``, ``tx, ty ∈ {-D, …, D}``,
``D = max_displacement // stride2`` (Dosovitskiy et al. 2015, eq. 1)::

    out[b, (ty+D)·(2D+1) + (tx+D), oy, ox] =
        1 / (k² C) · Σ_c Σ_{|i|,|j| ≤ r} f1p[b, c, y+j, x+i] · f2p[b, c, y+dy+j, x+dx+i]

with ``r = (k-1)/2``, ``f1p, f2p`` the inputs zero-padded by ``pad_size`` and the
patch centre ``(y, x) = (oy·stride1 + max_displacement, ox·stride1 + max_displacement)``
in padded coordinates. The output has ``(2D+1)²`` channels (441 for FlowNetC's
``pad_size=20, kernel_size=1, max_displacement=20, stride1=1, stride2=2``) and
``ceil((H + 2·pad_size - 2·(max_displacement + r)) / stride1)`` rows (``H`` for FlowNetC),
likewise for columns.

This is the indexing of NVIDIA's ``correlation_forward`` kernel (channel index =
y-displacement major, x-displacement minor; normalisation by ``k² C``). For
``kernel_size > 1`` that kernel reads ``r`` pixels before its padded buffer at
the top-left border; here those pixels are zeros. FlowNetC uses ``kernel_size = 1``,
where the two agree exactly.

For speed on CPU the layer loops over the ``2D+1`` vertical displacements only:
for each, one batched matrix product per image row gives the dot products of
every ``f1`` column with every ``f2`` column of the displaced row band, and a
``gather`` keeps the ``2D+1`` horizontal displacements (no ``(B, C, 441, H, W)``
tensor is formed). Autograd provides the backward pass.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def correlation(
    input1: Tensor,
    input2: Tensor,
    *,
    pad_size: int = 20,
    kernel_size: int = 1,
    max_displacement: int = 20,
    stride1: int = 1,
    stride2: int = 2,
) -> Tensor:
    """Correlation volume ``(B, (2D+1)², H_out, W_out)`` of ``input1, input2`` ``(B, C, H, W)``
    (module docstring for the formula)."""
    if input1.shape != input2.shape or input1.ndim != 4:
        raise ValueError(
            f"correlation: inputs must both be (B, C, H, W) of the same shape; got {tuple(input1.shape)} and {tuple(input2.shape)}"
        )
    if kernel_size < 1 or kernel_size % 2 == 0:
        raise ValueError(f"correlation: kernel_size={kernel_size}; expected an odd number >= 1")
    if stride1 < 1 or stride2 < 1 or max_displacement < 0 or pad_size < 0:
        raise ValueError(
            f"correlation: need stride1, stride2 >= 1 and pad_size, max_displacement >= 0; got "
            f"stride1={stride1}, stride2={stride2}, pad_size={pad_size}, max_displacement={max_displacement}"
        )
    B, C, H, W = input1.shape
    r = (kernel_size - 1) // 2
    D = max_displacement // stride2
    out_h = math.ceil((H + 2 * pad_size - 2 * (max_displacement + r)) / stride1)
    out_w = math.ceil((W + 2 * pad_size - 2 * (max_displacement + r)) / stride1)
    if out_h < 1 or out_w < 1:
        raise ValueError(
            f"correlation: a {H}x{W} input gives an empty output with pad_size={pad_size}, "
            f"max_displacement={max_displacement}, kernel_size={kernel_size}"
        )
    # Pad by pad_size (as NVIDIA) plus r zeros so that every patch read stays in bounds;
    # padded coordinate q here is q - r in NVIDIA's buffer.
    p = pad_size + r
    # rows/columns of products needed around the patch centres; the furthest read,
    # max_displacement + D·stride2 + span, never exceeds the padded size
    span_h = (out_h - 1) * stride1 + 1 + 2 * r
    span_w = (out_w - 1) * stride1 + 1 + 2 * r
    f1 = F.pad(input1, (p, p, p, p))
    f2 = F.pad(input2, (p, p, p, p))
    # f1 rows/columns used start at max_displacement (patch centre - r, in the +r frame)
    y0 = x0 = max_displacement
    a = f1[:, :, y0 : y0 + span_h, x0 : x0 + span_w]
    a_rows = a.permute(0, 2, 3, 1).reshape(B * span_h, span_w, C)  # one matrix per row
    # columns of f2 that any x-displacement reads, and which of them each (x, tx) takes
    c0 = x0 - D * stride2
    n_cols = span_w + 2 * D * stride2
    take = torch.arange(span_w, device=a.device)[:, None] + stride2 * torch.arange(2 * D + 1, device=a.device)[None, :]
    take = take.expand(B * span_h, span_w, 2 * D + 1)
    planes = []
    for ty in range(-D, D + 1):
        dy = ty * stride2
        b = f2[:, :, y0 + dy : y0 + dy + span_h, c0 : c0 + n_cols]
        b_rows = b.permute(0, 2, 1, 3).reshape(B * span_h, C, n_cols)
        dots = torch.bmm(a_rows, b_rows)  # (B·span_h, span_w, n_cols): every pair in the row band
        planes.append(torch.gather(dots, 2, take))  # (B·span_h, span_w, 2D+1): the displaced ones
    # (2D+1 ty, B·span_h, span_w, 2D+1 tx) -> (B, ty, tx, span_h, span_w)
    prod = torch.stack(planes, 0).reshape(2 * D + 1, B, span_h, span_w, 2 * D + 1)
    prod = prod.permute(1, 0, 4, 2, 3).reshape(B, (2 * D + 1) ** 2, span_h, span_w)
    norm = 1.0 / (kernel_size * kernel_size * C)
    if kernel_size > 1:
        prod = F.avg_pool2d(prod, kernel_size, stride=stride1) * (kernel_size * kernel_size)
    elif stride1 > 1:
        prod = prod[:, :, ::stride1, ::stride1]
    return prod * norm


class Correlation(nn.Module):
    """:func:`correlation` as a module with NVIDIA's constructor arguments
    (``corr_multiply`` is accepted for compatibility; NVIDIA's kernel ignores it too)."""

    def __init__(
        self,
        pad_size: int = 20,
        kernel_size: int = 1,
        max_displacement: int = 20,
        stride1: int = 1,
        stride2: int = 2,
        corr_multiply: int = 1,
    ):
        super().__init__()
        self.pad_size = int(pad_size)
        self.kernel_size = int(kernel_size)
        self.max_displacement = int(max_displacement)
        self.stride1 = int(stride1)
        self.stride2 = int(stride2)
        self.corr_multiply = int(corr_multiply)

    @property
    def out_channels(self) -> int:
        """``(2·(max_displacement // stride2) + 1)²`` (441 for FlowNetC)."""
        return (2 * (self.max_displacement // self.stride2) + 1) ** 2

    def forward(self, input1: Tensor, input2: Tensor) -> Tensor:
        return correlation(
            input1,
            input2,
            pad_size=self.pad_size,
            kernel_size=self.kernel_size,
            max_displacement=self.max_displacement,
            stride1=self.stride1,
            stride2=self.stride2,
        )

    def extra_repr(self) -> str:
        return (
            f"pad_size={self.pad_size}, kernel_size={self.kernel_size}, max_displacement={self.max_displacement}, "
            f"stride1={self.stride1}, stride2={self.stride2}"
        )
