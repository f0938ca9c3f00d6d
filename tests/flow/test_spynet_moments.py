"""SpyNet's closed-form Monte Carlo dropout (``mc_mode="moments"``) against sampled passes,
and the dropout rate as a differentiable parameter of the flow points' σ."""
import cv2
import numpy as np
import pytest
import torch
from skimage import data

from flowins.flow.base import prepare_pair
from flowins.flow.mc_dropout import keep_probability
from flowins.flow.points import FlowPoints, grid_candidates
from flowins.flow.spynet import SpyNetProvider

F64 = torch.float64


@pytest.fixture(scope="module")
def pair():
    """A 96 x 128 crop (a multiple of 32: no resizing inside SpyNet) of the Middlebury
    'motorcycle' stereo pair at 1/4 size, as prepared float images (1, 3, H, W) in [0, 1]."""
    left, right, _ = data.stereo_motorcycle()
    H, W = left.shape[:2]
    small = [cv2.resize(x, (W // 4, H // 4), interpolation=cv2.INTER_AREA) for x in (left, right)]
    r0, c0 = (small[0].shape[0] - 96) // 2, (small[0].shape[1] - 128) // 2
    crops = [np.ascontiguousarray(x[r0 : r0 + 96, c0 : c0 + 128]) for x in small]
    return prepare_pair(*crops), crops


@pytest.fixture(scope="module")
def moments(pair):
    (A, B), _ = pair
    provider = SpyNetProvider(p=0.2, mc_mode="moments", sigma_floor=0.02)
    with torch.no_grad():
        return provider, provider.moments(A, B)


def test_closed_form_spread_is_the_monte_carlo_spread(pair, moments):
    """σ_MC of 300 sampled passes against ``sqrt(p / (1 - p)) dropout_unit`` at the rate the CPU
    dropout really draws (``p`` rounded to a multiple of 1/256), pixel by pixel. With 300 passes
    a sample std has a relative error of about 1/sqrt(600) = 4 %."""
    (A, B), _ = pair
    _, result = moments
    sampler = SpyNetProvider(mc_passes=10, p=0.2)
    torch.manual_seed(0)
    with torch.no_grad():
        samples = sampler.mc_samples(A, B, passes=300)  # (300, 1, 2, H, W)
    assert samples.shape == (300, 1, 2, 96, 128)
    p = 1.0 - keep_probability(0.2)
    assert p == 51 / 256
    predicted = (p / (1 - p)) ** 0.5 * result.dropout_unit
    assert float(predicted.min()) > 0
    ratio = (samples.std(0) / predicted).flatten()
    assert abs(float(ratio.median()) - 1.0) < 0.05, float(ratio.median())
    assert float(((ratio - 1).abs() < 0.2).double().mean()) > 0.99
    assert float(((ratio - 1).abs() < 0.1).double().mean()) > 0.9
    # the spread varies over the image (so the agreement is pixel by pixel, not one constant)
    assert float(result.dropout_unit.max() / result.dropout_unit.median()) > 5
    # the sampled mean is the closed-form (deterministic) flow, within its standard error
    z = (samples.mean(0) - result.flow) / (predicted / 300**0.5)
    assert float((z.abs() < 3).double().mean()) > 0.99 and float(z.abs().max()) < 6


def test_moments_flow_is_the_deterministic_flow(pair, moments):
    (A, B), crops = pair
    provider, result = moments
    with torch.no_grad():
        deterministic = SpyNetProvider(mc_passes=0).estimate(A, B).flow
        plain = provider.spynet(A, B)  # the whole network, split nowhere
    assert float(result.flow.abs().max()) > 1.0  # a real flow (disparity of the stereo pair)
    torch.testing.assert_close(result.flow, deterministic, rtol=0, atol=1e-5)
    torch.testing.assert_close(result.flow, plain, rtol=0, atol=1e-5)
    # the provider call in moments mode is the closed form, with both parts of σ
    called = provider(*crops)
    torch.testing.assert_close(called.flow, result.flow, rtol=0, atol=1e-5)
    assert called.dropout_unit is not None and called.floor is not None


def test_sigma_is_the_larger_of_the_dropout_spread_and_the_floor(pair, moments):
    (A, _), _ = pair
    provider, result = moments
    unit, floor = result.dropout_unit.double(), result.floor.double()
    expected = torch.maximum((0.2 / 0.8) ** 0.5 * unit, floor)
    torch.testing.assert_close(result.sigma.double(), expected, rtol=1e-6, atol=0)
    torch.testing.assert_close(result.floor, provider.floor(A))
    assert float(floor.min()) >= 0.02 * (1 - 1e-6)  # sigma_floor
    # both regimes occur on this image, so the max is exercised
    spread_wins = ((0.2 / 0.8) ** 0.5 * unit > floor).double().mean()
    assert 0.05 < float(spread_wins) < 0.95, float(spread_wins)
    assert result.sigma.shape == result.flow.shape == unit.shape == (1, 2, 96, 128)


def test_flow_points_recompute_sigma_at_another_rate_with_a_gradient(moments):
    _, result = moments
    points = grid_candidates(result.flow[0], result.sigma[0], stride_px=8, border_px=8,
                             dropout_unit_px=result.dropout_unit[0], floor_px=result.floor[0])
    assert len(points) == 10 * 14  # (96 - 16) / 8 rows, (128 - 16) / 8 columns
    # at the provider's rate: the provider's σ
    torch.testing.assert_close(points.at_dropout_rate(0.2).sigma_px, points.sigma_px, rtol=1e-6, atol=0)
    # at another rate: the formula, evaluated independently
    unit, floor = points.dropout_unit_px.double().numpy(), points.floor_px.double().numpy()
    for p in (0.05, 0.5):
        expected = np.maximum(np.sqrt(p / (1 - p)) * unit, floor)
        np.testing.assert_allclose(points.at_dropout_rate(p).sigma_px.double().numpy(), expected, rtol=1e-6)
    # everything else is kept
    moved = points.at_dropout_rate(0.5)
    assert moved.uv1_px is points.uv1_px and moved.flow_px is points.flow_px
    assert moved.dropout_unit_px is points.dropout_unit_px and moved.floor_px is points.floor_px

    # d σ / d p: autograd against central differences, in float64
    pts = points.to(torch.zeros((), dtype=F64))
    weights = torch.linspace(0.5, 1.5, 2 * len(pts), dtype=F64).reshape(-1, 2)

    def objective(p):
        return (pts.at_dropout_rate(p).sigma_px * weights).sum()

    p = torch.tensor(0.3, dtype=F64, requires_grad=True)
    objective(p).backward()
    eps = 1e-6
    numeric = (objective(torch.tensor(0.3 + eps, dtype=F64)) - objective(torch.tensor(0.3 - eps, dtype=F64))) / (2 * eps)
    assert float(p.grad) == pytest.approx(float(numeric), rel=1e-7)
    # closed form: d/dp sqrt(p / (1 - p)) = 1 / (2 sqrt(p) (1 - p)^1.5), on the points the spread dominates
    spread = (0.3 / 0.7) ** 0.5 * pts.dropout_unit_px
    active = spread > pts.floor_px
    assert 0 < int(active.sum()) < active.numel()
    closed = ((weights * pts.dropout_unit_px)[active]).sum() / (2 * 0.3**0.5 * 0.7**1.5)
    assert float(p.grad) == pytest.approx(float(closed), rel=1e-10)


def test_points_without_moments_cannot_change_rate():
    z = torch.zeros(3, 2)
    with pytest.raises(ValueError, match="carry no dropout moments"):
        FlowPoints(z, z, z + 1).at_dropout_rate(0.3)


def test_moments_mode_needs_the_finest_level_and_a_known_mode():
    with pytest.raises(ValueError, match=r"mc_mode='moments' needs the dropout in the finest level"):
        SpyNetProvider(mc_mode="moments", dropout_level=3)
    with pytest.raises(ValueError, match=r"mc_mode='bogus'; expected 'sample' or 'moments'"):
        SpyNetProvider(mc_mode="bogus")
    # the finest level, named by number, is accepted
    assert SpyNetProvider(mc_mode="moments", dropout_level=5, mc_passes=0).mc_mode == "moments"


def test_spynet_on_another_device_meets_no_cpu_tensor_and_gives_the_cpu_flow(pair, fake_device):
    """The provider moved to a device (``conftest.FakeDevice``, a GPU's stand-in): the images
    follow it and every pyramid level, warp, dropout moment and σ floor stays there; the
    flow and σ are the CPU's (one float32 network, to rounding)."""
    _, crops = pair
    out = {}
    for device in ("cpu", "meta"):
        provider = SpyNetProvider(p=0.2, mc_mode="moments", sigma_floor=0.02)
        if device == "meta":
            fake_device.place(provider)
        with fake_device() as mode:
            assert provider.device.type == device
            result = provider(*crops)
            assert result.flow.device.type == device and result.dropout_unit.device.type == device
            out[device] = [x.cpu() for x in (result.flow, result.sigma, result.dropout_unit)]
        assert mode.slips == {}, mode.slips
    for cpu, moved in zip(out["cpu"], out["meta"]):
        assert torch.allclose(moved, cpu, rtol=1e-4, atol=1e-4)
