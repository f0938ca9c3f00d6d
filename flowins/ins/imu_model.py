"""The IMU's error model: noise densities, bias walks and ranges of a sensor (``configs/imu``).

Datasheets and Kalibr give white-noise densities (``σ_a`` m/s²/√Hz, ``σ_ω`` rad/s/√Hz)
and bias random walks (m/s³/√Hz, rad/s²/√Hz). A filter on a real recording also meets
errors these leave out (scale and axis misalignment, vibration, time stamps), so a
preset carries an ``inflation`` of the densities it hands the filter.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from flowins.ins.mechanization import ProcessNoise

#: Kalibr's key -> ImuModel field
KALIBR_KEYS = {
    "accelerometer_noise_density": "acc_noise",
    "gyroscope_noise_density": "gyro_noise",
    "accelerometer_random_walk": "acc_bias_walk",
    "gyroscope_random_walk": "gyro_bias_walk",
}


@dataclass(frozen=True)
class ImuModel:
    """A sensor's error model (all 1-σ spectral densities, per axis)."""

    name: str
    acc_noise: float  # m/s²/√Hz
    gyro_noise: float  # rad/s/√Hz
    acc_bias_walk: float = 0.0  # m/s³/√Hz
    gyro_bias_walk: float = 0.0  # rad/s²/√Hz
    inflation: float = 1.0
    acc_range_mps2: float | None = None
    gyro_range_rps: float | None = None
    rate_hz: float | None = None
    source: str = ""

    def __post_init__(self) -> None:
        for key in ("acc_noise", "gyro_noise", "acc_bias_walk", "gyro_bias_walk", "inflation"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ValueError(f"imu.{key} ({self.name}) must be a finite number >= 0, got {value!r}")
        if self.inflation == 0:
            raise ValueError(f"imu.inflation ({self.name}) must be > 0")

    def noise(self) -> dict[str, float]:
        """The densities the filter uses: the noise densities times ``inflation``, the walks as given."""
        return {"acc_noise": self.acc_noise * self.inflation, "gyro_noise": self.gyro_noise * self.inflation,
                "acc_bias_walk": self.acc_bias_walk, "gyro_bias_walk": self.gyro_bias_walk}

    def process_noise(self, discretization: str = "density") -> ProcessNoise:
        return ProcessNoise(**self.noise(), discretization=discretization)


def _number(value: Any, *, key: str, file: Path) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        raise ValueError(f"{file}: {key} is {value!r}; expected a finite number >= 0")
    return float(value)


def read_kalibr_imu(path: str | Path, *, inflation: float = 1.0) -> ImuModel:
    """An :class:`ImuModel` from a Kalibr IMU YAML file (``accelerometer_noise_density``,
    ``gyroscope_noise_density``, ``accelerometer_random_walk``, ``gyroscope_random_walk``,
    ``update_rate``), flat or under one key (``imu0:``, as Kalibr's camchain outputs)."""
    from flowins.data.csvio import read_yaml

    file = Path(path)
    data = read_yaml(file, what="a Kalibr IMU file (imu=kalibr imu.path=FILE)")
    if not any(k in data for k in KALIBR_KEYS):
        nested = [v for v in data.values() if isinstance(v, dict) and any(k in v for k in KALIBR_KEYS)]
        if len(nested) != 1:
            raise ValueError(f"{file}: no Kalibr IMU keys ({', '.join(KALIBR_KEYS)}) at the top level or under "
                             f"exactly one key; found keys {sorted(data)}")
        data = nested[0]
    missing = [k for k in KALIBR_KEYS if k not in data]
    if missing:
        raise ValueError(f"{file}: missing {', '.join(missing)}; a Kalibr IMU file has {', '.join(KALIBR_KEYS)}")
    values = {field: _number(data[key], key=key, file=file) for key, field in KALIBR_KEYS.items()}
    rate = data.get("update_rate")
    rate = None if rate is None else _number(rate, key="update_rate", file=file)
    return ImuModel(name=f"kalibr:{file.name}", **values, inflation=inflation, rate_hz=rate, source=str(file))


def imu_model(cfg: Any, *, recording: bool, sensor: str | None = None) -> ImuModel:
    """The :class:`ImuModel` of the ``imu`` config group: a preset, ``kalibr`` (read from
    ``imu.path``) or ``auto``: the preset ``sensor`` the recording names (its metadata's
    ``imu``), else ``imu.recording`` on a recording and ``imu.simulated`` on the simulated walk."""
    cfg = dict(cfg)
    if cfg.get("name") == "auto":
        choice = sensor or cfg["recording" if recording else "simulated"]
        if choice not in cfg or not isinstance(cfg[choice], Mapping):
            presets = [k for k, v in cfg.items() if isinstance(v, Mapping)]
            raise ValueError(f"imu=auto: the recording names the IMU preset {choice!r} (metadata.yaml imu), which is "
                             f"none of {presets}; name one with imu=...")
        cfg = dict(cfg[choice])
    if cfg.get("name") == "kalibr":
        path = cfg.get("path")
        if not path or path == "???":
            raise ValueError("imu=kalibr needs imu.path=FILE (a Kalibr IMU YAML file)")
        return read_kalibr_imu(path, inflation=float(cfg.get("inflation", 1.0)))
    fields = ("name", "acc_noise", "gyro_noise", "acc_bias_walk", "gyro_bias_walk", "inflation", "acc_range_mps2",
              "gyro_range_rps", "source")
    unknown = sorted(set(cfg) - set(fields) - {"path", "rate_hz"})
    if unknown:
        raise ValueError(f"imu: unknown keys {unknown}; expected {', '.join(fields)}")
    return ImuModel(**{k: cfg[k] for k in fields if k in cfg})
