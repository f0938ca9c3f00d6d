"""DIS dense flow: accuracy against exact ground truth, direction, and its uncertainty."""
import cv2
import numpy as np
import pytest
import torch

from flowins.flow.classical import DISProvider, fb_residual, min_eigenvalue
from flowins.data.reference_flow import endpoint_error, middlebury_pair, simulator_pair


def textured(h: int = 120, w: int = 160, seed: int = 0) -> np.ndarray:
    """A smooth random texture ``(h, w)`` float64 in [0, 1] (blurred noise, several scales)."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w))
    for sigma in (1.5, 4.0):
        img += cv2.GaussianBlur(rng.random((h, w)), (0, 0), sigma) * sigma
    img -= img.min()
    return img / img.max()


def shifted_pair(du: float, dv: float, h: int = 120, w: int = 160) -> tuple[np.ndarray, np.ndarray]:
    """``(image1, image2)`` uint8 RGB with ``image1(u, v) = image2(u + du, v + dv)``."""
    base = textured(h + 40, w + 40).astype(np.float32)
    u, v = np.meshgrid(np.arange(w, dtype=np.float32) + 20, np.arange(h, dtype=np.float32) + 20)
    one = base[20 : 20 + h, 20 : 20 + w]
    two = cv2.remap(base, u - du, v - dv, cv2.INTER_CUBIC)  # image2(x) = base(x - d)
    to_rgb = lambda g: np.repeat(np.clip(np.rint(g * 255), 0, 255).astype(np.uint8)[..., None], 3, -1)
    return to_rgb(one), to_rgb(two)


def run(provider: DISProvider, pair) -> tuple[np.ndarray, np.ndarray]:
    result = provider(pair.image1, pair.image2)
    return result.flow[0].permute(1, 2, 0).numpy(), result.sigma[0].permute(1, 2, 0).numpy()


def test_dis_epe_middlebury():
    pair = middlebury_pair()
    flow, _ = run(DISProvider(), pair)
    epe = endpoint_error(flow, pair.flow, pair.mask).mean()
    # measured 0.81 px (medium preset, 185 x 125, |flow| up to 15 px)
    assert epe < 1.0, epe


def test_dis_epe_simulator():
    pair = simulator_pair()
    flow, _ = run(DISProvider(), pair)
    epe = endpoint_error(flow, pair.flow, pair.mask).mean()
    # measured 0.39 px (medium), 0.63 (fast), 0.83 (ultrafast); 76 % of the pixels are valid & static
    assert epe < 0.49, epe
    fast, _ = run(DISProvider("ultrafast"), pair)
    assert endpoint_error(fast, pair.flow, pair.mask).mean() < 1.05  # measured 0.83


@pytest.mark.parametrize("du, dv", [(2.5, -1.5), (-3.25, 0.75)])
def test_dis_direction_synthetic_translation(du, dv):
    a, b = shifted_pair(du, dv)
    result = DISProvider()(a, b)
    inner = result.flow[0, :, 15:-15, 15:-15]
    med = inner.reshape(2, -1).median(dim=1).values
    assert torch.allclose(med, torch.tensor([du, dv]), atol=0.05), med  # measured within 0.032 px


def test_dis_batch_equals_pairs():
    a1, b1 = shifted_pair(1.0, 0.5)
    a2, b2 = shifted_pair(-2.0, 1.0)
    both = DISProvider()(np.stack([a1, a2]), np.stack([b1, b2]))
    assert both.flow.shape == both.sigma.shape == (2, 2, 120, 160)
    assert both.flow.dtype == torch.float32 and (both.sigma > 0).all()
    one = DISProvider()(a2, b2)
    torch.testing.assert_close(both.flow[1:], one.flow)
    torch.testing.assert_close(both.sigma[1:], one.sigma)


def test_uniform_pair_is_uncertain_not_confident():
    gray = np.full((96, 128, 3), 128, np.uint8)
    result = DISProvider()(gray, gray)
    assert result.flow.abs().max() < 1e-3  # DIS returns zero flow ...
    assert (result.sigma > 20.0).all()  # ... but σ says it is unknown: β / sqrt(ε) = 40 px
    a, b = shifted_pair(1.0, 1.0)
    textured_sigma = DISProvider()(a, b).sigma.median()
    assert textured_sigma < 0.5, textured_sigma  # measured 0.17 px


def test_sigma_tracks_error_on_middlebury():
    pair = middlebury_pair()
    flow, sigma = run(DISProvider(), pair)
    err = np.abs(flow - pair.flow)[pair.mask]
    s = sigma[pair.mask]
    within = (err < s).mean()
    # measured 0.69 within ±1σ; mean |error| 0.31 px in the confident half, 1.20 px in the least confident tenth
    assert 0.55 < within < 0.85, within
    assert err[s <= np.median(s)].mean() * 3 < err[s >= np.percentile(s, 90)].mean()


def test_fb_residual_closed_form():
    h, w = 20, 30
    f = np.zeros((h, w, 2), np.float32)
    f[..., 0], f[..., 1] = 1.5, -0.5
    np.testing.assert_allclose(fb_residual(f, -f), 0.0, atol=1e-6)
    # b(x) = (c u, 0), linear in u: r = f + (c (u + f_u), 0) away from the border
    c = 0.1
    u = np.arange(w, dtype=np.float32)[None, :].repeat(h, 0)
    b = np.stack([c * u, np.zeros_like(u)], -1)
    r = fb_residual(f, b)
    expected = f[..., 0] + c * (u + f[..., 0])
    np.testing.assert_allclose(r[2:-2, 2:-2, 0], expected[2:-2, 2:-2], atol=1e-4)
    np.testing.assert_allclose(r[..., 1], -0.5, atol=1e-6)


def test_min_eigenvalue_aperture_and_scaling():
    u = np.arange(64, dtype=np.float32)[None, :].repeat(48, 0)
    ramp = 0.01 * u
    assert np.abs(min_eigenvalue(ramp, 9)).max() < 1e-9  # an edge: one direction only (aperture problem)
    tex = textured(48, 64).astype(np.float32)
    lam = min_eigenvalue(tex, 9)
    assert (lam > 0).mean() > 0.99
    np.testing.assert_allclose(min_eigenvalue(0.5 * tex, 9), 0.25 * lam, rtol=1e-4, atol=1e-12)
    np.testing.assert_allclose(min_eigenvalue(tex.T.copy(), 9), lam.T, rtol=1e-4, atol=1e-12)


def test_bad_arguments():
    with pytest.raises(ValueError, match="preset"):
        DISProvider("slow")
    with pytest.raises(ValueError, match="sigma0_px"):
        DISProvider(sigma0_px=0.0)
