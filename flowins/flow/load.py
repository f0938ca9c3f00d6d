"""A recording's flow pairs for a job: the dense provider or the sparse tracker of the
config, run once on the frames and cached by content (or the recording's own
``tracks.csv``), undistorted with the camera's calibration."""
from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from flowins.cache import cache_root
from flowins.config import instantiate
from flowins.data.load import Recording
from flowins.flow.pairs import FlowPairs, cache_key, cached, dense_pairs, sparse_pairs, track_pairs

log = logging.getLogger("flowins")


def load_flow(kind: str, rec: Recording, cfg: Mapping[str, Any], *, progress: bool) -> FlowPairs | str:
    """The dense or sparse flow pairs of the recording (computed once, then cached),
    or the reason they can't be had."""
    seq = rec.sequence
    if seq is None or seq.camera is None:
        return "the sequence has no camera"
    pairs_cfg = cfg["flow_pairs"]
    step = int(pairs_cfg["step"])
    if kind == "sparse" and cfg["sparse"].get("source") == "tracks":
        if seq.tracks is None:
            return "sparse.source=tracks but the sequence has no tracks.csv"
        return track_pairs(seq.tracks, sigma_px=float(cfg["sparse"]["sigma_px"]), step=step).undistorted(seq.camera)
    if seq.frames is None:
        return "the sequence has no camera frames"
    settings = cfg["flow"] if kind == "dense" else cfg["sparse"]
    target = settings if kind == "dense" else settings["tracker"]  # what instantiate builds
    extra = dict(stride_px=pairs_cfg["stride_px"], border_px=pairs_cfg["border_px"],
                 input_scale=pairs_cfg["input_scale"]) if kind == "dense" else {}
    provider = instantiate(target, "flow" if kind == "dense" else "sparse.tracker")
    weights = provider if isinstance(provider, torch.nn.Module) else None  # keyed by its state dict
    # closed-form dropout keeps σ's moments, which give σ at every rate: one cache for all rates
    rate = settings.get("p") if kind == "dense" and settings.get("mc_mode") == "moments" else None
    keyed = settings if rate is None else {k: v for k, v in settings.items() if k != "p"}
    key = cache_key(kind=kind, source=rec.content_key, provider=keyed, weights=weights, step=step, **extra)
    path = Path(cfg["cache_dir"] or cache_root()) / "flow" / f"{kind}-{key}.npz"
    label = str(target.get("_target_", "")).rsplit(".", 1)[-1]

    def compute() -> FlowPairs:
        if kind == "dense":
            return dense_pairs(seq.frames, provider, step=step, batch_size=int(pairs_cfg["batch_size"]),
                               progress=progress, description=label, **extra)
        return sparse_pairs(seq.frames, provider, step=step, progress=progress, description=label)

    if path.is_file():
        log.info(f"{kind} flow: {label}, read from the cache {path}")
    pairs = cached(path, compute)
    if rate is not None:
        pairs = pairs.at_dropout_rate(float(rate))
    return pairs.undistorted(seq.camera)
