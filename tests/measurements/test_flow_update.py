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
