"""The flow networks' last convolutions by kernel rows (conv2d_rows) against F.conv2d, on CPU.

For the two layers that Monte Carlo dropout repeats, at the full resolution of a
``--size`` input (padded as the networks pad it), prints milliseconds per call of

* reference: ``F.conv2d`` on contiguous (NCHW) features and on channels-last (CL) ones;
* flowins: :func:`flowins.flow.conv.conv2d_rows` on the same two (from NCHW, its
  conversion to channels-last included; SpyNet's features arrive NCHW, FlowNet2's CL);

the ratios rows / conv2d for each input layout, and the largest difference from a
float64 convolution relative to the output's largest value (float32 rounding).

    python benchmarks/bench_conv_rows.py [--size 320x240] [--repeats 20]
"""
from __future__ import annotations

import argparse

import torch
import torch.nn.functional as F
from timing import interleaved_ms  # benchmarks/timing.py

from flowins.flow.conv import conv2d_rows

#: (name, input channels, output channels, kernel, size multiple)
LAYERS = (
    ("SpyNet, finest level, conv 4 (16->2, 7x7)", 16, 2, 7, 32),
    ("FlowNet2, predict_flow0 (16->2, 3x3)", 16, 2, 3, 64),
)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", default="320x240", help="WIDTHxHEIGHT of the input images")
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {torch.backends.cpu.get_cpu_capability()}, "
          f"median of {args.repeats}")
    print(f"{'layer':46s}{'features':>12s}{'conv2d':>8s}{'rows':>7s}{'ratio':>7s}{'conv2d CL':>11s}"
          f"{'rows CL':>9s}{'ratio':>7s}{'rel. error':>12s}")
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for name, c_in, c_out, k, multiple in LAYERS:
            h, w = (-(-s // multiple) * multiple for s in (height, width))
            x = torch.randn(1, c_in, h, w, generator=gen)
            weight, bias = torch.randn(c_out, c_in, k, k, generator=gen), torch.randn(c_out, generator=gen)
            pad = (k // 2, k // 2)
            x_cl = x.contiguous(memory_format=torch.channels_last)
            ref, rows, ref_cl, rows_cl = interleaved_ms(
                [lambda: F.conv2d(x, weight, bias, padding=pad),
                 lambda: conv2d_rows(x, weight, bias, pad),
                 lambda: F.conv2d(x_cl, weight, bias, padding=pad),
                 lambda: conv2d_rows(x_cl, weight, bias, pad)],
                args.repeats,
            )
            exact = F.conv2d(x.double(), weight.double(), bias.double(), padding=pad)
            err = float((conv2d_rows(x, weight, bias, pad).double() - exact).abs().max() / exact.abs().max())
            print(f"{name:46s}{f'{c_in}x{h}x{w}':>12s}{ref:8.2f}{rows:7.2f}{rows / ref:7.2f}{ref_cl:11.2f}"
                  f"{rows_cl:9.2f}{rows_cl / ref_cl:7.2f}{err:12.1e}")

if __name__ == "__main__":
    main()
