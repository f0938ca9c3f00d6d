"""Speed of FlowNet2 Monte Carlo dropout on CPU: run-once (upstream computed once) vs naive.

RANDOM WEIGHTS (NVIDIA's initialisation, no checkpoint): the flows are meaningless,
the figures are speed only. Prints ms per image pair for

* one plain forward (no dropout) — the reference;
* N_MC passes with dropout option #2 (concat0, paper's choice), upstream run once;
* N_MC passes with dropout option #1 (fusion encoder outputs), upstream run once;
* N_MC complete forward passes (the naive way);

with ratios to the plain forward, the peak resident memory of the process and the
torch thread count. Usage::

    python benchmarks/bench_flownet2_mc.py [--size 320x240] [--passes 10] [--repeats 3] [--device cpu]
"""
from __future__ import annotations

import argparse
import resource
import sys

import torch
from timing import interleaved_ms  # benchmarks/timing.py

from flowins.flow.base import pad_to_multiple
from flowins.flow.flownet2 import FlowNet2
from flowins.flow.mc_dropout import MCDropout


def _peak_rss_mib() -> float:
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / 1024.0 if sys.platform != "darwin" else rss / 2**20  # KiB on Linux, bytes on macOS


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", default="320x240", help="WIDTHxHEIGHT of the input images (padded to multiples of 64)")
    parser.add_argument("--passes", type=int, default=10, help="N_MC (paper: 10)")
    parser.add_argument("--p", type=float, default=0.2, help="dropout rate")
    parser.add_argument("--repeats", type=int, default=3, help="timings are the best of this many rounds (each round runs every row once)")
    parser.add_argument("--chunk", type=int, default=1, help="passes per batch in the run-once path (default 1, the provider's default; 0: all at once)")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    W, H = (int(v) for v in args.size.lower().split("x"))
    device = torch.device(args.device)

    print("FlowNet2 Monte Carlo dropout benchmark — RANDOM WEIGHTS, speed only (flows are meaningless)")
    torch.manual_seed(0)
    model = FlowNet2(dropout_option=2, p=args.p, passes=args.passes, chunk=args.chunk or None).eval().to(device)
    images = torch.rand(1, 3, 2, H, W)
    padded, _ = pad_to_multiple(images.flatten(1, 2), 64)
    inputs = (padded.unflatten(1, (3, 2)) * 255.0).to(device)
    Hp, Wp = inputs.shape[-2:]
    print(
        f"input {W}x{H} (padded to {Wp}x{Hp}), N_MC={args.passes}, p={args.p}, device={device}, "
        f"torch {torch.__version__}, threads={torch.get_num_threads()}"
    )

    def plain():
        model.dropout_option, model.mc_dropout = None, None
        return model(inputs)

    def once(option: int):
        def run():
            model.dropout_option, model.mc_dropout = option, MCDropout(args.p)
            return model.mc_samples(inputs, args.passes)

        return run

    def naive():
        model.dropout_option, model.mc_dropout = 2, MCDropout(args.p)
        return model.mc_samples_naive(inputs, args.passes)

    runs = [
        ("plain forward (no dropout)", plain),
        (f"option #2 run-once, N={args.passes}", once(2)),
        (f"option #1 run-once, N={args.passes}", once(1)),
        (f"naive {args.passes} full forwards", naive),
    ]
    with torch.no_grad():
        plain()  # warm-up (allocator, oneDNN primitives)
        once(2)()
        # interleaved (every row once per round): a shared CPU's speed drifts over minutes
        best = interleaved_ms([fn for _, fn in runs], args.repeats, reduce=min, warmup=False,
                              sync=torch.cuda.synchronize if device.type == "cuda" else None)
    rows = [(name, ms) for (name, _), ms in zip(runs, best)]
    ref = rows[0][1]
    print(f"{'':40s}{'ms':>10s}{'x plain':>10s}")
    for name, ms in rows:
        print(f"{name:40s}{ms:10.1f}{ms / ref:10.2f}")
    print(f"peak resident memory: {_peak_rss_mib():.0f} MiB (ru_maxrss, whole process)")
    if device.type == "cuda":
        print(f"peak CUDA memory: {torch.cuda.max_memory_allocated(device) / 2**20:.0f} MiB")


if __name__ == "__main__":
    main()
