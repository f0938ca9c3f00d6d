"""``benchmarks/bench_noise_bound.py``'s search (:func:`coordinate_search`) on functions whose
minimum is known in closed form."""
import importlib.util
import math
from pathlib import Path

import pytest

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_noise_bound.py"
_SPEC = importlib.util.spec_from_file_location("bench_noise_bound", _PATH)
bench = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(bench)


def _bowl(target: dict[str, float], calls: list):
    """``1 + Σ (log10 v - log10 t)²``: minimum 1 at ``target``; logs every call."""
    def score(values):
        calls.append(dict(values))
        return 1.0 + sum((math.log10(values[k]) - math.log10(t)) ** 2 for k, t in target.items())
    return score


def test_reaches_a_minimum_on_the_step_grid():
    target = {"a": 0.01, "b": 10 ** 0.75}
    calls = []
    best, values, evals = bench.coordinate_search(_bowl(target, calls), {"a": 1.0, "b": 1.0, "c": 7.0}, ["a", "b"],
                                                  [1.0, 0.5, 0.25], rounds=3, max_evals=1000)
    assert best == pytest.approx(1.0, abs=1e-12)
    assert values["a"] == pytest.approx(0.01, rel=1e-12) and values["b"] == pytest.approx(10 ** 0.75, rel=1e-12)
    assert values["c"] == 7.0  # not searched
    assert evals == len(calls)
    assert all(c["c"] == 7.0 for c in calls)


def test_keeps_only_steps_that_gain_enough():
    calls = []
    base = _bowl({"a": 0.5}, calls)

    def flat(values):  # the bowl shrunk to 1e-5 of its depth: no step gains 1e-3
        return 1.0 + 1e-5 * (base(values) - 1.0)

    best, values, evals = bench.coordinate_search(flat, {"a": 1.0}, ["a"], [1.0, 0.5], min_gain=1e-3)
    assert values == {"a": 1.0} and best == flat({"a": 1.0})
    # with no gain asked, the same search moves to the grid point nearest 0.5 (10^-0.5 ≈ 0.316 or 1)
    best0, values0, _ = bench.coordinate_search(flat, {"a": 1.0}, ["a"], [1.0, 0.5], min_gain=0.0)
    assert best0 < best and values0["a"] == pytest.approx(10 ** -0.5, rel=1e-12)


def test_stops_at_max_evals_with_the_best_so_far():
    calls = []
    best, values, evals = bench.coordinate_search(_bowl({"a": 1e-6, "b": 1e6}, calls), {"a": 1.0, "b": 1.0}, ["a", "b"],
                                                  [1.0], rounds=100, max_evals=7)
    assert evals == len(calls) == 7
    scored = [1.0 + sum((math.log10(c[k]) - t) ** 2 for k, t in (("a", -6), ("b", 6))) for c in calls]
    assert best == min(scored)
    assert values == calls[scored.index(best)]
