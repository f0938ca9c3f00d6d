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
from flowins.evaluation.motion import vehicle_hint
from flowins.jobs.cli import console_logging
from flowins.measurements.vehicle import VehicleSettings
from flowins.settings import flow_config, train_settings, training_setup
from flowins.training.data import SequenceDataModule
from flowins.training.module import FilterLearner, selection_table
from flowins.training.parameters import FilterParameters

log = logging.getLogger("flowins")


def run(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """Fit, test on the held-out sequences, and return the held-out results."""
    console_logging()
    settings = train_settings(cfg)
    pl.seed_everything(settings.seed, workers=True)
    out = Path(cfg["output_dir"])
    out.mkdir(parents=True, exist_ok=True)
    methods = list(settings.methods)
    data = SequenceDataModule(train=cfg["data"]["train"], val=cfg["data"]["val"],
                              select=cfg["data"].get("select") or [],
                              config={**cfg, "flow": flow_config(cfg, moments=settings.flow_moments)},
                              methods=methods, batch_size=settings.data.batch_size, progress=settings.progress,
                              seed=settings.seed)
    data.setup()
    setup = training_setup(cfg, [*data.sequences["train"], *data.sequences["val"], *data.select_sequences],
                           recorded=settings.recorded)
    log.info(setup.filter.describe())
    mode = (setup.filter.navigation.measurements.get("vehicle") or VehicleSettings()).mode
    for seq in [*data.sequences["train"], *data.sequences["val"]]:
        hint = vehicle_hint(seq.gnss, platform_named="vehicle" in seq.streams, mode=mode)
        if hint:
            log.info(f"{seq.name}: {hint} To learn how much it holds to it: experiment=real_vehicle.")
    tuned, start, learn = setup.parameters
    params = FilterParameters(start, learn, bounds=setup.parameters.bounds, adaptive=settings.model.adaptive,
                              adaptive_decades=settings.model.adaptive_decades,
                              adaptive_angles_rad=settings.model.adaptive_angles_rad,
                              adaptive_compensate_gravity=settings.model.adaptive_compensate_gravity)
    log.info(f"learning {len(params.learned)} parameters: {', '.join(params.learned)}" if params.learned else
             "learning no constant parameter (model.learn=[]): every one kept at its start")
    for kind, network in params.adaptive.items():
        log.info(f"learning adaptive noise for {kind}: {sum(p.numel() for p in network.parameters())} weights "
                 f"(flowins/measurements/adaptive_noise.py), factors within 10^±{settings.model.adaptive_decades:g}"
                 + (f", the mounting's pitch and yaw within ±{settings.model.adaptive_angles_rad:g} rad"
                    if network.angles else "")
                 + (" from the car's acceleration (the filter's attitude)" if network.compensates_gravity else ""))
    module = FilterLearner(params, setup.filter.navigation, methods=methods, model=settings.model,
                           window_s=settings.window_s, curriculum_window_s=settings.curriculum_window_s or (),
                           reference={"start": start, "hand-tuned": tuned}, output_dir=str(out))
    logger = instantiate(cfg["logger"], "logger") if cfg.get("logger") else False
    checkpoints = out / "checkpoints"
    with _without_lightning_noise():
        bar = {} if "enable_progress_bar" in cfg["trainer"] else {"enable_progress_bar": bool(cfg.get("progress", True))}
        trainer: pl.Trainer = instantiate(cfg["trainer"], "trainer", logger=logger, enable_checkpointing=False, **bar)
        note = few_rows_note(trainer.strategy.root_device.type, settings.data.batch_size, len(methods))
        if note:
            log.info(note)
        trainer.validate(module, datamodule=data, verbose=False)  # the start: a candidate like every epoch
        trainer.fit(module, datamodule=data)
        trainer.save_checkpoint(checkpoints / "last.ckpt", weights_only=False)
        if module.use_average():  # the last epochs' mean iterate: one more candidate (model.average_epochs)
            trainer.validate(module, datamodule=data, verbose=False)
        chosen = module.select_best()
        if module.select_flow_gate:  # the chosen parameters with other flow gates: more candidates
            for _ in module.gate_variants(chosen):
                trainer.validate(module, datamodule=data, verbose=False)
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


#: filter rows per training step below which a step took longer on one H200 than on the 2-core
#: CPU (docs/performance.md, "One GPU": 2 rows 3.2x the CPU's time, 8 rows 1.8x, 32 rows 0.78x;
#: the two cross near 20)
GPU_ROWS = 20


def few_rows_note(device_type: str, batch_size: int, methods: int) -> str | None:
    """The note a run on a GPU gets when its steps run few filter rows (``batch_size``
    sequences times ``methods``), or None."""
    rows = batch_size * methods
    if device_type != "cuda" or rows >= GPU_ROWS:
        return None
    return (f"note: training on a GPU with {rows} filter row{'s' * (rows != 1)} per step (data.batch_size={batch_size} "
            f"x {methods} method{'s' * (methods != 1)}). A step is thousands of small operations, each a kernel launch, "
            f"whatever its rows; with fewer than about {GPU_ROWS} rows a step took longer on an H200 than on a "
            "2-core CPU (docs/performance.md, 'One GPU'). Raise data.batch_size where the data allow, or train on the CPU "
            "(trainer=cpu).")


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
