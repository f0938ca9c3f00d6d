"""Filter + smoother speed for ``ins_gnss_dense`` given the flow (issue target: >= 50x real time).

Reads the default simulated walk and its dense flow pairs (both cached by
``python evaluate.py``; computed here if missing) and times, in one run:

* flowins: closed-form batched IMU and flow Jacobians, one stacked update of the frame's
  points in 26x26 algebra;
* the paper's straightforward way: ``torch.func.jacrev`` for the IMU Jacobians (per
  sample) and the flow Jacobians (per point, through the triangulation) and the point-by-point
  sequential update, on the first ``--reference-s``
  seconds of the walk (it is slow), with its real-time factor scaled from that window.

* flowins on ``--batch B`` recordings in one batched pass (:func:`flowins.navigation.navigate_batch`):
  the walk B times, each copy with its own extra IMU noise and cut to its own length
  (300 s, 293 s, 286 s, ...), so that the runs differ in values, gating and length. Its
  real-time factor is the seconds of data of all B runs per second of wall time.

``--device cuda`` runs the filter and the smoother on the GPU (``filter.device``), and reads the
flow that ``evaluate.py flow.device=cuda`` cached (or computes it there). Timings there synchronise the GPU before reading the clock.

``filter.workers=N`` (an override) splits the batch over ``N`` worker processes
(:mod:`flowins.parallel`; the single run stays one process). ``filter.compile=true`` runs the
flow frames' update through ``torch.compile`` (:mod:`flowins.filter.compiling`): the warm-up
compiles the single run's shapes and prints what that took, each timed run follows an eager one
(the ratio of each pair printed: this machine's speed drifts between runs); the batch compiles
its shapes on its first 10 s, then runs eagerly and compiled, and prints any compiling left and
its rate without it.

The last line is ``RESULT single=<x>x batched=<x>x batch=<B> device=<device> workers=<N>``.

    python benchmarks/bench_flow_filter.py [--points 256] [--batch 8] [--reference-s 20] [--repeats 3]
                                           [--breakdown-s 60] [--count-ops-s 20] [--profile-s 0]
                                           [--device cpu|cuda] [--quick] [--cpp-wrapper] [KEY=VALUE ...]
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import statistics
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from flowins.data.streams import GnssStream, ImuStream
from flowins.data.load import load_recording
from flowins.flow.load import load_flow
from flowins.measurements.flow import FlowCamera
from flowins.config import check_device
from flowins.settings import filter_setup
from flowins.navigation import NavigationRun, navigate, navigate_batch

CONFIGS = str(Path(__file__).resolve().parents[1] / "configs")


def crop(rec, pairs, t_end):
    imu = rec.imu
    keep = imu.t_s <= t_end
    imu_c = ImuStream(imu.t_s[keep], imu.acc_mps2[keep], imu.gyro_rps[keep], name=imu.name)
    g = rec.gnss
    gk = g.t_s <= float(imu_c.t_s[-1])
    gnss_c = GnssStream(g.t_s[gk], g.lat_deg[gk], g.lon_deg[gk], g.alt_m[gk], g.h_acc_m[gk], g.v_acc_m[gk], name=g.name)
    pk = (pairs.t2_s <= float(imu_c.t_s[-1])).nonzero().squeeze(-1).tolist()
    sub = dataclasses.replace(pairs, t1_s=pairs.t1_s[pk], t2_s=pairs.t2_s[pk], points=[pairs.points[i] for i in pk])
    return imu_c, gnss_c, sub


def batch_runs(rec, pairs, camera, count: int, *, end_s: float | None = None, step_s: float = 7.0
               ) -> list[NavigationRun]:
    """The walk (up to ``end_s``) ``count`` times: run ``b`` cut ``step_s`` b seconds short (less
    when ``count`` runs would cut more than half the walk away), with extra white IMU noise of
    its own (1e-3 m/s², 1e-4 rad/s per sample, seed ``b``); run 0 is the walk itself."""
    runs = []
    end = float(rec.imu.t_s[-1]) if end_s is None else end_s
    step_s = min(step_s, 0.5 * (end - float(rec.imu.t_s[0])) / max(1, count - 1))
    for b in range(count):
        imu, gnss, sub = crop(rec, pairs, end - step_s * b)
        if b:
            gen = torch.Generator().manual_seed(b)
            acc = imu.acc_mps2 + 1e-3 * torch.randn(imu.acc_mps2.shape, generator=gen, dtype=imu.acc_mps2.dtype)
            gyro = imu.gyro_rps + 1e-4 * torch.randn(imu.gyro_rps.shape, generator=gen, dtype=imu.gyro_rps.dtype)
            imu = ImuStream(imu.t_s, acc, gyro, name=imu.name)
        runs.append(NavigationRun(imu, gnss, flow=sub, camera=camera))
    return runs


def synchronize(config) -> None:
    """Wait for the GPU's queued work (a CUDA filter's clock stops when its results exist)."""
    if torch.device(config.device).type == "cuda":
        torch.cuda.synchronize(config.device)


def run_batch(runs, config) -> tuple[float, list]:
    synchronize(config)
    start = time.perf_counter()
    results = navigate_batch(runs, config=config)
    synchronize(config)
    return time.perf_counter() - start, results


def run(imu, gnss, pairs, camera, config):
    """Filter + smoother (``navigate`` runs both)."""
    synchronize(config)
    start = time.perf_counter()
    result = navigate(NavigationRun(imu, gnss, flow=pairs, camera=camera), config=config)
    synchronize(config)
    return time.perf_counter() - start, result


#: (module, function) timed by --breakdown, in the order they are printed
STAGES = (
    ("flowins.measurements.flow_update", "flow_measurements"),
    ("flowins.filter.runner", "propagate_batched"),
    ("flowins.measurements.flow_update", "select_points"),
    ("flowins.filter.updater", "ekf_update"),
    ("flowins.measurements.flow_update", "epipolar_update"),
    ("flowins.navigation", "rts_smooth_batch"),
)


@contextlib.contextmanager
def restoring(saved: list[tuple[object, str, object]]):
    """On leaving, put each ``(owner, name, original)`` back where a wrapper replaced it."""
    try:
        yield
    finally:
        for owner, name, original in saved:
            setattr(owner, name, original)


@contextlib.contextmanager
def stages_wrapped(stack: list[str], spent: dict[str, float]):
    """Wrap each stage's function where its caller looks it up: while it runs its name is on
    ``stack`` and its wall time adds to ``spent`` (the wrappers add a few microseconds per call)."""
    import importlib

    saved = []
    for module_name, name in STAGES:
        module = importlib.import_module(module_name)
        original = getattr(module, name)
        saved.append((module, name, original))

        def wrapped(*a, _f=original, _name=name, **k):
            stack.append(_name)
            t0 = time.perf_counter()
            try:
                return _f(*a, **k)
            finally:
                spent[_name] = spent.get(_name, 0.0) + time.perf_counter() - t0
                stack.pop()

        setattr(module, name, wrapped)
    with restoring(saved):
        yield


def breakdown(imu, gnss, pairs, camera, config) -> None:
    """Wall time per stage, per flow frame."""
    spent: dict[str, float] = {name: 0.0 for _, name in STAGES}
    with stages_wrapped([], spent):
        total, _ = run(imu, gnss, pairs, camera, config)
    n = len(pairs)
    print(f"breakdown over {n} frames: {1e3 * total / n:.2f} ms per frame in all")
    for _, name in STAGES:
        print(f"  {name:18s} {1e3 * spent[name] / n:6.2f} ms per frame")
    print(f"  {'the rest':18s} {1e3 * (total - sum(spent.values())) / n:6.2f} ms per frame")


def makes_view(func, args, out) -> bool:
    """Whether an aten call only made a view of its input (no kernel, no copy): its schema
    returns an alias of the input (``OpOverload.is_view``: slices, transposes, ``unflatten``,
    ``diagonal``, ...) and the result shares the input's storage (``reshape`` of a
    non-contiguous tensor copies and counts as an operation)."""
    if not getattr(func, "is_view", False):
        return False
    source = next((a for a in args if isinstance(a, torch.Tensor)), None)
    result = out[0] if isinstance(out, (list, tuple)) and out else out
    if source is None or not isinstance(result, torch.Tensor):
        return True
    return result.untyped_storage().data_ptr() == source.untyped_storage().data_ptr()


def count_ops(imu, gnss, pairs, camera, config, runs=None) -> None:
    """PyTorch operations per flow frame (dispatcher calls, views apart: :func:`makes_view`), in
    all and per stage (the innermost stage running): what the per-operation overhead multiplies.
    With ``runs`` (a batch over the same frames) also the batch's operations per frame: on a GPU
    each is a kernel launch, so what a batch adds per run is what a batch costs per run there."""
    from torch.utils._python_dispatch import TorchDispatchMode

    stack: list[str] = []
    counts: dict[str, dict[str, int]] = {}

    class Count(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            where = counts.setdefault(stack[-1] if stack else "the rest", {"operations": 0, "views": 0})
            out = func(*args, **(kwargs or {}))
            where["views" if makes_view(func, args, out) else "operations"] += 1
            return out

    with stages_wrapped(stack, {}), Count(), torch.inference_mode():
        navigate(NavigationRun(imu, gnss, flow=pairs, camera=camera), config=config)
    n = len(pairs)
    ops, views = (sum(c[k] for c in counts.values()) for k in ("operations", "views"))
    print(f"per frame over {n} frames: {ops / n:.0f} operations and {views / n:.0f} views")
    for name in [name for _, name in STAGES] + ["the rest"]:
        c = counts.get(name, {"operations": 0, "views": 0})
        print(f"  {name:18s} {c['operations'] / n:5.0f} operations {c['views'] / n:5.0f} views")
    if runs:
        counts.clear()
        with stages_wrapped(stack, {}), Count(), torch.inference_mode():
            navigate_batch(runs, config=config)
        batch_ops = sum(c["operations"] for c in counts.values())
        print(f"a batch of {len(runs)} over the same frames: {batch_ops / n:.0f} operations per frame, "
              f"{(batch_ops - ops) / n / max(1, len(runs) - 1):.1f} more per frame for each run after the first")


def profile(imu, gnss, pairs, camera, config, runs=None) -> None:
    """``torch.profiler``'s table of the operations that take the most time: one recording,
    and the batch ``runs`` when given."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile as torch_profile

    import cProfile
    import io
    import pstats

    began = time.perf_counter()
    one = NavigationRun(imu, gnss, flow=pairs, camera=camera)
    for label, call in (("one recording", lambda: navigate(one, config=config)),
                        (f"batch of {len(runs or [])}", lambda: navigate_batch(runs, config=config))):
        if label.startswith("batch") and not runs:
            continue
        call()  # warm-up
        synchronize(config)
        start = time.perf_counter()
        call()
        synchronize(config)
        wall = time.perf_counter() - start
        gpu = [ProfilerActivity.CUDA] if config.device.type == "cuda" else []
        with torch_profile(activities=[ProfilerActivity.CPU, *gpu]) as prof:
            call()
            synchronize(config)
        averages = prof.key_averages()
        # the kernels' rows only (an operator's row repeats its kernels' time, as the table's total leaves out)
        busy = sum(e.self_device_time_total for e in averages if e.device_type != DeviceType.CPU) / 1e6
        print(f"profile, {label} ({time.perf_counter() - began:.0f} s into the profiles): {wall:.2f} s unprofiled; " + (
            f"the GPU busy {busy:.2f} s of it (kernels' own time): the rest the host's Python, dispatch and "
            "launches, and waits on the GPU" if gpu else f"{torch.get_num_threads()} CPU threads"))
        # on a GPU the kernels' own time: what a batch waits on once launches are few
        key = "self_device_time_total" if gpu else "self_cpu_time_total"
        print(averages.table(sort_by=key, row_limit=15 if gpu else 8))
        # the host's side: Python functions by their own time (a long builtin call on a GPU is a wait)
        host = cProfile.Profile()
        host.enable()
        call()
        synchronize(config)
        host.disable()
        text = io.StringIO()
        pstats.Stats(host, stream=text).sort_stats("tottime").print_stats(20)
        print(f"profile, {label}, the host's Python by own time:")
        print(text.getvalue().split("\n\n", 1)[-1].strip() + "\n")


@contextlib.contextmanager
def stage_times(spent: dict[str, float], enabled: bool):
    """While inside, ``BatchChain.finish`` and the navigation's smoother add their wall time to
    ``spent`` (when ``enabled``)."""
    if not enabled:
        yield
        return
    import flowins.navigation as navigation
    from bench_walk_tracks import timed as add_time
    from flowins.filter.chain import BatchChain

    saved = [(BatchChain, "finish", BatchChain.finish), (navigation, "rts_smooth_batch", navigation.rts_smooth_batch)]
    for owner, name, _ in saved:
        add_time(owner, name, spent)
    with restoring(saved):
        yield


def timed(rec, pairs, config, duration: float, args) -> tuple[float, float | None]:
    """The single run's median time over ``--repeats`` runs and the batch's real-time factor
    (None without ``--batch``), both printed."""
    times, eager_times = [], []
    against = config.compile != "false"  # compiled: each timed run follows an eager one, alternating
    for _ in range(args.repeats):
        if against:
            eager_s, _ = run(rec.imu, rec.gnss, pairs, FlowCamera.from_sequence(rec.sequence),
                             dataclasses.replace(config, compile="false"))
            eager_times.append(eager_s)
        seconds, result = run(rec.imu, rec.gnss, pairs, FlowCamera.from_sequence(rec.sequence), config)
        times.append(seconds)
    fast = statistics.median(times)
    if against:
        eager = statistics.median(eager_times)
        print(f"eager:         {eager:7.2f} s for {duration:.0f} s  -> {duration / eager:6.1f}x real time "
              f"(median of {args.repeats}, each run before a compiled one; compiled / eager time "
              f"{fast / eager:.2f}, each pair: {', '.join(f'{c / e:.2f}' for c, e in zip(times, eager_times))})")
    log = result.flow_log
    used = sum(e["valid"] for e in log) / max(1, len(log))
    print(f"flowins:       {fast:7.2f} s for {duration:.0f} s  -> {duration / fast:6.1f}x real time "
          f"(median of {args.repeats}; {used:.0f} valid points per frame)")
    if result.filter_steps:
        print(f"  {result.filter_steps}")

    batched = None
    if args.batch > 0:
        runs = batch_runs(rec, pairs, FlowCamera.from_sequence(rec.sequence), args.batch, step_s=args.step_s)
        seconds = sum(float(r.imu.t_s[-1] - r.imu.t_s[0]) for r in runs)
        spent: dict[str, float] = {}
        if against:  # the batch's shapes compiled on its first 10 s, then eager and compiled timed in turn
            short = batch_runs(rec, pairs, FlowCamera.from_sequence(rec.sequence), args.batch, end_s=10.0, step_s=0.0)
            _, warm = run_batch(short, config)
            print(f"batch warm-up, 10 s: {warm[0].filter_steps}")
            eager_wall, _ = run_batch(runs, dataclasses.replace(config, compile="false"))
            print(f"batch of {args.batch}, eager: {eager_wall:7.2f} s for {seconds:.0f} s of data -> "
                  f"{seconds / eager_wall:6.1f}x real time")
        with stage_times(spent, args.stages):
            wall, results = run_batch(runs, config)
        batched = seconds / wall
        print(f"batch of {args.batch}: {wall:7.2f} s for {seconds:.0f} s of data -> {batched:6.1f}x real time "
              f"({batched / (duration / fast):.2f}x the single run's rate)")
        compiling = max(r.filter_compile_s for r in results)  # one pass (per worker): its shapes' compiling
        if results[0].filter_steps:
            print(f"  {results[0].filter_steps}" + (f"; without it {seconds / (wall - compiling):.1f}x real time"
                                                    if compiling > 0 else ""))
        if args.stages and config.workers > 1:
            print(f"  (in {min(config.workers, args.batch)} worker processes: their stages are not timed here)")
        elif args.stages:
            print("  of which " + ", ".join(f"{name} {t:.2f} s" for name, t in spent.items()))
    return fast, batched


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, default=256)
    parser.add_argument("--batch", type=int, default=8, help="recordings in the batched run (0: skip it)")
    parser.add_argument("--reference-s", type=float, default=20.0, help="the paper's way over this many seconds (0: skip)")
    parser.add_argument("--repeats", type=int, default=3,
                        help="timed runs of the whole walk (0: none, and no batched run: only what else is asked)")
    parser.add_argument("--breakdown-s", type=float, default=60.0,
                        help="also time each stage over the first this many seconds (0: skip)")
    parser.add_argument("--profile-s", type=float, default=0.0,
                        help="also profile the first this many seconds, alone and as the batch (0: skip)")
    parser.add_argument("--count-ops-s", type=float, default=20.0,
                        help="also count PyTorch operations per frame over the first this many seconds (0: skip)")
    parser.add_argument("--device", default="cpu",
                        help="where the filter and the smoother run, and the flow if it is not cached: cpu | cuda | cuda:N")
    parser.add_argument("--quick", action="store_true", help="the 60 s walk instead of the 300 s one")
    parser.add_argument("--step-s", type=float, default=7.0,
                        help="each batched run this much shorter than the one before (0: all the whole walk)")
    parser.add_argument("--stages", action="store_true",
                        help="also print the batched run's seconds in BatchChain.finish and in the smoother")
    parser.add_argument("--cpp-wrapper", action="store_true",
                        help="with filter.compile: inductor's C++ wrapper (torch._inductor.config.cpp_wrapper) "
                        "instead of its Python one")
    parser.add_argument("overrides", nargs="*", help="evaluate.py's KEY=VALUE overrides of the filter, e.g. "
                        "filter.gnss_heading.second_pass=true")
    args = parser.parse_args()
    if args.cpp_wrapper:
        from torch._inductor import config as inductor

        inductor.cpp_wrapper = True
    for name in ("repeats", "batch", "step_s"):
        if getattr(args, name) < 0:
            parser.error(f"--{name.replace('_', '-')} must be >= 0, got {getattr(args, name)}")
    with initialize_config_dir(config_dir=CONFIGS, version_base=None):
        cfg = OmegaConf.to_container(compose("evaluate", overrides=[f"filter.flow.n_points={args.points}",
                                                                    f"flow.device={args.device}", *args.overrides]),
                                     resolve=False)
    rec = load_recording(cfg["sequence"], quick=args.quick, progress=True)
    pairs = load_flow("dense", rec, cfg, progress=True)
    config = dataclasses.replace(filter_setup(cfg, [rec], recorded=False).navigation,
                                 device=check_device(args.device, "--device"))
    duration = float(rec.imu.t_s[-1] - rec.imu.t_s[0])
    where = (f"on {torch.cuda.get_device_name(config.device)}" if config.device.type == "cuda"
             else f"on the CPU, {torch.get_num_threads()} threads")
    if config.workers > 1 and config.device.type == "cpu" and args.batch > 1:
        where += f" (the batch: {min(config.workers, args.batch)} worker processes of one thread)"

    print(f"{rec.name}: {duration:.0f} s, {len(pairs)} flow frames, up to {args.points} points each, "
          f"{len(rec.gnss)} GNSS fixes, float64, filter {where}")

    _, warm = run(*crop(rec, pairs, 10.0)[:3], FlowCamera.from_sequence(rec.sequence), config)  # warm-up
    if warm.filter_steps:  # filter.compile: the warm-up pays for the single run's shapes
        print(f"warm-up, 10 s: {warm.filter_steps}")
    fast = batched = None
    if args.repeats > 0:
        fast, batched = timed(rec, pairs, config, duration, args)

    workers = config.workers
    if args.reference_s > 0:
        paper = dataclasses.replace(config, jacobians="autodiff",
                                    flow_update=dataclasses.replace(config.flow_update, sequential=True))
        imu_c, gnss_c, pairs_c = crop(rec, pairs, args.reference_s)
        span = float(imu_c.t_s[-1] - imu_c.t_s[0])
        slow, _ = run(imu_c, gnss_c, pairs_c, FlowCamera.from_sequence(rec.sequence), paper)
        fast_c, _ = run(imu_c, gnss_c, pairs_c, FlowCamera.from_sequence(rec.sequence), config)
        print(f"paper's way:   {slow:7.2f} s for the first {span:.0f} s -> {span / slow:6.1f}x real time "
              f"(flowins on the same window: {fast_c:.2f} s, {slow / fast_c:.1f}x faster)")
    # the diagnostics look inside one process: the batch there too
    config = dataclasses.replace(config, workers=1)
    if args.breakdown_s > 0:
        breakdown(*crop(rec, pairs, args.breakdown_s), FlowCamera.from_sequence(rec.sequence), config)
    if args.count_ops_s > 0:
        camera = FlowCamera.from_sequence(rec.sequence)
        same = batch_runs(rec, pairs, camera, args.batch, end_s=args.count_ops_s, step_s=0.0) if args.batch > 1 else None
        count_ops(*crop(rec, pairs, args.count_ops_s), camera, config, same)
    if args.profile_s > 0:
        camera = FlowCamera.from_sequence(rec.sequence)
        short = batch_runs(rec, pairs, camera, args.batch, end_s=args.profile_s, step_s=2.0) if args.batch else None
        profile(*crop(rec, pairs, args.profile_s), camera, config, short)
    print(f"RESULT single={'n/a' if fast is None else f'{duration / fast:.1f}x'} batched={'n/a' if batched is None else f'{batched:.1f}x'} "
          f"batch={args.batch} device={config.device} workers={workers}")


if __name__ == "__main__":
    main()
