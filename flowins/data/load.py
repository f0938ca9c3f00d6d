"""A recording for a job: read from ``sequence.path`` or the built-in simulated walk.

``load_recording(cfg["sequence"])`` is what both jobs start from: a flowins folder, EuRoC,
ADVIO or KITTI raw read by :func:`flowins.data.read.read_sequence` (every input stream
inside the IMU's time span, or cropped to it with ``sequence.crop=true``), or the
simulated city walk (:func:`flowins.data.simulate.simulate`, cached).
"""
from __future__ import annotations

import dataclasses
import functools
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from flowins.data.fingerprint import camera_content_key
from flowins.data.sequence import Sequence, within_imu_span
from flowins.data.streams import GnssStream, ImuStream, PoseStream

log = logging.getLogger("flowins")


@dataclass
class Recording:
    """A job's input: the sequence, and what reading it changed."""

    sequence: Sequence
    #: what reading changed (a stream cropped to the IMU span), printed and kept in metrics.json
    warnings: list[str] = dataclasses.field(default_factory=list)

    @property
    def name(self) -> str:
        return self.sequence.name

    @property
    def imu(self) -> ImuStream:
        return self.sequence.imu

    @property
    def gnss(self) -> GnssStream | None:
        return self.sequence.gnss

    @property
    def truth(self) -> PoseStream | None:
        return self.sequence.groundtruth

    @property
    def sensor(self) -> str | None:
        """The IMU preset the recording names (``metadata.yaml`` ``imu``), or None."""
        return self.sequence.metadata.get("imu")

    @property
    def platform(self) -> str | None:
        """What carries the sensors (``metadata.yaml`` ``platform``, e.g. ``vehicle``), or None."""
        value = self.sequence.metadata.get("platform")
        return None if value is None else str(value)

    @functools.cached_property
    def content_key(self) -> str:
        """Content key of the recording's frames, calibration and tracks, the flow cache's
        key for the recording (:func:`flowins.data.fingerprint.camera_content_key`; it
        reads every frame file, so only once and only when flow is asked for)."""
        return camera_content_key(self.sequence)


def load_recording(cfg: Mapping[str, Any], *, quick: bool, progress: bool = False) -> Recording:
    """The ``sequence`` config group's recording: ``sequence.path=DIR`` read (flowins
    folder, EuRoC, ADVIO, KITTI raw), or the simulated city walk (cached); ``quick``: the
    walk's short version."""
    if cfg.get("path"):
        from flowins.data.read import read_sequence

        seq = read_sequence(cfg["path"], max_imu_gap_s=cfg["max_imu_gap_s"])
        seq, cropped = within_imu_span(seq, crop=cfg["crop"])
        for line in cropped:
            log.warning("warning: %s", line)
        return time_window(Recording(seq, cropped), cfg.get("start_s"), cfg.get("end_s"))
    if cfg["kind"] != "simulated_walk":
        raise ValueError(
            f"sequence.kind={cfg['kind']!r} is not supported; use the built-in 'simulated_walk' "
            "or give a recording with sequence.path=DIR"
        )
    from flowins.data.simulate import CameraConfig, SimulationConfig, simulate

    config = SimulationConfig(
        duration_s=float(cfg["quick_duration_s"] if quick else cfg["duration_s"]),
        seed=int(cfg["seed"]),
        imu_rate_hz=float(cfg["imu_rate_hz"]),
        camera=CameraConfig(**dict(cfg["camera"])),
        flow_every=0,
    )
    return time_window(Recording(simulate(config=config, progress=progress)), cfg.get("start_s"), cfg.get("end_s"))


def time_window(rec: Recording, start_s: float | None, end_s: float | None) -> Recording:
    """The part of ``rec`` from ``start_s`` to ``end_s`` seconds after its first IMU sample
    (``sequence.start_s``, ``sequence.end_s``; None: from the start, to the end): the IMU
    samples in it, and the frames, tracks, GNSS fixes and ground truth cropped to the IMU
    samples' span. Both None: ``rec`` itself."""
    if start_s is None and end_s is None:
        return rec
    imu = rec.imu
    t0, duration = float(imu.t_s[0]), float(imu.t_s[-1] - imu.t_s[0])
    a = 0.0 if start_s is None else float(start_s)
    b = duration if end_s is None else float(end_s)
    if a >= duration:
        raise ValueError(f"{rec.name}: start_s={start_s!r} (sequence.start_s or a data source's) is past its "
                         f"{duration:.3f} s of IMU data; expected a start inside it")
    if not 0.0 <= a < b:
        raise ValueError(f"{rec.name}: start_s={start_s!r}, end_s={end_s!r} (sequence.start_s/end_s or a data "
                         f"source's): expected 0 <= start_s < end_s, seconds after the first IMU sample")
    seq = dataclasses.replace(rec.sequence, imu=imu.slice_time(t0 + a, t0 + b))
    seq, _ = within_imu_span(seq, crop=True)
    if seq.groundtruth is not None:
        truth, span = seq.groundtruth, (float(seq.imu.t_s[0]), float(seq.imu.t_s[-1]))
        keep = (truth.t_s >= span[0]) & (truth.t_s <= span[1])
        if not bool(keep.any()):
            raise ValueError(f"{truth.name}: no ground truth in the window [{a:.3f}, {b:.3f}] s of {rec.name}")
        quat = None if truth.quat_wxyz is None else truth.quat_wxyz[keep]
        seq = dataclasses.replace(seq, groundtruth=PoseStream(truth.t_s[keep], truth.pos_m[keep], quat, name=truth.name))
    log.info(f"{rec.name}: {a:.3f} s to {min(b, duration):.3f} s after its first IMU sample "
             f"(start_s, end_s): {len(seq.imu)} of {len(imu)} IMU samples, every stream cropped to them")
    return Recording(seq, rec.warnings)
