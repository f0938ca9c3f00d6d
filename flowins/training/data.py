"""Training data: sequences with ground truth and their flow pairs, as a ``LightningDataModule``.

A source is either a recording (``{path: DIR}``: a flowins folder, EuRoC or ADVIO with
ground truth) or the simulated walk with a seed (``{seed: 3}``, optionally
``duration_s``). The flow network runs once per recording and setting, in
closed-form Monte Carlo dropout mode (:meth:`flowins.flow.spynet.SpyNetProvider.moments`),
and its points are cached on disk (the same cache ``evaluate.py`` uses): what depends on
no learned parameter is never recomputed, and the one that does, the dropout rate,
changes only an analytic factor of each point's σ.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import pytorch_lightning as pl
import torch
from torch.utils.data import DataLoader, Dataset, DistributedSampler

from flowins.config import setting
from flowins.data.load import load_recording
from flowins.flow.load import check_camera_mounting, load_flow, load_tracks, uses_tracks
from flowins.flow.pairs import FlowPairs
from flowins.measurements.flow import FlowCamera
from flowins.measurements.vehicle import platform_streams
from flowins.training.unroll import METHODS, TrainingSequence


def _sequence_config(source: Mapping[str, Any], base: Mapping[str, Any], key: str = "data source") -> dict[str, Any]:
    """The ``sequence`` config of one source (``base`` with its keys); errors name ``key``."""
    if not isinstance(source, Mapping):
        raise ValueError(f"{key}={source!r}: expected {{path: DIR}} or {{seed: N}}")
    window = {k: source[k] for k in ("start_s", "end_s") if k in source}
    if "path" in source and source["path"]:
        unknown = set(source) - {"path", "start_s", "end_s"}
        if unknown:
            raise ValueError(f"{key} {dict(source)}: a recording takes path, start_s and end_s; "
                             f"unknown keys {sorted(unknown)}")
        return {**base, "path": str(source["path"]), **window}
    unknown = set(source) - {"seed", "duration_s", "path", "start_s", "end_s"}
    if unknown or "seed" not in source:
        raise ValueError(
            f"{key} {dict(source)}: expected {{path: DIR}} or {{seed: N}} (optionally duration_s); "
            f"unknown keys {sorted(unknown)}" if unknown else f"{key} {dict(source)} has neither path nor seed"
        )
    cfg = {**base, "path": None, "seed": int(source["seed"]), **window}
    if "duration_s" in source:
        cfg["duration_s"] = float(source["duration_s"])
    return cfg


def load_training_sequence(
    source: Mapping[str, Any], cfg: Mapping[str, Any], *, methods: Sequence[str], progress: bool = False
) -> TrainingSequence:
    """One :class:`TrainingSequence` with the flow pairs ``methods`` need (computed or cached).

    ``cfg`` holds the groups ``sequence`` (the defaults of a simulated source), ``flow``,
    ``sparse``, ``flow_pairs`` and ``cache_dir``, as in ``configs/train.yaml``.
    """
    rec = load_recording(_sequence_config(source, cfg["sequence"]), quick=False, progress=progress)
    if rec.truth is None:
        raise ValueError(f"{rec.name}: training needs ground truth; the sequence has none")
    pairs: dict[str, FlowPairs | None] = {"dense": None, "sparse": None}
    tracks = None
    for kind, index in (("sparse", 1), ("dense", 2)):
        if any(METHODS[m][index] for m in methods):
            if kind == "sparse" and uses_tracks(cfg):
                tracks = load_tracks(rec, cfg, progress=progress)  # the multi-view update (filter.tracks)
                if isinstance(tracks, str):
                    raise ValueError(f"{rec.name}: sparse tracks unavailable: {tracks}")
                continue
            flow = load_flow(kind, rec, cfg, progress=progress)
            if isinstance(flow, str):
                raise ValueError(f"{rec.name}: {kind} flow unavailable: {flow}")
            pairs[kind] = flow
    if setting(cfg, "sequence.check_mounting", bool):
        check_camera_mounting(rec, {"sparse": pairs["sparse"] if tracks is None else tracks, "dense": pairs["dense"]})
    return TrainingSequence(rec.name, rec.imu, rec.gnss, rec.truth, FlowCamera.from_sequence(rec.sequence),
                            pairs["dense"], pairs["sparse"], tracks, rec.sensor, platform_streams(rec.platform))


class _Sequences(Dataset):
    def __init__(self, items: list[TrainingSequence]) -> None:
        self.items = items

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, index: int) -> TrainingSequence:
        return self.items[index]


def _identity(batch: TrainingSequence) -> TrainingSequence:
    return batch


def _as_list(batch: list[TrainingSequence]) -> list[TrainingSequence]:
    return list(batch)


class SequenceDataModule(pl.LightningDataModule):
    """Training and held-out sequences. A training batch is a list of ``batch_size`` whole
    sequences (the module cuts them into windows and runs their windows together); a
    held-out batch is one sequence. The ``select`` sequences (long held-out walks, possibly
    none) have no loader: :class:`~flowins.training.module.FilterLearner` runs them all at
    once at each validation (:attr:`select_sequences`). ``prepare_data`` simulates and runs
    the flow network once (cached)."""

    def __init__(
        self,
        *,
        train: Sequence[Mapping[str, Any]],
        val: Sequence[Mapping[str, Any]],
        config: Mapping[str, Any],
        methods: Sequence[str],
        batch_size: int = 1,
        progress: bool = True,
        seed: int = 0,
        select: Sequence[Mapping[str, Any]] = (),
    ) -> None:
        super().__init__()
        if not train or not val:
            raise ValueError("data: need at least one training and one held-out (val) sequence")
        if not (isinstance(batch_size, int) and batch_size >= 1):
            raise ValueError(f"data.batch_size={batch_size!r}: expected an integer >= 1")
        self.batch_size = batch_size
        self.seed = int(seed)
        self.sources = {"train": list(train), "val": list(val), "select": list(select)}
        for split, sources in self.sources.items():
            for i, source in enumerate(sources):
                _sequence_config(source, {}, f"data.{split}[{i}]")
        self.config = config
        self.methods = list(methods)
        self.progress = progress
        self.sequences: dict[str, list[TrainingSequence]] = {}

    def prepare_data(self) -> None:
        self.setup()

    def setup(self, stage: str | None = None) -> None:
        for split, sources in self.sources.items():
            if split not in self.sequences:
                self.sequences[split] = [
                    load_training_sequence(s, self.config, methods=self.methods, progress=self.progress) for s in sources
                ]

    @property
    def select_sequences(self) -> list[TrainingSequence]:
        """The ``select`` sequences (after :meth:`setup`; empty without ``select`` sources)."""
        return list(self.sequences.get("select", []))

    def _loader(self, split: str, shuffle: bool) -> DataLoader:
        return DataLoader(_Sequences(self.sequences[split]), batch_size=None, shuffle=shuffle, collate_fn=_identity)

    def train_dataloader(self) -> DataLoader:
        """Shuffled batches of ``batch_size`` sequences, in an order that depends on ``seed``
        alone; with several processes (DDP) each process takes its own share of the sequences
        (``trainer.use_distributed_sampler`` is off, so that every process validates every
        held-out sequence and the processes agree on the best validation)."""
        sequences = _Sequences(self.sequences["train"])
        trainer = getattr(self, "trainer", None)
        if trainer is not None and trainer.world_size > 1:
            sampler = DistributedSampler(sequences, num_replicas=trainer.world_size, rank=trainer.global_rank,
                                         shuffle=True, seed=self.seed)
            return DataLoader(sequences, batch_size=self.batch_size, sampler=sampler, collate_fn=_as_list)
        # the order comes from its own generator, seeded once: what else draws from torch's global
        # one (building each sequence's flow network does) does not change the training
        order = torch.Generator().manual_seed(self.seed)
        return DataLoader(sequences, batch_size=self.batch_size, shuffle=True, collate_fn=_as_list, generator=order)

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", False)

    def test_dataloader(self) -> DataLoader:
        return self._loader("val", False)

    def transfer_batch_to_device(self, batch, device, dataloader_idx: int):
        # the filter runs where its inputs are (float64, CPU by default); the sequence is not moved
        return batch
