"""PyTorch operations of one training step, forward and backward: what a GPU launches per step.

One training step on a window of a simulated walk (seed 1, as ``bench_train_memory.py``: the
training config's settings, 128 points per frame, soft gates, SpyNet in closed-form dropout,
its flow cached), counted with a dispatch mode (views apart, as ``bench_flow_filter.py
--count-ops-s`` counts them), then timed without the count; and the same for the filter alone
without gradients (what ``navigate`` runs for evaluation) over the same window.

On a GPU each counted operation is a kernel launch. Where the rows of a step are few (a
training step runs one sequence's windows: ``data.batch_size=1``), a step there costs its
operations times the GPU's time per operation, whatever the rows' size; this script prints
the count per frame so that it can be set against that time (``bench_flow_filter.py --device
cuda`` gives one run's seconds and operations per frame).

``--device cuda`` runs the steps on the GPU, and ``--rows 2,8,32`` also times a step whose
batched filter runs that many rows (the window repeated, as ``data.batch_size`` sequences times the
methods make rows): the time per row says how much a larger batch would gain there.

``--compile`` times the step ``train.py`` takes by default (the window under ``ins_dense`` and
``ins_gnss_dense``, two rows of one batched pass, forward and backward) eagerly and with
``filter.compile=true`` (:mod:`flowins.filter.compiling`: the flow frames' update through inductor,
its backward with it), ``--repeats`` rounds that run each once, interleaved (this machine's speed
drifts): the first compiled step's time (it compiles), the medians, their ratio, and how far the
loss and the gradients of the two ways lie apart (the still start of the walks magnifies rounding:
docs/performance.md).

    python benchmarks/bench_train_ops.py [--window 20] [--points 128] [--method ins_dense]
                                         [--device cpu|cuda] [--rows 2,8,32] [--compile [--repeats 3]]
"""
from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import hydra
import torch
from omegaconf import OmegaConf
from torch.utils._python_dispatch import TorchDispatchMode

from bench_flow_filter import makes_view
from flowins.settings import flow_config, training_setup
from flowins.training.data import load_training_sequence
from flowins.training.parameters import FilterParameters
from flowins.config import check_device
from flowins.training.unroll import run_window, run_windows, window_loss

CONFIGS = str(Path(__file__).resolve().parents[1] / "configs")


class Count(TorchDispatchMode):
    """Operations (not views) per phase."""

    def __init__(self) -> None:
        super().__init__()
        self.phase = "forward"
        self.counts = {"forward": 0, "backward": 0}

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        if not makes_view(func, args, out):
            self.counts[self.phase] += 1
        return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--window", type=float, default=20.0, help="seconds of the walk (20: the first epochs' windows)")
    parser.add_argument("--points", type=int, default=128)
    parser.add_argument("--method", default="ins_dense")
    parser.add_argument("--device", default="cpu", help="where the filter's unroll runs: cpu | cuda | cuda:N")
    parser.add_argument("--rows", default="", help="comma-separated row counts whose batched step is also timed")
    parser.add_argument("--compile", action="store_true",
                        help="also time train.py's default step eagerly and with filter.compile=true, interleaved")
    parser.add_argument("--repeats", type=int, default=3, help="--compile: the timed rounds")
    args = parser.parse_args()
    if args.repeats < 1:
        raise SystemExit(f"error: --repeats {args.repeats}: expected at least 1")
    device = check_device(args.device, "--device")
    try:
        row_counts = [int(r) for r in args.rows.split(",") if r.strip()]
    except ValueError:
        raise SystemExit(f"error: --rows {args.rows!r}: expected comma-separated integers, e.g. 2,8,32") from None
    if any(r < 1 for r in row_counts):
        raise SystemExit(f"error: --rows {args.rows!r}: each count must be >= 1")
    with hydra.initialize_config_dir(config_dir=CONFIGS, version_base="1.3"):
        cfg = OmegaConf.to_container(hydra.compose("train", overrides=["output_dir=/tmp"]), resolve=True)
    cfg["flow"]["device"] = str(device)  # the walk's flow on the same device (cached for both)
    pair = ["ins_dense", "ins_gnss_dense"]  # --compile: train.py's default rows
    seq = load_training_sequence({"seed": 1, "duration_s": 60.0}, {**cfg, "flow": flow_config(cfg, moments=True)},
                                 methods=sorted({args.method, *(pair if args.compile else [])}))
    cfg["filter"]["flow"]["n_points"] = args.points
    setup = training_setup(cfg, [seq], recorded=False)
    _, start, learn = setup.parameters
    params = FilterParameters(start, learn, bounds=setup.parameters.bounds).to(device)
    t = seq.imu.t_s
    i_b = min(int(torch.searchsorted(t, t[0] + args.window)), len(t) - 1)
    pairs = seq.dense if seq.dense is not None else seq.sparse
    frames = int((pairs.t2_s <= t[i_b]).sum()) if pairs is not None else 0
    if frames == 0:
        raise SystemExit(f"error: --method {args.method}: no flow frames in the window (a flow method is needed)")

    def synchronize() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    def step(count: Count | None, *, grad: bool) -> float:
        synchronize()
        t0 = time.perf_counter()
        with torch.set_grad_enabled(grad):
            config = params.apply(setup.filter.navigation, training=True, device=device)  # the parameters' graph, per step
            result = run_window(seq, args.method, config, (0, i_b), dropout_p=params.value("dropout_p"))
            loss = window_loss(result.track, seq.truth).loss
            if grad:
                if count is not None:
                    count.phase = "backward"
                loss.backward()
        synchronize()
        return time.perf_counter() - t0

    def batched_step(count: int) -> float:
        """One training step whose filter runs ``count`` rows (the window repeated)."""
        synchronize()
        t0 = time.perf_counter()
        config = params.apply(setup.filter.navigation, training=True, device=device)
        results = run_windows([seq] * count, args.method, config, [(0, i_b)] * count,
                              dropout_p=params.value("dropout_p"))
        loss = sum(window_loss(r.track, seq.truth).loss for r in results) / count
        loss.backward()
        synchronize()
        return time.perf_counter() - t0

    rows = {}
    for name, grad in (("training step", True), ("filter alone", False)):
        count = Count()
        with count:
            step(count, grad=grad)
        rows[name] = (count.counts, step(None, grad=grad))
    where = (torch.cuda.get_device_name(device) if device.type == "cuda"
             else f"the CPU with {torch.get_num_threads()} threads")
    print(f"{args.method}, a {args.window:.0f} s window ({frames:.0f} frames, {args.points} points each), {where}")
    for name, (counts, seconds) in rows.items():
        total = counts["forward"] + counts["backward"]
        print(f"{name:14s} {counts['forward'] / frames:6.0f} forward + {counts['backward'] / frames:5.0f} backward "
              f"operations per frame ({total} in all); {seconds:.2f} s here, {1e6 * seconds / max(1, total):.1f} µs "
              "per operation")
    for count in row_counts:
        batched_step(count)  # warm-up (the GPU's kernels and memory for this shape)
        seconds = batched_step(count)
        print(f"a step of {count:3d} rows: {seconds:6.2f} s, {seconds / count:6.3f} s per row "
              f"({seconds / rows['training step'][1]:.2f}x one row's step)")
    if args.compile:
        compare_compiled(seq, params, setup.filter.navigation, pair, i_b, args.repeats)
    ratio = sum(rows["training step"][0].values()) / max(1, sum(rows["filter alone"][0].values()))
    print(f"RESULT training_ops_per_frame={sum(rows['training step'][0].values()) / frames:.0f} "
          f"filter_ops_per_frame={sum(rows['filter alone'][0].values()) / frames:.0f} ratio={ratio:.1f}")


def compare_compiled(seq, params: FilterParameters, navigation, methods: list[str], i_b: int, repeats: int) -> None:
    """A step of ``methods`` (one row each) on the window eagerly and with ``filter.compile=true``:
    the first compiled step's seconds, then ``repeats`` interleaved rounds, their medians and ratio,
    and the two ways' largest differences of the loss and of each gradient (relative)."""
    import statistics

    learned = [q for q in params.parameters() if q.requires_grad]

    def step(compile: str) -> tuple[float, torch.Tensor, list[torch.Tensor]]:
        t0 = time.perf_counter()
        config = dataclasses.replace(params.apply(navigation, training=True, device=torch.device("cpu")), compile=compile)
        results = run_windows([seq] * len(methods), methods, config, [(0, i_b)] * len(methods),
                              dropout_p=params.value("dropout_p"))
        loss = sum(window_loss(r.track, seq.truth).loss for r in results)
        grads = torch.autograd.grad(loss, learned, allow_unused=True)
        return time.perf_counter() - t0, loss.detach(), [g for g in grads if g is not None]

    eager_s, eager_loss, eager_grads = step("false")
    first_s, loss, grads = step("true")
    print(f"a step of {' + '.join(methods)}: eager {eager_s:.2f} s (its first), compiled {first_s:.2f} s "
          "(its first: it compiles)")
    times: dict[str, list[float]] = {"false": [], "true": []}
    for _ in range(repeats):
        for how in times:
            times[how].append(step(how)[0])
    eager, compiled = statistics.median(times["false"]), statistics.median(times["true"])
    apart = max(float((g - e).abs().max() / e.abs().max().clamp_min(1e-300)) for g, e in zip(grads, eager_grads))
    print(f"  eager {' '.join(f'{t:.2f}' for t in times['false'])} s, compiled {' '.join(f'{t:.2f}' for t in times['true'])} s "
          f"(medians {eager:.2f} / {compiled:.2f} s: {eager / compiled:.2f}x); loss {float(eager_loss):.6g} eager, "
          f"{float(loss):.6g} compiled; gradients apart by up to {apart:.1e} of their largest entry")
    print(f"RESULT compiled_step_speedup={eager / compiled:.2f} first_compiled_step_s={first_s:.1f}")


if __name__ == "__main__":
    main()
