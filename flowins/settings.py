"""The jobs' Hydra config as flowins objects: one builder from a job's config and its
recordings to everything the filter needs.

``evaluate.py`` and ``train.py`` compose the config; :func:`evaluate_settings` and
:func:`train_settings` check every key against the dataclass it builds (:mod:`flowins.config`:
each error names its dotted key) before any work. Once the recordings are read,
:func:`filter_setup` resolves the IMU preset (:func:`~flowins.sensor.resolve_imu`, the one place it is
chosen), builds the :class:`~flowins.navigation.NavigationConfig`, applies a ``train.py``
checkpoint and gives the flow provider's config: both jobs, the training data and the
benchmarks start from it.

Data flow: ``config -> settings (checked) -> recordings -> filter_setup -> navigation``.
"""
from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from flowins.config import bounded, build, check_device, check_target, setting
from flowins.ins.imu_model import ImuModel
from flowins.ins.mechanization import ProcessNoise
from flowins.measurements.registry import measurement_settings
from flowins.navigation import NavigationConfig
from flowins.parallel import available_cores
from flowins.sensor import SensorRecording, resolve_imu
from flowins.training.parameters import (
    FROZEN_BY_DEFAULT,
    NAMES,
    NOISE_NAMES,
    FilterParameters,
    ModelSettings,
    starting_values,
)
from flowins.training.unroll import METHODS

log = logging.getLogger("flowins")

#: the filter's precision: float64 only. In float32 the pose copy's nugget (1e-9) is below
#: the rounding of the position variances and the flow update's covariances lose their
#: definiteness (measured on the 60 s walk: ins_gnss smoother 3.6e6 m, ins_dense NaN)
_DTYPES = {"float64": torch.float64}


# ---------------------------------------------------------------------------
# The jobs' keys: one dataclass per group, checked by flowins.config.build
# ---------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class FlowPairSettings:
    """``flow_pairs`` (``configs/common``): which frame pairs the flow providers see."""

    step: int = bounded(1, minimum=1)
    input_scale: float = bounded(0.5, minimum=1e-3, maximum=1.0)
    stride_px: int = bounded(8, minimum=1)
    border_px: int = bounded(8, minimum=0)
    batch_size: int = bounded(4, minimum=1)


@dataclass(frozen=True, kw_only=True)
class SequenceSettings:
    """``sequence`` (``configs/sequence``): a recording (``path``) or the simulated walk."""

    kind: str = "simulated_walk"
    path: str | None = None
    max_imu_gap_s: float = bounded(0.2, minimum=1e-6)
    crop: bool = False
    #: imu_to_camera's rotation against the gyroscope and the flow (flowins/flow/mounting.py)
    check_mounting: bool = True
    start_s: float | None = bounded(None, minimum=0.0)
    end_s: float | None = bounded(None, minimum=1e-6)
    duration_s: float = bounded(300.0, minimum=1.0)
    quick_duration_s: float = bounded(60.0, minimum=1.0)
    seed: int = 0
    #: one simulated walk per seed, all in one batched filter
    seeds: tuple[int, ...] | None = bounded(None, nonempty=True)
    imu_rate_hz: float = bounded(100.0, minimum=1.0)
    #: the simulated camera (:class:`flowins.data.simulate.CameraConfig`'s keys)
    camera: dict[str, Any] = bounded({})

    def __post_init__(self) -> None:
        if self.seeds is not None:
            if self.path:
                raise ValueError("sequence.seeds: simulated walks only; a recording (sequence.path) has no seed")
            if len(set(self.seeds)) != len(self.seeds):
                raise ValueError(f"sequence.seeds={list(self.seeds)!r}: a seed appears twice")


@dataclass(frozen=True, kw_only=True)
class JobSettings:
    """The keys both jobs take: the groups (``sequence``, ``imu``, ``filter``, ``flow``,
    ``sparse``; the last four checked where they are built) and ``configs/common``."""

    sequence: SequenceSettings
    imu: Any
    filter: Any
    flow: Any
    sparse: Any
    flow_pairs: FlowPairSettings
    cache_dir: str | None = None
    output_dir: str | None = None
    progress: bool = True


@dataclass(frozen=True, kw_only=True)
class CheckpointSettings:
    """``model`` of ``evaluate.py``: a ``train.py`` checkpoint's learned values, or none."""

    checkpoint: str | None = None


@dataclass(frozen=True, kw_only=True)
class EvaluateSettings(JobSettings):
    """``configs/evaluate.yaml``: the Table I rows and what the job writes."""

    methods: dict[str, dict[str, bool]]
    combinations: tuple[str, ...]
    flow_panels: int = bounded(3, minimum=0)
    quick: bool = False
    plots: bool = True
    model: CheckpointSettings = CheckpointSettings()

    def __post_init__(self) -> None:
        names = ", ".join(self.methods)
        if not self.combinations:
            raise ValueError(f"combinations=[]: expected a list of at least one of {names} (configs/method/)")
        for name in self.combinations:
            if name not in self.methods:
                raise ValueError(f"combinations: unknown combination {name!r}; expected one of {names} "
                                 "(configs/method/)")

    def uses(self, kind: str) -> bool:
        """Whether a chosen row fuses ``kind`` (``gnss``, ``sparse``, ``dense``)."""
        return any(self.methods[name][kind] for name in self.combinations)


@dataclass(frozen=True, kw_only=True)
class SourceSettings:
    """One of ``data.train`` / ``data.val``: a recording ``{path: DIR}`` or a simulated walk
    ``{seed: N}``, optionally a part of it (``start_s``, ``end_s``) or, simulated, its length."""

    path: str | None = None
    seed: int | None = None
    duration_s: float | None = bounded(None, minimum=1.0)
    start_s: float | None = bounded(None, minimum=0.0)
    end_s: float | None = bounded(None, minimum=1e-6)

    def __post_init__(self) -> None:
        if not self.path and self.seed is None:
            raise ValueError("expected {path: DIR} or {seed: N} (optionally duration_s, start_s, end_s)")


@dataclass(frozen=True, kw_only=True)
class DataSettings:
    """``data`` (``configs/data``): training and held-out sources, sequences per step, and
    the long held-out sources ``select`` that choose the checkpoint (empty: ``val`` chooses)."""

    train: tuple[SourceSettings, ...] = bounded(nonempty=True)
    val: tuple[SourceSettings, ...] = bounded(nonempty=True)
    batch_size: int = bounded(1, minimum=1)
    select: tuple[SourceSettings, ...] = ()


@dataclass(frozen=True, kw_only=True)
class TrainSettings(JobSettings):
    """``configs/train.yaml``: what is learned, on which rows and windows."""

    methods: tuple[str, ...] = bounded(nonempty=True)
    window_s: float = bounded(minimum=1e-3)
    curriculum_window_s: tuple[float, ...] | None = bounded((), minimum=1e-3)
    seed: int = 0
    flow_moments: bool = True
    data: DataSettings
    model: ModelSettings
    trainer: Any
    logger: Any = None

    def __post_init__(self) -> None:
        for name in self.methods:
            if name not in METHODS:
                raise ValueError(f"methods: unknown {name!r}; expected names from {', '.join(METHODS)}")

    @property
    def recorded(self) -> bool:
        """Whether any source is a recording (``path``), not a simulated walk."""
        return any(source.path for source in (*self.data.train, *self.data.val, *self.data.select))


def _job(cls: type, cfg: Mapping[str, Any]) -> Any:
    """``cls`` built from the whole job config (every key checked, errors name it)."""
    return build(cls, cfg, "")


def evaluate_settings(cfg: Mapping[str, Any]) -> EvaluateSettings:
    """``evaluate.py``'s config checked and built before any work (the ``filter`` group and a
    named ``imu`` preset too, the dense and sparse providers' keys where a row uses them)."""
    settings = _job(EvaluateSettings, cfg)
    check_filter_settings(cfg, recorded=bool(settings.sequence.path))
    if settings.uses("dense"):
        check_flow(cfg["flow"])
    if settings.uses("sparse"):
        sparse = cfg["sparse"]
        source = sparse.get("source")
        if source not in ("tracker", "tracks"):
            raise ValueError(f"sparse.source={source!r}: expected tracker (run sparse.tracker on the frames) or "
                             "tracks (the recording's tracks.csv)")
        if source == "tracks":
            setting(cfg, "sparse.sigma_px", float, minimum=1e-6)
        else:
            check_target(sparse["tracker"], "sparse.tracker")
    return settings


def train_settings(cfg: Mapping[str, Any]) -> TrainSettings:
    """``train.py``'s config checked and built before any work."""
    settings = _job(TrainSettings, cfg)
    setting(cfg, "trainer.max_epochs", int | None, minimum=-1, default=None)  # Lightning's own Trainer key
    accelerator = cfg["trainer"].get("accelerator")
    if accelerator in ("gpu", "cuda") and not torch.cuda.is_available():  # Lightning's own error is a traceback
        raise ValueError(f"trainer.accelerator={accelerator} (trainer=gpu): torch {torch.__version__} sees no CUDA GPU "
                         "here (torch.cuda.is_available() is False); use trainer=cpu, or install torch's CUDA build")
    check_filter_settings(cfg, recorded=settings.recorded)
    vehicle = (cfg["filter"].get("measurements") or {}).get("vehicle") or {}
    if vehicle.get("mounting") == "fit":
        raise ValueError("filter.measurements.vehicle.mounting=fit: a first pass per run is evaluate.py's; train.py "
                         "takes the mounting as given (filter.measurements.vehicle.mount_*_rad, lever_*_m) or learns "
                         "it (model.learn: vehicle_mount_*_rad, vehicle_lever_*_m)")
    check_flow(cfg["flow"])
    return settings


def check_flow(flow: Mapping[str, Any]) -> None:
    """The ``flow`` group's provider (``_target_``) and, where it has one, its ``device``."""
    check_target(flow, "flow")
    if "device" in flow:
        check_device(flow["device"], "flow.device")


def check_filter_settings(cfg: Mapping[str, Any], *, recorded: bool) -> None:
    """The ``filter`` group (and a named ``imu`` preset) checked before a recording is read:
    the values are built once with placeholder IMU densities, which the preset replaces later."""
    if cfg["imu"].get("name") != "auto":
        resolve_imu(cfg["imu"], [], recorded=recorded)
    navigation_config(cfg["filter"], ImuModel("check", 1.0, 1.0))


# ---------------------------------------------------------------------------
# The filter's settings
# ---------------------------------------------------------------------------


#: the ``filter`` group's keys whose :class:`NavigationConfig` field has another name
FILTER_KEYS = {"init": "start", "flow": "flow_update"}
#: the ``filter`` keys that fill ``NavigationConfig.noise`` (:class:`ProcessNoise`)
NOISE_KEYS = tuple(f.name for f in dataclasses.fields(ProcessNoise))
#: the IMU noise keys whose null takes the IMU preset's value (:func:`~flowins.sensor.resolve_imu`)
_IMU_NOISE = ("acc_noise", "gyro_noise", "acc_bias_walk", "gyro_bias_walk")


def filter_keys() -> tuple[str, ...]:
    """Every key of the ``filter`` group: :data:`NOISE_KEYS`, then one per field of
    :class:`NavigationConfig` (renamed by :data:`FILTER_KEYS`)."""
    config_key = {field: key for key, field in FILTER_KEYS.items()}
    return (*NOISE_KEYS, *(config_key.get(f.name, f.name) for f in dataclasses.fields(NavigationConfig)
                           if f.name != "noise"))


def navigation_config(cfg: Mapping[str, Any], imu: ImuModel | None = None) -> NavigationConfig:
    """:class:`NavigationConfig` from the ``filter`` config group (:func:`filter_keys`: the
    dataclass's fields; a new setting is a field and a YAML line); its IMU noise keys that are
    null come from ``imu`` (:func:`~flowins.sensor.resolve_imu`). Every value is checked against the
    settings it builds; errors name the key. A key the group leaves out takes the field's default."""
    known = filter_keys()
    for key in cfg:
        if key not in known:
            raise ValueError(f"filter.{key}: unknown key; filter takes {', '.join(known)}")
    if cfg.get("dtype", "float64") not in _DTYPES:
        raise ValueError(f"filter.dtype={cfg['dtype']!r}: expected one of {list(_DTYPES)} (float32 is not "
                         "precise enough for the pose augmentation and the flow update)")
    noise = {key: cfg[key] for key in NOISE_KEYS if key in cfg}
    for key in _IMU_NOISE:
        if noise.get(key) is None:
            noise[key] = None if imu is None else imu.noise()[key]
        if noise[key] is None:
            raise ValueError(f"filter.{key} is null and no imu preset was given; set filter.{key} or choose imu=...")
    values, ready = {}, {"noise": build(ProcessNoise, noise, "filter")}
    defaults = NavigationConfig()
    config_key = {field: key for key, field in FILTER_KEYS.items()}
    for field in dataclasses.fields(NavigationConfig):
        key = config_key.get(field.name, field.name)
        if field.name == "noise" or key not in cfg or cfg[key] is None and field.name == "tracks":
            continue
        value, default = cfg[key], getattr(defaults, field.name)
        if field.name == "dtype":
            ready["dtype"] = _DTYPES[value]
        elif field.name == "measurements":
            ready["measurements"] = measurement_settings(value or {})
        elif dataclasses.is_dataclass(default):
            ready[field.name] = build(type(default), value, f"filter.{key}")
        elif field.name == "workers" and isinstance(value, str):
            if value != "auto":
                raise ValueError(f"filter.workers={value!r}: expected an integer >= 1 or auto")
            values["workers"] = available_cores()
        elif field.name == "compile" and isinstance(value, bool):  # YAML's false / true
            values["compile"] = str(value).lower()
        else:
            values[field.name] = value
    ready.setdefault("measurements", measurement_settings({}))  # every registered kind at its defaults
    return build(NavigationConfig, values, "filter", **ready)


def flow_config(cfg: Mapping[str, Any], *, moments: bool, dropout_p: float | None = None) -> dict[str, Any]:
    """The dense flow provider's config (``flow``): with ``dropout_p`` (a checkpoint's learned
    rate) the provider's ``p`` replaced; with ``moments`` SpyNet's Monte Carlo dropout in
    closed form (``mc_mode=moments``), as training runs it: the mean flow is the
    deterministic one whatever the rate, and the rate only scales σ."""
    flow = dict(cfg["flow"])
    if dropout_p is not None and "p" in flow and abs(dropout_p - float(flow["p"])) > 1e-9 * float(flow["p"]):
        flow["p"] = dropout_p  # a rate learned away from the configured one (not its float round trip)
    if moments and str(flow.get("_target_", "")).endswith("SpyNetProvider"):
        flow["mc_mode"] = "moments"
    return flow


def describe_flow(flow: Mapping[str, Any], configured: Mapping[str, Any]) -> str:
    """One line: the dense provider, its dropout mode and rate, and whether that is the flow
    a run with the configured provider (no checkpoint) computes."""
    name = str(flow.get("_target_", "?")).rpartition(".")[2]
    if "p" in flow:
        mode = ("closed-form dropout" if flow.get("mc_mode") == "moments" else
                f"{flow.get('mc_passes', '?')} Monte Carlo dropout passes")
        name += f", {mode} at p = {float(flow['p']):.4g}"
    same = dict(flow) == dict(configured)
    return f"dense flow: {name} ({'the configured flow' if same else 'differs from the configured flow: ' + _changes(flow, configured)})"


def _changes(flow: Mapping[str, Any], configured: Mapping[str, Any]) -> str:
    keys = [k for k in dict.fromkeys([*configured, *flow]) if flow.get(k) != configured.get(k)]
    return ", ".join(f"{k} {configured.get(k)!r} -> {flow.get(k)!r}" for k in keys)


@dataclass(frozen=True)
class FilterSetup:
    """Everything the filter needs for a job's recordings (:func:`filter_setup`)."""

    #: the IMU preset's error model
    imu: ImuModel
    #: the ``filter`` group with the preset's noise and a checkpoint's learned values
    navigation: NavigationConfig
    #: the dense flow provider's config (:func:`flow_config`)
    flow: dict[str, Any]
    #: a checkpoint's learned values by parameter name; None without a checkpoint
    learned: dict[str, float] | None = None

    def describe_flow(self, configured: Mapping[str, Any]) -> str:
        """:func:`describe_flow` of this setup's provider against the ``configured`` one."""
        return describe_flow(self.flow, configured)

    def describe(self) -> str:
        """One line: the preset and the densities the filter uses."""
        noise = self.navigation.noise
        return (f"imu: {self.imu.name} ({self.imu.source or 'config'}): filter densities acc "
                f"{float(noise.acc_noise):.3g} m/s²/√Hz, gyro {float(noise.gyro_noise):.3g} rad/s/√Hz, walks "
                f"{float(noise.acc_bias_walk):.3g} m/s³/√Hz, {float(noise.gyro_bias_walk):.3g} rad/s²/√Hz")


def filter_setup(cfg: Mapping[str, Any], recordings: Sequence[SensorRecording], *, recorded: bool,
                 checkpoint: str | None = None, moments: bool = False) -> FilterSetup:
    """The one builder from a job's config and its recordings to the filter's settings.

    The IMU preset is resolved with the recordings' sensor (:func:`~flowins.sensor.resolve_imu`), the
    ``filter`` group built on it (:func:`navigation_config`), and with ``checkpoint``
    (``model.checkpoint``) a ``train.py`` checkpoint's learned noise, gates and flow noise
    written in, its dropout rate given to the flow provider. The provider otherwise runs as
    configured, so a run with a checkpoint and one without compute the same flow when the
    rate was not learned (the default); ``moments`` (``train.py``'s ``flow_moments``, or
    ``flow.mc_mode=moments``) runs SpyNet's dropout in closed form (:func:`flow_config`)."""
    imu = resolve_imu(cfg["imu"], recordings, recorded=recorded)
    navigation = navigation_config(cfg["filter"], imu)
    if not checkpoint:
        return FilterSetup(imu, navigation, flow_config(cfg, moments=moments))
    params = FilterParameters.from_checkpoint(checkpoint)
    learned = params.values()
    log.info(f"learned parameters from {checkpoint}: " + ", ".join(f"{k}={v:.4g}" for k, v in learned.items()))
    for kind, network in params.adaptive.items():
        angles = (f" and its mounting's pitch and yaw within ±{float(network.angle_bound_rad):g} rad"
                  + (" (read from the car's acceleration)" if network.compensates_gravity else "") if network.angles else "")
        log.info(f"adaptive noise from {checkpoint}: the {kind} σs{angles} set at each update by a learned network "
                 f"over the IMU's last second ({sum(p.numel() for p in network.parameters())} weights)")
    return FilterSetup(imu, params.apply(navigation, training=False),
                       flow_config(cfg, moments=moments, dropout_p=learned["dropout_p"]), learned)


# ---------------------------------------------------------------------------
# Training: the parameters' hand-tuned values, starts and what is learned
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class ParameterSets:
    """The hand-tuned values, the starting values, the names learned and each parameter's
    bound in decades around its start (None: unbounded) (:func:`parameter_sets`); unpacks
    as ``(tuned, start, learn)``."""

    tuned: dict[str, float]
    start: dict[str, float]
    learn: set[str]
    bounds: dict[str, float | None]

    def __iter__(self):
        return iter((self.tuned, self.start, self.learn))


def parameter_sets(cfg: Mapping[str, Any], base: NavigationConfig) -> ParameterSets:
    """(hand-tuned values, starting values, names to learn) and the bounds from the ``model``
    group and the filter config ``base``; unpacks as a 3-tuple."""
    model = cfg["model"] if isinstance(cfg["model"], ModelSettings) else build(ModelSettings, cfg["model"], "model")
    tuned = starting_values(base, dropout_p=float(cfg["flow"].get("p", 0.2)))
    start = {**tuned, **model.start}
    start = {k: v * model.mistune if k in NOISE_NAMES else v for k, v in start.items()}
    learn = set(NAMES) - FROZEN_BY_DEFAULT if model.learn is None else set(model.learn)
    learn -= set(model.freeze)
    if base.flow_update.augmentation_mode == "limit" and model.learn is None:
        learn -= {"sigma_p0", "sigma_q0"}  # the limit mode has no forgetting variances to learn
    return ParameterSets(tuned, start, learn, model.parameter_bounds())


@dataclass(frozen=True)
class TrainingSetup:
    """What learning starts from (:func:`training_setup`)."""

    filter: FilterSetup
    parameters: ParameterSets


def training_setup(cfg: Mapping[str, Any], sequences: Sequence[SensorRecording], *, recorded: bool) -> TrainingSetup:
    """The filter's settings for training ``sequences`` (:func:`filter_setup`, with
    ``flow_moments``) and the parameters' hand-tuned values, starts and names learned."""
    setup = filter_setup(cfg, sequences, recorded=recorded, moments=bool(cfg.get("flow_moments", True)))
    return TrainingSetup(setup, parameter_sets(cfg, setup.navigation))
