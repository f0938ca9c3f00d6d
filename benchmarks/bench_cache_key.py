"""What keying the flow cache by content costs, against what computing flow must read anyway.

On the simulated walk (``--seconds``, default 300 s: ``evaluate.py``'s default, cached
under ``$FLOWINS_CACHE``), prints in one run the milliseconds of

* the content key: :func:`flowins.data.fingerprint.camera_content_key` (the SHA-256
  of every frame's file, the frame times, the calibration);
* reference: decoding every frame once (:meth:`flowins.data.CameraFrames.read`), the
  least that computing flow over the recording does;

and their ratio; then the keys of the flow pairs' code and of the simulation.

    python benchmarks/bench_cache_key.py [--seconds 300] [--repeats 3]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from timing import interleaved_ms  # noqa: E402

from flowins.cache import source_digest  # noqa: E402
from flowins.data.fingerprint import camera_content_key  # noqa: E402
from flowins.data.simulate import SimulationConfig, simulate  # noqa: E402
from flowins.flow.pairs import FLOW_CODE  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=300.0)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    config = SimulationConfig(duration_s=args.seconds, seed=0, flow_every=0)
    seq = simulate(config=config)
    frames = seq.frames
    megabytes = sum(f.stat().st_size for f in frames.files) / 1e6

    def decode_all() -> None:
        for i in range(len(frames)):
            frames.read(i)

    key_ms, decode_ms = interleaved_ms([lambda: camera_content_key(seq), decode_all], args.repeats)
    print(f"simulated walk: {args.seconds:.0f} s, {len(frames)} frames, {megabytes:.0f} MB of PNG")
    print(f"content key (SHA-256 of every frame):   {key_ms:8.1f} ms  ({key_ms / len(frames):.3f} ms per frame)")
    print(f"reference: decode every frame once:     {decode_ms:8.1f} ms  ({decode_ms / len(frames):.3f} ms per frame)")
    print(f"ratio key / decode: {key_ms / decode_ms:.3f}")
    print(f"keys: recording {camera_content_key(seq)}, simulation {config.key()}, "
          f"flow code {source_digest(*FLOW_CODE)[:16]}")


if __name__ == "__main__":
    main()
