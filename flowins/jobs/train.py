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

from flowins.config import instantiate
from flowins.ins.imu_model import imu_model
from flowins.jobs.cli import console_logging
from flowins.settings import check_train_settings, flow_settings, navigation_config, parameter_sets
from flowins.training.data import SequenceDataModule
from flowins.training.module import FilterLearner, selection_table
from flowins.training.parameters import FilterParameters

log = logging.getLogger("flowins")


def run(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """Fit, test on the held-out sequences, and return the held-out results."""
    console_logging()
    check_train_settings(cfg)
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
                              batch_size=int(cfg["data"].get("batch_size", 1)), progress=bool(cfg.get("progress", True)),
                              seed=int(cfg.get("seed", 0)))
    model = cfg["model"]
    module = FilterLearner(
        params, base, methods=methods, window_s=float(cfg["window_s"]),
        curriculum_window_s=[float(w) for w in cfg.get("curriculum_window_s") or []],
        nll_weight=float(model["nll_weight"]), orientation_weight_m_per_rad=float(model["orientation_weight_m_per_rad"]),
        innovation_weight=float(model["innovation_weight"]),
        lr=float(model["lr"]), lr_final=float(model["lr_final"]), warmup_steps=int(model["warmup_steps"]),
        accumulate_windows=int(model["accumulate_windows"]), gradient_clip=float(model["gradient_clip"]),
        reference={"start": start, "hand-tuned": tuned}, output_dir=str(out),
    )
    logger = instantiate(cfg["logger"], "logger") if cfg.get("logger") else False
    checkpoints = out / "checkpoints"
    with _without_lightning_noise():
        bar = {} if "enable_progress_bar" in cfg["trainer"] else {"enable_progress_bar": bool(cfg.get("progress", True))}
        trainer: pl.Trainer = instantiate(cfg["trainer"], "trainer", logger=logger, enable_checkpointing=False, **bar)
        trainer.validate(module, datamodule=data, verbose=False)  # the start: a candidate like every epoch
        trainer.fit(module, datamodule=data)
        trainer.save_checkpoint(checkpoints / "last.ckpt", weights_only=False)
        chosen = module.select_best()
        best = checkpoints / "best.ckpt"
        trainer.save_checkpoint(best, weights_only=False)
        log.info("\n" + selection_table(module.history, chosen))
        trainer.test(module, datamodule=data, verbose=False)
    learned = module.params.values()
    if trainer.is_global_zero:
        (out / "selection.json").write_text(json.dumps({"history": module.history, "chosen": chosen["label"]}, indent=2))
        (out / "learned_parameters.json").write_text(json.dumps(learned, indent=2))
    log.info(f"\nlearned parameters: {out / 'learned_parameters.json'}")
    log.info(f"checkpoint ({chosen['label']}): {best}\n  python evaluate.py model.checkpoint={best}")
    log.info(f"skipped windows (non-finite loss or gradient): {module.skipped_windows}; trained: {module.trained_windows}")
    return {"learned": learned, "start": start, "hand-tuned": tuned, "checkpoint": str(best),
            "chosen": chosen["label"], "history": module.history, "skipped_windows": module.skipped_windows}


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
