"""Which IMU error model a job's recordings get, and the checks every recording's IMU passes.

:func:`resolve_imu` is the one place the preset is chosen (``imu=auto``: the preset the
recordings' metadata name, else the white noise measured over their still starts,
:func:`measured_imu`); every reading is checked against the sensor's range, for an axis stuck
at it (:func:`check_saturation`) and for a gyroscope the accelerometer contradicts
(:func:`check_gyro_consistency`).
"""
from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Mapping, Sequence
from typing import Any, Protocol

from flowins.config import setting
from flowins.data.streams import ImuStream
from flowins.ins.consistency import gyro_consistency
from flowins.ins.imu_model import ImuModel, imu_model, still_noise_densities
from flowins.ins.initialization import still_interval
from flowins.ins.saturation import find_saturation

log = logging.getLogger("flowins")


class SensorRecording(Protocol):
    """What :func:`resolve_imu` reads of a recording: its IMU stream and the IMU preset its
    metadata names (``metadata.yaml`` ``imu``; None: it names none)."""

    @property
    def imu(self) -> ImuStream: ...

    @property
    def sensor(self) -> str | None: ...


def resolve_imu(imu_cfg: Mapping[str, Any], recordings: Sequence[SensorRecording], *, recorded: bool) -> ImuModel:
    """The IMU's error model for a job's ``recordings``: the one place the preset is chosen.

    ``imu=auto`` takes the preset the recordings' metadata name (they must agree), else, for
    recordings read from a path (``recorded``), the white noise measured over their still
    starts (:func:`measured_imu`) and ``imu.recording`` where there is none, and
    ``imu.simulated`` for the simulated walk; a named preset or ``imu=kalibr`` is taken as it is. Every reading of every
    recording is checked against the sensor's range (:meth:`ImuModel.check_readings`) and,
    unless ``imu.check_saturation`` is false, for an axis stuck at its range
    (:func:`check_saturation`) and, unless ``imu.check_consistency`` is false, its gyroscope
    against its accelerometer (:func:`check_gyro_consistency`)."""
    sensors = list(dict.fromkeys(rec.sensor for rec in recordings))
    if imu_cfg.get("name") == "auto" and len(sensors) > 1:
        raise ValueError(f"imu=auto: the recordings name different IMU presets {sensors} (metadata.yaml imu); "
                         "name one with imu=...")
    imu = imu_model(imu_cfg, recording=recorded, sensor=sensors[0] if sensors else None)
    if imu_cfg.get("name") == "auto" and recorded and sensors == [None]:
        imu = measured_imu(imu_cfg, recordings, fallback=imu)
    check = setting({"imu": imu_cfg}, "imu.check_consistency", bool, default=True)
    saturation = setting({"imu": imu_cfg}, "imu.check_saturation", bool, default=True)
    for rec in recordings:
        imu.check_readings(rec.imu)
        if saturation:
            check_saturation(rec.imu)
        if check:
            check_gyro_consistency(rec.imu)
    return imu


def measured_imu(imu_cfg: Mapping[str, Any], recordings: Sequence[SensorRecording], *, fallback: ImuModel) -> ImuModel:
    """The IMU model of recordings that name no sensor: the white-noise floor measured over
    each one's still start (:func:`~flowins.ins.initialization.still_interval`, at least
    ``imu.still_noise_min_s`` long; :func:`~flowins.ins.imu_model.still_noise_densities`, which
    a vibrating start does not fool), their RMS over the recordings, times
    ``imu.still_noise_inflation``, where that is above ``fallback``'s (the ``imu.recording``
    preset's) inflated densities: a still start sees the sensor's white noise but none of the
    errors a preset's inflation covers (scale, misalignment, vibration in motion, timing), so
    the measurement raises the preset's densities for a noisier sensor and never lowers them.
    The bias walks and ranges are ``fallback``'s. ``fallback`` is returned as it is when
    ``imu.still_noise`` is false, and with the reasons in its ``source`` when no recording
    starts still for long enough with a white floor to measure (a start whose vibration
    covers it); the source of a measured model names the recordings left out and why."""
    enabled = setting({"imu": imu_cfg}, "imu.still_noise", bool, default=True)
    min_s = setting({"imu": imu_cfg}, "imu.still_noise_min_s", float, minimum=0.0, default=2.0)
    inflation = setting({"imu": imu_cfg}, "imu.still_noise_inflation", float, minimum=1e-12, default=10.0)
    if not enabled:
        return fallback
    measured, refused = [], []
    for rec in recordings:
        stream = rec.imu
        still = still_interval(stream.t_s, stream.acc_mps2, stream.gyro_rps)
        if still.end < 10 or still.duration_s < min_s:
            refused.append(f"{stream.name}: still for {still.duration_s:.2f} s only (imu.still_noise_min_s={min_s:g})")
            continue
        m = still_noise_densities(stream.t_s, stream.acc_mps2, stream.gyro_rps, still.end)
        if not m.trusted:
            refused.append(f"{stream.name} {m.start_s:.2f}–{m.end_s:.2f} s: {m.reason}")
            continue
        measured.append((stream.name, m))
    if not measured:
        why = "; ".join(refused) or "no recording"
        return dataclasses.replace(fallback, source=f"{fallback.source}; the still start's noise is not measured "
                                                     f"({why}), so {fallback.name}'s densities are used")
    acc = math.sqrt(sum(m.acc_noise**2 for _, m in measured) / len(measured))
    gyro = math.sqrt(sum(m.gyro_noise**2 for _, m in measured) / len(measured))
    where = "; ".join(f"{name} {m.start_s:.2f}–{m.end_s:.2f} s ({m.samples} samples; all variance as white noise "
                      f"would read acc {m.acc_raw:.3g}, gyro {m.gyro_raw:.3g})" for name, m in measured)
    preset = fallback.noise()
    used = {key: (value * inflation, "measured") if value * inflation >= preset[key] else
            (preset[key], f"{fallback.name}'s, above the measured")
            for key, value in (("acc_noise", acc), ("gyro_noise", gyro))}
    (acc_used, acc_from), (gyro_used, gyro_from) = used["acc_noise"], used["gyro_noise"]
    source = (f"white-noise floor measured over the still start ({where}): acc {acc:.3g} m/s²/√Hz, gyro {gyro:.3g} "
              f"rad/s/√Hz, × {inflation:g} (imu.still_noise_inflation); the filter takes acc {acc_used:.3g} "
              f"({acc_from}) and gyro {gyro_used:.3g} ({gyro_from}); walks and ranges of {fallback.name}"
              + (f"; not measured on {'; '.join(refused)}" if refused else ""))
    return dataclasses.replace(fallback, name="measured", acc_noise=acc_used, gyro_noise=gyro_used, inflation=1.0,
                               source=source)


def check_saturation(stream: Any) -> None:
    """A ValueError naming ``stream`` and each axis that sticks at its range
    (:func:`~flowins.ins.saturation.find_saturation`): the filter would take the clipped
    readings for the motion."""
    found = find_saturation(stream.t_s, stream.acc_mps2, stream.gyro_rps)
    if found:
        raise ValueError(f"{stream.name}: the IMU saturates: " + "; ".join(f.describe() for f in found)
                         + ". The filter would take the clipped readings for the motion; cut the recording to the "
                         "part within the sensor's range, or set imu.check_saturation=false to run anyway")


def check_gyro_consistency(stream: Any) -> None:
    """A ValueError naming ``stream`` when its gyroscope disagrees with its accelerometer
    (:func:`~flowins.ins.consistency.gyro_consistency`), and deg/s when that is why."""
    result = gyro_consistency(stream.t_s, stream.acc_mps2, stream.gyro_rps)
    if result.consistent:
        if result.bias_rps is not None:
            log.info(f"{stream.name}: the gyroscope agrees with the accelerometer less {result.describe_bias()} "
                     f"({result.bias_source})")
        return
    hint = ("the readings look like deg/s: convert them to rad/s (× π/180)" if result.fix == "deg/s" else
            "check the gyroscope's unit (rad/s expected) and that its axes are the accelerometer's")
    raise ValueError(f"{stream.name}: the gyroscope's rotation does not explain the accelerometer's tilt: "
                     f"{result.describe()}; {hint}, or set imu.check_consistency=false to run anyway")
