"""A recording's flow pairs for a job: the dense provider or the sparse tracker of the
config, run once on the frames and cached by content (or the recording's own
``tracks.csv``), undistorted with the camera's calibration."""
from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from flowins.cache import cache_root
from flowins.config import instantiate, setting
from flowins.data.load import Recording
from flowins.data.sequence import Tracks
from flowins.flow.mounting import MountingCheck, check_mounting
from flowins.flow.pairs import FlowPairs, cache_key, cached, dense_pairs, ideal_pixels, sparse_pairs, track_pairs

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


def check_camera_mounting(rec: Recording, flows: Mapping[str, FlowPairs | Tracks | str | None]) -> MountingCheck | None:
    """``imu_to_camera``'s rotation against the gyroscope and the first of ``flows`` there is
    (``sparse``, then ``dense``; tracks as pairs of consecutive frames):
    :func:`~flowins.flow.mounting.check_mounting`. Printed: a warning when the calibration
    looks wrong (also added to ``rec.warnings``, which ``metrics.json`` keeps), else one
    line. None without flow or calibration."""
    seq = rec.sequence
    flow = next((f for f in (flows.get("sparse"), flows.get("dense")) if isinstance(f, (FlowPairs, Tracks))), None)
    if flow is None or seq.camera is None or seq.imu_to_camera is None:
        return None
    pairs = track_pairs(flow, sigma_px=1.0) if isinstance(flow, Tracks) else flow
    result = check_mounting(rec.imu.t_s, rec.imu.gyro_rps, pairs, seq.camera.K, seq.imu_to_camera.rotation_wxyz)
    if result.warn:
        line = f"{rec.name}: {result.describe()}; sequence.check_mounting=false skips this check"
        log.warning("warning: %s", line)
        rec.warnings.append(line)
    else:
        log.info(f"camera mounting: {result.describe()}")
    return result


TRACKS_FORMAT = 1


def uses_tracks(cfg: Mapping[str, Any]) -> bool:
    """Whether a job's sparse rows take tracks over many frames (``filter.tracks.window >= 1``, the
    multi-view update) instead of flow pairs."""
    return setting(cfg, "filter.tracks.window", int, minimum=0) >= 1


def load_tracks(rec: Recording, cfg: Mapping[str, Any], *, progress: bool) -> Tracks | str:
    """The recording's sparse tracks over many frames for the multi-view update
    (``filter.tracks.window >= 1``), in the ideal pinhole image, or the reason they can't be had:
    its own ``tracks.csv`` (``sparse.source=tracks``), or ``sparse.tracker`` run over its frames
    with track ids kept across them (:func:`~flowins.flow.sparse.track_sequence`: the end points
    of one pair seed the next, fresh corners top them up), computed once and cached."""
    seq = rec.sequence
    if seq is None or seq.camera is None:
        return "the sequence has no camera"
    if cfg["sparse"].get("source") == "tracks":
        if seq.tracks is None:
            return "sparse.source=tracks but the sequence has no tracks.csv"
        return undistort_tracks(seq.tracks, seq.camera)
    if seq.frames is None:
        return "the sequence has no camera frames"
    from flowins.flow.sparse import track_sequence

    target = cfg["sparse"]["tracker"]
    provider = instantiate(target, "sparse.tracker")
    key = cache_key(kind="tracks", source=rec.content_key, provider=target, tracks_format=TRACKS_FORMAT)
    path = Path(cfg["cache_dir"] or cache_root()) / "flow" / f"tracks-{key}.npz"
    label = str(target.get("_target_", "")).rsplit(".", 1)[-1]
    if path.is_file():
        log.info(f"sparse tracks: {label}, read from the cache {path}")
        return undistort_tracks(read_tracks(path), seq.camera)
    if progress:
        log.info(f"sparse tracks: running {label} over {len(seq.frames)} frames with track ids kept")
    tracks = track_sequence(seq.frames, provider, name=f"{label} tracks").tracks
    write_tracks(path, tracks)
    return undistort_tracks(tracks, seq.camera)


def write_tracks(path: Path, tracks: Tracks) -> None:
    """One ``.npz`` of the track rows (written to a partial file, then renamed)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.partial.npz")  # one per process: no two write one file
    np.savez_compressed(tmp, version=TRACKS_FORMAT, t_s=tracks.t_s.numpy(), track_id=tracks.track_id.numpy(),
                        uv_px=tracks.uv_px.numpy(), name=str(tracks.name))
    tmp.replace(path)


def read_tracks(path: Path) -> Tracks:
    with np.load(path, allow_pickle=False) as z:
        if "version" not in z or int(z["version"]) != TRACKS_FORMAT:
            raise ValueError(f"{path}: not a flowins tracks file of format version {TRACKS_FORMAT}")
        return Tracks(torch.from_numpy(z["t_s"]), torch.from_numpy(z["track_id"]), torch.from_numpy(z["uv_px"]),
                      name=str(z["name"]))


def undistort_tracks(tracks: Tracks, camera) -> Tracks:
    """``tracks`` with their pixels in the ideal pinhole image of ``camera`` (radial-tangential
    distortion removed; itself without distortion)."""
    if not any(camera.distortion):
        return tracks
    return Tracks(tracks.t_s, tracks.track_id, ideal_pixels(tracks.uv_px, camera), name=tracks.name,
                  frame_times_s=tracks.frame_times_s)
