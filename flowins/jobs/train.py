"""The training job: learn the filter's parameters on sequences with ground truth.

``configs -> data (sequences, cached flow) -> FilterLearner (unrolled filter) ->
Lightning Trainer (fit, then the held-out test) -> checkpoint, TensorBoard, table``.
"""
from __future__ import annotations

import contextlib
import json
import logging
import warnings
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import pytorch_lightning as pl

from flowins.config import check_target, check_value, instantiate, setting
from flowins.jobs.cli import console_logging
from flowins.training.parameters import NAMES, NOISE_NAMES, FROZEN_BY_DEFAULT, FilterParameters, starting_values

log = logging.getLogger("flowins")


def parameter_sets(cfg: Mapping[str, Any], base) -> tuple[dict[str, float], dict[str, float], set[str]]:
    """(hand-tuned values, starting values, names to learn) from the ``model`` group."""
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
    from flowins.jobs.evaluate import check_data_settings
    from flowins.training.unroll import METHODS

    methods = cfg["methods"]
    if isinstance(methods, str) or not hasattr(methods, "__len__") or not len(methods):
        raise ValueError(f"methods={methods!r}: expected a list of at least one of {', '.join(METHODS)}")
    for m in methods:
        if not isinstance(m, str) or m not in METHODS:
            raise ValueError(f"methods: unknown {m!r}; expected names from {', '.join(METHODS)}")
    setting(cfg, "window_s", float, minimum=1e-3)
    setting(cfg, "seed", int)
    for key in ("flow_moments", "progress"):
        setting(cfg, key, bool, default=True)
    for key, minimum in (("lr", 1e-12), ("gradient_clip", 1e-12), ("nll_weight", 0.0),
                         ("orientation_weight_m_per_rad", 0.0), ("mistune", 1e-12)):
        setting(cfg, f"model.{key}", float, minimum=minimum)
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
            for name, tp in (("path", str | None), ("seed", int), ("duration_s", float)):
                if name in source:
                    check_value(source[name], tp, f"{key}.{name}")
    setting(cfg, "trainer.max_epochs", int | None, minimum=-1, default=None)
    check_data_settings(cfg)
    check_target(cfg["flow"], "flow")


def run(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """Fit, test on the held-out sequences, and return the held-out results."""
    console_logging()
    check_train_settings(cfg)

    from flowins.ins.imu_model import imu_model
    from flowins.jobs.evaluate import navigation_config
    from flowins.training.data import SequenceDataModule
    from flowins.training.module import FilterLearner

    pl.seed_everything(int(cfg.get("seed", 0)), workers=True)
    out = Path(cfg["output_dir"])
    out.mkdir(parents=True, exist_ok=True)
    methods = list(cfg["methods"])
    recording = any(item.get("path") for part in ("train", "val") for item in cfg["data"][part])
    base = navigation_config(cfg["filter"], imu_model(cfg["imu"], recording=recording))
    tuned, start, learn = parameter_sets(cfg, base)
    params = FilterParameters(start, learn)
    log.info(f"learning {len(params.learned)} parameters: {', '.join(params.learned)}")
    data_cfg = {**cfg, "flow": flow_settings(cfg)}
    data = SequenceDataModule(train=cfg["data"]["train"], val=cfg["data"]["val"], config=data_cfg, methods=methods,
                              progress=bool(cfg.get("progress", True)))
    module = FilterLearner(
        params, base, methods=methods, window_s=float(cfg["window_s"]), nll_weight=float(cfg["model"]["nll_weight"]),
        orientation_weight_m_per_rad=float(cfg["model"]["orientation_weight_m_per_rad"]),
        lr=float(cfg["model"]["lr"]), gradient_clip=float(cfg["model"]["gradient_clip"]),
        reference={"start": start, "hand-tuned": tuned}, output_dir=str(out),
    )
    checkpoint = pl.callbacks.ModelCheckpoint(dirpath=out / "checkpoints", filename="best", monitor="val/rmse_mean_m",
                                              mode="min", save_last=True)
    logger = instantiate(cfg["logger"], "logger") if cfg.get("logger") else False
    with _without_lightning_noise():
        trainer: pl.Trainer = instantiate(cfg["trainer"], "trainer", logger=logger, callbacks=[checkpoint])
        trainer.fit(module, datamodule=data)
        best = checkpoint.best_model_path or None
        if best:
            module.params.load_state_dict(FilterParameters.from_checkpoint(best).state_dict())
        trainer.test(module, datamodule=data, verbose=False)
    learned = module.params.values()
    (out / "learned_parameters.json").write_text(json.dumps(learned, indent=2))
    log.info(f"\nlearned parameters: {out / 'learned_parameters.json'}")
    if best:
        log.info(f"checkpoint: {best}\n  python evaluate.py model.checkpoint={best}")
    log.info(f"skipped windows (non-finite loss or gradient): {module.skipped_windows}; trained: {module.trained_windows}")
    return {"learned": learned, "start": start, "hand-tuned": tuned, "checkpoint": best,
            "skipped_windows": module.skipped_windows}


class _NotTheLitLoggerTip(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return "litlogger" not in record.getMessage()


@contextlib.contextmanager
def _without_lightning_noise() -> Iterator[None]:
    """Lightning, on every run, prints two messages that say nothing about the run; this
    drops exactly those two and nothing else:

    * torch deprecates ``LeafSpec`` (a ``FutureWarning`` in torch 2.13), which Lightning's own
      ``CombinedLoader`` still builds (``pytorch_lightning/utilities/_pytree.py``, through
      2.6.6): not flowins' code to change;
    * the "Tip" that advertises the litlogger package, logged by every ``Trainer`` that has
      no LitLogger.
    """
    tip = logging.getLogger("pytorch_lightning.utilities.rank_zero")
    no_tip = _NotTheLitLoggerTip()
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"`isinstance\(treespec, LeafSpec\)` is deprecated",
                                category=FutureWarning, module=r"pytorch_lightning\.utilities\._pytree")
        tip.addFilter(no_tip)
        try:
            yield
        finally:
            tip.removeFilter(no_tip)
