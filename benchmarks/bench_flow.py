"""Flow providers on CPU: time per pair, peak memory, and accuracy on exact ground truth.

For each provider that imports (DIS and Shi–Tomasi + LK from this package; SpyNet
and FlowNet 2.0 when present, FlowNet 2.0 with NVIDIA's *random* initialisation
unless ``--flownet2-checkpoint`` is given) a worker process times one pair at
320x240 and 512x384, without and with Monte Carlo dropout where the provider has
it, and reports the process's peak resident memory after each configuration
(``ru_maxrss``: cumulative within a provider's worker, configurations run from
small to large). Each worker also times DIS (medium) at 320x240 first, the
reference of the ratio column, so ratios stand on a shared machine.

Then an accuracy table on the two reference pairs of :mod:`flowins.flow.flo`
(Middlebury *Motorcycle* at 1/4 size, and a simulator pair with exact flow):
end-point error (EPE; LK on its points), the share of component errors within
±1σ, and the median σ.

    python benchmarks/bench_flow.py [--providers dis,lk,spynet,flownet2] [--threads 2] [--min-time 1.0]
                                    [--flownet2-checkpoint PATH]

Prints markdown tables. Never fails on time.
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import numpy as np

SIZES = ((320, 240), (512, 384))
ALL = ("dis", "lk", "spynet", "flownet2")


def _build(name: str, mc: bool, checkpoint: str | None):
    """A provider by name, or a string saying why it is not available."""
    try:
        if name == "dis":
            from flowins.flow.classical import DISProvider

            return DISProvider()
        if name == "lk":
            from flowins.flow.sparse import ShiTomasiLK

            return ShiTomasiLK()
        if name == "spynet":
            from flowins.flow.spynet import SpyNetProvider

            return SpyNetProvider(mc_passes=10 if mc else 0, p=0.2)
        if name == "flownet2":
            from flowins.flow.flownet2.provider import FlowNet2Provider

            option = 2 if mc else None
            if checkpoint:
                return FlowNet2Provider(checkpoint, dropout_option=option, p=0.2, passes=10)
            return FlowNet2Provider.untrained(dropout_option=option, p=0.2, passes=10)
    except Exception as exc:  # noqa: BLE001 - reported, not swallowed: the table says why
        return f"not available ({type(exc).__name__}: {str(exc).splitlines()[0][:80]})"
    raise ValueError(f"unknown provider {name!r}; expected one of {ALL}")


def _has_mc(name: str) -> bool:
    return name in ("spynet", "flownet2")


def _images(width: int, height: int):
    import cv2
    import torch

    from flowins.data.reference_flow import middlebury_pair

    pair = middlebury_pair(1)
    a, b = (cv2.resize(x, (width, height), interpolation=cv2.INTER_AREA) for x in (pair.image1, pair.image2))
    return torch.from_numpy(a), torch.from_numpy(b)


def _time(provider, a, b, min_time_s: float) -> tuple[float, float]:
    """Median and best seconds per call over at least ``min_time_s`` (at least one call after a
    warm-up; a single timed call when the warm-up took over 5 s)."""
    import torch

    with torch.inference_mode():
        t0 = time.perf_counter()
        provider(a, b)  # warm-up (allocations, OpenCV/oneDNN kernels)
        first = time.perf_counter() - t0
        times: list[float] = []
        while not times or (sum(times) < min_time_s and first < 5.0):
            t0 = time.perf_counter()
            provider(a, b)
            times.append(time.perf_counter() - t0)
    return float(np.median(times)), float(min(times))


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def worker(name: str, threads: int, min_time_s: float, checkpoint: str | None) -> list[dict]:
    """One provider, every size and dropout setting; rows as dicts (run in a fresh process)."""
    import torch

    torch.set_num_threads(threads)
    from flowins.flow.classical import DISProvider

    a, b = _images(*SIZES[0])
    reference = _time(DISProvider(), a, b, min_time_s)[0]
    rows = []
    for mc in ((False, True) if _has_mc(name) else (False,)):
        provider = _build(name, mc, checkpoint)
        for width, height in SIZES:
            row = dict(provider=name, mc=mc, size=f"{width}x{height}", reference_ms=reference * 1e3)
            if isinstance(provider, str):
                rows.append(dict(row, error=provider))
                continue
            a, b = _images(width, height)
            seconds, best = _time(provider, a, b, min_time_s)
            rows.append(
                dict(row, ms=seconds * 1e3, best_ms=best * 1e3, ratio=seconds / reference, peak_rss_mib=_peak_rss_mib())
            )
    return rows


def _accuracy(provider, pair) -> tuple[float, float, float, int]:
    """EPE, share of component errors within ±1σ, median σ, number of points."""
    import cv2

    from flowins.data.reference_flow import endpoint_error

    result = provider(pair.image1, pair.image2)
    if hasattr(result, "points"):  # sparse: ground truth at the points
        p = result.points.numpy().astype(np.float32)
        truth = cv2.remap(pair.flow, p[:, :1], p[:, 1:], cv2.INTER_LINEAR).reshape(-1, 2)
        iu = np.rint(p).astype(int)
        keep = pair.mask[iu[:, 1], iu[:, 0]]
        flow, sigma, truth = result.flow.numpy()[keep], result.sigma.numpy()[keep], truth[keep]
    else:
        flow = result.flow[0].permute(1, 2, 0).numpy()[pair.mask]
        sigma = result.sigma[0].permute(1, 2, 0).numpy()[pair.mask]
        truth = pair.flow[pair.mask]
    epe = float(endpoint_error(flow, truth).mean())
    within = float((np.abs(flow - truth) < sigma).mean())
    return epe, within, float(np.median(sigma)), len(flow)


def accuracy_table(names: list[str], checkpoint: str | None) -> list[str]:
    from flowins.flow.classical import DISProvider
    from flowins.data.reference_flow import middlebury_pair, simulator_pair

    pairs = [middlebury_pair(), simulator_pair()]
    candidates = []
    if "dis" in names:
        candidates += [(f"DIS {p}", DISProvider(p)) for p in ("ultrafast", "fast", "medium")]
    if "lk" in names:
        candidates.append(("Shi-Tomasi + LK (points)", _build("lk", False, None)))
    if "spynet" in names:
        candidates += [("SpyNet", _build("spynet", False, None)), ("SpyNet, MC dropout x10", _build("spynet", True, None))]
    if "flownet2" in names and checkpoint:
        candidates.append(("FlowNet2, MC dropout x10", _build("flownet2", True, checkpoint)))
    head = " | ".join(f"{p.name}: EPE px | ±1σ | med σ px" for p in pairs)
    lines = [f"| provider | {head} |", "|---|" + "---:|" * (3 * len(pairs))]
    for label, provider in candidates:
        if isinstance(provider, str):
            lines.append(f"| {label} | {provider} |" + " |" * (3 * len(pairs) - 1))
            continue
        cells = []
        for pair in pairs:
            epe, within, med, n = _accuracy(provider, pair)
            cells += [f"{epe:.3f}" + (f" (n={n})" if hasattr(provider, "track") else ""), f"{within:.2f}", f"{med:.3f}"]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    if "flownet2" in names and not checkpoint:
        lines.append("")
        lines.append("FlowNet2: no accuracy without NVIDIA's checkpoint (--flownet2-checkpoint); timings use random weights.")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--providers", default=",".join(ALL), help=f"comma-separated subset of {','.join(ALL)}")
    parser.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    parser.add_argument("--min-time", type=float, default=1.0, help="seconds of timed calls per configuration")
    parser.add_argument("--flownet2-checkpoint", default=None)
    parser.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(args.worker, args.threads, args.min_time, args.flownet2_checkpoint)))
        return
    names = [n.strip() for n in args.providers.split(",") if n.strip()]
    unknown = sorted(set(names) - set(ALL))
    if unknown:
        parser.error(f"unknown providers {unknown}; expected a subset of {ALL}")

    import torch

    print(f"# flow providers, CPU, torch {torch.__version__}, {args.threads} thread(s)\n")
    lines = [
        "| provider | MC dropout | size | ms / pair (median) | best ms | x DIS medium 320x240 (same process) | peak RSS MiB |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    for name in names:
        cmd = [sys.executable, __file__, "--worker", name, "--threads", str(args.threads), "--min-time", str(args.min_time)]
        if args.flownet2_checkpoint:
            cmd += ["--flownet2-checkpoint", args.flownet2_checkpoint]
        done = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            tail = (done.stderr.strip().splitlines() or ["?"])[-1][:100]
            lines.append(f"| {name} | | | worker failed: {tail} | | | |")
            continue
        for row in json.loads(done.stdout.strip().splitlines()[-1]):
            mc = ("x10" if row["mc"] else "off") if _has_mc(name) else "n/a"
            label = name + (" (random weights)" if name == "flownet2" and not args.flownet2_checkpoint else "")
            if "error" in row:
                lines.append(f"| {label} | {mc} | {row['size']} | {row['error']} | | | |")
            else:
                lines.append(
                    f"| {label} | {mc} | {row['size']} | {row['ms']:.1f} | {row['best_ms']:.1f} | {row['ratio']:.2f} "
                    f"(ref {row['reference_ms']:.1f} ms) | {row['peak_rss_mib']:.0f} |"
                )
    print("\n".join(lines))
    print()
    torch.set_num_threads(args.threads)
    print("## accuracy on exact ground truth\n")
    print("\n".join(accuracy_table(names, args.flownet2_checkpoint)))


if __name__ == "__main__":
    main()
