"""Writing a :class:`~flowins.data.Sequence` as a flowins folder (:func:`write_folder`)."""
from __future__ import annotations

import datetime
import os
import shutil
from collections.abc import Iterable, Iterator
from collections.abc import Sequence as Seq
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from torch import Tensor

from flowins.data.folder.format import (
    FILES,
    FRAME_FILE_COLUMNS,
    FRAME_VIDEO_COLUMNS,
    GNSS_COLUMNS,
    GROUNDTRUTH_COLUMNS,
    IMU_COLUMNS,
    TRACK_COLUMNS,
)
from flowins.data.sequence import CameraFrames, PinholeCamera, Sequence
from flowins.geometry.camera import RigidTransform




def _format_rows(columns: Seq[Tensor | np.ndarray], integer: Seq[bool] | None = None) -> Iterator[str]:
    """CSV lines of equal-length columns; floats as ``repr`` (exact float64 round trip)."""
    lists = [torch.as_tensor(c).tolist() for c in columns]
    integer = integer or [False] * len(lists)
    for row in zip(*lists):
        yield ",".join(str(int(x)) if is_int else repr(float(x)) for x, is_int in zip(row, integer))


def _write_csv(file: Path, header: Seq[str], lines: Iterable[str]) -> None:
    with open(file, "w", encoding="utf-8", newline="\n") as out:
        out.write(",".join(header) + "\n")
        out.writelines(line + "\n" for line in lines)


def _plain(value: Any, where: str) -> Any:
    """``value`` with tensors, arrays, paths and tuples turned into YAML-safe builtins."""
    if isinstance(value, Tensor):
        value = value.detach().cpu().numpy()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            if not isinstance(k, (str, int, float, bool)):
                raise ValueError(f"metadata{where}: key {k!r} of type {type(k).__name__}; expected str, int, float or bool keys")
            out[k] = _plain(v, f"{where}.{k}")
        return out
    if isinstance(value, (list, tuple)):
        return [_plain(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if value is None or isinstance(value, (str, int, float, bool, datetime.date)):
        return value  # (YAML itself reads dates as datetime.date / datetime.datetime)
    raise ValueError(
        f"metadata{where}: value of type {type(value).__name__}; expected numbers, strings, lists, dicts, "
        "tensors or arrays (something metadata.yaml can hold)"
    )


def _link_or_copy(src: Path, dst: Path) -> None:
    if dst.exists() and dst.resolve() == src.resolve():
        return  # already in place (e.g. written by write_frame_images)
    if dst.exists() or dst.is_symlink():
        dst.unlink()
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def _inside(child: Path, parent: Path) -> bool:
    try:
        child.resolve().relative_to(parent.resolve())
        return True
    except ValueError:
        return False


def _clear(folder: Path, keep: Seq[Path]) -> None:
    """Remove the format's files from ``folder``; a frame source listed in ``keep`` stays."""
    for name in FILES:
        target = folder / name
        if any(_inside(k, target) for k in keep):
            continue
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        elif target.exists() or target.is_symlink():
            target.unlink()


def _frame_names(files: Seq[Path]) -> list[str]:
    """Keep the source names unless two different files share one (or a name cannot go in a CSV)."""
    by_name: dict[str, Path] = {}
    for file in files:
        other = by_name.setdefault(file.name, file)
        unsafe = any(ch in file.name for ch in ",\n\r") or file.name != file.name.strip()
        if unsafe or other.resolve() != file.resolve():
            return [f"{i:06d}{f.suffix.lower()}" for i, f in enumerate(files)]
    return [file.name for file in files]


def _frames_in_place(frames: CameraFrames, folder: Path) -> bool:
    """Whether the frames already are ``folder/frames/*`` (or ``folder/frames.mp4``): nothing to copy."""
    if frames.files is not None:
        target = (folder / "frames").resolve()
        return all(f.resolve().parent == target for f in frames.files)
    return frames.video.resolve() == (folder / "frames.mp4").resolve()


def _write_frames(frames: CameraFrames, folder: Path) -> None:
    t_s = frames.t_s
    if frames.files is not None:
        (folder / "frames").mkdir(exist_ok=True)
        names = _frame_names(frames.files)
        for src, name in zip(frames.files, names):
            _link_or_copy(src, folder / "frames" / name)
        _write_csv(folder / "frames.csv", FRAME_FILE_COLUMNS, (f"{float(t)!r},{n}" for t, n in zip(t_s.tolist(), names)))
    else:
        _link_or_copy(frames.video, folder / "frames.mp4")
        _write_csv(folder / "frames.csv", FRAME_VIDEO_COLUMNS, _format_rows([t_s, frames.indices], [False, True]))


def _calibration_dict(camera: PinholeCamera | None, transform: RigidTransform | None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if camera is not None:
        out["camera"] = {
            "width": camera.width,
            "height": camera.height,
            "fx": camera.fx,
            "fy": camera.fy,
            "cx": camera.cx,
            "cy": camera.cy,
        }
        if camera.distortion:
            out["camera"]["distortion"] = [float(c) for c in camera.distortion]
    if transform is not None:
        q, t = transform.rotation_wxyz, transform.translation_m
        if tuple(q.shape) != (4,) or tuple(t.shape) != (3,):
            raise ValueError(
                f"imu_to_camera has rotation {tuple(q.shape)} and translation {tuple(t.shape)}; expected one "
                "transform: (4,) and (3,)"
            )
        out["imu_to_camera"] = {"rotation": [float(x) for x in q.tolist()], "translation": [float(x) for x in t.tolist()]}
    return out


def write_folder(
    seq: Sequence, path: str | os.PathLike, *, overwrite: bool = False, copy_frames: bool = True
) -> Path:
    """Write ``seq`` as a flowins folder at ``path``; returns the folder.

    Every present part is written; floats as ``repr`` so that :func:`read_folder`
    gives identical float64 arrays. Image files are hard-linked (copied where a
    link is impossible) into ``frames/`` under their own names, renamed to
    ``{i:06d}{suffix}`` when two different files share a name; a video is copied
    to ``frames.mp4`` with ``t,index`` rows. With ``copy_frames=False`` no image
    data is copied: frames that already are ``path/frames/*`` (or
    ``path/frames.mp4``, e.g. written there by :func:`write_frame_images` or a
    simulator) are listed in ``frames.csv`` as they are; other frames are left
    out (the calibration is still written).

    Args:
        overwrite: allow a non-empty ``path``; the format's files in it are
            replaced (images that are the sequence's own frames stay; a
            ``camchain-imucam.yaml`` is removed: the calibration is written as
            ``calibration.yaml``).

    Raises:
        ValueError: ``path`` is a non-empty folder and ``overwrite`` is False, or
            a part cannot be written (missing image, unsupported metadata value).
    """
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{folder}: exists and is not a folder; expected a folder (or nothing) to write the sequence to")
    if folder.is_dir() and any(folder.iterdir()):
        if not overwrite:
            raise ValueError(f"{folder}: folder exists and is not empty; pass overwrite=True (--overwrite) to replace it")
    # Everything that can fail is checked before anything is removed.
    keep: list[Path] = []
    write_frames = seq.frames is not None and (copy_frames or _frames_in_place(seq.frames, folder))
    if write_frames:
        keep = list(seq.frames.files) if seq.frames.files is not None else [seq.frames.video]
        missing = next((k for k, f in enumerate(keep) if not f.is_file()), None)
        if missing is not None:
            raise ValueError(
                f"{seq.frames.name}: frame source {keep[missing]} (row {missing}, 0-based) does not exist; "
                "cannot copy it (pass copy_frames=False / --no-frames to leave the frames out)"
            )
    metadata = _plain(dict(seq.metadata), "") if seq.metadata else {}
    calibration = _calibration_dict(seq.camera, seq.imu_to_camera)
    folder.mkdir(parents=True, exist_ok=True)
    _clear(folder, keep)

    imu = seq.imu
    _write_csv(folder / "imu.csv", IMU_COLUMNS, _format_rows([imu.t_s, *imu.acc_mps2.T, *imu.gyro_rps.T]))
    if calibration:
        with open(folder / "calibration.yaml", "w", encoding="utf-8") as out:
            yaml.safe_dump(calibration, out, sort_keys=False)
    if write_frames:
        _write_frames(seq.frames, folder)
    if seq.tracks is not None:
        tr = seq.tracks
        _write_csv(
            folder / "tracks.csv", TRACK_COLUMNS,
            _format_rows([tr.t_s, tr.track_id, tr.uv_px[:, 0], tr.uv_px[:, 1]], [False, True, False, False]),
        )
    if seq.gnss is not None:
        g = seq.gnss
        _write_csv(folder / "gnss.csv", GNSS_COLUMNS, _format_rows([g.t_s, g.lat_deg, g.lon_deg, g.alt_m, g.h_acc_m, g.v_acc_m]))
    if seq.groundtruth is not None:
        gt = seq.groundtruth
        if gt.quat_wxyz is not None:
            lines = _format_rows([gt.t_s, *gt.pos_m.T, *gt.quat_wxyz.T])
        else:
            lines = (line + ",,,," for line in _format_rows([gt.t_s, *gt.pos_m.T]))
        _write_csv(folder / "groundtruth.csv", GROUNDTRUTH_COLUMNS, lines)
    if metadata:
        with open(folder / "metadata.yaml", "w", encoding="utf-8") as out:
            yaml.safe_dump(metadata, out, sort_keys=False)
    return folder


def write_frame_images(
    path: str | os.PathLike, images: Iterable[Tensor | np.ndarray], t_s: Tensor | np.ndarray | Seq[float], *, overwrite: bool = False
) -> CameraFrames:
    """Write in-memory images as ``frames/{i:06d}.png`` plus ``frames.csv`` (``t,file``).

    Args:
        path: the sequence folder (created if needed).
        images: iterable of ``(H, W, 3)`` uint8 RGB images (tensors or arrays),
            one per timestamp, all of one size.
        t_s: ``(N,)`` strictly increasing frame times [s].
        overwrite: allow replacing an existing ``frames.csv`` / ``frames/``.

    Returns:
        :class:`~flowins.data.sequence.CameraFrames` of the written files (give
        it to a :class:`Sequence`, then :func:`write_folder` with
        ``overwrite=True`` into the same folder keeps these images in place).
    """
    import cv2

    folder = Path(path)
    times = torch.as_tensor(np.asarray(t_s, dtype=np.float64) if not isinstance(t_s, Tensor) else t_s)
    n = int(times.reshape(-1).shape[0]) if times.ndim <= 1 else -1
    files = tuple(folder / "frames" / f"{i:06d}.png" for i in range(max(n, 0)))
    CameraFrames(times, files=files, name="write_frame_images: t_s", check_files=False)  # validates times first
    if not overwrite and ((folder / "frames.csv").exists() or ((folder / "frames").is_dir() and any((folder / "frames").iterdir()))):
        raise ValueError(f"{folder}: frames.csv or frames/ already exist; pass overwrite=True to replace them")
    if overwrite and (folder / "frames").is_dir():
        shutil.rmtree(folder / "frames")
    (folder / "frames").mkdir(parents=True, exist_ok=True)
    size = None
    count = 0
    for i, image in enumerate(images):
        array = image.detach().cpu().numpy() if isinstance(image, Tensor) else np.asarray(image)
        if array.dtype != np.uint8 or array.ndim != 3 or array.shape[2] != 3:
            raise ValueError(f"write_frame_images: image {i} has shape {array.shape} and type {array.dtype}; expected (H, W, 3) uint8 RGB")
        if size is None:
            size = array.shape[:2]
        elif array.shape[:2] != size:
            raise ValueError(f"write_frame_images: image {i} is {array.shape[1]}x{array.shape[0]}; expected {size[1]}x{size[0]} like image 0")
        if i >= n:
            raise ValueError(f"write_frame_images: more images than the {n} timestamps; expected one image per time")
        if not cv2.imwrite(str(files[i]), cv2.cvtColor(np.ascontiguousarray(array), cv2.COLOR_RGB2BGR)):
            raise ValueError(f"write_frame_images: cannot write {files[i]}")
        count += 1
    if count != n:
        raise ValueError(f"write_frame_images: {count} images for {n} timestamps; expected one image per time")
    _write_csv(folder / "frames.csv", FRAME_FILE_COLUMNS, (f"{t!r},{f.name}" for t, f in zip(times.tolist(), files)))
    return CameraFrames(times, files=files, name=str(folder / "frames.csv"))
