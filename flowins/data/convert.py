"""Convert any supported sequence (flowins, EuRoC, ADVIO, KITTI raw) to the flowins folder format.

::

    python -m flowins.data.convert SRC OUT [--overwrite] [--no-frames]

Reads ``SRC`` with :func:`flowins.data.read.read_sequence`, writes ``OUT`` with
:func:`flowins.data.folder.write_folder`, reads ``OUT`` back and prints its
one-line summary. A ``ValueError`` (bad input) prints ``error: ...`` and exits
with status 2, without a traceback.
"""
from __future__ import annotations

import argparse
import sys

from flowins.data.folder import read_folder, write_folder
from flowins.data.read import read_sequence


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m flowins.data.convert",
        description="Convert a sequence (flowins folder, EuRoC, ADVIO or KITTI raw) to the flowins folder format.",
    )
    parser.add_argument("src", metavar="SRC", help="sequence folder to read")
    parser.add_argument("out", metavar="OUT", help="folder to write (flowins format)")
    parser.add_argument("--overwrite", action="store_true", help="replace the format's files in a non-empty OUT")
    parser.add_argument("--no-frames", action="store_true", help="do not copy images/video (calibration is kept)")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the converter; returns the exit status (0 ok, 2 bad input)."""
    args = _parser().parse_args(argv)
    try:
        seq = read_sequence(args.src)
        out = write_folder(seq, args.out, overwrite=args.overwrite, copy_frames=not args.no_frames)
        written = read_folder(out)
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(written.describe())
    return 0


if __name__ == "__main__":
    sys.exit(main())
