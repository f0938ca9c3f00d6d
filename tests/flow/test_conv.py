"""conv2d_rows: the kernel-row form of a convolution against F.conv2d (values and gradients)."""
import pytest
import torch
import torch.nn.functional as F

from flowins.flow.conv import conv2d_rows, cpu_channels_last


@pytest.mark.parametrize(
    "kernel, padding, bias, channels_last",
    [((7, 7), (3, 3), True, False), ((3, 3), (1, 1), True, True), ((3, 5), (1, 2), False, False),
     ((3, 3), (0, 1), True, False), ((5, 1), (2, 0), True, True)],
)
def test_equals_conv2d(kernel, padding, bias, channels_last):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 6, 9, 11, dtype=torch.float64, generator=g)
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    w = torch.randn(2, 6, *kernel, dtype=torch.float64, generator=g)
    b = torch.randn(2, dtype=torch.float64, generator=g) if bias else None
    expected = F.conv2d(x, w, b, padding=padding)
    got = conv2d_rows(x, w, b, padding)
    assert got.shape == expected.shape
    torch.testing.assert_close(got, expected, rtol=1e-12, atol=1e-12)


def test_float32_rounding_only():
    g = torch.Generator().manual_seed(1)
    x, w, b = torch.randn(1, 16, 40, 56, generator=g), torch.randn(2, 16, 7, 7, generator=g), torch.randn(2, generator=g)
    expected = F.conv2d(x.double(), w.double(), b.double(), padding=3)
    err = (conv2d_rows(x, w, b, (3, 3)).double() - expected).abs().max()
    assert err < 1e-6 * float(expected.abs().max())


def test_gradients_against_finite_differences():
    g = torch.Generator().manual_seed(2)
    x = torch.randn(1, 3, 5, 6, dtype=torch.float64, generator=g, requires_grad=True)
    w = torch.randn(2, 3, 3, 3, dtype=torch.float64, generator=g, requires_grad=True)
    b = torch.randn(2, dtype=torch.float64, generator=g, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x, w, b: conv2d_rows(x, w, b, (1, 1)), (x, w, b))


def test_bad_shapes_are_named():
    with pytest.raises(ValueError, match=r"\(B, C, H, W\) and \(O, C, kh, kw\)"):
        conv2d_rows(torch.zeros(1, 4, 5, 5), torch.zeros(2, 3, 3, 3), None, (1, 1))
    with pytest.raises(ValueError, match="kernel height 7 exceeds"):
        conv2d_rows(torch.zeros(1, 4, 3, 9), torch.zeros(2, 4, 7, 3), None, (0, 1))


def test_channels_last_on_cpu_only_for_images():
    x = torch.zeros(1, 3, 4, 5)
    assert cpu_channels_last(x).is_contiguous(memory_format=torch.channels_last)
    v = torch.zeros(3, 4)
    assert cpu_channels_last(v) is v
