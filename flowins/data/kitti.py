"""Reader for KITTI raw drives (Geiger, Lenz, Stiller, Urtasun, IJRR 2013).

One drive, as unpacked from KITTI's ``*_sync.zip`` (or ``*_extract.zip``) and
``*_calib.zip``::

    2011_09_26/                          the date folder
      calib_cam_to_cam.txt               S_rect_0i: w h; R_rect_00: 9 numbers; P_rect_0i: 12 numbers (row-major)
      calib_imu_to_velo.txt              R: 9 numbers; T: 3 numbers   (x_velo = R x_imu + T)
      calib_velo_to_cam.txt              R: 9 numbers; T: 3 numbers   (x_cam0 = R x_velo + T, unrectified)
      2011_09_26_drive_0001_sync/
        oxts/timestamps.txt              one "YYYY-MM-DD HH:MM:SS.fffffffff" per packet
        oxts/data/0000000000.txt, ...    one line of 30 numbers per packet (below)
        image_0i/timestamps.txt          one time per image, same format
        image_0i/data/0000000000.png     rectified images: 00/01 grey left/right, 02/03 colour

The calibration files are looked for in the drive folder, then in its parent.

An OXTS packet (KITTI devkit ``readme.txt``), in this order: ``lat, lon`` [deg],
``alt`` [m], ``roll`` (0 = level, positive = left side up), ``pitch`` (positive =
front down), ``yaw`` (0 = east, positive = counter-clockwise) [rad], ``vn, ve,
vf, vl, vu`` [m/s], ``ax, ay, az`` (vehicle front, left, top), ``af, al, au``
(forward, leftward, upward: a level frame) [m/s^2], ``wx, wy, wz`` (vehicle
axes), ``wf, wl, wu`` [rad/s], ``pos_accuracy`` [m], ``vel_accuracy`` [m/s],
``navstat, numsats, posmode, velmode, orimode``.

What this reader builds, and why:

* **IMU** (the OXTS frame: x forward, y left, z up, which is also the "IMU" of
  ``calib_imu_to_velo.txt``): ``acc_mps2 = (ax, ay, az)``, ``gyro_rps = (wx, wy,
  wz)`` as written; ``af..au`` and ``wf..wu`` (a level, heading-aligned frame,
  not what a body-fixed IMU measures) are not used. ``ax..az`` are taken to be
  specific force, gravity included (about +9.8 on z for a level vehicle at rest),
  so nothing is added: KITTI drives read ``az`` ≈ 9.8 at rest, and AI-IMU dead
  reckoning (Brossard et al., T-IV 2020, ``mbrossar/ai-imu-dr``) integrates
  ``ax..az`` as ``R f + (0, 0, -9.80665)``, a model that needs specific force.
  The reader checks it: a median ``|a|`` below 2 m/s^2 (gravity removed, or
  units of g) is an error, not repaired.
* **Ground truth**: the OXTS's own GNSS/INS solution, which KITTI uses as its
  reference. Position: ``lat, lon, alt`` in a local East-North-Up plane whose
  origin is the first packet (``metadata["origin_*"]``). Orientation (body to
  ENU): ``R = Rz(yaw) Ry(pitch) Rx(roll)``, the product of KITTI's
  ``convertOxtsToPose``; for x forward, y left, z up a positive rotation about y
  lowers the front and one about x raises the left side, the readme's signs.
* **GNSS**: the same ``lat, lon, alt`` with ``h_acc_m = max(pos_accuracy,
  gnss_h_acc_floor_m)`` (the OXTS reports 0 in some packets, and a stream
  accuracy must be > 0) and ``v_acc_m = 1.5 h_acc_m`` (KITTI has no vertical
  accuracy). These are blended GNSS/INS positions at every packet, not raw
  fixes: the same numbers as the ground truth. ``alt`` is used as the height
  (KITTI does not say above which datum; within one drive only differences matter).
* **Camera** ``i`` (rectified images, so no distortion): ``fx = P[0,0]``, ``fy =
  P[1,1]``, ``cx = P[0,2]``, ``cy = P[1,2]`` of ``P_rect_0i``, size ``S_rect_0i``;
  ``imu_to_camera = T_i · R_rect_00 · T_cam0_velo · T_velo_imu``, the devkit's
  ``y = P_rect_0i R_rect_00 T_cam0_velo T_velo_imu x`` with ``P_rect_0i = K [I | t_i]``,
  ``t_i = K⁻¹ P_rect_0i[:, 3]`` (for KITTI ``(P[0,3]/fx, 0, 0)``: camera i's
  offset from rectified camera 0).

Time: ``t_s`` is seconds since the first OXTS packet, for every stream (frames
included). Timestamps are parsed as exact integer nanoseconds; the first is
``metadata["time_offset_ns"]`` (the text read as UTC; the files name no time
zone) and ``metadata["start_time"]`` (the text).

Timestamp policy: nothing is dropped or reordered. A timestamp equal to or
before the previous one (KITTI raw has repeated packets in some drives) is a
``ValueError`` naming ``timestamps.txt`` and both lines; so is an OXTS step
above ``max_imu_gap_s`` (GNSS/INS dropouts): pass a larger ``max_imu_gap_s`` to
bridge one, or cut the drive.
"""
from __future__ import annotations

import datetime
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch

from flowins.data.csvio import check_increasing, require_file, rigid_transform_from_matrix
from flowins.data.sequence import CameraFrames, PinholeCamera, Sequence
from flowins.data.streams import gap_hint, GnssStream, ImuStream, PoseStream
from flowins.geometry import quaternion as quat
from flowins.geometry.camera import RigidTransform
from flowins.geometry.geodesy import LocalTangentPlane

__all__ = ["OXTS_COLUMNS", "read_kitti_raw"]

OXTS_COLUMNS = (
    "lat", "lon", "alt", "roll", "pitch", "yaw", "vn", "ve", "vf", "vl", "vu",
    "ax", "ay", "az", "af", "al", "au", "wx", "wy", "wz", "wf", "wl", "wu",
    "pos_accuracy", "vel_accuracy", "navstat", "numsats", "posmode", "velmode", "orimode",
)
_COL = {name: j for j, name in enumerate(OXTS_COLUMNS)}
_OXTS_LAYOUT = f"one line of {len(OXTS_COLUMNS)} space-separated numbers ({' '.join(OXTS_COLUMNS)})"
_TIME_LAYOUT = "one 'YYYY-MM-DD HH:MM:SS.fffffffff' per line"
_TIME = re.compile(r"(\d{4})-(\d{2})-(\d{2}) (\d{2}):(\d{2}):(\d{2})(?:\.(\d{1,9}))?")
_EPOCH_DAY = datetime.date(1970, 1, 1).toordinal()
_CALIB_FILES = ("calib_cam_to_cam.txt", "calib_imu_to_velo.txt", "calib_velo_to_cam.txt")
# Below this median |a| [m/s^2] ax..az cannot be specific force (1 g at rest).
_MIN_MEDIAN_ACC_MPS2 = 2.0


# ---------------------------------------------------------------------------
# Text files
# ---------------------------------------------------------------------------


def _nanoseconds(text: str, *, file: Path, line: int) -> int:
    """``YYYY-MM-DD HH:MM:SS[.f...]`` as integer nanoseconds since 1970 (read as UTC)."""
    match = _TIME.fullmatch(text)
    if match is None:
        raise ValueError(f"{file}: line {line}: {text!r} is not a timestamp; expected {_TIME_LAYOUT}")
    year, month, day, hour, minute, second = (int(g) for g in match.groups()[:6])
    try:
        stamp = datetime.datetime(year, month, day, hour, minute, second)
    except ValueError as exc:
        raise ValueError(f"{file}: line {line}: {text!r} is not a valid date and time ({exc})") from None
    seconds = (stamp.date().toordinal() - _EPOCH_DAY) * 86400 + hour * 3600 + minute * 60 + second
    return seconds * 1_000_000_000 + int((match.group(7) or "0").ljust(9, "0"))


def _read_timestamps(file: Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """``(t_ns (N,) int64, lines (N,) 1-based, texts)`` of a KITTI ``timestamps.txt`` (blank lines skipped)."""
    require_file(file, what=f"the timestamps ({_TIME_LAYOUT})")
    texts, lines = [], []
    for number, line in enumerate(file.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
        if line.strip():
            texts.append(line.strip())
            lines.append(number)
    if not texts:
        raise ValueError(f"{file}: no timestamps; expected {_TIME_LAYOUT}")
    t_ns = np.array([_nanoseconds(t, file=file, line=k) for t, k in zip(texts, lines)], dtype=np.int64)
    return t_ns, np.asarray(lines, dtype=np.int64), texts


def _read_packet(file: Path) -> np.ndarray:
    """The 30 numbers of one OXTS packet file."""
    rows = [(k, line.split()) for k, line in enumerate(file.read_text(errors="replace").splitlines(), start=1) if line.strip()]
    if len(rows) != 1:
        raise ValueError(f"{file}: {len(rows)} non-blank lines; expected {_OXTS_LAYOUT}")
    line, cells = rows[0]
    if len(cells) != len(OXTS_COLUMNS):
        raise ValueError(f"{file}: line {line}: {len(cells)} values; expected {_OXTS_LAYOUT}")
    try:
        values = np.array(cells, dtype=np.float64)
    except ValueError:
        values = np.array([_float_or_nan(c) for c in cells])
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        j = int(bad[0])
        raise ValueError(
            f"{file}: line {line}, column {j + 1} ({OXTS_COLUMNS[j]}): {cells[j]!r} is not a finite number; "
            f"expected {_OXTS_LAYOUT}"
        )
    return values


def _float_or_nan(cell: str) -> float:
    try:
        return float(cell)
    except ValueError:
        return float("nan")


def _read_oxts(drive: Path, *, max_gap_s: float) -> tuple[np.ndarray, list[str], np.ndarray]:
    """``(t_ns (N,), timestamp texts, packets (N, 30))``; packet k is ``oxts/data/{k:010d}.txt``."""
    stamps = drive / "oxts" / "timestamps.txt"
    t_ns, lines, texts = _read_timestamps(stamps)
    hint = gap_hint(max_gap_s)
    check_increasing(t_ns, lines, path=stamps, unit="ns", max_step=int(round(max_gap_s * 1e9)), max_step_hint=hint)
    folder = drive / "oxts" / "data"
    found = {p.name for p in folder.glob("*.txt")}
    expected = [f"{k:010d}.txt" for k in range(len(t_ns))]
    missing, extra = sorted(set(expected) - found), sorted(found - set(expected))
    if missing or extra:
        odd = f"{missing[0]} is missing" if missing else f"{extra[0]} has no timestamp"
        raise ValueError(
            f"{folder}: {len(found)} packet files for the {len(t_ns)} timestamps of {stamps} ({odd}); "
            "expected one file per timestamp, numbered from 0000000000.txt"
        )
    return t_ns, texts, np.stack([_read_packet(folder / name) for name in expected])


def _calibration_lines(file: Path) -> dict[str, tuple[int, str]]:
    """``{key: (1-based line, text after the colon)}`` of a KITTI ``calib_*.txt``."""
    out: dict[str, tuple[int, str]] = {}
    for number, line in enumerate(file.read_text(errors="replace").splitlines(), start=1):
        key, colon, rest = line.partition(":")
        if colon:
            out[key.strip()] = (number, rest)
    return out


def _calibration_numbers(file: Path, table: dict[str, tuple[int, str]], key: str, count: int) -> np.ndarray:
    if key not in table:
        raise ValueError(f"{file}: no '{key}:' line; expected '{key}: ' followed by {count} numbers")
    line, text = table[key]
    try:
        values = np.array([float(c) for c in text.split()], dtype=np.float64)
    except ValueError:
        values = np.full(0, np.nan)
    if values.shape != (count,) or not np.isfinite(values).all():
        raise ValueError(f"{file}: line {line}: {key}:{text!r}; expected {count} finite numbers")
    return values


# ---------------------------------------------------------------------------
# Streams
# ---------------------------------------------------------------------------


def _imu(t_s: torch.Tensor, packets: np.ndarray, *, stamps: Path, max_gap_s: float) -> ImuStream:
    acc = packets[:, _COL["ax"] : _COL["az"] + 1]
    median = float(np.median(np.linalg.norm(acc, axis=1)))
    if median < _MIN_MEDIAN_ACC_MPS2:
        raise ValueError(
            f"{stamps.parent / 'data'}: median |(ax, ay, az)| is {median:.3g} m/s^2, below {_MIN_MEDIAN_ACC_MPS2:g}; "
            "expected specific force with gravity included (about 9.81 at rest), in m/s^2"
        )
    gyro = packets[:, _COL["wx"] : _COL["wz"] + 1]
    return ImuStream(t_s, torch.from_numpy(acc.copy()), torch.from_numpy(gyro.copy()), name=str(stamps), max_gap_s=max_gap_s)


def _gnss(t_s: torch.Tensor, packets: np.ndarray, *, stamps: Path, floor_m: float) -> GnssStream:
    h_acc = np.maximum(packets[:, _COL["pos_accuracy"]], floor_m)
    lat, lon, alt = (torch.from_numpy(packets[:, _COL[k]].copy()) for k in ("lat", "lon", "alt"))
    return GnssStream(t_s, lat, lon, alt, torch.from_numpy(h_acc), torch.from_numpy(1.5 * h_acc), name=str(stamps))


def _groundtruth(t_s: torch.Tensor, packets: np.ndarray, *, stamps: Path) -> tuple[PoseStream, LocalTangentPlane]:
    lat, lon, alt = (packets[:, _COL[k]] for k in ("lat", "lon", "alt"))
    origin = LocalTangentPlane(float(lat[0]), float(lon[0]), float(alt[0]))
    roll, pitch, yaw = (torch.from_numpy(packets[:, _COL[k]].copy()) for k in ("roll", "pitch", "yaw"))
    poses = PoseStream(t_s, origin.to_enu(lat, lon, alt), quat.from_euler(roll, pitch, yaw), name=str(stamps))
    return poses, origin


# ---------------------------------------------------------------------------
# Camera
# ---------------------------------------------------------------------------


def _calibration_files(drive: Path) -> list[Path]:
    """The three calibration files, from the drive folder or its parent."""
    files = [next((d / name for d in (drive, drive.parent) if (d / name).is_file()), None) for name in _CALIB_FILES]
    missing = [name for name, file in zip(_CALIB_FILES, files) if file is None]
    if missing:
        raise ValueError(
            f"{drive}: the images need the KITTI calibration; looked for {', '.join(_CALIB_FILES)} in {drive} and "
            f"{drive.parent}, and did not find {', '.join(missing)}"
        )
    return files


def _rigid(file: Path, rotation_key: str, translation_key: str | None) -> np.ndarray:
    """A homogeneous 4 x 4 from a rotation line (9 numbers) and a translation line (3 numbers)."""
    table = _calibration_lines(file)
    M = np.eye(4)
    M[:3, :3] = _calibration_numbers(file, table, rotation_key, 9).reshape(3, 3)
    if translation_key is not None:
        M[:3, 3] = _calibration_numbers(file, table, translation_key, 3)
    rigid_transform_from_matrix(M, where=f"{file}: {rotation_key}")  # checks the rotation block
    return M


def _read_camera(drive: Path, camera: int) -> tuple[PinholeCamera, RigidTransform, dict[str, Any]]:
    cam_to_cam, imu_to_velo, velo_to_cam = _calibration_files(drive)
    table = _calibration_lines(cam_to_cam)
    P = _calibration_numbers(cam_to_cam, table, f"P_rect_0{camera}", 12).reshape(3, 4)
    width, height = _calibration_numbers(cam_to_cam, table, f"S_rect_0{camera}", 2)
    K = P[:, :3]
    if K[0, 1] != 0 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise ValueError(
            f"{cam_to_cam}: P_rect_0{camera} = {P.tolist()}; expected a rectified projection "
            "[[fx, 0, cx, *], [0, fy, cy, *], [0, 0, 1, *]]"
        )
    pinhole = PinholeCamera(width, height, K[0, 0], K[1, 1], K[0, 2], K[1, 2], name=f"{cam_to_cam}: P_rect_0{camera}")
    offset = np.eye(4)
    offset[:3, 3] = np.linalg.solve(K, P[:, 3])
    chain = offset @ _rigid(cam_to_cam, "R_rect_00", None) @ _rigid(velo_to_cam, "R", "T") @ _rigid(imu_to_velo, "R", "T")
    transform = rigid_transform_from_matrix(chain, where=f"{cam_to_cam}: P_rect_0{camera} R_rect_00 T_cam_velo T_velo_imu")
    files = {"calib_cam_to_cam": str(cam_to_cam), "calib_imu_to_velo": str(imu_to_velo), "calib_velo_to_cam": str(velo_to_cam)}
    return pinhole, transform, files


def _read_frames(drive: Path, camera: int, offset_ns: int, *, check_files: bool) -> CameraFrames:
    stamps = drive / f"image_0{camera}" / "timestamps.txt"
    t_ns, lines, _ = _read_timestamps(stamps)
    check_increasing(t_ns, lines, path=stamps, unit="ns")
    files = tuple(drive / f"image_0{camera}" / "data" / f"{k:010d}.png" for k in range(len(t_ns)))
    if check_files:
        for file, line in zip(files, lines.tolist()):
            if not file.is_file():
                raise ValueError(f"{stamps}: line {line}: image {file} does not exist")
    t_s = torch.from_numpy((t_ns - np.int64(offset_ns)).astype(np.float64) / 1e9)
    return CameraFrames(t_s, files=files, name=str(stamps), check_files=False)


def _camera_folder(drive: Path, camera: int | None) -> int | None:
    """``camera`` if its images exist, ``None`` if the drive has no images at all (or ``camera`` is None)."""
    if camera is None:
        return None
    if camera not in (0, 1, 2, 3):
        raise ValueError(f"read_kitti_raw: camera={camera!r}; expected 0, 1 (grey), 2, 3 (colour) or None")
    if (drive / f"image_0{camera}").is_dir():
        return camera
    found = sorted(p.name for p in drive.glob("image_0*") if p.is_dir())
    if found:
        raise ValueError(
            f"{drive / f'image_0{camera}'}: folder does not exist, but {', '.join(found)} do; "
            "pass camera=<one of them> or camera=None"
        )
    return None


# ---------------------------------------------------------------------------
# Reader
# ---------------------------------------------------------------------------


def read_kitti_raw(
    path: str | Path,
    *,
    camera: int | None = 0,
    max_imu_gap_s: float = 0.2,
    check_frames: bool = True,
    gnss_h_acc_floor_m: float = 0.02,
) -> Sequence:
    """Read one KITTI raw drive folder (``..._drive_NNNN_sync`` or ``_extract``) into a :class:`Sequence`.

    Args:
        path: the drive folder, holding ``oxts/``.
        camera: which ``image_0i`` folder to read (0, 1 grey; 2, 3 colour), or
            ``None`` for OXTS only. A drive without any ``image_0*`` folder is
            read without frames; one that lacks only the requested camera is an error.
        max_imu_gap_s: largest allowed step between OXTS packets [s].
        check_frames: check that every image listed exists (read lazily either way).
        gnss_h_acc_floor_m: smallest GNSS ``h_acc_m`` [m] (``pos_accuracy`` below
            it, e.g. 0, is raised to it; ``metadata["gnss_floored_rows"]`` counts them).

    See the module docstring for the frames, conventions and timestamp policy.
    ``metadata`` names the IMU preset (``imu: oxts_rt3003``) and the platform
    (``platform: vehicle``).

    Raises ``ValueError`` naming the file and 1-based line for a missing file, a
    packet without 30 numbers, a bad timestamp, a timestamp not after the
    previous one, a gap above ``max_imu_gap_s``, accelerations without gravity,
    or images without calibration.
    """
    drive = Path(path)
    if not (drive / "oxts").is_dir():
        raise ValueError(f"{drive / 'oxts'}: folder does not exist; expected a KITTI raw drive folder holding oxts/")
    for key, value in (("max_imu_gap_s", max_imu_gap_s), ("gnss_h_acc_floor_m", gnss_h_acc_floor_m)):
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"read_kitti_raw: {key}={value!r}; expected a finite number > 0")
    t_ns, texts, packets = _read_oxts(drive, max_gap_s=max_imu_gap_s)
    stamps = drive / "oxts" / "timestamps.txt"
    t_s = torch.from_numpy((t_ns - t_ns[0]).astype(np.float64) / 1e9)
    groundtruth, origin = _groundtruth(t_s, packets, stamps=stamps)
    metadata: dict[str, Any] = {
        "format": "kitti",
        "source": "KITTI raw",
        "imu": "oxts_rt3003",  # the IMU preset (configs/imu) of KITTI's OXTS RT3003
        "platform": "vehicle",  # a car: the vehicle motion constraint applies (flowins/measurements/vehicle.py)
        "time_offset_ns": int(t_ns[0]),
        "start_time": texts[0],
        "acc": "OXTS ax, ay, az: specific force (gravity included), x forward, y left, z up",
        "origin_lat_deg": origin.origin_lat_deg,
        "origin_lon_deg": origin.origin_lon_deg,
        "origin_alt_m": origin.origin_alt_m,
        "groundtruth_source": "OXTS RT3003 GNSS/INS solution",
        "groundtruth_frame": "ENU about the first packet; body = OXTS (x forward, y left, z up)",
        "gnss_h_acc_floor_m": float(gnss_h_acc_floor_m),
        "gnss_floored_rows": int((packets[:, _COL["pos_accuracy"]] < gnss_h_acc_floor_m).sum()),
        "camera": None,
    }
    pinhole = imu_to_camera = frames = None
    camera = _camera_folder(drive, camera)
    if camera is not None:
        pinhole, imu_to_camera, metadata["calibration"] = _read_camera(drive, camera)
        frames = _read_frames(drive, camera, int(t_ns[0]), check_files=check_frames)
        metadata["camera"] = f"image_0{camera}"
    return Sequence(
        _imu(t_s, packets, stamps=stamps, max_gap_s=max_imu_gap_s),
        name=drive.resolve().name or str(drive),
        camera=pinhole,
        imu_to_camera=imu_to_camera,
        frames=frames,
        gnss=_gnss(t_s, packets, stamps=stamps, floor_m=gnss_h_acc_floor_m),
        groundtruth=groundtruth,
        metadata=metadata,
        path=drive,
    )
