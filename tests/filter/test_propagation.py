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


def _naive_plan(node_steps, K):
    """The plan from its definition: padding nodes first, each interval's steps, then sentinels."""
    B, m = len(node_steps), max(len(s) for s in node_steps)
    intervals = [[[]] * (m - len(s)) + [list(range(a, b + 1)) for a, b in zip([0] + [x + 1 for x in s[:-1]], s)]
                 for s in node_steps]
    L = max(1, max(len(i) for row in intervals for i in row))
    group = [[[b * K + k for k in i] + [B * K] * (L - len(i)) for i in row] for b, row in enumerate(intervals)]
    node_step = [[-1] * (m - len(s)) + list(s) for s in node_steps]
    real = [[False] * (m - len(s)) + [True] * len(s) for s in node_steps]
    return torch.tensor(group), torch.tensor(node_step), real


@pytest.mark.parametrize("rows", [3, 9, 40])
def test_node_plans_of_few_and_many_rows_follow_the_definition(rows):
    from flowins.filter.propagation import plan_nodes
    gen = torch.Generator().manual_seed(rows)
    K = 13
    node_steps = []
    for b in range(rows):
        picked = sorted(torch.randperm(K - 1, generator=gen)[: int(torch.randint(0, 4, (1,), generator=gen))].tolist())
        node_steps.append([] if b % 4 == 1 else picked + [K - 1])  # some rows report nothing
    group, node_step, real = _naive_plan(node_steps, K)
    plan = plan_nodes(node_steps, K)
    assert torch.equal(plan.group, group) and torch.equal(plan.node_step, node_step) and plan.real == real


def test_a_plan_padded_to_fixed_sizes_gives_the_same_nodes():
    """A compiled step's shapes (:func:`runner._segment_steps`): ``Δt = 0`` steps put before each
    row's own, padding nodes first and every interval grown to the steps' count give the plan's
    own nodes unchanged (to rounding), for rows with three, one and no nodes."""
    from flowins.filter.propagation import pad_plan, plan_nodes

    x0, P0, acc, gyro, dt = _inputs(11)
    B, K, shift = 3, 11, 5
    xs, Ps = x0.expand(B, -1).clone(), P0.expand(B, -1, -1).clone()
    xs[1, 3] += 0.5  # the rows differ
    node_steps = [[2, 7, 10], [10], []]
    noise = ProcessNoise(acc_bias_walk=1e-4)
    kwargs = dict(gravity_mps2=STANDARD_GRAVITY_MPS2)
    rows = [t.expand(B, *t.shape).clone() for t in (acc, gyro, dt)]
    own = propagate_batched(xs, Ps, *rows, plan_nodes(node_steps, K), variances=noise.variances(rows[2]), **kwargs)
    padded = [torch.cat((t.new_zeros(B, shift, *t.shape[2:]), t), 1) for t in rows]
    plan = pad_plan(plan_nodes([[s + shift for s in steps] for steps in node_steps], K + shift),
                    nodes=4, slots=K + shift, sentinel=B * (K + shift))
    assert plan.group.shape == (B, 4, K + shift) and plan.real[0] == [False, True, True, True]
    got = propagate_batched(xs, Ps, *padded, plan, variances=noise.variances(padded[2]), **kwargs)
    for a, b in zip(got, own):
        assert a.shape[1] == 4 and b.shape[1] == 3
        torch.testing.assert_close(a[:, 1:], b, rtol=0, atol=1e-12 * max(1.0, float(b.abs().max())))
    with pytest.raises(ValueError, match="more than 2 of 16"):
        pad_plan(plan, nodes=2, slots=16, sentinel=0)
