"""Zero-velocity updates against the closed-form Kalman update; flow frames from flow pairs."""
import torch

from flowins.measurements.flow_update import FlowFrame, FlowUpdate
from flowins.measurements.zero_velocity import ZeroVelocity
from flowins.filter.chain import ChainBuilder
from flowins.flow.pairs import FlowPairs
from flowins.flow.points import FlowPoints
from flowins.measurements.flow import FlowCamera
from flowins.measurements.flow_update import flow_frames
from flowins.state import STATE, STATE_DIM

F64 = torch.float64


def random_spd(gen, n):
    A = torch.randn(n, n, generator=gen, dtype=F64)
    return A @ A.T / n + 0.1 * torch.eye(n, dtype=F64)


def test_zero_velocity_is_the_linear_kalman_update_on_the_velocity_block():
    gen = torch.Generator().manual_seed(0)
    mean = torch.randn(STATE_DIM, generator=gen, dtype=F64)
    mean[STATE.q] = mean[STATE.q] / mean[STATE.q].norm()
    mean[STATE.q_prev] = mean[STATE.q_prev] / mean[STATE.q_prev].norm()
    cov = random_spd(gen, STATE_DIM)
    chain = ChainBuilder()
    chain.add_node(0.0, torch.eye(STATE_DIM, dtype=F64), mean, cov)
    ZeroVelocity(0.0, sigma_mps=0.02).apply(chain)
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
