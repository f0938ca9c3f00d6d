"""The simulator's sensor models against the closed-form truth."""
import math
from dataclasses import replace

import torch

from flowins.data.simulate.gnss import GnssErrors, simulate_fixes
from flowins.data.simulate.scenario import SimulationConfig, simulate_imu
from flowins.data.synthetic import ImuErrors, Walk, WalkConfig
from flowins.filter.propagation import propagate_mean
from flowins.ins.mechanization import STANDARD_GRAVITY_MPS2
from flowins.state import make_state, split

F64 = torch.float64


def test_noise_free_simulated_imu_integrates_to_a_centimetre_after_60_s():
    """The full walk (bounce and hand shake included), jittered 100 Hz samples,
    integrated by the flowins mechanization from the true initial state."""
    config = SimulationConfig(duration_s=65.0, imu_errors=ImuErrors(0, 0, 0, 0, 0, 0, 0))
    walk = Walk(WalkConfig(duration_s=65.0))
    t, acc, gyro, truth = simulate_imu(walk, config, torch.Generator().manual_seed(0))
    assert torch.equal(truth["T_a"], torch.ones(3, dtype=F64)) and float(truth["b_a"].abs().max()) == 0.0
    x0 = make_state(p=walk.position(t[0]), v=walk.velocity(t[:1])[0], q=walk.quaternion(t[0]))
    xs = propagate_mean(x0, acc[1:], gyro[1:], torch.diff(t), STANDARD_GRAVITY_MPS2, "midpoint")
    err = (split(xs).p - walk.position(t[1:])).norm(dim=-1)
    assert float(t[-1]) > 64.0
    assert float(err.max()) < 0.01, f"max position error {float(err.max()):.3g} m"
    # and the walk really moves and shakes: the test is not trivially easy
    assert float((walk.position(t[-1:]) - walk.position(t[:1])).norm()) > 40.0
    assert float(gyro[1000:, 0].abs().max()) > 0.1  # roll rate of the hand shake, rad/s


def test_simulated_imu_errors_follow_the_configured_model():
    errors = ImuErrors(acc_noise=0.0, gyro_noise=0.0, acc_bias_walk=0.0, gyro_bias_walk=0.0)
    config = SimulationConfig(duration_s=20.0, imu_errors=errors)
    walk = Walk(WalkConfig(duration_s=20.0))
    clean = simulate_imu(walk, replace(config, imu_errors=ImuErrors(0, 0, 0, 0, 0, 0, 0)), torch.Generator().manual_seed(1))
    t, acc, gyro, truth = simulate_imu(walk, config, torch.Generator().manual_seed(1))
    assert torch.equal(t, clean[0])
    # acc = f / T_a + b_a with a constant turn-on bias and scale, gyro = w + b_w
    torch.testing.assert_close(acc, clean[1] / truth["T_a"] + truth["b_a"], rtol=0, atol=1e-12)
    torch.testing.assert_close(gyro, clean[2] + truth["b_w"], rtol=0, atol=1e-12)
    assert 0.001 < float((truth["T_a"] - 1).abs().max()) < 0.06  # scale errors of ±1-2 % (1.5 % std)
    steps = torch.diff(t)
    assert float(steps.min()) < 0.0095 and float(steps.max()) > 0.0105  # jittered, non-equidistant


def test_gnss_errors_are_consistent_with_the_reported_accuracy():
    G = 20000
    gen = torch.Generator().manual_seed(0)
    truth = torch.zeros(G, 3, dtype=F64)
    canyon = 0.5 + 0.5 * torch.sin(torch.arange(G, dtype=F64) / 300.0)
    errors = GnssErrors(multipath_probability=0.05)
    measured, h_acc, v_acc, multipath = simulate_fixes(truth, canyon, errors, gen)
    assert float(h_acc.min()) >= errors.min_acc_m and float(h_acc.max()) <= errors.max_acc_m
    assert float(h_acc.max() - h_acc.min()) > 10.0  # varies with the canyon
    torch.testing.assert_close(v_acc, errors.vertical_ratio * h_acc)
    clean = ~multipath
    z = measured[clean] / torch.stack((h_acc, h_acc, v_acc), -1)[clean]
    assert z.std(dim=0).sub(1.0).abs().max() < 0.1  # errors as large as the radius says
    # correlated between consecutive fixes (Gauss-Markov, 10 s at 1 Hz: ρ = e^-0.1)
    zc = measured[:, 0] / h_acc
    pair = clean[:-1] & clean[1:]
    rho = float(torch.corrcoef(torch.stack((zc[:-1][pair], zc[1:][pair])))[0, 1])
    assert abs(rho - math.exp(-0.1)) < 0.05
    rate = float(multipath.double().mean())
    expected = float((errors.multipath_probability * (1 + 2 * canyon) / 3).mean())
    assert abs(rate - expected) < 0.2 * expected
    outlier_z = (measured[multipath, :2] / h_acc[multipath].unsqueeze(-1)).norm(dim=-1)
    assert float(outlier_z.median()) > 2.0  # displaced by 20-60 m, more than the radius says
