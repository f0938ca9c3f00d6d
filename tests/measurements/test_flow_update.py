"""The flow updater's step (flowins.measurements.flow_update.flow_iteration) as one graph."""
from __future__ import annotations

import torch


def test_a_flow_iteration_is_one_graph_equal_to_eager():
    """``flow_iteration`` (triangulation, Jacobians, epipolar reduction, gated update) under
    ``torch.compile(fullgraph=True)`` with a backend that needs no compiler: no graph break,
    no read-back, the same posterior, weights and counts as eager (bench_compile.py's frames)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_compile.py"
    spec = importlib.util.spec_from_file_location("bench_compile", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    inputs = bench.frame(2, 24)
    with torch.inference_mode():
        want = bench.step(*inputs)
        torch._dynamo.reset()
        got = torch.compile(bench.step, fullgraph=True, backend="eager")(*inputs)
    assert int(want[3][:, 0].min()) >= 10  # valid points in every row: a real update
    for a, b in zip(got, want):
        assert torch.equal(a, b)


def test_a_flow_frame_s_whole_update_is_one_graph_equal_to_eager():
    """``flow_frame_step``: the selection, two iterations, the gate, the prior kept where no point
    is valid and the recovery's count and inflation, under ``torch.compile(fullgraph=True)`` with a
    backend that needs no compiler: no graph break, no read-back, the same Gaussians, log values
    and counts as eager. One row's points are all padding (its prior stays); the other row has
    been gated for a frame less than the recovery waits, and its frame is gated again (it inflates)."""
    import importlib.util
    from pathlib import Path

    from flowins.filter.ekf import Gate
    from flowins.measurements.flow_update import FlowRecovery, FlowUpdate, flow_frame_step

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_compile.py"
    spec = importlib.util.spec_from_file_location("bench_compile", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    x, cov, points, camera, mask, _ = bench.frame(2, 40)
    mask[1] = False  # row 1: no real point
    update = FlowUpdate(n_points=24, iterations=2, gate=Gate(threshold=1e-4),  # most points out: a gated frame
                        recovery=FlowRecovery(after_frames=3, max_accepted=0.99, min_valid=4))
    gated = torch.tensor([2, 2])

    def step(x, cov, points, mask, gated):
        out = flow_frame_step(x, cov, points, camera, mask, update=update, select=True, gated=gated, likelihood=True)
        return out.mean, out.cov, out.gated, out.failed, out.nll, out.nll_count, *out.values.values()

    with torch.inference_mode():
        want = step(x, cov, points, mask, gated)
        torch._dynamo.reset()
        got = torch.compile(step, fullgraph=True, backend="eager")(x, cov, points, mask, gated)
    for a, b in zip(got, want, strict=True):
        assert torch.equal(a, b)
    valid, accepted, inflated = want[6], want[10], want[-1]
    assert int(valid[0]) >= 10 and int(valid[1]) == 0  # row 0 updates with the selected points
    assert float(accepted[0]) <= 0.99 * float(valid[0]), (accepted, valid)
    assert inflated.tolist() == [True, False] and want[2].tolist() == [0, 0]  # row 0 reached 3 gated frames
    assert torch.equal(want[0][1], x[1]) and torch.equal(want[1][1], cov[1])  # row 1 keeps its prior
    inflation = update.recovery.inflation(x)
    assert float((want[1][0] - inflation).diagonal().min()) > -1e-12  # row 0's covariance holds the inflation
