"""The GNSS floor's oracle against closed forms: running means, generalised least squares."""
import math

import pytest
import torch

from flowins.evaluation.gnss_floor import (
    estimate_correlation_s,
    gnss_floor,
    offset_estimates,
)
from flowins.geometry import quaternion

F64 = torch.float64


def gls_prefix(y: torch.Tensor, s: torch.Tensor, t: torch.Tensor, tau: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Naive reference: for each prefix 0..k, the GLS mean ``1ᵀΣ⁻¹y / 1ᵀΣ⁻¹1`` and its σ,
    with the explicit covariance ``Σ_ij = s_i s_j exp(-|t_i - t_j| / τ)`` (one axis)."""
    means, sigmas = [], []
    for k in range(1, y.shape[0] + 1):
        dt = (t[:k, None] - t[None, :k]).abs()
        corr = torch.exp(-dt / tau) if tau > 0 else torch.eye(k, dtype=F64)
        cov = s[:k, None] * s[None, :k] * corr
        ones = torch.ones(k, dtype=F64)
        w = torch.linalg.solve(cov, ones)
        means.append((w @ y[:k]) / (w @ ones))
        sigmas.append((w @ ones) ** -0.5)
    return torch.stack(means), torch.stack(sigmas)


def gauss_markov(n: int, d: int, tau: float, gen: torch.Generator, dt: float = 1.0) -> torch.Tensor:
    """``(n, d)`` unit-variance first-order Gauss-Markov samples ``dt`` apart."""
    phi = math.exp(-dt / tau)
    w = torch.randn(n, d, generator=gen, dtype=F64) * math.sqrt(1 - phi**2)
    z = torch.zeros(n, d, dtype=F64)
    z[0] = torch.randn(d, generator=gen, dtype=F64)
    for k in range(1, n):
        z[k] = phi * z[k - 1] + w[k]
    return z


def test_white_constant_sigma_is_the_running_mean():
    gen = torch.Generator().manual_seed(0)
    y = torch.randn(40, 3, generator=gen, dtype=F64) * 7 + 3
    s = torch.full_like(y, 7.0)
    t = torch.arange(40, dtype=F64)
    est = offset_estimates(y, s, t, correlation_s=0.0, gate=None)
    running = torch.cumsum(y, 0) / torch.arange(1, 41, dtype=F64).unsqueeze(-1)
    torch.testing.assert_close(est.offset_m, running, rtol=0, atol=1e-10)
    torch.testing.assert_close(est.offset_sigma_m[:, 0], 7.0 / torch.arange(1, 41, dtype=F64).sqrt(), rtol=1e-10, atol=0)
    assert bool(est.used.all())


@pytest.mark.parametrize("tau", [0.0, 3.0, 10.0])
def test_matches_generalised_least_squares(tau):
    gen = torch.Generator().manual_seed(1)
    G = 30
    t = torch.cumsum(0.5 + torch.rand(G, generator=gen, dtype=F64), 0)  # uneven spacing
    s = 3.0 + 20.0 * torch.rand(G, 3, generator=gen, dtype=F64)
    y = torch.randn(G, 3, generator=gen, dtype=F64) * s + torch.tensor([5.0, -2.0, 1.0], dtype=F64)
    est = offset_estimates(y, s, t, correlation_s=tau, gate=None)
    for axis in range(3):
        mean, sigma = gls_prefix(y[:, axis], s[:, axis], t, tau)
        torch.testing.assert_close(est.offset_m[:, axis], mean, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(est.offset_sigma_m[:, axis], sigma, rtol=1e-7, atol=1e-9)


def test_gate_leaves_out_an_outlier_exactly():
    gen = torch.Generator().manual_seed(2)
    G, tau = 25, 5.0
    t = torch.arange(G, dtype=F64)
    s = torch.full((G, 3), 4.0, dtype=F64)
    y = gauss_markov(G, 3, tau, gen) * 4.0
    y[12] += torch.tensor([300.0, -200.0, 0.0], dtype=F64)
    est = offset_estimates(y, s, t, correlation_s=tau)
    assert est.used.tolist() == [i != 12 for i in range(G)]
    keep = torch.arange(G) != 12
    mean, _ = gls_prefix(y[keep, 0], s[keep, 0], t[keep], tau)
    torch.testing.assert_close(est.offset_m[keep, 0], mean, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(est.offset_m[12], est.offset_m[11])  # the outlier changes nothing


def test_correlation_time_estimate():
    gen = torch.Generator().manual_seed(3)
    n, tau = 20000, 10.0
    z = gauss_markov(n, 2, tau, gen)
    t = torch.arange(n, dtype=F64)
    assert estimate_correlation_s(z, t) == pytest.approx(tau, rel=0.1)
    # multipath-like outliers (3 % of the samples, 8 sigma) are left out of the estimate
    jumps = torch.rand(n, generator=gen, dtype=F64) < 0.03
    assert estimate_correlation_s(z + 8.0 * jumps.unsqueeze(-1), t) == pytest.approx(tau, rel=0.1)
    white = torch.randn(n, 2, generator=gen, dtype=F64)
    assert estimate_correlation_s(white, t) < 0.3


def walk(n: int = 600) -> tuple[torch.Tensor, torch.Tensor]:
    t = torch.linspace(0.0, 60.0, n, dtype=F64)
    pos = torch.stack((10 * torch.cos(t / 10), 15 * torch.sin(t / 8), 0.1 * t), -1)
    return t, pos


def test_floor_is_zero_for_errorless_or_constant_fixes_in_another_frame():
    t, truth = walk()
    R = quaternion.to_matrix(quaternion.from_rotation_vector(torch.tensor([0.1, -0.2, 2.0], dtype=F64)))
    fix_t = t[::10]
    fixes = truth[::10] @ R.T + torch.tensor([100.0, -50.0, 7.0], dtype=F64)
    sigma = torch.full_like(fixes, 5.0)
    for offset in (0.0, 12.0):  # a constant error is a change of frame: the oracle pays nothing
        floor = gnss_floor(fix_t, fixes + offset, sigma, t, truth, correlation_s=10.0)
        assert floor.rmse_m < 1e-8 and floor.horizontal_rmse_m < 1e-8
        assert floor.fixes_used == floor.fixes == fix_t.numel()


def test_floor_does_not_depend_on_the_frame_and_grows_with_the_errors():
    t, truth = walk()
    gen = torch.Generator().manual_seed(4)
    fix_t = t[::10]
    noise = torch.randn(fix_t.numel(), 3, generator=gen, dtype=F64)
    sigma = torch.full((fix_t.numel(), 3), 3.0, dtype=F64)
    base = gnss_floor(fix_t, truth[::10] + 3.0 * noise, sigma, t, truth, correlation_s=0.0)
    R = quaternion.to_matrix(quaternion.from_rotation_vector(torch.tensor([0.0, 0.0, 1.0], dtype=F64)))
    moved = gnss_floor(fix_t, (truth[::10] + 3.0 * noise) @ R.T + 40.0, sigma, t, truth, correlation_s=0.0)
    assert moved.rmse_m == pytest.approx(base.rmse_m, rel=1e-6)
    bigger = gnss_floor(fix_t, truth[::10] + 6.0 * noise, 2 * sigma, t, truth, correlation_s=0.0)
    # the offset estimates are linear in the errors; the two rigid alignments (truth to
    # fixes, track to truth) are not, but nearly so for errors this small against the walk
    assert bigger.rmse_m == pytest.approx(2 * base.rmse_m, rel=1e-2)
    assert base.rmse_m > 0.1


def test_bad_input_is_named():
    t = torch.arange(5, dtype=F64)
    y = torch.zeros(5, 3, dtype=F64)
    s = torch.ones(5, 3, dtype=F64)
    s[3, 1] = 0.0
    with pytest.raises(ValueError, match="row 3"):
        offset_estimates(y, s, t, correlation_s=1.0)
    with pytest.raises(ValueError, match="strictly increasing; row 2"):
        offset_estimates(y, torch.ones(5, 3, dtype=F64), torch.tensor([0.0, 1.0, 1.0, 2.0, 3.0], dtype=F64), correlation_s=1.0)
    with pytest.raises(ValueError, match="correlation_s"):
        offset_estimates(y, torch.ones(5, 3, dtype=F64), t, correlation_s=-1.0)


def test_a_bad_sigma_is_named_by_the_callers_row():
    t, truth = walk()
    fix_t = torch.cat((torch.tensor([-5.0], dtype=F64), t[::10]))  # the first fix is before the truth
    fixes = torch.cat((truth[:1], truth[::10]))
    sigma = torch.ones_like(fixes)
    sigma[4, 2] = -1.0
    with pytest.raises(ValueError, match="fix_sigma_m must be > 0; row 4"):
        gnss_floor(fix_t, fixes, sigma, t, truth)
