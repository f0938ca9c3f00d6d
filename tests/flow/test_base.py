"""Provider contract helpers: the Monte Carlo statistics against numpy."""
import numpy as np
import pytest
import torch

from flowins.flow.base import mc_statistics


def test_mc_statistics_equal_numpy_mean_and_unbiased_std():
    g = torch.Generator().manual_seed(0)
    samples = 3.0 + 0.01 * torch.randn(10, 2, 2, 5, 7, generator=g, dtype=torch.float64)
    mean, std = mc_statistics(samples)
    ref = samples.numpy()
    np.testing.assert_allclose(mean.numpy(), ref.mean(0), rtol=1e-14)
    np.testing.assert_allclose(std.numpy(), ref.std(0, ddof=1), rtol=1e-10)
    _, floored = mc_statistics(samples, floor=0.012)
    np.testing.assert_allclose(floored.numpy(), np.maximum(ref.std(0, ddof=1), 0.012), rtol=1e-10)


def test_mc_statistics_float32_keeps_small_spreads_on_large_means():
    """Two passes (mean, then deviations): no cancellation of a 0.01 px spread on a 100 px flow."""
    g = torch.Generator().manual_seed(1)
    samples = (100.0 + 0.01 * torch.randn(10, 1, 2, 30, 40, generator=g, dtype=torch.float64))
    _, std = mc_statistics(samples.float())
    ref = samples.numpy().std(0, ddof=1)
    assert np.abs(std.double().numpy() - ref).max() < 1e-3 * ref.mean()


def test_mc_statistics_need_two_passes():
    with pytest.raises(ValueError, match="at least 2 passes"):
        mc_statistics(torch.zeros(1, 3))
