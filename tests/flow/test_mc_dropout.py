"""Monte Carlo dropout helpers: the mask's rate, unbiasedness, run-once sampling, concrete dropout."""
import math

import pytest
import torch

from flowins.flow.mc_dropout import ConcreteDropout, MCDropout, drop_mask, keep_like, keep_mask, mc_flow, mc_samples


@pytest.mark.parametrize("p", [0.05, 0.2, 0.5])
def test_keep_mask_has_the_stated_rate_and_no_pattern(p):
    torch.manual_seed(0)
    mask, keep = keep_mask((400, 1000), p)
    assert mask.dtype == torch.bool and mask.shape == (400, 1000)
    assert abs(keep - (1 - p)) <= 0.5 / 256 + 1e-12  # p rounded to 1/256
    n = mask.numel()
    rate = float(mask.double().mean())
    assert abs(rate - keep) < 5 * math.sqrt(keep * (1 - keep) / n)
    # every byte position of the 64-bit draws is used alike (the top byte, 7-bit, is not)
    per_position = mask.reshape(-1)[: (n // 7) * 7].view(-1, 7).double().mean(0)
    assert float((per_position - keep).abs().max()) < 6 * math.sqrt(keep * (1 - keep) / (n / 7))
    # neighbouring elements are independent
    flat = mask.reshape(-1).double()
    corr = float(torch.corrcoef(torch.stack((flat[:-1], flat[1:])))[0, 1])
    assert abs(corr) < 0.01


def test_keep_like_follows_the_memory_order_of_its_input():
    """Byte k of the mask stream goes to element k of the input's memory: a contiguous
    input gets exactly ``~drop_mask``, a channels-last one the same stream in NHWC order."""
    x = torch.zeros(2, 5, 6, 7)
    g = torch.Generator().manual_seed(3)
    state = g.get_state()
    keep = keep_like(x, 0.3, generator=g)
    g.set_state(state)
    assert torch.equal(keep, ~drop_mask(x.shape, 0.3, generator=g))
    cl = x.contiguous(memory_format=torch.channels_last)
    g.set_state(state)
    keep_cl = keep_like(cl, 0.3, generator=g)
    assert keep_cl.stride() == cl.stride()
    g.set_state(state)
    assert torch.equal(keep_cl.permute(0, 2, 3, 1), ~drop_mask((2, 6, 7, 5), 0.3, generator=g))
    strided = torch.zeros(5, 8)[:, ::2]  # not dense: the mask in logical order
    g.set_state(state)
    keep_s = keep_like(strided, 0.3, generator=g)
    g.set_state(state)
    assert torch.equal(keep_s, ~drop_mask((5, 4), 0.3, generator=g))


def test_run_once_passes_equal_dropout_then_head_with_the_same_generator():
    """One buffer for the dropped features of every pass (no autograd), or a ``masked_head``
    that applies the mask itself: each pass still equals ``head(MCDropout(x))``."""
    x = torch.randn(2, 3, 6, 5)
    w = torch.randn(2, 3, 3, 3)

    def head(f):
        return torch.nn.functional.conv2d(f, w, padding=1)

    def masked_head(scaled, keep):
        return head(scaled * keep)

    layer = MCDropout(0.3, seed=11)
    naive = torch.stack([head(layer(x)) for _ in range(5)])
    with torch.no_grad():
        once = mc_samples(head, x, MCDropout(0.3, seed=11), 5, chunk=1)
        masked = mc_samples(head, x, MCDropout(0.3, seed=11), 5, chunk=1, masked_head=masked_head)
    tracked = mc_samples(head, x, MCDropout(0.3, seed=11), 5, chunk=1)  # autograd on: no buffer
    for got in (once, masked, tracked):
        torch.testing.assert_close(got, naive, rtol=0, atol=1e-6)
    assert (naive[0] - naive[1]).abs().max() > 0.1  # the passes differ (no buffer aliasing)


def test_mc_dropout_is_unbiased_and_active_in_eval_mode():
    torch.manual_seed(1)
    drop = MCDropout(0.3).eval()
    x = torch.full((200, 500), 2.0)
    y = drop(x)
    zero_rate = float((y == 0).double().mean())
    assert abs(zero_rate - 77 / 256) < 0.01  # round(256 * 0.3) = 77
    assert abs(float(y.mean()) - 2.0) < 0.02
    assert torch.equal(MCDropout(0.0)(x), x)
    with pytest.raises(ValueError, match="0 <= p < 1"):
        MCDropout(1.0)


@pytest.mark.parametrize("layer", [MCDropout, ConcreteDropout])
def test_seeded_dropout_repeats_its_masks_and_leaves_the_global_generator_alone(layer):
    x = torch.ones(64, 300)
    torch.manual_seed(123)
    before = torch.get_rng_state()
    a, b = layer(0.3, seed=7), layer(0.3, seed=7)
    first = [a(x) for _ in range(3)]
    assert torch.equal(torch.get_rng_state(), before)  # the layer draws from its own generator
    assert all(torch.equal(u, v) for u, v in zip(first, [b(x) for _ in range(3)]))  # same seed, same masks
    assert not torch.equal(first[0], first[1])  # successive calls still differ
    assert not torch.equal(first[0], layer(0.3, seed=8)(x))
    unseeded = layer(0.3)
    unseeded(x)
    assert not torch.equal(torch.get_rng_state(), before)  # None: torch's global generator


def test_mc_samples_runs_the_head_on_repeated_features_with_context():
    torch.manual_seed(2)
    features = torch.randn(3, 4, 5)
    context = torch.randn(3, 2, 5)
    calls = []

    def head(x, c):
        calls.append(x.shape[0])
        return x.sum(1, keepdim=True) + c[:, :1]

    samples = mc_samples(head, features, MCDropout(0.0), passes=6, context=(context,), chunk=4)
    assert samples.shape == (6, 3, 1, 5) and calls == [12, 6]
    expected = features.sum(1, keepdim=True) + context[:, :1]
    torch.testing.assert_close(samples, expected.expand(6, -1, -1, -1))
    mean, std, _ = mc_flow(head, features, MCDropout(0.5), passes=50, context=(context,))
    assert float(std.min()) > 0  # dropout makes the passes differ


def test_concrete_dropout_rate_is_differentiable():
    torch.manual_seed(3)
    drop = ConcreteDropout(0.2, temperature=0.1)
    assert abs(float(drop.p.detach()) - 0.2) < 1e-6
    x = torch.ones(1000)
    loss = drop(x).var()
    loss.backward()
    assert drop.p_logit.grad is not None and torch.isfinite(drop.p_logit.grad) and float(drop.p_logit.grad) != 0.0
