"""The batched propagation's node bookkeeping (its numbers against the jacrev reference are in test_runner)."""
import pytest
import torch

from flowins.filter.propagation import propagate_batched, propagate_reference
from flowins.ins.mechanization import STANDARD_GRAVITY_MPS2, ProcessNoise
from flowins.state import STATE_DIM, make_state

F64 = torch.float64


def _inputs(K: int):
    gen = torch.Generator().manual_seed(7)
    x0 = make_state(p=torch.zeros(3, dtype=F64), v=torch.tensor([1.0, 0.2, 0.0], dtype=F64),
                    q=torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=F64))
    P0 = torch.eye(STATE_DIM, dtype=F64) * 1e-2
    acc = torch.randn(K, 3, generator=gen, dtype=F64) * 0.3 + torch.tensor([0.0, 0.0, STANDARD_GRAVITY_MPS2], dtype=F64)
    gyro = torch.randn(K, 3, generator=gen, dtype=F64) * 0.1
    dt = torch.full((K,), 0.01, dtype=F64)
    return x0, P0, acc, gyro, dt


@pytest.mark.parametrize("nodes", [[2, 3, 10], [0, 10], [10], [4, 9, 10]])
def test_unequal_node_intervals_match_the_reference(nodes):
    x0, P0, acc, gyro, dt = _inputs(11)
    steps = torch.tensor(nodes)
    kwargs = dict(noise=ProcessNoise(acc_bias_walk=1e-4), gravity_mps2=STANDARD_GRAVITY_MPS2)
    fast = propagate_batched(x0, P0, acc, gyro, dt, steps, **kwargs)
    ref = propagate_reference(x0, P0, acc, gyro, dt, steps, **kwargs)
    for a, b in zip(fast, ref):
        assert a.shape[0] == len(nodes)
        torch.testing.assert_close(a, b, rtol=0, atol=1e-10 * max(1.0, float(b.abs().max())))


@pytest.mark.parametrize(("nodes", "message"), [
    ([3, 9], "must end with the last step index"),
    ([], "must end with the last step index"),
    ([5, 5, 10], "strictly increasing"),
    ([-1, 10], "strictly increasing"),
])
def test_bad_node_steps_are_refused(nodes, message):
    x0, P0, acc, gyro, dt = _inputs(11)
    with pytest.raises(ValueError, match=message):
        propagate_batched(x0, P0, acc, gyro, dt, torch.tensor(nodes, dtype=torch.long), noise=ProcessNoise(),
                          gravity_mps2=STANDARD_GRAVITY_MPS2)
