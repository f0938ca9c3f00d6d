"""Zero-velocity updates against the closed-form Kalman update and blind to the heading; flow
frames from flow pairs."""
import math

import pytest
import torch

from flowins.measurements.flow_update import FlowFrame, FlowUpdate
from flowins.measurements.gnss_heading import HeadingAlignment
from flowins.measurements.zero_velocity import ZeroVelocity
from flowins.filter.chain import ChainBuilder
from flowins.flow.pairs import FlowPairs
from flowins.flow.points import FlowPoints
from flowins.measurements.flow import FlowCamera
from flowins.measurements.flow_update import flow_frames
from flowins.evaluation.consistency import heading_consistency
from flowins.filter.runner import run_filter
from flowins.filter.unobservable import unobservable_directions
from flowins.geometry import quaternion as quat
from flowins.ins.initialization import InitialUncertainty, initial_covariance
from flowins.ins.mechanization import ProcessNoise
from flowins.state import STATE, STATE_DIM, make_state

F64 = torch.float64


def random_spd(gen, n):
    A = torch.randn(n, n, generator=gen, dtype=F64)
    return A @ A.T / n + 0.1 * torch.eye(n, dtype=F64)


def _random_prior(seed=0):
    gen = torch.Generator().manual_seed(seed)
    mean = torch.randn(STATE_DIM, generator=gen, dtype=F64)
    mean[STATE.q] = mean[STATE.q] / mean[STATE.q].norm()
    mean[STATE.q_prev] = mean[STATE.q_prev] / mean[STATE.q_prev].norm()
    return mean, random_spd(gen, STATE_DIM)


def test_zero_velocity_is_the_linear_kalman_update_on_the_velocity_block():
    mean, cov = _random_prior()
    chain = ChainBuilder()
    chain.add_node(0.0, torch.eye(STATE_DIM, dtype=F64), mean, cov)
    ZeroVelocity(0.0, sigma_mps=0.02, keeps_heading=False).apply(chain)
    # closed form with an explicit H = [0 I 0]
    H = torch.zeros(3, STATE_DIM, dtype=F64)
    H[:, STATE.v] = torch.eye(3, dtype=F64)
    S = H @ cov @ H.T + 0.02**2 * torch.eye(3, dtype=F64)
    K = cov @ H.T @ torch.linalg.inv(S)
    expect_mean = mean + K @ (-mean[STATE.v])
    expect_cov = (torch.eye(STATE_DIM, dtype=F64) - K @ H) @ cov
    torch.testing.assert_close(chain.cov, expect_cov, atol=1e-10, rtol=1e-9)
    # quaternions are re-normalised after every update; compare the rest
    keep = torch.ones(STATE_DIM, dtype=torch.bool)
    keep[STATE.q] = keep[STATE.q_prev] = False
    torch.testing.assert_close(chain.mean[keep], expect_mean[keep], atol=1e-10, rtol=1e-9)
    assert chain.log[-1]["kind"] == "zero_velocity"


def _heading_information(at, cov):
    """``N_ψᵀ P⁻¹ N_ψ`` with ``N_ψ`` at the state ``at``: what the covariance knows along the turn
    about the vertical there."""
    n = unobservable_directions(at)[:, 3]
    return float(n @ torch.linalg.solve(cov, n))


@pytest.mark.parametrize("speed", [0.05, 1.0])
def test_zero_velocity_keeps_what_the_covariance_knows_about_the_heading(speed):
    """Turning the whole state about the vertical leaves a zero velocity's likelihood as it is, so
    the information along that turn at the updated estimate is the same as along the turn at
    the prior's before the update. The plain update (``H = ∂v/∂x``) adds ``|e_z × v̂|² / σ²``
    along the prior's turn (``P⁺⁻¹ = P⁻¹ + Hᵀ R⁻¹ H``). The velocity is updated all the same."""
    mean, cov = _random_prior(1)
    mean[STATE.v] = speed * mean[STATE.v] / mean[STATE.v].norm()
    chains = {}
    for keeps in (True, False):
        chains[keeps] = ChainBuilder()
        chains[keeps].add_node(0.0, torch.eye(STATE_DIM, dtype=F64), mean, cov)
        ZeroVelocity(0.0, sigma_mps=0.02, keeps_heading=keeps).apply(chains[keeps])
    before = _heading_information(mean, cov)
    kept = _heading_information(chains[True].mean, chains[True].cov)
    plain = _heading_information(mean, chains[False].cov)
    turn = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0], dtype=F64), mean[STATE.v])
    assert kept == pytest.approx(before, rel=1e-8)
    assert plain == pytest.approx(before + float(turn @ turn) / 0.02**2, rel=1e-8)
    assert float(chains[True].mean[STATE.v].norm()) < 0.2 * speed
    torch.linalg.cholesky(chains[True].cov)  # positive definite


def test_a_still_start_with_a_free_yaw_keeps_it_free():
    """A still, tilted IMU with a noisy accelerometer, started at the right attitude but with the
    yaw free (σ π) and 10 s of zero-velocity updates at 10 Hz. Nothing in it observes the heading:
    the filter's heading σ stays at π. The plain update takes the turn of its small velocity
    estimates for heading information: its σ falls below π / 2 within 5 s and, by 10 s, below the
    σ under which a run with GNSS counts the yaw as known and never aligns it to the fixes
    (``HeadingAlignment.unknown_yaw_sigma_rad``)."""
    gen = torch.Generator().manual_seed(2)
    n = 1001
    t = torch.arange(n, dtype=F64) * 0.01
    q0 = quat.from_rotation_vector(torch.tensor([0.03, -0.02, 0.8], dtype=F64))
    gravity_b = quat.to_matrix(q0).T @ torch.tensor([0.0, 0.0, 9.80665], dtype=F64)
    acc = gravity_b + 0.03 * torch.randn(n, 3, generator=gen, dtype=F64)
    gyro = 1e-3 * torch.randn(n, 3, generator=gen, dtype=F64)
    mean0 = make_state(p=torch.zeros(3, dtype=F64), v=torch.zeros(3, dtype=F64), q=q0)
    cov0 = initial_covariance(q0, InitialUncertainty(yaw_rad=math.pi))
    sigma = {}
    for keeps in (True, False):
        zupts = [ZeroVelocity(0.1 * k, 0.01, keeps_heading=keeps) for k in range(1, 100)]
        track = run_filter(t_s=t, acc_mps2=acc, gyro_rps=gyro, mean0=mean0, cov0=cov0, events=zupts,
                           noise=ProcessNoise(acc_noise=3e-3, gyro_noise=2e-4))
        q = track.mean[:, STATE.q]
        sigma[keeps] = heading_consistency(q, track.cov[:, STATE.q, STATE.q], q).sigma_rad
        at_5s = int((track.t <= 5.0).sum()) - 1
    assert float((sigma[True] - math.pi).abs().max()) < 1e-3 * math.pi
    assert float(sigma[False][at_5s]) < math.pi / 2
    assert float(sigma[False][-1]) < HeadingAlignment().unknown_yaw_sigma_rad


def _points(n):
    return FlowPoints(torch.zeros(n, 2, dtype=F64), torch.zeros(n, 2, dtype=F64), torch.ones(n, 2, dtype=F64))


def test_flow_frames_chain_pairs_insert_augmentations_at_gaps_and_count_pairs_outside():
    camera = FlowCamera(torch.eye(3, dtype=F64), torch.eye(3, dtype=F64), torch.zeros(3, dtype=F64))
    t1 = torch.tensor([0.0, 0.1, 0.2, 0.5, 0.6, 9.0], dtype=F64)
    t2 = torch.tensor([0.1, 0.2, 0.3, 0.6, 0.7, 9.1], dtype=F64)
    pairs = FlowPairs(t1, t2, [_points(n) for n in (3, 4, 5, 6, 7, 8)], "dense")
    update = FlowUpdate(n_points=2)
    events, outside = flow_frames(pairs, camera, update, t_min_s=0.0, t_max_s=5.0)
    assert outside == 1
    assert [round(e.time_s, 3) for e in events] == [0.0, 0.1, 0.2, 0.3, 0.5, 0.6, 0.7]
    assert [len(e.points) for e in events] == [0, 3, 4, 5, 0, 6, 7]
    assert all(isinstance(e, FlowFrame) and e.update is update for e in events)
