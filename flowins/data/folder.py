"""The flowins folder format: one folder per sequence, plain CSV and YAML.

::

    imu.csv          t,ax,ay,az,wx,wy,wz           [s, m/s², rad/s]          (required)
    frames.csv       t,file   (images under frames/)  or  t,index  (frames.mp4)
    tracks.csv       t,track_id,u,v                 [s, -, px, px]
    gnss.csv         t,lat,lon,alt,h_acc,v_acc      [s, deg, deg, m, m, m]
    groundtruth.csv  t,px,py,pz,qw,qx,qy,qz         [s, m, -] (q empty in every row = positions only)
    calibration.yaml camera: {width, height, fx, fy, cx, cy, distortion},
                     imu_to_camera: {rotation, translation} (or its inverse, camera_to_imu)
    camchain-imucam.yaml  Kalibr's calibration (cam0), read in place of calibration.yaml
    metadata.yaml    free-form mapping -> Sequence.metadata

Every CSV has a header row. Floats are written with ``repr`` (the shortest text
that parses back to the same float64), so ``write_folder`` then ``read_folder``
gives bit-identical arrays. See ``docs/sequence_format.md`` for the conventions.

Every error is a ``ValueError`` that names the file, the 1-based line of the
file (``line N``) where there is one, and what was expected. Errors raised by the
stream constructors (which count 0-based data rows) are rewritten to name the
line of the file.
"""
from __future__ import annotations

import datetime
import os
import re
import shutil
from collections.abc import Iterable, Iterator
from collections.abc import Sequence as Seq
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from torch import Tensor

from flowins.data.kalibr import CAMCHAIN, read_kalibr_camchain, read_kalibr_timeshift
from flowins.data.sequence import CameraFrames, PinholeCamera, Sequence, Tracks
from flowins.data.streams import GnssStream, ImuStream, PoseStream
from flowins.geometry import quaternion as quat
from flowins.geometry.camera import RigidTransform

__all__ = ["FILES", "read_folder", "write_folder", "write_frame_images"]

IMU_COLUMNS = ("t", "ax", "ay", "az", "wx", "wy", "wz")
FRAME_FILE_COLUMNS = ("t", "file")
FRAME_VIDEO_COLUMNS = ("t", "index")
TRACK_COLUMNS = ("t", "track_id", "u", "v")
GNSS_COLUMNS = ("t", "lat", "lon", "alt", "h_acc", "v_acc")
GROUNDTRUTH_COLUMNS = ("t", "px", "py", "pz", "qw", "qx", "qy", "qz")
CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "distortion")
EXTRINSIC_KEYS = ("rotation", "translation")
EXTRINSIC_NAMES = ("imu_to_camera", "camera_to_imu")
#: Largest disagreement allowed between ``imu_to_camera`` and the inverse of ``camera_to_imu``
#: when a calibration.yaml gives both: far below any calibration's accuracy (about 1e-3 rad and
#: 1e-3 m), above the rounding of numbers printed with six decimals.
EXTRINSIC_AGREEMENT_RAD = 1e-5
EXTRINSIC_AGREEMENT_M = 1e-5

#: Every name the format owns inside a sequence folder.
FILES = (
    "imu.csv",
    "frames.csv",
    "frames",
    "frames.mp4",
    "tracks.csv",
    "gnss.csv",
    "groundtruth.csv",
    "calibration.yaml",
    CAMCHAIN,
    "metadata.yaml",
)

# Plausibility bounds of the IMU units (medians over the whole file).
_ACC_MEDIAN_MIN_MPS2 = 2.0
_ACC_MEDIAN_MAX_MPS2 = 50.0
_GYRO_MEDIAN_MAX_RPS = 20.0
# A quaternion read from a file whose norm is this close to 1 is kept bit-for-bit.
_UNIT_NORM_TOL = 1e-15


# ---------------------------------------------------------------------------
# CSV parsing (numpy, with file and line in every message)
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class _Table:
    """Cells of a CSV file: ``cells[r][c]`` (stripped strings) and the 1-based file line of row ``r``."""

    file: Path
    columns: tuple[str, ...]
    cells: list[list[str]]
    lines: np.ndarray  # (R,) int64

    def floats(self, column: str, *, expected: str = "a number") -> np.ndarray:
        """Column ``column`` as ``(R,)`` float64; a cell that is not a number names its line."""
        c = self.columns.index(column)
        text = [row[c] for row in self.cells]
        try:
            return np.array(text, dtype=np.float64)
        except ValueError:
            pass
        for row, cell in enumerate(text):
            try:
                float(cell)
            except ValueError:
                raise ValueError(
                    f"{self.file}: line {self.lines[row]}: column '{column}' is {cell!r}; expected {expected}"
                ) from None
        raise AssertionError("unreachable: numpy rejected a column that float() accepts")  # pragma: no cover

    def integers(self, column: str, *, expected: str = "an integer") -> np.ndarray:
        """Column ``column`` as ``(R,)`` int64 (plain decimal integers only)."""
        c = self.columns.index(column)
        out = np.empty(len(self.cells), dtype=np.int64)
        for row, cells in enumerate(self.cells):
            try:
                out[row] = int(cells[c])
            except (ValueError, OverflowError):
                raise ValueError(
                    f"{self.file}: line {self.lines[row]}: column '{column}' is {cells[c]!r}; expected {expected}"
                ) from None
        return out

    def strings(self, column: str) -> list[str]:
        c = self.columns.index(column)
        return [row[c] for row in self.cells]

    def line_of_row(self, row: int) -> int:
        return int(self.lines[row])


def _read_text(file: Path) -> str:
    try:
        return file.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{file}: not UTF-8 text ({exc}); expected a CSV/YAML text file") from None


def _read_table(file: Path, columns: Seq[str], *, alternatives: Seq[Seq[str]] = ()) -> _Table:
    """Parse a CSV with a header row equal to ``columns`` (or one of ``alternatives``).

    Blank lines are skipped (line numbers still count them). Every data line must
    have as many comma-separated cells as the header.
    """
    accepted = [tuple(columns), *(tuple(a) for a in alternatives)]
    lines = _read_text(file).splitlines()
    header_index = next((i for i, line in enumerate(lines) if line.strip()), None)
    expected_text = " or ".join(repr(",".join(a)) for a in accepted)
    if header_index is None:
        raise ValueError(f"{file}: the file is empty; expected a header row {expected_text} and data rows")
    found = tuple(cell.strip() for cell in lines[header_index].split(","))
    if found not in accepted:
        raise ValueError(
            f"{file}: line {header_index + 1}: header is {','.join(found)!r}; expected {expected_text} "
            "(column names, in this order)"
        )
    cells: list[list[str]] = []
    numbers: list[int] = []
    for i in range(header_index + 1, len(lines)):
        line = lines[i]
        if not line.strip():
            continue
        row = [cell.strip() for cell in line.split(",")]
        if len(row) != len(found):
            raise ValueError(
                f"{file}: line {i + 1}: {len(row)} comma-separated cells; expected {len(found)} "
                f"({','.join(found)})"
            )
        cells.append(row)
        numbers.append(i + 1)
    if not cells:
        raise ValueError(f"{file}: no data rows after the header (line {header_index + 1}); expected at least one")
    return _Table(file=file, columns=found, cells=cells, lines=np.array(numbers, dtype=np.int64))


_ROWS_PATTERN = re.compile(r"rows (\d+) and (\d+) \(0-based;? ?")
_ROW_PATTERN = re.compile(r"row (\d+) \(0-based\)")


def _rows_to_lines(message: str, table: _Table) -> str:
    """Rewrite a constructor's ``row k (0-based)`` as the file's ``line N``."""

    def line(k: str) -> str:
        k_int = int(k)
        return str(table.line_of_row(k_int)) if 0 <= k_int < len(table.lines) else f"(row {k})"

    message = _ROWS_PATTERN.sub(lambda m: f"lines {line(m.group(1))} and {line(m.group(2))} (", message)
    message = _ROW_PATTERN.sub(lambda m: f"line {line(m.group(1))}", message)
    message = message.replace(" ()", "")
    if str(table.file) not in message:
        message = f"{table.file}: {message}"
    return message


@contextmanager
def _lines_for(table: _Table) -> Iterator[None]:
    """Re-raise a constructor's ``ValueError`` with file lines instead of 0-based rows."""
    try:
        yield
    except ValueError as exc:
        raise ValueError(_rows_to_lines(str(exc), table)) from None


def _keep_unit_rows(q_file: Tensor, q_normalised: Tensor) -> Tensor:
    """The file's quaternion rows where they are already unit to float64 precision.

    Dividing a unit quaternion by its norm again can change its last bit, so a
    constructor's re-normalisation would break the exact write -> read round trip;
    rows with ``|norm - 1| <= 1e-15`` are kept as written (a no-op rotation-wise).
    """
    norm = torch.linalg.vector_norm(q_file, dim=-1, keepdim=True)
    return torch.where((norm - 1.0).abs() <= _UNIT_NORM_TOL, q_file, q_normalised)


# ---------------------------------------------------------------------------
# YAML parsing (with the line of each key)
# ---------------------------------------------------------------------------


def _load_yaml(file: Path) -> tuple[Any, yaml.Node | None]:
    text = _read_text(file)
    try:
        return yaml.safe_load(text), yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ValueError(f"{file}: {where}not valid YAML ({problem})") from None


def _yaml_line(node: yaml.Node | None, *keys: str) -> int | None:
    """1-based line of the value at ``keys`` in a composed YAML tree (or of the deepest key found)."""
    line = None if node is None else node.start_mark.line + 1
    for key in keys:
        if not isinstance(node, yaml.MappingNode):
            break
        for k, v in node.value:
            if isinstance(k, yaml.ScalarNode) and k.value == key:
                node, line = v, k.start_mark.line + 1
                break
        else:
            break
    return line


def _at(file: Path, root: yaml.Node | None, *keys: str) -> str:
    line = _yaml_line(root, *keys)
    return f"{file}: line {line}: " if line is not None else f"{file}: "


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _number_list(value: Any, lengths: Seq[int], *, file: Path, root: yaml.Node | None, keys: Seq[str], what: str) -> list[float]:
    if value is None and 0 in lengths:
        return []
    if not isinstance(value, list) or len(value) not in lengths or not all(_is_number(v) for v in value):
        sizes = " or ".join(str(n) for n in lengths)
        raise ValueError(
            f"{_at(file, root, *keys)}{'.'.join(keys)} is {value!r}; expected a list of {sizes} numbers ({what})"
        )
    return [float(v) for v in value]


def _mapping(value: Any, allowed: Seq[str], *, file: Path, root: yaml.Node | None, keys: Seq[str]) -> dict:
    label = ".".join(keys) if keys else "the file"
    if not isinstance(value, dict):
        raise ValueError(f"{_at(file, root, *keys)}{label} is {value!r}; expected a mapping with keys {', '.join(allowed)}")
    unknown = [k for k in value if k not in allowed]
    if unknown:
        raise ValueError(
            f"{_at(file, root, *keys, str(unknown[0]))}{label} has unknown key {unknown[0]!r}; "
            f"expected only {', '.join(allowed)}"
        )
    return value


def _read_camera(cam_value: Any, *, file: Path, root: yaml.Node | None) -> PinholeCamera:
    cam = _mapping(cam_value, CAMERA_KEYS, file=file, root=root, keys=("camera",))
    for key in CAMERA_KEYS[:-1]:
        if key not in cam:
            raise ValueError(f"{_at(file, root, 'camera')}camera has no '{key}'; expected {', '.join(CAMERA_KEYS[:-1])} (and optional distortion)")
        if not _is_number(cam[key]):
            raise ValueError(f"{_at(file, root, 'camera', key)}camera.{key} is {cam[key]!r}; expected a number (pixels)")
    distortion = _number_list(
        cam.get("distortion"), (0, 4, 5), file=file, root=root, keys=("camera", "distortion"), what="k1, k2, p1, p2[, k3]"
    )
    try:
        return PinholeCamera(cam["width"], cam["height"], cam["fx"], cam["fy"], cam["cx"], cam["cy"], tuple(distortion))
    except ValueError as exc:
        raise ValueError(f"{_at(file, root, 'camera')}{exc}") from None


def _read_extrinsic(value: Any, key: str, *, file: Path, root: yaml.Node | None) -> RigidTransform:
    """``{rotation: [qw, qx, qy, qz], translation: [x, y, z]}`` at ``key`` as a transform."""
    ext = _mapping(value, EXTRINSIC_KEYS, file=file, root=root, keys=(key,))
    for part in EXTRINSIC_KEYS:
        if part not in ext:
            raise ValueError(f"{_at(file, root, key)}{key} has no '{part}'; expected rotation [qw, qx, qy, qz] and translation [x, y, z]")
    q = _number_list(ext["rotation"], (4,), file=file, root=root, keys=(key, "rotation"), what="qw, qx, qy, qz")
    t = _number_list(ext["translation"], (3,), file=file, root=root, keys=(key, "translation"), what="x, y, z in metres")
    q_file = torch.tensor(q, dtype=torch.float64)
    try:
        transform = RigidTransform(q_file, torch.tensor(t, dtype=torch.float64))
    except ValueError as exc:
        raise ValueError(f"{_at(file, root, key, 'rotation')}{exc}") from None
    object.__setattr__(transform, "rotation_wxyz", _keep_unit_rows(q_file, transform.rotation_wxyz))
    return transform


def _check_inverse(imu_to_camera: RigidTransform, camera_to_imu: RigidTransform, *, file: Path, root: yaml.Node | None) -> None:
    """Both extrinsics given: ``camera_to_imu`` must be the inverse of ``imu_to_camera``."""
    inverse = camera_to_imu.inverse()
    angle_rad = float(quat.angle_between(imu_to_camera.rotation_wxyz, inverse.rotation_wxyz))
    offset_m = float(torch.linalg.vector_norm(imu_to_camera.translation_m - inverse.translation_m))
    if angle_rad > EXTRINSIC_AGREEMENT_RAD or offset_m > EXTRINSIC_AGREEMENT_M:
        raise ValueError(
            f"{_at(file, root, 'camera_to_imu')}imu_to_camera and camera_to_imu disagree: the inverse of "
            f"camera_to_imu differs from imu_to_camera by {angle_rad:.3g} rad ({np.degrees(angle_rad):.3g} deg) "
            f"in rotation and {offset_m:.3g} m in translation; expected inverses of each other (within "
            f"{EXTRINSIC_AGREEMENT_RAD:g} rad and {EXTRINSIC_AGREEMENT_M:g} m), or give only one of them"
        )


def read_calibration(file: str | Path) -> tuple[PinholeCamera | None, RigidTransform | None]:
    """A flowins ``calibration.yaml``: ``(camera, imu_to_camera)``; a part the file lacks is ``None``.

    The extrinsics may be given as ``imu_to_camera`` (``x_cam = R x_imu + t``), as
    ``camera_to_imu`` (its inverse: the camera's pose in the IMU frame, EuRoC's
    ``T_BS``, Kalibr's ``T_imu_cam``), or both; both must then agree to within
    :data:`EXTRINSIC_AGREEMENT_RAD` and :data:`EXTRINSIC_AGREEMENT_M`, and
    ``imu_to_camera`` is returned as written.
    """
    file = Path(file)
    data, root = _load_yaml(file)
    data = _mapping(data, ("camera", *EXTRINSIC_NAMES), file=file, root=root, keys=())
    camera = _read_camera(data["camera"], file=file, root=root) if "camera" in data else None
    transform = None
    if "imu_to_camera" in data:
        transform = _read_extrinsic(data["imu_to_camera"], "imu_to_camera", file=file, root=root)
    if "camera_to_imu" in data:
        camera_to_imu = _read_extrinsic(data["camera_to_imu"], "camera_to_imu", file=file, root=root)
        if transform is None:
            transform = camera_to_imu.inverse()
        else:
            _check_inverse(transform, camera_to_imu, file=file, root=root)
    return camera, transform


def _read_any_calibration(folder: Path) -> tuple[PinholeCamera | None, RigidTransform | None, Path | None]:
    """``calibration.yaml`` or, in its place, Kalibr's ``camchain-imucam.yaml`` (cam0); the file read."""
    calibration, camchain = folder / "calibration.yaml", folder / CAMCHAIN
    if calibration.is_file() and camchain.is_file():
        raise ValueError(
            f"{folder}: holds both calibration.yaml and {CAMCHAIN}; expected one of them (keep one: "
            "two calibrations could disagree)"
        )
    if calibration.is_file():
        return *read_calibration(calibration), calibration
    if not camchain.is_file():
        return None, None, None
    shift_s = read_kalibr_timeshift(camchain, "cam0")
    if shift_s != 0.0:
        raise ValueError(
            f"{camchain}: cam0.timeshift_cam_imu = {shift_s!r} s; the folder format needs frames.csv and tracks.csv "
            "on the IMU clock and does not shift them: add the shift to their t (t_imu = t_cam + shift) and set "
            "timeshift_cam_imu to 0.0"
        )
    return *read_kalibr_camchain(camchain, "cam0"), camchain


# ---------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------


def _read_imu(file: Path, *, max_gap_s: float, check_units: bool) -> ImuStream:
    table = _read_table(file, IMU_COLUMNS)
    units = {"t": "s", "ax": "m/s²", "ay": "m/s²", "az": "m/s²", "wx": "rad/s", "wy": "rad/s", "wz": "rad/s"}
    cols = {c: table.floats(c, expected=f"a number ({u})") for c, u in units.items()}
    with _lines_for(table):
        imu = ImuStream(
            cols["t"],
            np.stack([cols["ax"], cols["ay"], cols["az"]], axis=1),
            np.stack([cols["wx"], cols["wy"], cols["wz"]], axis=1),
            name=str(file),
            max_gap_s=max_gap_s,
        )
    if check_units:
        acc = float(np.median(np.linalg.norm(imu.acc_mps2.numpy(), axis=1)))
        gyro = float(np.median(np.linalg.norm(imu.gyro_rps.numpy(), axis=1)))
        if acc < _ACC_MEDIAN_MIN_MPS2:
            raise ValueError(
                f"{file}: accelerometer magnitude median {acc:.4g}; expected m/s² (≈9.81 at rest); "
                "the file looks like it is in g (multiply ax, ay, az by 9.80665)"
            )
        if acc > _ACC_MEDIAN_MAX_MPS2:
            raise ValueError(
                f"{file}: accelerometer magnitude median {acc:.4g}; expected m/s² (≈9.81 at rest); "
                "the file looks like it is in mg or cm/s²"
            )
        if gyro > _GYRO_MEDIAN_MAX_RPS:
            raise ValueError(
                f"{file}: gyroscope magnitude median {gyro:.4g}; expected rad/s; "
                "the file looks like it is in deg/s (multiply wx, wy, wz by pi/180)"
            )
    return imu


def _read_frames(folder: Path, camera: PinholeCamera | None, *, check_frames: bool) -> CameraFrames:
    file = folder / "frames.csv"
    table = _read_table(file, FRAME_FILE_COLUMNS, alternatives=(FRAME_VIDEO_COLUMNS,))
    t_s = table.floats("t", expected="a time in seconds")
    expected_size = camera.size if camera is not None else None
    with _lines_for(table):
        if table.columns == FRAME_FILE_COLUMNS:
            names = table.strings("file")
            for row, name in enumerate(names):
                if not name:
                    raise ValueError(f"{file}: line {table.line_of_row(row)}: empty file name; expected an image under frames/")
            frames = CameraFrames(
                t_s,
                files=tuple(folder / "frames" / n for n in names),
                name=str(file),
                expected_size=expected_size,
                check_files=check_frames,
            )
        else:
            video = folder / "frames.mp4"
            if check_frames and not video.is_file():
                raise ValueError(f"{file}: header '{','.join(FRAME_VIDEO_COLUMNS)}' needs the video {video}; it does not exist")
            frames = CameraFrames(
                t_s,
                video=video,
                indices=torch.from_numpy(table.integers("index", expected="a 0-based video frame number")),
                name=str(file),
                expected_size=expected_size,
                check_files=check_frames,
            )
        if check_frames:
            frames.read(0)  # surfaces unreadable images and a size that disagrees with the calibration now
    return frames


def _read_tracks(file: Path, camera: PinholeCamera, frames: CameraFrames | None) -> Tracks:
    table = _read_table(file, TRACK_COLUMNS)
    t_s = table.floats("t", expected="a time in seconds")
    ids = table.integers("track_id", expected="a non-negative integer track id")
    uv = np.stack([table.floats("u", expected="a pixel column"), table.floats("v", expected="a pixel row")], axis=1)
    with _lines_for(table):
        return Tracks(t_s, torch.from_numpy(ids), uv, name=str(file), image_size=camera.size,
                      frame_times_s=None if frames is None else frames.t_s)


def _read_gnss(file: Path) -> GnssStream:
    table = _read_table(file, GNSS_COLUMNS)
    units = {"t": "s", "lat": "deg", "lon": "deg", "alt": "m", "h_acc": "m", "v_acc": "m"}
    c = {k: table.floats(k, expected=f"a number ({u})") for k, u in units.items()}
    with _lines_for(table):
        return GnssStream(c["t"], c["lat"], c["lon"], c["alt"], c["h_acc"], c["v_acc"], name=str(file))


def _read_groundtruth(file: Path) -> PoseStream:
    table = _read_table(file, GROUNDTRUTH_COLUMNS)
    t_s = table.floats("t", expected="a time in seconds")
    pos = np.stack([table.floats(k, expected="a position in metres") for k in ("px", "py", "pz")], axis=1)
    q_index = [GROUNDTRUTH_COLUMNS.index(k) for k in ("qw", "qx", "qy", "qz")]
    empty = np.array([[row[i] == "" for i in q_index] for row in table.cells])
    partial = np.nonzero(empty.any(axis=1) & ~empty.all(axis=1))[0]
    if partial.size:
        raise ValueError(
            f"{file}: line {table.line_of_row(int(partial[0]))}: some of qw,qx,qy,qz are empty; "
            "expected all four numbers or all four empty"
        )
    has_q = ~empty[:, 0]
    mixed = np.nonzero(has_q != has_q[0])[0]
    if mixed.size:
        k = int(mixed[0])
        first, this = ("has", "has no") if has_q[0] else ("has no", "has")
        raise ValueError(
            f"{file}: line {table.line_of_row(k)} {this} orientation but line {table.line_of_row(0)} {first}; "
            "expected qw,qx,qy,qz empty in every row (positions only) or in none"
        )
    quat = None
    if has_q[0]:
        quat = np.stack([table.floats(k, expected="a quaternion component (or empty)") for k in ("qw", "qx", "qy", "qz")], axis=1)
    with _lines_for(table):
        poses = PoseStream(t_s, pos, quat, name=str(file))
    if quat is not None:
        object.__setattr__(poses, "quat_wxyz", _keep_unit_rows(torch.from_numpy(quat), poses.quat_wxyz))
    return poses


def _read_metadata(file: Path) -> dict[str, Any]:
    data, root = _load_yaml(file)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ValueError(f"{_at(file, root)}the document is a {type(data).__name__}; expected a mapping (key: value)")
    return data


def read_folder(
    path: str | os.PathLike, *, max_imu_gap_s: float = 0.2, check_frames: bool = True, check_units: bool = True
) -> Sequence:
    """Read a sequence stored in the flowins folder format.

    Args:
        path: the sequence folder (holding at least ``imu.csv``).
        max_imu_gap_s: largest allowed step between IMU timestamps [s].
        check_frames: check that every image file (or the video) exists and read
            frame 0 once, so that an unreadable image or an image size that
            disagrees with ``calibration.yaml`` is reported now.
        check_units: reject an ``imu.csv`` whose median accelerometer magnitude is
            outside [2, 50] m/s² (g or mg units) or whose median gyroscope
            magnitude exceeds 20 rad/s (deg/s units).

    Returns:
        The :class:`~flowins.data.sequence.Sequence`, named after the folder.

    Raises:
        ValueError: naming the file, the line (``line N``, 1-based, of the file)
            and what was expected.
    """
    folder = Path(path)
    if not folder.is_dir():
        raise ValueError(f"{folder}: not a folder; expected a flowins sequence folder holding imu.csv")
    imu_file = folder / "imu.csv"
    if not imu_file.is_file():
        raise ValueError(f"{imu_file}: missing; expected imu.csv (t,ax,ay,az,wx,wy,wz) in every flowins sequence folder")
    imu = _read_imu(imu_file, max_gap_s=max_imu_gap_s, check_units=check_units)

    camera, transform, calibration = _read_any_calibration(folder)
    for part in ("frames.csv", "tracks.csv"):
        if (folder / part).is_file() and (camera is None or transform is None):
            missing = f"calibration.yaml is missing (and so is {CAMCHAIN})" if calibration is None else (
                f"{calibration} has no '{'camera' if camera is None else 'imu_to_camera'}' (nor 'camera_to_imu')"
            )
            raise ValueError(
                f"{folder / part}: needs the camera calibration, but {missing}; expected calibration.yaml with "
                "camera and imu_to_camera"
            )

    frames = _read_frames(folder, camera, check_frames=check_frames) if (folder / "frames.csv").is_file() else None
    tracks = _read_tracks(folder / "tracks.csv", camera, frames) if (folder / "tracks.csv").is_file() else None
    gnss = _read_gnss(folder / "gnss.csv") if (folder / "gnss.csv").is_file() else None
    groundtruth = _read_groundtruth(folder / "groundtruth.csv") if (folder / "groundtruth.csv").is_file() else None
    metadata = _read_metadata(folder / "metadata.yaml") if (folder / "metadata.yaml").is_file() else {}
    return Sequence(
        imu,
        name=metadata["name"] if isinstance(metadata.get("name"), str) else folder.resolve().name or str(folder),
        camera=camera,
        imu_to_camera=transform,
        frames=frames,
        tracks=tracks,
        gnss=gnss,
        groundtruth=groundtruth,
        metadata=metadata,
        path=folder,
    )


# ---------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------


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
