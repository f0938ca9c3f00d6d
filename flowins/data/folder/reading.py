"""Reading a flowins folder (:func:`read_folder`) and its calibration."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from torch import Tensor

from flowins.data.csvio import is_number, lines_for, load_yaml, read_table, yaml_at, yaml_mapping, yaml_number_list
from flowins.data.folder.format import (
    _ACC_MEDIAN_MAX_MPS2,
    _ACC_MEDIAN_MIN_MPS2,
    _GYRO_MEDIAN_MAX_RPS,
    _UNIT_NORM_TOL,
    CAMERA_KEYS,
    EXTRINSIC_AGREEMENT_M,
    EXTRINSIC_AGREEMENT_RAD,
    EXTRINSIC_KEYS,
    EXTRINSIC_NAMES,
    FRAME_FILE_COLUMNS,
    FRAME_VIDEO_COLUMNS,
    GNSS_COLUMNS,
    GROUNDTRUTH_COLUMNS,
    IMU_COLUMNS,
    TRACK_COLUMNS,
)
from flowins.data.kalibr import CAMCHAIN, read_kalibr_camchain, read_kalibr_timeshift
from flowins.data.sequence import CameraFrames, PinholeCamera, Sequence, Tracks
from flowins.data.streams import GnssStream, ImuStream, PoseStream
from flowins.geometry import quaternion as quat
from flowins.geometry.camera import RigidTransform


def _keep_unit_rows(q_file: Tensor, q_normalised: Tensor) -> Tensor:
    """The file's quaternion rows where they are already unit to float64 precision.

    Dividing a unit quaternion by its norm again can change its last bit, so a
    constructor's re-normalisation would break the exact write -> read round trip;
    rows with ``|norm - 1| <= 1e-15`` are kept as written (a no-op rotation-wise).
    """
    norm = torch.linalg.vector_norm(q_file, dim=-1, keepdim=True)
    return torch.where((norm - 1.0).abs() <= _UNIT_NORM_TOL, q_file, q_normalised)


def _read_camera(cam_value: Any, *, file: Path, root: yaml.Node | None) -> PinholeCamera:
    cam = yaml_mapping(cam_value, CAMERA_KEYS, file=file, root=root, keys=("camera",))
    for key in CAMERA_KEYS[:-1]:
        if key not in cam:
            raise ValueError(f"{yaml_at(file, root, 'camera')}camera has no '{key}'; expected {', '.join(CAMERA_KEYS[:-1])} (and optional distortion)")
        if not is_number(cam[key]):
            raise ValueError(f"{yaml_at(file, root, 'camera', key)}camera.{key} is {cam[key]!r}; expected a number (pixels)")
    distortion = yaml_number_list(
        cam.get("distortion"), (0, 4, 5), file=file, root=root, keys=("camera", "distortion"), what="k1, k2, p1, p2[, k3]"
    )
    try:
        return PinholeCamera(cam["width"], cam["height"], cam["fx"], cam["fy"], cam["cx"], cam["cy"], tuple(distortion))
    except ValueError as exc:
        raise ValueError(f"{yaml_at(file, root, 'camera')}{exc}") from None


def _read_extrinsic(value: Any, key: str, *, file: Path, root: yaml.Node | None) -> RigidTransform:
    """``{rotation: [qw, qx, qy, qz], translation: [x, y, z]}`` at ``key`` as a transform."""
    ext = yaml_mapping(value, EXTRINSIC_KEYS, file=file, root=root, keys=(key,))
    for part in EXTRINSIC_KEYS:
        if part not in ext:
            raise ValueError(f"{yaml_at(file, root, key)}{key} has no '{part}'; expected rotation [qw, qx, qy, qz] and translation [x, y, z]")
    q = yaml_number_list(ext["rotation"], (4,), file=file, root=root, keys=(key, "rotation"), what="qw, qx, qy, qz")
    t = yaml_number_list(ext["translation"], (3,), file=file, root=root, keys=(key, "translation"), what="x, y, z in metres")
    q_file = torch.tensor(q, dtype=torch.float64)
    try:
        transform = RigidTransform(q_file, torch.tensor(t, dtype=torch.float64))
    except ValueError as exc:
        raise ValueError(f"{yaml_at(file, root, key, 'rotation')}{exc}") from None
    object.__setattr__(transform, "rotation_wxyz", _keep_unit_rows(q_file, transform.rotation_wxyz))
    return transform


def _check_inverse(imu_to_camera: RigidTransform, camera_to_imu: RigidTransform, *, file: Path, root: yaml.Node | None) -> None:
    """Both extrinsics given: ``camera_to_imu`` must be the inverse of ``imu_to_camera``."""
    inverse = camera_to_imu.inverse()
    angle_rad = float(quat.angle_between(imu_to_camera.rotation_wxyz, inverse.rotation_wxyz))
    offset_m = float(torch.linalg.vector_norm(imu_to_camera.translation_m - inverse.translation_m))
    if angle_rad > EXTRINSIC_AGREEMENT_RAD or offset_m > EXTRINSIC_AGREEMENT_M:
        raise ValueError(
            f"{yaml_at(file, root, 'camera_to_imu')}imu_to_camera and camera_to_imu disagree: the inverse of "
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
    data, root = load_yaml(file)
    data = yaml_mapping(data, ("camera", *EXTRINSIC_NAMES), file=file, root=root, keys=())
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




def _read_imu(file: Path, *, max_gap_s: float, check_units: bool) -> ImuStream:
    table = read_table(file, IMU_COLUMNS)
    units = {"t": "s", "ax": "m/s²", "ay": "m/s²", "az": "m/s²", "wx": "rad/s", "wy": "rad/s", "wz": "rad/s"}
    cols = {c: table.floats(c, expected=f"a number ({u})") for c, u in units.items()}
    with lines_for(table):
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
    table = read_table(file, FRAME_FILE_COLUMNS, alternatives=(FRAME_VIDEO_COLUMNS,))
    t_s = table.floats("t", expected="a time in seconds")
    expected_size = camera.size if camera is not None else None
    with lines_for(table):
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
    table = read_table(file, TRACK_COLUMNS)
    t_s = table.floats("t", expected="a time in seconds")
    ids = table.integers("track_id", expected="a non-negative integer track id")
    uv = np.stack([table.floats("u", expected="a pixel column"), table.floats("v", expected="a pixel row")], axis=1)
    with lines_for(table):
        return Tracks(t_s, torch.from_numpy(ids), uv, name=str(file), image_size=camera.size,
                      frame_times_s=None if frames is None else frames.t_s)


def _read_gnss(file: Path) -> GnssStream:
    table = read_table(file, GNSS_COLUMNS)
    units = {"t": "s", "lat": "deg", "lon": "deg", "alt": "m", "h_acc": "m", "v_acc": "m"}
    c = {k: table.floats(k, expected=f"a number ({u})") for k, u in units.items()}
    with lines_for(table):
        return GnssStream(c["t"], c["lat"], c["lon"], c["alt"], c["h_acc"], c["v_acc"], name=str(file))


def _read_groundtruth(file: Path) -> PoseStream:
    table = read_table(file, GROUNDTRUTH_COLUMNS)
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
    with lines_for(table):
        poses = PoseStream(t_s, pos, quat, name=str(file))
    if quat is not None:
        object.__setattr__(poses, "quat_wxyz", _keep_unit_rows(torch.from_numpy(quat), poses.quat_wxyz))
    return poses


def _read_metadata(file: Path) -> dict[str, Any]:
    data, root = load_yaml(file)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ValueError(f"{yaml_at(file, root)}the document is a {type(data).__name__}; expected a mapping (key: value)")
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
