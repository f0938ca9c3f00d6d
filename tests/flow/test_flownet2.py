"""FlowNet2: NVIDIA key/shape compatibility, checkpoint loading, warping and Monte Carlo dropout.

Random weights throughout (NVIDIA's checkpoints cannot be shipped); FlowNet2 is
heavy on CPU (~1 s per forward even at 64x64), so one model is shared per module
and most dropout checks run on the fusion network given the upstream features.
"""
from __future__ import annotations

import contextlib
import math

import pytest
import torch

from flowins.flow.flownet2 import (
    FlowNet2,
    FlowNet2C,
    FlowNet2Provider,
    FlowNet2S,
    brightness_error,
    channel_norm,
    load_checkpoint,
    warp,
)
from flowins.flow.flownet2.networks import FlowNetFusion
from flowins.flow.mc_dropout import ConcreteDropout, MCDropout

# Key names and shapes read off NVIDIA/flownet2-pytorch (networks/*.py, submodules.py):
# conv = Sequential(Conv2d, LeakyReLU) -> ".0."; predict_flow = bare Conv2d;
# ConvTranspose2d weights are (in, out, k, k); FlowNetS's flow upsamplers have no bias.
NVIDIA_KEYS = {
    "flownetc.conv1.0.weight": (64, 3, 7, 7),
    "flownetc.conv3.0.weight": (256, 128, 5, 5),
    "flownetc.conv_redir.0.weight": (32, 256, 1, 1),
    "flownetc.conv3_1.0.weight": (256, 473, 3, 3),  # 32 redirected + 441 correlation channels
    "flownetc.predict_flow2.weight": (2, 194, 3, 3),
    "flownetc.upsampled_flow6_to_5.bias": (2,),
    "flownets_1.conv1.0.weight": (64, 12, 7, 7),
    "flownets_2.deconv2.0.weight": (386, 64, 4, 4),
    "flownets_d.conv0.0.weight": (64, 6, 3, 3),
    "flownets_d.inter_conv5.0.weight": (512, 1026, 3, 3),
    "flownets_d.predict_flow2.weight": (2, 64, 3, 3),
    "flownetfusion.conv0.0.weight": (64, 11, 3, 3),
    "flownetfusion.deconv0.0.weight": (162, 16, 4, 4),
    "flownetfusion.inter_conv0.0.weight": (16, 82, 3, 3),
    "flownetfusion.predict_flow0.weight": (2, 16, 3, 3),
    "flownetfusion.upsampled_flow1_to_0.bias": (2,),
}
NVIDIA_ABSENT = ["flownets_1.upsampled_flow6_to_5.bias", "flownets_2.upsampled_flow3_to_2.bias"]
NVIDIA_PARAMETER_COUNT = 162_518_834  # the string in NVIDIA's models.py


@pytest.fixture(scope="module")
def provider():
    return FlowNet2Provider.untrained("FlowNet2", seed=0, dropout_option=2, p=0.2, passes=10)


@pytest.fixture(scope="module")
def model(provider):
    return provider.model


@pytest.fixture(scope="module")
def pair():
    torch.manual_seed(5)
    return torch.rand(1, 3, 2, 64, 64) * 255.0


@pytest.fixture(scope="module")
def fusion_input(model, pair):
    with torch.no_grad():
        return model.fusion_input(pair)


class FixedMasks(torch.nn.Module):
    """Test dropout: pre-drawn masks, one per pass of a ``batch``-sized input, used in call
    order whatever the chunking, so two paths that consume the passes in the same order
    (pass-major, as :func:`~flowins.flow.mc_dropout.mc_samples` repeats) see the same masks."""

    def __init__(self, passes: int, batch: int = 1, p: float = 0.3, seed: int = 0):
        super().__init__()
        self.passes, self.batch, self.p, self.seed = passes, batch, p, seed
        self.masks, self.used, self.seen_shapes = None, 0, []

    def forward(self, x):
        self.seen_shapes.append(tuple(x.shape))
        if self.masks is None:
            g = torch.Generator().manual_seed(self.seed)
            self.masks = (torch.rand((self.passes * self.batch, *x.shape[1:]), generator=g) >= self.p).to(x.dtype)
        n = x.shape[0]
        assert self.used + n <= self.masks.shape[0], "more passes than masks"
        mask = self.masks[self.used : self.used + n]
        self.used += n
        return x * mask / (1 - self.p)


# ------------------------------------------------------------------ architecture
def test_known_nvidia_keys_and_shapes(model):
    sd = model.state_dict()
    for key, shape in NVIDIA_KEYS.items():
        assert key in sd, key
        assert tuple(sd[key].shape) == shape, key
    for key in NVIDIA_ABSENT:
        assert key not in sd
    assert sum(p.numel() for p in model.parameters()) == NVIDIA_PARAMETER_COUNT


def _save_nvidia(path, sd, prefix=""):
    torch.save({"epoch": 0, "arch": "FlowNet2", "state_dict": {prefix + k: v for k, v in sd.items()}, "best_EPE": 1.5}, path)


def test_checkpoint_roundtrip_strict(model, tmp_path):
    sd = {k: v.clone() for k, v in model.state_dict().items()}
    sd["flownetfusion.predict_flow0.bias"] = torch.tensor([1.25, -0.5])
    path = tmp_path / "FlowNet2_checkpoint.pth.tar"
    _save_nvidia(path, sd)
    before = model.flownetfusion.predict_flow0.bias.detach().clone()
    meta = load_checkpoint(model, path)
    assert meta["best_EPE"] == 1.5 and meta["epoch"] == 0
    torch.testing.assert_close(model.flownetfusion.predict_flow0.bias.detach(), torch.tensor([1.25, -0.5]))
    with torch.no_grad():
        model.flownetfusion.predict_flow0.bias.copy_(before)


def test_checkpoint_with_dataparallel_prefix(tmp_path):
    torch.manual_seed(1)
    src, dst = FlowNet2S(), FlowNet2S()
    path = tmp_path / "FlowNet2-S_checkpoint.pth.tar"
    _save_nvidia(path, src.state_dict(), prefix="module.")
    dst.mc_dropout = ConcreteDropout(0.2)  # flowins-only parameter (mc_dropout.p_logit): allowed
    load_checkpoint(dst, path)
    for key, value in src.state_dict().items():
        assert torch.equal(value, dst.state_dict()[key]), key
    # without the flowins extra, the file is an exact strict match for plain load_state_dict too
    FlowNet2S().load_state_dict({k[len("module."):]: v for k, v in torch.load(path)["state_dict"].items()}, strict=True)


def test_wrong_variant_is_rejected_with_a_list(model, tmp_path):
    path = tmp_path / "FlowNet2-C_checkpoint.pth.tar"
    _save_nvidia(path, FlowNet2C().state_dict())
    with pytest.raises(ValueError) as info:
        load_checkpoint(model, path)
    msg = str(info.value)
    assert str(path) in msg and "FlowNet2" in msg and "FlowNet2C" in msg
    assert "missing keys" in msg and "flownetc.conv1.0.weight" in msg
    assert "unexpected keys" in msg and "conv_redir.0.weight" in msg


def test_shape_mismatch_is_listed(tmp_path):
    sd = FlowNet2S().state_dict()
    sd["conv1.0.weight"] = torch.zeros(64, 12, 7, 7)  # FlowNetS-in-FlowNet2 input, not FlowNet2S's 6
    path = tmp_path / "bad.pth.tar"
    _save_nvidia(path, sd)
    with pytest.raises(ValueError, match=r"shape mismatches: conv1\.0\.weight: checkpoint \(64, 12, 7, 7\) vs model \(64, 6, 7, 7\)"):
        load_checkpoint(FlowNet2S(), path)


def test_no_checkpoint_explains_licence():
    with pytest.raises(ValueError, match=r"research.*flow\.checkpoint=/path/FlowNet2_checkpoint\.pth\.tar"):
        FlowNet2Provider(None)


# ------------------------------------------------------------------ warping
def _resample2d_loop(image, flow):
    """NVIDIA's Resample2d kernel: floor/alpha from the unclamped position, indices clamped."""
    B, C, H, W = image.shape
    out = torch.zeros_like(image)
    for b in range(B):
        for y in range(H):
            for x in range(W):
                xf, yf = x + float(flow[b, 0, y, x]), y + float(flow[b, 1, y, x])
                alpha, beta = xf - math.floor(xf), yf - math.floor(yf)
                xl, xr = min(max(math.floor(xf), 0), W - 1), min(max(math.floor(xf) + 1, 0), W - 1)
                yt, yb = min(max(math.floor(yf), 0), H - 1), min(max(math.floor(yf) + 1, 0), H - 1)
                out[b, :, y, x] = (
                    (1 - alpha) * (1 - beta) * image[b, :, yt, xl]
                    + alpha * (1 - beta) * image[b, :, yt, xr]
                    + (1 - alpha) * beta * image[b, :, yb, xl]
                    + alpha * beta * image[b, :, yb, xr]
                )
    return out


def test_warp_matches_resample2d_kernel():
    torch.manual_seed(2)
    image = torch.rand(2, 3, 6, 7, dtype=torch.float64)
    flow = torch.randn(2, 2, 6, 7, dtype=torch.float64) * 4  # many samples fall outside
    torch.testing.assert_close(warp(image, flow), _resample2d_loop(image, flow))


def test_channel_norm_and_brightness_error():
    x = torch.zeros(1, 3, 2, 2, requires_grad=True)
    channel_norm(x).sum().backward()
    assert torch.isfinite(x.grad).all()
    img = torch.rand(1, 3, 5, 5)
    flow = torch.zeros(1, 2, 5, 5)
    assert torch.equal(brightness_error(img, img, flow), torch.zeros(1, 1, 5, 5))
    torch.testing.assert_close(channel_norm(torch.tensor([[[[3.0]], [[4.0]]]])), torch.tensor([[[[5.0]]]]))


# ------------------------------------------------------------------ Monte Carlo dropout
@pytest.mark.parametrize("option", [1, 2])
def test_upstream_runs_once(model, pair, option, monkeypatch):
    monkeypatch.setattr(model, "dropout_option", option)
    fusion = model.flownetfusion
    calls = {"flownetc": 0, "fusion.conv2_1": 0, "head passes": 0}
    hooks = [
        model.flownetc.register_forward_hook(lambda *a: calls.__setitem__("flownetc", calls["flownetc"] + 1)),
        fusion.conv2_1.register_forward_hook(
            lambda *a: calls.__setitem__("fusion.conv2_1", calls["fusion.conv2_1"] + 1)
        ),
    ]
    for name in ("head", "head_strips"):  # the head runs whole, or strip by strip (option #2, one pass at a time)
        method = getattr(fusion, name)

        def counted(*args, method=method, **kwargs):
            calls["head passes"] += 1
            return method(*args, **kwargs)

        monkeypatch.setattr(fusion, name, counted)
    try:
        with torch.no_grad():
            samples = model.mc_samples(pair, 10)
    finally:
        for h in hooks:
            h.remove()
    assert samples.shape == (10, 1, 2, 64, 64)
    assert calls["flownetc"] == 1 and calls["fusion.conv2_1"] == 1  # upstream of both options: once
    chunk = model.chunk or 10
    assert calls["head passes"] == -(-10 // chunk)  # the head ran once per chunk of passes
    assert (samples.std(0) > 0).float().mean() > 0.99


def test_option2_spread_and_small_p_limit(model, fusion_input):
    fusion = model.flownetfusion
    torch.manual_seed(0)
    with torch.no_grad():
        det = fusion(fusion_input)
        wide = fusion.mc_samples(fusion_input, dropout=torch.nn.Dropout(0.2).train(), option=2, passes=10)
        tiny = fusion.mc_samples(fusion_input, dropout=torch.nn.Dropout(1e-6).train(), option=2, passes=10)
    scale = det.abs().mean()
    assert (wide.std(0) > 0).all()
    assert (wide.mean(0) - det).abs().mean() < 0.5 * wide.std(0).mean() + 0.1 * scale
    assert (tiny.mean(0) - det).abs().mean() < 1e-3 * scale  # ~3 of 3.4M elements dropped
    assert tiny.std(0).mean() < 1e-2 * wide.std(0).mean()


@pytest.mark.parametrize("option", [1, 2])
@pytest.mark.parametrize("chunk", [None, 3])
def test_run_once_equals_full_forwards_with_same_masks_fusion(model, fusion_input, option, chunk):
    fusion = model.flownetfusion
    once_masks, naive_masks = FixedMasks(10), FixedMasks(10)
    with torch.no_grad():
        once = fusion.mc_samples(fusion_input, dropout=once_masks, option=option, passes=10, chunk=chunk)
        naive = torch.stack([fusion(fusion_input, dropout=naive_masks, option=option) for _ in range(10)])
    torch.testing.assert_close(once, naive, rtol=1e-4, atol=1e-4 * float(naive.abs().max()))
    # where the dropout acts (paper Fig. 3): #2 the 82-channel concat0; #1 out_conv1 + out_conv2
    H, W = fusion_input.shape[-2:]
    per_pass = 82 * H * W if option == 2 else 128 * (H // 2) * (W // 2) + 128 * (H // 4) * (W // 4)
    assert math.prod(naive_masks.seen_shapes[0][1:]) == per_pass


@pytest.mark.parametrize("batch_norm", [False, True])
@pytest.mark.parametrize("height, rows", [(13, 4), (8, 32), (9, 1), (12, 2)])
def test_head_strips_equal_the_whole_head(batch_norm, height, rows):
    """Strip by strip (halo of two rows, zero padding only at the image's edges) = the head
    on the whole masked tensor, with and without BatchNorm (eval)."""
    torch.manual_seed(9)
    fusion = FlowNetFusion(batch_norm=batch_norm).double().eval()
    if batch_norm:  # non-trivial running statistics
        bn = fusion.inter_conv0[1]
        bn.running_mean.uniform_(-1, 1), bn.running_var.uniform_(0.5, 2), bn.weight.data.uniform_(0.5, 2)
        bn.bias.data.uniform_(-1, 1)
    scaled = torch.randn(2, 82, height, 7, dtype=torch.float64)
    keep = torch.rand(2, 82, height, 7) > 0.3
    with torch.no_grad():
        expected = fusion.head(scaled * keep)
        got = fusion.head_strips(scaled, keep, rows=rows)
    torch.testing.assert_close(got, expected, rtol=1e-12, atol=1e-12)


def test_strip_passes_equal_full_forwards_with_seeded_dropout(model, fusion_input):
    """The default path (MCDropout, one pass at a time: strips, channels-last masks) draws
    the masks a full forward of the fusion network draws, from the same seed."""
    fusion = model.flownetfusion
    with torch.no_grad():
        once = fusion.mc_samples(fusion_input, dropout=MCDropout(0.3, seed=4), option=2, passes=4, chunk=1)
        layer = MCDropout(0.3, seed=4)
        naive = torch.stack([fusion(fusion_input, dropout=layer, option=2) for _ in range(4)])
    torch.testing.assert_close(once, naive, rtol=1e-4, atol=1e-4 * float(naive.abs().max()))
    assert (once[0] - once[1]).abs().max() > 1e-3 * float(naive.abs().max())


@contextlib.contextmanager
def submodule_replaced(module: torch.nn.Module, name: str, replacement: torch.nn.Module):
    """``module.<name>`` is ``replacement`` inside the block and the original after it.

    Not ``monkeypatch.setattr``: a submodule lives in ``module._modules``, not in the
    instance ``__dict__``, and pytest >= 9.2 undoes such a patch by deleting the
    attribute, which removes the submodule itself."""
    original = getattr(module, name)
    setattr(module, name, replacement)
    try:
        yield
    finally:
        setattr(module, name, original)


def test_run_once_equals_full_forwards_flownet2(model, pair):
    passes = 3
    original = model.mc_dropout
    with torch.no_grad():
        with submodule_replaced(model, "mc_dropout", FixedMasks(passes, seed=7)):
            once = model.mc_samples(pair, passes)
        with submodule_replaced(model, "mc_dropout", FixedMasks(passes, seed=7)):
            naive = model.mc_samples_naive(pair, passes)
    torch.testing.assert_close(once, naive, rtol=1e-4, atol=1e-4 * float(naive.abs().max()))
    assert model.mc_dropout is original  # the shared model is left as it was


# ------------------------------------------------------------------ provider
def test_provider_odd_size_and_sigma(provider):
    torch.manual_seed(3)
    image1 = (torch.rand(100, 130, 3) * 255).to(torch.uint8)
    image2 = torch.roll(image1, 2, dims=1)
    result = provider(image1, image2)
    assert result.flow.shape == (1, 2, 100, 130) and result.sigma.shape == (1, 2, 100, 130)
    assert result.flow.dtype == torch.float32 and torch.isfinite(result.flow).all()
    assert (result.sigma >= provider.sigma_floor).all() and (result.sigma > provider.sigma_floor).float().mean() > 0.5


def test_provider_without_dropout_reports_the_floor():
    provider = FlowNet2Provider.untrained("FlowNet2S", dropout_option=None, sigma_floor=0.7)
    result = provider(torch.rand(3, 40, 50), torch.rand(3, 40, 50))
    assert result.flow.shape == (1, 2, 40, 50)
    assert torch.equal(result.sigma, torch.full_like(result.flow, 0.7))
    with pytest.raises(ValueError, match="fusion network"):
        FlowNet2Provider.untrained("FlowNet2S", dropout_option=2)


def test_provider_rejects_bad_inputs(provider):
    with pytest.raises(ValueError, match="differ in shape"):
        provider(torch.rand(3, 64, 64), torch.rand(3, 64, 72))
    with pytest.raises(ValueError, match="dtype"):
        provider(torch.zeros(64, 64, 3, dtype=torch.int32), torch.zeros(64, 64, 3, dtype=torch.int32))


def test_fusion_rejects_unknown_option():
    with pytest.raises(ValueError, match="expected one of"):
        FlowNet2(dropout_option=3)
    with pytest.raises(ValueError, match="needs a dropout module"):
        FlowNetFusion()(torch.zeros(1, 11, 8, 8), option=2)
