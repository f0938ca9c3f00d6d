"""The plain-torch correlation layer against a naive loop over NVIDIA's kernel indexing."""
from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from flowins.flow.flownet2.correlation import Correlation, correlation


def correlation_loop(f1, f2, *, pad_size, kernel_size, max_displacement, stride1, stride2):
    """Direct transcription of NVIDIA's ``correlation_forward``: one output value at a time
    (patch centre ``o·stride1 + max_displacement`` in the zero-padded maps; reads outside
    the padded maps are 0)."""
    B, C, H, W = f1.shape
    r = (kernel_size - 1) // 2
    D = max_displacement // stride2
    f1p = F.pad(f1, (pad_size,) * 4)
    f2p = F.pad(f2, (pad_size,) * 4)
    Hp, Wp = f1p.shape[-2:]
    out_h = math.ceil((Hp - 2 * (max_displacement + r)) / stride1)
    out_w = math.ceil((Wp - 2 * (max_displacement + r)) / stride1)

    def at(fp, y, x):
        if 0 <= y < Hp and 0 <= x < Wp:
            return fp[:, :, y, x]
        return torch.zeros(B, C, dtype=fp.dtype)

    channels = []
    for tj in range(-D, D + 1):
        for ti in range(-D, D + 1):
            rows = []
            for oy in range(out_h):
                cols = []
                for ox in range(out_w):
                    y1, x1 = oy * stride1 + max_displacement, ox * stride1 + max_displacement
                    y2, x2 = y1 + tj * stride2, x1 + ti * stride2
                    acc = 0
                    for j in range(-r, r + 1):
                        for i in range(-r, r + 1):
                            acc = acc + (at(f1p, y1 + j, x1 + i) * at(f2p, y2 + j, x2 + i)).sum(1)
                    cols.append(acc / (kernel_size * kernel_size * C))
                rows.append(torch.stack(cols, -1))
            channels.append(torch.stack(rows, -2))
    return torch.stack(channels, 1)


CONFIGS = [
    dict(pad_size=2, kernel_size=1, max_displacement=2, stride1=1, stride2=1),
    dict(pad_size=4, kernel_size=1, max_displacement=4, stride1=1, stride2=2),  # FlowNetC's pattern, scaled
    dict(pad_size=3, kernel_size=3, max_displacement=2, stride1=2, stride2=1),
    dict(pad_size=1, kernel_size=1, max_displacement=2, stride1=1, stride2=1),  # output smaller than input
]


@pytest.mark.parametrize("cfg", CONFIGS)
def test_values_and_grads_match_loop(cfg):
    torch.manual_seed(0)
    f1 = torch.randn(2, 3, 5, 6, dtype=torch.float64, requires_grad=True)
    f2 = torch.randn(2, 3, 5, 6, dtype=torch.float64, requires_grad=True)
    fast = correlation(f1, f2, **cfg)
    slow = correlation_loop(f1, f2, **cfg)
    assert fast.shape == slow.shape
    torch.testing.assert_close(fast, slow, rtol=1e-12, atol=1e-12)
    weight = torch.randn_like(fast)
    g_fast = torch.autograd.grad((fast * weight).sum(), (f1, f2))
    g_slow = torch.autograd.grad((slow * weight).sum(), (f1, f2))
    for a, b in zip(g_fast, g_slow):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_flownetc_configuration_matches_loop():
    """pad 20, kernel 1, max displacement 20, strides 1 and 2: 441 channels, same size."""
    torch.manual_seed(1)
    f1, f2 = torch.randn(1, 4, 4, 5), torch.randn(1, 4, 4, 5)
    layer = Correlation(pad_size=20, kernel_size=1, max_displacement=20, stride1=1, stride2=2, corr_multiply=1)
    out = layer(f1, f2)
    assert layer.out_channels == 441 and out.shape == (1, 441, 4, 5)
    ref = correlation_loop(f1, f2, pad_size=20, kernel_size=1, max_displacement=20, stride1=1, stride2=2)
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-6)


def test_channel_order_is_y_major():
    """image 2 = image 1 moved by (dx, dy) = (-4, +2): the peak is at channel (dy/2 + 10)·21 + (dx/2 + 10)."""
    torch.manual_seed(2)
    f1 = torch.randn(1, 16, 24, 24)
    f2 = torch.roll(f1, shifts=(2, -4), dims=(2, 3))  # f2[y + 2, x - 4] = f1[y, x]
    out = correlation(f1, f2)
    peak = out[0, :, 8:16, 8:16].mean((1, 2)).argmax().item()
    assert peak == (1 + 10) * 21 + (-2 + 10)


@pytest.mark.parametrize(
    "cfg",
    [
        dict(pad_size=2, kernel_size=1, max_displacement=2, stride1=1, stride2=2),
        dict(pad_size=2, kernel_size=3, max_displacement=1, stride1=2, stride2=1),
    ],
)
def test_gradcheck(cfg):
    torch.manual_seed(3)
    f1 = torch.randn(1, 2, 4, 4, dtype=torch.float64, requires_grad=True)
    f2 = torch.randn(1, 2, 4, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: correlation(a, b, **cfg), (f1, f2))


def test_rejects_bad_inputs():
    with pytest.raises(ValueError, match="same shape"):
        correlation(torch.zeros(1, 2, 4, 4), torch.zeros(1, 2, 4, 5))
    with pytest.raises(ValueError, match="odd"):
        correlation(torch.zeros(1, 2, 4, 4), torch.zeros(1, 2, 4, 4), kernel_size=2)
