"""The IMU's error model: noise densities, bias walks and ranges of a sensor (``configs/imu``).

Datasheets and Kalibr give white-noise densities (``σ_a`` m/s²/√Hz, ``σ_ω`` rad/s/√Hz)
and bias random walks (m/s³/√Hz, rad/s²/√Hz). A filter on a real recording also meets
errors these leave out (scale and axis misalignment, vibration, time stamps), so a
preset carries an ``inflation`` of the densities it hands the filter.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from flowins.config import build, setting
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
        for key in ("acc_range_mps2", "gyro_range_rps"):
            value = getattr(self, key)
            if value is not None and not value > 0:
                raise ValueError(f"imu.{key} ({self.name}) must be > 0 or null (unchecked), got {value!r}")

    def check_readings(self, imu: Any) -> None:
        """Every reading of ``imu`` (an :class:`~flowins.data.streams.ImuStream`) within the
        sensor's range (``imu.acc_range_mps2``, ``imu.gyro_range_rps``; null: unchecked),
        with 5 % of margin for the sensor's own scale errors; else a ValueError naming the
        stream, the sample and the key. A gyroscope in deg/s is named as such."""
        import torch

        for array, key, unit in ((imu.acc_mps2, "acc_range_mps2", "m/s²"), (imu.gyro_rps, "gyro_range_rps", "rad/s")):
            limit = getattr(self, key)
            if limit is None:
                continue
            peak = array.abs().amax(-1)
            over = torch.nonzero(peak > 1.05 * limit)
            if not over.numel():
                continue
            k = int(over[0, 0])
            what = "accelerometer" if key.startswith("acc") else "gyroscope"
            hint = f"fix or remove the sample, or set imu.{key} to the sensor's range"
            if what == "gyroscope":
                degrees = float(array.norm(dim=-1).median())
                if float(peak.max()) <= 1.05 * limit * 180.0 / math.pi and degrees > 0.5:
                    hint = (f"the readings look like deg/s (median |ω| {degrees:.3g}; {over.shape[0]} samples beyond "
                            "the range): convert them to rad/s (× π/180)")
            raise ValueError(f"{imu.name}: sample {k} (0-based, t = {float(imu.t_s[k]):.3f} s): {what} reading "
                             f"{float(peak[k]):.6g} {unit} beyond the sensor's range ±{limit:g} {unit} (imu.{key}, "
                             f"preset {self.name}); {hint}")

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
        path = setting({"imu": cfg}, "imu.path", str)
        model = read_kalibr_imu(path, inflation=setting({"imu": cfg}, "imu.inflation", float, minimum=0.0, default=1.0))
        ranges = {key: setting({"imu": cfg}, f"imu.{key}", float | None, minimum=0.0, default=None)
                  for key in ("acc_range_mps2", "gyro_range_rps")}
        return dataclasses.replace(model, **{k: v for k, v in ranges.items() if v is not None})
    checks = ("path", "check_consistency", "check_saturation")
    return build(ImuModel, {k: v for k, v in cfg.items() if k not in checks}, "imu")


@dataclass(frozen=True)
class MeasuredNoise:
    """White-noise densities measured over a still interval (:func:`still_noise_densities`).

    Attributes:
        acc_noise, gyro_noise: the white floor (m/s²/√Hz, rad/s/√Hz) of the quietest axis, by
            its one-σ upper bound.
        acc_axes, gyro_axes: the floor of each axis.
        acc_raw, gyro_raw: the standard deviation times √Δt (RMS over the axes): what the
            floor would be if all the variance were white noise; far above the floor, the
            still start vibrates.
        trusted: False when the floor can't be told from the vibration (``reason`` says why).
    """

    acc_noise: float  # m/s²/√Hz
    gyro_noise: float  # rad/s/√Hz
    samples: int
    start_s: float
    end_s: float
    acc_axes: tuple[float, float, float] = (math.nan,) * 3
    gyro_axes: tuple[float, float, float] = (math.nan,) * 3
    acc_raw: float = math.nan
    gyro_raw: float = math.nan
    trusted: bool = True
    reason: str = ""


def white_floor(t_s: Any, x: Any, *, trim: float = 6.0) -> tuple[list[float], list[bool], list[float]]:
    """Per column of ``x`` ``(N, C)``: the white-noise density ``N`` (unit/√Hz) under a
    vibration, and whether the vibration covers the floor at every frequency.

    A still platform's vibration moves it back and forth: the integral of what it adds to the
    readings (a velocity or an angle) stays bounded, while white noise's integral grows as
    ``N √t``. In the readings' spectrum vibration therefore vanishes toward low frequencies
    (readings that are the differences of a bounded, white integral have the spectrum
    ``∝ sin²(π f Δt)``, which is ``∝ f²`` at low frequencies), and white noise is flat. The
    spectrum is the periodogram of the readings less a straight line in time (Hann window,
    two-sided, so white noise of density ``N`` reads ``N²``), from its third bin to below
    Nyquist; it is fitted as ``N² (1 + r sin²(π f Δt))`` by Whittle's likelihood (each bin an
    exponential variable about the model), ``N²`` in closed form for each ``r`` of a grid from
    0 to ``1 / sin²(π f_min Δt)`` (the vibration may not exceed the floor at the lowest
    frequency fitted). Bins more than ``trim`` times the model (tones; an exponential
    variable is that far out once in 400) are left out and the fit repeated. The second value
    is True where the fitted ``r`` sits at the grid's end: the floor is then only an upper
    bound. The third is the number of bins the floor rests on, ``Σ 1 / (1 + r sin²)²`` over
    the bins kept (a floor measured where vibration dominates all but a few bins is uncertain:
    its relative σ is about ``1 / √bins``)."""
    import torch

    t = torch.as_tensor(t_s, dtype=torch.float64)
    x = torch.as_tensor(x, dtype=torch.float64)
    n = x.shape[0]
    dt = float(torch.diff(t).median())
    tau = (t - t.mean()) / max(float(t[-1] - t[0]), 1e-12)
    design = torch.stack((torch.ones_like(tau), tau), -1)
    x = x - design @ torch.linalg.lstsq(design, x).solution
    window = torch.hann_window(n, periodic=False, dtype=torch.float64)
    power = torch.fft.rfft(x * window[:, None], dim=0).abs() ** 2 * dt / float((window * window).sum())
    f = torch.fft.rfftfreq(n, dt).to(torch.float64)
    keep = (f >= 3.0 / (n * dt)) & (f < f[-1])
    power, f = power[keep], f[keep]
    rise = torch.sin(math.pi * f * dt) ** 2
    rates = torch.cat((torch.zeros(1, dtype=torch.float64),
                       torch.logspace(-6, 0, 121, dtype=torch.float64) / float(rise[0])))
    shape = 1.0 + rates[:, None] * rise[None, :]  # (R, K)
    floors, covered, bins = [], [], []
    for column in power.T:
        use = torch.ones_like(column, dtype=torch.bool)
        for _ in range(10):
            m = use.to(column.dtype)
            level = (column / shape * m).sum(-1) / m.sum()  # (R,)
            nll = (torch.log(shape) * m).sum(-1) + m.sum() * torch.log(level)
            best = int(nll.argmin())
            now = column / (level[best] * shape[best]) <= trim
            if bool((now == use).all()):
                break
            use = now
        floors.append(float(level[best]) ** 0.5)
        covered.append(best == rates.shape[0] - 1)
        bins.append(float((use.to(column.dtype) / shape[best] ** 2).sum()))
    return floors, covered, bins


def still_noise_densities(t_s: Any, acc_mps2: Any, gyro_rps: Any, end: int) -> MeasuredNoise:
    """The white-noise densities of rows ``[0, end)`` of a still IMU, vibration or not: the
    white floor of each axis (:func:`white_floor`) and, as the sensor's, the quietest axis's
    (vibration only adds, and a sensor's axes share one noise figure) by its one-σ upper
    bound ``N (1 + 1 / √bins)``: a floor that rests on a few bins below a strong vibration is
    uncertain, and the least of three uncertain floors is low by chance (a filter told too
    little noise trusts itself too much). Untrusted when every axis of a sensor is covered by
    vibration down to the lowest frequency. Needs ``end >= 10``."""
    import torch

    if end < 10:
        raise ValueError(f"still_noise_densities: {end} still samples; need at least 10")
    t = torch.as_tensor(t_s, dtype=torch.float64)[:end]
    dt = float(torch.diff(t).median())
    out: dict[str, Any] = {}
    reasons = []
    for key, x in (("acc", acc_mps2), ("gyro", gyro_rps)):
        x = torch.as_tensor(x, dtype=torch.float64)[:end]
        floors, covered, bins = white_floor(t, x)
        out[f"{key}_axes"] = tuple(floors)
        out[f"{key}_noise"] = min(f * (1.0 + 1.0 / math.sqrt(max(b, 1.0))) for f, b in zip(floors, bins))
        out[f"{key}_raw"] = float((x - x.mean(0)).pow(2).mean().sqrt()) * math.sqrt(dt)
        if all(covered):
            what = "accelerometer" if key == "acc" else "gyroscope"
            reasons.append(f"the {what}'s vibration covers its white noise down to {3.0 / (end * dt):.2g} Hz")
    return MeasuredNoise(samples=end, start_s=float(t[0]), end_s=float(t[-1]), trusted=not reasons,
                         reason="; ".join(reasons), **out)
