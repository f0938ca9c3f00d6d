"""The jobs' Hydra config as flowins objects: one typed builder for both jobs.

Every value is checked against the settings it builds (:mod:`flowins.config`) before any
work, and every error names its dotted key. ``evaluate.py`` and ``train.py`` compose the
config; this module turns it into a :class:`~flowins.navigation.NavigationConfig`, the
flow update, the start, and checks the jobs' own keys.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from flowins.config import build, check_target, check_value, setting
from flowins.filter.ekf import Gate
from flowins.ins.imu_model import ImuModel
from flowins.ins.initialization import InitialUncertainty
from flowins.ins.mechanization import ProcessNoise
from flowins.measurements.flow_update import FlowUpdate
from flowins.measurements.gnss import GnssRecovery
from flowins.measurements.gnss_heading import HeadingAlignment
from flowins.navigation import NavigationConfig
from flowins.start import StartSettings


#: the filter's precision: float64 only. In float32 the pose copy's nugget (1e-9) is below
#: the rounding of the position variances and the flow update's covariances lose their
#: definiteness (measured on the 60 s walk: ins_gnss smoother 3.6e6 m, ins_dense NaN)
_DTYPES = {"float64": torch.float64}


def start_settings(cfg: Mapping[str, Any]) -> StartSettings:
    """:class:`~flowins.start.StartSettings` from ``filter.init`` (values checked by key)."""
    return build(StartSettings, cfg, "filter.init")


def navigation_config(cfg: Mapping[str, Any], imu: ImuModel | None = None) -> NavigationConfig:
    """:class:`NavigationConfig` from the ``filter`` config group; its IMU noise keys that are
    null come from ``imu`` (the ``imu`` config group, :func:`flowins.ins.imu_model.imu_model`).
    Every value is checked against the settings it builds; errors name the key."""
    if cfg["dtype"] not in _DTYPES:
        raise ValueError(f"filter.dtype={cfg['dtype']!r}: expected one of {list(_DTYPES)} (float32 is not "
                         "precise enough for the pose augmentation and the flow update)")
    noise = {}
    for key in ("acc_noise", "gyro_noise", "acc_bias_walk", "gyro_bias_walk"):
        noise[key] = cfg[key] if cfg[key] is not None else (None if imu is None else imu.noise()[key])
        if noise[key] is None:
            raise ValueError(f"filter.{key} is null and no imu preset was given; set filter.{key} or choose imu=...")
    noise.update(acc_scale_walk=cfg["acc_scale_walk"], discretization=cfg["discretization"])
    simple = ("gnss_noise_scale", "gnss_correlation_s", "output_every", "scheme", "gravity_mps2", "jacobians")
    groups = ("init", "initial", "gnss_gate", "gnss_recovery", "gnss_heading", "flow", "dtype")
    known = (*noise, *simple, *groups)
    for key in cfg:
        if key not in known:
            raise ValueError(f"filter.{key}: unknown key; filter takes {', '.join(known)}")
    return build(
        NavigationConfig,
        {key: cfg[key] for key in simple},
        "filter",
        noise=build(ProcessNoise, noise, "filter"),
        initial=build(InitialUncertainty, cfg["initial"], "filter.initial"),
        start=start_settings(cfg["init"]),
        gnss_gate=build(Gate, cfg["gnss_gate"], "filter.gnss_gate"),
        gnss_recovery=build(GnssRecovery, cfg["gnss_recovery"], "filter.gnss_recovery"),
        gnss_heading=build(HeadingAlignment, cfg["gnss_heading"], "filter.gnss_heading"),
        dtype=_DTYPES[cfg["dtype"]],
        flow_update=flow_update_config(cfg["flow"]),
    )


def flow_update_config(cfg: Mapping[str, Any]) -> FlowUpdate:
    """:class:`FlowUpdate` from ``filter.flow`` (values checked by key)."""
    return build(FlowUpdate, cfg, "filter.flow")


def check_job_settings(cfg: Mapping[str, Any]) -> None:
    """The job's own keys (``combinations``, ``flow_pairs``, ``sequence``, ...) checked
    before any work: each error names the key and what was expected."""
    combinations, methods = cfg["combinations"], cfg["methods"]
    if isinstance(combinations, str) or not hasattr(combinations, "__len__") or not len(combinations):
        raise ValueError(f"combinations={combinations!r}: expected a list of at least one of {', '.join(methods)} "
                         "(configs/method/)")
    for name in combinations:
        if not isinstance(name, str) or name not in methods:
            raise ValueError(f"combinations: unknown combination {name!r}; expected one of {', '.join(methods)} "
                             "(configs/method/)")
    for key in ("quick", "progress", "plots"):
        setting(cfg, key, bool)
    setting(cfg, "flow_panels", int, minimum=0)
    setting(cfg, "model.checkpoint", str | None)
    check_data_settings(cfg)
    check_filter_settings(cfg)
    flows = {kind for name in combinations for kind in ("sparse", "dense") if methods[name][kind]}
    if "dense" in flows:
        check_target(cfg["flow"], "flow")
    if "sparse" in flows:
        source = setting(cfg, "sparse.source", str)
        if source not in ("tracker", "tracks"):
            raise ValueError(f"sparse.source={source!r}: expected tracker (run sparse.tracker on the frames) or "
                             "tracks (the recording's tracks.csv)")
        if source == "tracks":
            setting(cfg, "sparse.sigma_px", float, minimum=1e-6)
        else:
            check_target(cfg["sparse"]["tracker"], "sparse.tracker")


def check_filter_settings(cfg: Mapping[str, Any]) -> None:
    """The ``filter`` group (and a named ``imu`` preset) checked before a recording is read:
    the values are built once with placeholder IMU densities, which the preset replaces later."""
    from flowins.ins.imu_model import imu_model

    if cfg["imu"].get("name") != "auto":
        imu_model(cfg["imu"], recording=bool(cfg["sequence"].get("path")))
    navigation_config(cfg["filter"], ImuModel("check", 1.0, 1.0))


def check_data_settings(cfg: Mapping[str, Any]) -> None:
    """The keys both jobs share (``flow_pairs``, ``sequence``, ``cache_dir``), checked by key."""
    setting(cfg, "cache_dir", str | None)
    setting(cfg, "flow_pairs.step", int, minimum=1)
    setting(cfg, "flow_pairs.input_scale", float, minimum=1e-3, maximum=1.0)
    setting(cfg, "flow_pairs.stride_px", int, minimum=1)
    setting(cfg, "flow_pairs.border_px", int, minimum=0)
    setting(cfg, "flow_pairs.batch_size", int, minimum=1)
    setting(cfg, "sequence.path", str | None)
    setting(cfg, "sequence.max_imu_gap_s", float, minimum=1e-6)
    setting(cfg, "sequence.crop", bool)
    setting(cfg, "sequence.start_s", float | None, minimum=0.0, default=None)
    setting(cfg, "sequence.end_s", float | None, minimum=1e-6, default=None)
    if not cfg["sequence"].get("path"):
        setting(cfg, "sequence.duration_s", float, minimum=1.0)
        setting(cfg, "sequence.quick_duration_s", float, minimum=1.0)
        setting(cfg, "sequence.seed", int)
        setting(cfg, "sequence.imu_rate_hz", float, minimum=1.0)
    seeds = cfg["sequence"].get("seeds")
    if seeds is not None:
        if cfg["sequence"].get("path"):
            raise ValueError("sequence.seeds: simulated walks only; a recording (sequence.path) has no seed")
        if isinstance(seeds, (str, bytes)) or not hasattr(seeds, "__len__") or not len(seeds):
            raise ValueError(f"sequence.seeds={seeds!r}: expected a list of integers, e.g. [0,1,2,3]")
        for i, seed in enumerate(seeds):
            check_value(seed, int, f"sequence.seeds[{i}]")
        if len(set(seeds)) != len(seeds):
            raise ValueError(f"sequence.seeds={list(seeds)!r}: a seed appears twice")


def parameter_sets(cfg: Mapping[str, Any], base) -> tuple[dict[str, float], dict[str, float], set[str]]:
    """(hand-tuned values, starting values, names to learn) from the ``model`` group."""
    from flowins.training.parameters import FROZEN_BY_DEFAULT, NAMES, NOISE_NAMES, starting_values

    model = cfg["model"]
    p = float(cfg["flow"].get("p", 0.2))
    tuned = starting_values(base, dropout_p=p)
    start = {**tuned, **{k: float(v) for k, v in (model.get("start") or {}).items()}}
    unknown = sorted(set(model.get("start") or {}) - set(NAMES))
    if unknown:
        raise ValueError(f"model.start: unknown parameters {unknown}; expected names from {list(NAMES)}")
    mistune = float(model.get("mistune", 1.0))
    if not mistune > 0:
        raise ValueError(f"model.mistune must be > 0, got {mistune}")
    start = {k: v * mistune if k in NOISE_NAMES else v for k, v in start.items()}
    learn = set(NAMES) - FROZEN_BY_DEFAULT if model.get("learn") is None else set(model["learn"])
    learn -= set(model.get("freeze") or [])
    if base.flow_update.augmentation_mode == "limit" and model.get("learn") is None:
        learn -= {"sigma_p0", "sigma_q0"}  # the limit mode has no forgetting variances to learn
    return tuned, start, learn


def flow_settings(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """The flow provider config, in closed-form dropout mode where the provider has one."""
    flow = dict(cfg["flow"])
    if cfg.get("flow_moments", True) and str(flow.get("_target_", "")).endswith("SpyNetProvider"):
        flow["mc_mode"] = "moments"
    return flow


def check_train_settings(cfg: Mapping[str, Any]) -> None:
    """The training job's keys checked before any work; each error names the key."""
    from flowins.training.parameters import NAMES
    from flowins.training.unroll import METHODS

    methods = cfg["methods"]
    if isinstance(methods, str) or not hasattr(methods, "__len__") or not len(methods):
        raise ValueError(f"methods={methods!r}: expected a list of at least one of {', '.join(METHODS)}")
    for m in methods:
        if not isinstance(m, str) or m not in METHODS:
            raise ValueError(f"methods: unknown {m!r}; expected names from {', '.join(METHODS)}")
    setting(cfg, "window_s", float, minimum=1e-3)
    setting(cfg, "seed", int)
    setting(cfg, "data.batch_size", int, minimum=1, default=1)
    for key in ("flow_moments", "progress"):
        setting(cfg, key, bool, default=True)
    for key, minimum in (("lr", 1e-12), ("lr_final", 1e-12), ("gradient_clip", 1e-12), ("nll_weight", 0.0),
                         ("orientation_weight_m_per_rad", 0.0), ("innovation_weight", 0.0), ("mistune", 1e-12)):
        setting(cfg, f"model.{key}", float, minimum=minimum)
    setting(cfg, "model.warmup_steps", int, minimum=0)
    setting(cfg, "model.accumulate_windows", int, minimum=1)
    curriculum = cfg.get("curriculum_window_s") or []
    if isinstance(curriculum, (str, Mapping)) or not isinstance(curriculum, (list, tuple)):
        raise ValueError(f"curriculum_window_s={curriculum!r}: expected a list of window lengths (s), e.g. [5.0, 10.0]")
    for i, w in enumerate(curriculum):
        if check_value(w, float, f"curriculum_window_s[{i}]") < 1e-3:
            raise ValueError(f"curriculum_window_s[{i}]={w!r}: expected a window length >= 0.001 s")
    setting(cfg, "model.checkpoint", str | None)
    start = cfg["model"].get("start") or {}
    if not isinstance(start, Mapping):
        raise ValueError(f"model.start={start!r}: expected a mapping of parameter name to starting value")
    for name, value in start.items():
        if name not in NAMES:
            raise ValueError(f"model.start.{name}: unknown parameter; expected names from {', '.join(NAMES)}")
        setting(cfg, f"model.start.{name}", float, minimum=0.0)
    for key in ("learn", "freeze"):
        names = cfg["model"].get(key)
        if names is None and key == "learn":
            continue
        if isinstance(names, str) or not isinstance(names, (list, tuple)):
            raise ValueError(f"model.{key}={names!r}: expected a list of parameter names ({', '.join(NAMES)})")
        for name in names:
            if not isinstance(name, str) or name not in NAMES:
                raise ValueError(f"model.{key}: unknown parameter {name!r}; expected names from {', '.join(NAMES)}")
    for part in ("train", "val"):
        sources = cfg["data"][part]
        if isinstance(sources, str) or not isinstance(sources, (list, tuple)) or not sources:
            raise ValueError(f"data.{part}={sources!r}: expected a list of sources, each {{path: DIR}} or {{seed: N}}")
        for i, source in enumerate(sources):
            key = f"data.{part}[{i}]"
            if not isinstance(source, Mapping) or not (source.get("path") or "seed" in source):
                raise ValueError(f"{key}={source!r}: expected {{path: DIR}} or {{seed: N}} (optionally duration_s)")
            for name, tp in (("path", str | None), ("seed", int), ("duration_s", float), ("start_s", float),
                             ("end_s", float)):
                if name in source:
                    check_value(source[name], tp, f"{key}.{name}")
    setting(cfg, "trainer.max_epochs", int | None, minimum=-1, default=None)
    check_data_settings(cfg)
    check_filter_settings(cfg)
    check_target(cfg["flow"], "flow")
