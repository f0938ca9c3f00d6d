"""``benchmarks/bench_adaptive_factors.py``: the σs a network sets, against closed forms."""
import math

import pytest
import torch

from flowins.measurements.adaptive_noise import AdaptiveNoise

F64 = torch.float64


def _imu(seconds=30.0, rate=100.0):
    gen = torch.Generator().manual_seed(1)
    t = torch.arange(0.0, seconds, 1.0 / rate, dtype=F64)
    acc = torch.tensor([0.0, 0.0, 9.81], dtype=F64) + torch.randn(len(t), 3, generator=gen, dtype=F64)
    gyro = 0.1 * torch.randn(len(t), 3, generator=gen, dtype=F64)
    return t, acc, gyro


def test_a_network_pinned_at_its_bound_says_so_and_one_that_varies_does_not(repo_module):
    """Head bias -100 on the lateral output: every lateral factor is the bound 10^-1 (σ × 0.1 at
    every percentile, every update pinned); zero on the vertical one with zero weights: exactly
    σ. Random weights: factors that spread, none at a bound."""
    bench = repo_module("benchmarks/bench_adaptive_factors.py")
    t, acc, gyro = _imu()
    times = torch.arange(5.0, 29.0, 1.0, dtype=F64)
    sigmas = torch.tensor([0.5, 2.0], dtype=F64)
    net = AdaptiveNoise()
    with torch.no_grad():
        net.head.bias.copy_(torch.tensor([-100.0, 0.0], dtype=F64))
    q, pinned = bench.summary(net, sigmas, t, acc, gyro, times)
    torch.testing.assert_close(q[:, 0], torch.full((3,), 0.05, dtype=F64), rtol=1e-12, atol=0)
    torch.testing.assert_close(q[:, 1], torch.full((3,), 2.0, dtype=F64), rtol=1e-12, atol=0)
    assert pinned == len(times)
    with torch.no_grad():
        gen = torch.Generator().manual_seed(2)
        for p in net.parameters():
            p.copy_(0.5 * torch.randn(p.shape, generator=gen, dtype=F64))
    q, pinned = bench.summary(net, sigmas, t, acc, gyro, times)
    assert pinned == 0 and bool((q[2] > q[0]).all())


def test_the_angle_summary_finds_the_slope_of_a_linear_slip(repo_module):
    """Angles only from the linear path with ``W`` mapping the lateral force (IMU y, in g) to
    the yaw by 0.04 rad per g and the forward one to the pitch by -0.08: the printed slopes are
    those, with correlation ±1 (small angles: the tanh bound of 0.5 rad hardly bends them)."""
    bench = repo_module("benchmarks/bench_adaptive_factors.py")
    from flowins.measurements.adaptive_noise import imu_windows, steady_window

    t, acc, gyro = _imu()
    acc = acc * torch.tensor([0.3, 0.3, 0.0], dtype=F64) + torch.tensor([0.0, 0.0, 9.80665], dtype=F64)
    net = AdaptiveNoise(angles=2, angle_bound_rad=0.5)
    with torch.no_grad():
        net.recent.weight.zero_()
        net.recent.weight[0, 3], net.recent.weight[1, 4] = -0.08, 0.04
    times = torch.arange(5.0, 29.0, 0.5, dtype=F64)
    C_cb = torch.eye(3, dtype=F64)
    lines = bench.angle_summary(net, imu_windows(t, acc, gyro, times), steady_window(C_cb[2]), C_cb)
    assert "-0.0800 rad per g of forward force, correlation -1.000" in lines[0]
    assert "+0.0400 rad per g of lateral force, correlation +1.000" in lines[1]


def test_an_acceleration_networks_angles_are_summed_up_against_the_acceleration(repo_module):
    """A network that reads the car's acceleration, on an IMU pitched 0.05 rad nose up (a slope:
    its forward specific force holds g sin 0.05 more than the acceleration): at that attitude the
    slope against the forward acceleration is its weight, -0.08 rad per g, with correlation -1;
    without an attitude it says it cannot."""
    bench = repo_module("benchmarks/bench_adaptive_factors.py")
    from flowins.geometry import quaternion as quat
    from flowins.measurements.adaptive_noise import imu_windows, steady_window

    t, acc, gyro = _imu()
    pitch = torch.tensor(-0.05, dtype=F64)  # the attitude's Euler pitch: nose up
    q = quat.from_euler(torch.zeros((), dtype=F64), pitch, torch.zeros((), dtype=F64))
    gravity_in_imu = quat.to_matrix(q)[2, :] * 9.80665  # C(q)ᵀ (0, 0, g)
    acc = acc * torch.tensor([0.3, 0.3, 0.0], dtype=F64) + gravity_in_imu
    assert float(gravity_in_imu[0]) == pytest.approx(9.80665 * math.sin(0.05), rel=1e-12)
    net = AdaptiveNoise(angles=2, angle_bound_rad=0.5, compensate_gravity=True)
    with torch.no_grad():
        net.recent.weight.zero_()
        net.recent.weight[0, 3], net.recent.weight[1, 4] = -0.08, 0.04
    times = torch.arange(5.0, 29.0, 0.5, dtype=F64)
    C_cb = torch.eye(3, dtype=F64)
    windows, steady = imu_windows(t, acc, gyro, times), steady_window(C_cb[2])
    lines = bench.angle_summary(net, windows, steady, C_cb, q.expand(len(times), 4))
    assert "-0.0800 rad per g of forward acceleration, correlation -1.000" in lines[0]
    assert "+0.0400 rad per g of lateral acceleration, correlation +1.000" in lines[1]
    # the last 0.2 s's mean acceleration (g), from readings without gravity: a = f - C(q)ᵀ g
    true_acceleration = imu_windows(t, acc - gravity_in_imu, gyro, times)[:, 3:, -20:].mean(-1)
    with torch.no_grad():
        _, angles = net(windows, steady, true_acceleration)
    levels = torch.tensor([0.1, 0.5, 0.9], dtype=F64)
    expected = " / ".join(f"{v:+.4f}" for v in torch.quantile(angles[:, 0], levels).tolist())
    assert f"pitch offset p10 / p50 / p90 {expected} rad" in lines[0], (expected, lines[0])
    assert bench.angle_summary(net, windows, steady, C_cb) == [
        "  angles: the network reads the car's acceleration, which needs an attitude; the recording has no "
        "reference orientation"]
