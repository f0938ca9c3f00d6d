"""SpyNet + Monte Carlo dropout on CPU: cost of the run-once scheme, and accuracy.

Prints, per image size, milliseconds per pair (median of ``--repeats`` rounds after
a warm-up round; each round runs the three once, interleaved) for

* plain:     one deterministic SpyNet forward (the reference, ratio 1.0);
* run-once:  :class:`SpyNetProvider` with N passes, upstream once, last conv N times
             (its whole call: input checks and the σ floor included);
* naive:     N full forwards, each with its own dropout mask;

their ratios to plain, the process's peak RSS after each size, the thread count,
and the end-point error on the Middlebury 2014 'motorcycle' pair of scikit-image
(left -> right flow ``(-d, 0)`` at pixels with ground truth) at three scales.

    python benchmarks/bench_spynet_mc.py [--passes 10] [--repeats 5] [--threads N] [--chunk K]

Timings on a shared machine vary from run to run; compare ratios within one run.
"""

from __future__ import annotations

import argparse
import resource

import cv2
import numpy as np
import torch
from skimage import data
from timing import interleaved_ms  # benchmarks/timing.py

from flowins.flow.spynet import SpyNetProvider


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def as_batch(image: np.ndarray) -> torch.Tensor:
    return (
        torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float()
        / 255.0
    )


def shifted_pair(width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    big = cv2.resize(
        data.astronaut(), (width + 8, height + 8), interpolation=cv2.INTER_AREA
    )
    return as_batch(big[:height, :width]), as_batch(
        np.roll(big, (2, 3), axis=(0, 1))[:height, :width]
    )


def motorcycle_epe(
    provider: SpyNetProvider, scale: float
) -> tuple[float, float, tuple[int, int]]:
    left, right, disp = data.stereo_motorcycle()
    H, W = disp.shape
    w, h = round(W * scale), round(H * scale)
    if (w, h) != (W, H):
        left = cv2.resize(left, (w, h), interpolation=cv2.INTER_AREA)
        right = cv2.resize(right, (w, h), interpolation=cv2.INTER_AREA)
        disp = cv2.resize(
            disp.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST
        ) * (w / W)
    valid = np.isfinite(disp)
    flow = provider(left, right).flow[0].numpy()
    return (
        float(np.hypot(flow[0] + disp, flow[1])[valid].mean()),
        float(np.abs(disp[valid]).mean()),
        (w, h),
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--passes", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch intra-op threads (default: torch's)",
    )
    parser.add_argument(
        "--chunk",
        type=int,
        default=None,
        help="MC passes per head batch (0: all; default: the provider's)",
    )
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    provider = SpyNetProvider(mc_passes=args.passes)
    if args.chunk is not None:
        provider.mc_chunk = args.chunk or None
    net = provider.spynet
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, N = {args.passes} passes, "
        f"dropout before conv {provider.dropout_conv} of level {provider.dropout_level}, "
        f"{provider.mc_chunk or args.passes} pass(es) per chunk, median of {args.repeats}"
    )
    print(
        f"{'size':>9} {'plain ms':>9} {'run-once ms':>12} {'naive ms':>9} {'once/plain':>11} {'naive/plain':>12} {'peak RSS MiB':>13}"
    )
    with torch.no_grad():
        for width, height in ((320, 240), (512, 384)):
            a, b = shifted_pair(width, height)
            plain, once, naive = interleaved_ms(
                [
                    lambda a=a, b=b: net(a, b),
                    lambda a=a, b=b: provider(a, b),
                    lambda a=a, b=b: provider.naive_samples(a, b, passes=args.passes, batched=False),
                ],
                args.repeats,
            )
            print(
                f"{width}x{height:<5} {plain:9.1f} {once:12.1f} {naive:9.1f} {once / plain:11.2f} {naive / plain:12.2f} "
                f"{peak_rss_mib():13.0f}"
            )

        print(
            "\nEPE on Middlebury 2014 'motorcycle' (scikit-image, left -> right = (-d, 0)), weights REDS4, "
            f"N = {args.passes}:"
        )
        for scale in (0.25, 0.5, 1.0):
            epe, zero, (w, h) = motorcycle_epe(provider, scale)
            print(f"  {w}x{h}: EPE {epe:.3f} px  (zero flow {zero:.3f} px)")


if __name__ == "__main__":
    main()
