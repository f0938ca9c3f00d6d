"""Mechanization against finite differences, closed forms and an exactly known walk (float64)."""
from __future__ import annotations

import pytest
import torch

from flowins.data.synthetic import Walk, WalkConfig, sample_times
from flowins.filter.ekf import dynamics_jacobians
from flowins.filter.propagation import propagate_mean
from flowins.geometry import quaternion as quat
from flowins.ins.jacobians import mechanization_jacobians
from flowins.ins.mechanization import STANDARD_GRAVITY_MPS2, ProcessNoise, mechanize
from flowins.state import NOISE, NOISE_DIM, STATE, STATE_DIM, make_state, split

F64 = torch.float64
G0 = STANDARD_GRAVITY_MPS2
SCHEMES = ("midpoint", "paper")


def random_case(seed: int, *batch: int, zero_rotation: bool = False, dt_s: float | None = None):
    """A generic state (non-unit quaternions, biases, scale ≠ 1) and IMU sample."""
    g = torch.Generator().manual_seed(seed)

    def randn(*shape):
        return torch.randn(*batch, *shape, generator=g, dtype=F64)

    q = randn(4)
    q = 1.3 * q / q.norm(dim=-1, keepdim=True)
    x = make_state(
        p=randn(3) * 5.0,
        v=randn(3),
        q=q,
        b_a=0.1 * randn(3),
        b_w=0.05 * randn(3),
        T_a=1.0 + 0.05 * randn(3),
        p_prev=randn(3),
        q_prev=randn(4),
    )
    acc = randn(3) * 2.0 + torch.tensor([0.0, 0.0, G0], dtype=F64)
    gyro = split(x).b_w.clone() if zero_rotation else randn(3)
    if dt_s is None:
        dt = 0.005 + 0.02 * torch.rand(batch, generator=g, dtype=F64)
    else:
        dt = torch.full(batch, dt_s, dtype=F64)
    return x, acc, gyro, dt


def central_differences(f, x: torch.Tensor, h: float = 1e-6) -> torch.Tensor:
    """``∂f/∂x`` ``(m, n)`` of ``f: (n,) -> (m,)`` by central differences."""
    cols = []
    for i in range(x.shape[-1]):
        e = torch.zeros_like(x)
        e[i] = h
        cols.append((f(x + e) - f(x - e)) / (2.0 * h))
    return torch.stack(cols, dim=-1)


def step(scheme):
    def f(x, eps, acc, gyro, dt):
        return mechanize(x, eps, acc, gyro, dt, G0, scheme)

    return f


# ------------------------------------------------------------------ Jacobians


@pytest.mark.parametrize("scheme", SCHEMES)
@pytest.mark.parametrize(
    "case", ["generic", "zero_rotation", "zero_dt"], ids=["generic", "zero_rotation", "zero_dt"]
)
def test_autodiff_jacobians_match_finite_differences(scheme, case):
    x, acc, gyro, dt = random_case(
        {"generic": 1, "zero_rotation": 2, "zero_dt": 3}[case],
        zero_rotation=case == "zero_rotation",
        dt_s=0.0 if case == "zero_dt" else None,
    )
    f = step(scheme)
    F_x, F_eps = dynamics_jacobians(f, x, NOISE_DIM, acc, gyro, dt)
    assert F_x.shape == (STATE_DIM, STATE_DIM) and F_eps.shape == (STATE_DIM, NOISE_DIM)
    zeros = x.new_zeros(NOISE_DIM)
    fd_x = central_differences(lambda xx: f(xx, zeros, acc, gyro, dt), x)
    fd_eps = central_differences(lambda e: f(x, e, acc, gyro, dt), zeros)
    torch.testing.assert_close(F_x, fd_x, rtol=0, atol=1e-7)
    torch.testing.assert_close(F_eps, fd_eps, rtol=0, atol=1e-7)
    if case == "zero_dt":
        # Δt = 0 is the identity map; only the random walks still enter
        torch.testing.assert_close(f(x, zeros, acc, gyro, dt), x, rtol=0, atol=0)
        torch.testing.assert_close(F_x, torch.eye(STATE_DIM, dtype=F64), rtol=0, atol=0)
        expected = torch.zeros(STATE_DIM, NOISE_DIM, dtype=F64)
        for name in ("b_a", "b_w", "T_a"):
            expected[STATE.slice(name), NOISE.slice(name)] = torch.eye(3, dtype=F64)
        torch.testing.assert_close(F_eps, expected, rtol=0, atol=0)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_analytic_jacobians_match_autodiff(scheme):
    x, acc, gyro, dt = random_case(4, 16)
    gyro = gyro.clone()
    b_w = split(x).b_w
    gyro[:4] = b_w[:4]  # zero rotation rows
    gyro[4] = b_w[4] + torch.tensor([1e-3, 0.0, 0.0], dtype=F64) / dt[4]  # |θ| = 1e-3, the series switch
    gyro[5] = b_w[5] + torch.tensor([0.0, 0.9e-3, 0.0], dtype=F64) / dt[5]  # just below it
    dt = dt.clone()
    dt[6] = 0.0
    F_ad, G_ad = dynamics_jacobians(step(scheme), x, NOISE_DIM, acc, gyro, dt)
    F, G = mechanization_jacobians(x, acc, gyro, dt, scheme)
    assert F.shape == (16, STATE_DIM, STATE_DIM) and G.shape == (16, STATE_DIM, NOISE_DIM)
    torch.testing.assert_close(F, F_ad, rtol=0, atol=1e-9)
    torch.testing.assert_close(G, G_ad, rtol=0, atol=1e-9)


def test_analytic_jacobians_take_any_batch_shape():
    x, acc, gyro, dt = random_case(5, 3, 2)
    F, G = mechanization_jacobians(x, acc, gyro, dt, "midpoint")
    assert F.shape == (3, 2, STATE_DIM, STATE_DIM) and G.shape == (3, 2, STATE_DIM, NOISE_DIM)
    F1, G1 = mechanization_jacobians(x[2, 1], acc[2, 1], gyro[2, 1], dt[2, 1], "midpoint")
    torch.testing.assert_close(F[2, 1], F1, rtol=0, atol=1e-15)
    torch.testing.assert_close(G[2, 1], G1, rtol=0, atol=1e-15)


# ------------------------------------------------------------------ mean propagation


@pytest.mark.parametrize("scheme", SCHEMES)
def test_propagate_mean_equals_sequential_steps(scheme):
    K = 257
    g = torch.Generator().manual_seed(6)
    x0, _, _, _ = random_case(7)
    acc = 3.0 * torch.randn(K, 3, generator=g, dtype=F64) + torch.tensor([0.0, 0.0, G0], dtype=F64)
    gyro = 2.0 * torch.randn(K, 3, generator=g, dtype=F64)
    gyro[10:20] = split(x0).b_w  # a stretch without rotation
    dt = 0.01 * (1.0 + 0.3 * (2 * torch.rand(K, generator=g, dtype=F64) - 1))
    dt[50] = 0.0
    out = propagate_mean(x0, acc, gyro, dt, G0, scheme)
    assert out.shape == (K, STATE_DIM)
    x = x0
    zeros = x0.new_zeros(NOISE_DIM)
    rows = []
    for k in range(K):
        x = mechanize(x, zeros, acc[k], gyro[k], dt[k], G0, scheme)
        rows.append(x)
    torch.testing.assert_close(out, torch.stack(rows), rtol=0, atol=1e-9)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_device_at_rest_stays_at_rest(scheme):
    """``ã = Cᵀ g / T_a + b_a``, ``ω̃ = b_ω``: the corrected specific force cancels gravity exactly."""
    x0, _, _, _ = random_case(8)
    s = split(x0)
    x0 = make_state(p=s.p, v=torch.zeros(3, dtype=F64), q=s.q, b_a=s.b_a, b_w=s.b_w, T_a=s.T_a)
    R = quat.to_matrix(s.q)
    acc = (R.T @ torch.tensor([0.0, 0.0, G0], dtype=F64)) / s.T_a + s.b_a
    K = 100
    out = propagate_mean(x0, acc.expand(K, 3), s.b_w.expand(K, 3), torch.full((K,), 0.01, dtype=F64), G0, scheme)
    torch.testing.assert_close(out, x0.expand(K, STATE_DIM), rtol=0, atol=1e-12)


# ------------------------------------------------------------------ a known trajectory


def integrate_walk(walk: Walk, duration_s: float, rate_hz: float, jitter: float, scheme: str) -> torch.Tensor:
    """Position errors ``(K,)`` of the noise-free integration against the closed-form walk."""
    t = sample_times(duration_s, rate_hz, jitter, torch.Generator().manual_seed(11))
    # "midpoint": the sample represents the interval (t_{k-1}, t_k]; "paper": the reading at t_k
    t_imu = 0.5 * (t[1:] + t[:-1]) if scheme == "midpoint" else t[1:]
    acc, gyro = walk.imu(t_imu)
    x0 = make_state(p=walk.position(t[0]), v=walk.velocity(t[:1])[0], q=walk.quaternion(t[0]))
    xs = propagate_mean(x0, acc, gyro, torch.diff(t), G0, scheme)
    return (split(xs).p - walk.position(t[1:])).norm(dim=-1)


@pytest.mark.parametrize("scheme", SCHEMES)
@pytest.mark.parametrize("jitter", [0.0, 0.1])
def test_noise_free_walk_is_integrated_to_a_centimetre(scheme, jitter):
    """5 s standstill then 60 s of walking the loop at 100 Hz, smooth (no bounce or sway)."""
    walk = Walk(WalkConfig(bounce_m=0.0, sway_rad=0.0))
    err = integrate_walk(walk, 65.0, 100.0, jitter, scheme)
    assert err.shape == (6500,)
    assert float(err.max()) < 0.01, f"max position error {float(err.max()):.4g} m"


@pytest.mark.parametrize("scheme, order", [("paper", 1), ("midpoint", 2)])
def test_error_shrinks_with_the_order_of_the_scheme(scheme, order):
    """Halving Δt on the bouncy walk divides the error by 2^order: discretisation, not a bug.

    15 s = 5 s standstill, 3 s ramp, 7 s of walking with 1.8 Hz bounce and sway.
    """
    walk = Walk()
    e100 = float(integrate_walk(walk, 15.0, 100.0, 0.0, scheme).max())
    e200 = float(integrate_walk(walk, 15.0, 200.0, 0.0, scheme).max())
    ratio = e100 / e200
    expected = 2.0**order
    assert 0.85 * expected < ratio < 1.15 * expected, f"{scheme}: {e100:.3g} m / {e200:.3g} m = {ratio:.3f}"


# ------------------------------------------------------------------ process noise


def test_process_noise_density_discretization():
    dt = torch.tensor([0.01, 0.005, 0.02], dtype=F64)
    noise = ProcessNoise(
        acc_noise=torch.tensor([1e-3, 2e-3, 3e-3], dtype=F64),
        gyro_noise=2e-4,
        acc_bias_walk=1e-4,
        gyro_bias_walk=1e-5,
        acc_scale_walk=3e-6,
    )
    var = noise.variances(dt)
    assert var.shape == (3, NOISE_DIM)
    d = dt.unsqueeze(-1)
    torch.testing.assert_close(var[:, NOISE.acc], torch.tensor([1e-3, 2e-3, 3e-3], dtype=F64) ** 2 / d)
    torch.testing.assert_close(var[:, NOISE.gyro], (2e-4) ** 2 / d.expand(3, 3))
    torch.testing.assert_close(var[:, NOISE.b_a], (1e-4) ** 2 * d.expand(3, 3))
    torch.testing.assert_close(var[:, NOISE.b_w], (1e-5) ** 2 * d.expand(3, 3))
    torch.testing.assert_close(var[:, NOISE.T_a], (3e-6) ** 2 * d.expand(3, 3))
    torch.testing.assert_close(noise.covariance(dt), torch.diag_embed(var), rtol=0, atol=0)


def test_process_noise_paper_discretization():
    dt = torch.tensor([0.01, 0.02], dtype=F64)
    noise = ProcessNoise(acc_noise=3e-3, gyro_noise=2e-4, gyro_bias_walk=1e-5, discretization="paper")
    var = noise.variances(dt)
    d = dt.unsqueeze(-1)
    torch.testing.assert_close(var[:, NOISE.acc], (3e-3) ** 2 * d.expand(2, 3))
    torch.testing.assert_close(var[:, NOISE.gyro], (2e-4) ** 2 * d.expand(2, 3))
    torch.testing.assert_close(var[:, NOISE.b_w], (1e-5) ** 2 * d.expand(2, 3))
    torch.testing.assert_close(var[:, NOISE.b_a], torch.zeros(2, 3, dtype=F64), rtol=0, atol=0)


@pytest.mark.parametrize("discretization", ["density", "paper"])
def test_process_noise_is_zero_for_zero_dt(discretization):
    noise = ProcessNoise(acc_bias_walk=1e-4, gyro_bias_walk=1e-5, acc_scale_walk=1e-6, discretization=discretization)
    var = noise.variances(torch.tensor([0.0, 0.01], dtype=F64))
    assert torch.isfinite(var).all()
    torch.testing.assert_close(var[0], torch.zeros(NOISE_DIM, dtype=F64), rtol=0, atol=0)
    assert (var[1] > 0).all()
    # the gradient through the Δt = 0 branch is finite too
    dt = torch.zeros(1, dtype=F64, requires_grad=True)
    (grad,) = torch.autograd.grad(noise.variances(dt).sum(), dt)
    assert torch.isfinite(grad).all()


@pytest.mark.parametrize("name", ["acc_noise", "gyro_noise", "acc_bias_walk", "gyro_bias_walk", "acc_scale_walk"])
def test_process_noise_rejects_negative_parameters(name):
    with pytest.raises(ValueError, match=name):
        ProcessNoise(**{name: -1e-3})
    with pytest.raises(ValueError, match=name):
        ProcessNoise(**{name: float("nan")})


def test_process_noise_rejects_unknown_discretization():
    with pytest.raises(ValueError, match="'exact'"):
        ProcessNoise(discretization="exact")


# ------------------------------------------------------------------ argument checking


def test_unknown_scheme_is_named_in_the_error():
    x, acc, gyro, dt = random_case(9)
    with pytest.raises(ValueError, match="'rk4'"):
        mechanize(x, x.new_zeros(NOISE_DIM), acc, gyro, dt, G0, "rk4")
    with pytest.raises(ValueError, match="'rk4'"):
        mechanization_jacobians(x, acc, gyro, dt, "rk4")
    with pytest.raises(ValueError, match="'rk4'"):
        propagate_mean(x, acc.expand(2, 3), gyro.expand(2, 3), dt.expand(2), G0, "rk4")
