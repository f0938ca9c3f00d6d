"""``benchmarks/bench_adaptive_ceiling.py``'s hand-written σ form against its closed form."""
import importlib.util
import math
from pathlib import Path

import pytest
import torch

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_adaptive_ceiling.py"
_SPEC = importlib.util.spec_from_file_location("bench_adaptive_ceiling", _PATH)
bench = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(bench)


@pytest.mark.parametrize(("forward", "up", "lateral"), [("x", "z", 1), ("-y", "z", 0), ("z", "-x", 1)])
def test_the_hand_form_reads_the_car_s_axes_and_the_last_fifth_of_a_second(forward, up, lateral):
    """Windows whose last 0.2 s hold a sideways mean ``a``, a forward mean ``b`` and a vertical
    swing of standard deviation ``s`` (the samples before it wild, so that reading them shows):
    the factors are ``sqrt(1 + (a/a0)²)`` and ``sqrt(1 + (b/b0)² + (s/s0)²)``; at rest, 1 and 1."""
    fwd, vert = bench.AXES[forward][0], bench.AXES[up][0]
    assert lateral not in (fwd, vert)
    a, b, s = 0.3, -0.2, 0.05
    windows = torch.zeros(2, 6, 100, dtype=torch.float64)
    windows[0, 3:, :80] = 5.0  # outside the last 20 samples: must not count
    windows[0, 3 + lateral, 80:] = a
    windows[0, 3 + fwd, 80:] = b
    windows[0, 3 + vert, 80:] = 1.0 + s * torch.tensor([1.0, -1.0], dtype=torch.float64).repeat(10) * math.sqrt(19 / 20)
    windows[1, 3 + vert] = 1.0  # at rest: gravity only
    scales = {"a_lat": 0.1, "a_fwd": 0.4, "s_up": 0.02}
    f = bench.hand_form(scales, forward, up)(windows)
    expected = [math.sqrt(1 + (a / 0.1) ** 2), math.sqrt(1 + (b / 0.4) ** 2 + (s / 0.02) ** 2)]
    torch.testing.assert_close(f[0], torch.tensor(expected, dtype=torch.float64), rtol=1e-12, atol=0)
    torch.testing.assert_close(f[1], torch.ones(2, dtype=torch.float64), rtol=0, atol=0)

