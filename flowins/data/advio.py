"""Reader for the ADVIO iPhone recordings (Cortés, Solin, Rahtu, Kannala, ECCV 2018).

One sequence folder (``advio-01`` ... ``advio-23``)::

    ground-truth/pose.csv           t [s], x, y, z [m], qw, qx, qy, qz      (README: "poses.csv")
    iphone/accelerometer.csv        t [s], ax, ay, az [g]
    iphone/gyro.csv                 t [s], wx, wy, wz [rad/s]                (README: "gyroscope.csv")
    iphone/frames.mov, frames.csv   H.264 video; t [s], frame number
    iphone/platform-location.csv    t [s], latitude, longitude [deg], horizontal accuracy [m],
                                    altitude [m], vertical accuracy [m][, speed [m/s]]
                                    (released archives: "platform-locations.csv")
    iphone/arkit.csv                t [s], x, y, z [m], qw, qx, qy, qz

The CSV files have no header. What was verified, and where (AaltoVision/ADVIO on
GitHub):

* ``README.md``: the folder layout; accelerations "in 'g's"; gyroscope in the
  Apple device frame; frames 60 fps, 1280 x 720 portrait, "packed into an
  H.264/MPEG-4 video file"; platform location stores latitude, longitude,
  HorizontalAccuracy, Altitude, VerticalAccuracy, Speed (in that order, after
  the time); timestamps of all sensors on one clock (seconds since device boot);
  the ground truth is a "camera pose ... sampled at 100 Hz".
* ``scripts/visualization/my_utils.py``: ``read_pose`` reads ``pose.csv`` and
  ``arkit.csv`` as 8 columns ``t, x, y, z, q0..q3`` and builds
  ``np.quaternion(M[:,4], M[:,5], M[:,6], M[:,7])`` (numpy-quaternion is
  ``(w, x, y, z)``): the quaternion is scalar first. ``read_frames`` reads
  ``frames.csv`` as ``t, frame number``, and ``get_frame`` uses the *row*
  index of ``frames.csv`` as the frame number in the video; the rosbag script
  (``scripts/rosbag/advio_to_rosbag.py``) likewise reads the video sequentially,
  one frame per row. flowins does the same: video index = 0-based row.
* ``scripts/rosbag/sync-data.py``: ``accelerometer.csv`` and ``gyro.csv`` are
  ``t, x, y, z`` and are not sampled together; ADVIO's own tool interpolates
  the accelerometer linearly onto the gyro timestamps (``np.interp``), as this
  reader does.
* ``calibration/README.md`` and ``calibration/iphone-0{1..4}.yaml``: intrinsics
  per recording batch (see :data:`IPHONE_CALIBRATIONS`) for portrait images
  (``image_width: 720``, ``image_height: 1280``) and the Kalibr camera-IMU
  transform ``T_cam_imu`` (:data:`IPHONE_T_CAM_IMU`).

The released archives use ``gyro.csv``, ``pose.csv`` and
``platform-locations.csv`` where the README says ``gyroscope.csv``,
``poses.csv`` and ``platform-location.csv``; both spellings are accepted (the
archive names are a third-party observation, not checked against the data).

Not verified (no data at hand):

* whether OpenCV decodes ``frames.mov`` as portrait (720 x 1280, what the
  calibration expects) or landscape: ADVIO's ``get_frame`` rotates a decoded
  frame of height 720 by 90 degrees clockwise, which suggests landscape storage
  with a rotation flag. A landscape decode makes :meth:`CameraFrames.read` raise
  its size mismatch error; ``metadata["video_size_wh"]`` records what OpenCV
  reports.
* which body the ground-truth pose describes: the README says "camera pose",
  but it is computed from the iPhone's IMU; it is stored unconverted.
* one public third-party loader claims ``accelerometer.csv`` is already in
  m/s^2 and ``pose.csv`` scalar-last; the ADVIO README and tools say g and
  scalar-first. A file already in m/s^2 is caught by the unit check below.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from flowins.data.csvio import (
    NumericTable,
    check_increasing,
    read_numeric,
    require_file,
    rigid_transform_from_matrix,
)
from flowins.data.sequence import CameraFrames, PinholeCamera, Sequence
from flowins.data.streams import gap_hint, GnssStream, ImuStream, PoseStream
from flowins.geometry.camera import RigidTransform

__all__ = [
    "IPHONE_CALIBRATIONS",
    "IPHONE_T_CAM_IMU",
    "STANDARD_GRAVITY_MPS2",
    "IphoneCalibration",
    "default_calibration",
    "read_advio",
    "read_calibration",
]

STANDARD_GRAVITY_MPS2 = 9.80665
# After the g -> m/s^2 conversion the median |a| is about 9.8; above this the
# file must already have been in m/s^2 (a second conversion gives about 96).
_MAX_MEDIAN_ACC_MPS2 = 30.0


@dataclass(frozen=True)
class IphoneCalibration:
    """Intrinsics of one ADVIO recording batch, portrait ``720 x 1280`` images."""

    sequences: tuple[int, int]  # first and last sequence number, inclusive
    source: str
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float]  # k1, k2, p1, p2


# AaltoVision/ADVIO calibration/README.md: "The ADVIO data was collected in four
# batches, and the calibrations were done for each batch separately", with the
# table rows 1-12, 13-17, 18-19, 20-23 (columns fx, fy, cx, cy, r1, r2, k1, k2 =
# radial k1, k2 then tangential p1, p2, as in the yaml files' radial-tangential
# "data"). The yaml files give more digits: iphone-02.yaml matches the 1-12 row,
# iphone-03.yaml the 13-17 row (its p1 0.000783 is printed 0.0007 in the table)
# and iphone-04.yaml the 18-19 row (iphone-01.yaml repeats it with cy 619.31,
# a typo in one of the two). No yaml file holds the 20-23 row: its numbers are
# the README table's four digits.
IPHONE_CALIBRATIONS: tuple[IphoneCalibration, ...] = (
    IphoneCalibration((1, 12), "calibration/iphone-02.yaml", 1077.2, 1079.3, 362.145, 636.3873,
                      (0.0478, 0.0339, -0.00033, -0.00091)),
    IphoneCalibration((13, 17), "calibration/iphone-03.yaml", 1082.4, 1084.4, 364.6778, 643.3080,
                      (0.0366, 0.0803, 0.000783, -0.000215)),
    IphoneCalibration((18, 19), "calibration/iphone-04.yaml", 1076.9, 1078.5, 360.96, 639.31,
                      (0.0510, -0.0354, -0.0054, 0.0473)),
    IphoneCalibration((20, 23), "calibration/README.md (table row 20-23)", 1081.1, 1082.1, 359.59, 640.79,
                      (0.0556, -0.0454, 0.0009, -0.0018)),
)
IPHONE_IMAGE_WIDTH, IPHONE_IMAGE_HEIGHT = 720, 1280  # iphone-0*.yaml: image_width, image_height

# AaltoVision/ADVIO calibration/README.md, "iPhone camera to IMU transformation":
# "Calibration performed with the Kalibr toolbox. Very stable, assumed the same
# for all sequences"; the same matrix is T_cam_imu in calibration/iphone-0*.yaml.
# Kalibr's T_cam_imu maps IMU coordinates to camera coordinates, x_cam = T x_imu,
# which is flowins' imu_to_camera. The rotation is about diag(1, -1, -1): camera
# x along the device's x (right in portrait), camera y and z (down, forward out
# of the back camera) opposite the Apple device frame's y (up) and z (out of the
# screen), as expected for the rear camera.
IPHONE_T_CAM_IMU = (
    (0.9999763379093255, -0.004079205042965442, -0.005539287650170447, -0.008977668364731128),
    (-0.004066386342107199, -0.9999890330121858, 0.0023234365646622014, 0.07557012320238939),
    (-0.00554870467502187, -0.0023008567036498766, -0.9999819588046867, -0.005545773942541918),
    (0.0, 0.0, 0.0, 1.0),
)

_ACC_LAYOUT = "t [s], ax, ay, az [g] (no header)"
_GYRO_LAYOUT = "t [s], wx, wy, wz [rad/s] (no header)"
_FRAMES_LAYOUT = "t [s], frame number (no header)"
_POSE_LAYOUT = "t [s], x, y, z [m], qw, qx, qy, qz (no header)"
_LOCATION_LAYOUT = (
    "t [s], latitude, longitude [deg], horizontal accuracy [m], altitude [m], vertical accuracy [m]"
    "[, speed [m/s]] (no header)"
)
_CALIBRATION_LAYOUT = (
    "camera: {width, height, fx, fy, cx, cy, distortion}, "
    "imu_to_camera: {rotation: [qw, qx, qy, qz], translation: [x, y, z]}"
)


def _first_existing(folder: Path, names: tuple[str, ...], *, what: str) -> Path:
    for name in names:
        if (folder / name).is_file():
            return folder / name
    also = f" (also looked for {', '.join(names[1:])})" if len(names) > 1 else ""
    return require_file(folder / names[0], what=what + also)


def _optional(folder: Path, names: tuple[str, ...]) -> Path | None:
    return next((folder / n for n in names if (folder / n).is_file()), None)


def _sequence_number(folder: Path) -> int | None:
    match = re.search(r"(\d+)$", folder.name)
    return int(match.group(1)) if match else None


def default_calibration(sequence: int) -> IphoneCalibration:
    """The ADVIO calibration of sequence ``sequence`` (1..23)."""
    for calibration in IPHONE_CALIBRATIONS:
        if calibration.sequences[0] <= sequence <= calibration.sequences[1]:
            return calibration
    raise ValueError(f"ADVIO sequence number {sequence}; expected 1..23")


def read_calibration(path: str | Path) -> tuple[PinholeCamera, RigidTransform]:
    """A flowins ``calibration.yaml``: ``(camera, imu_to_camera)``.

    Layout::

        camera: {width: 720, height: 1280, fx: ..., fy: ..., cx: ..., cy: ..., distortion: [k1, k2, p1, p2]}
        imu_to_camera: {rotation: [qw, qx, qy, qz], translation: [x, y, z]}   # x_cam = R x_imu + t

    ``distortion`` may be omitted or ``[]`` (undistorted images).
    """
    from flowins.data.folder import read_calibration as read_flowins_calibration

    path = Path(path)
    camera, transform = read_flowins_calibration(path)
    if camera is None or transform is None:
        raise ValueError(f"{path}: needs both 'camera' and 'imu_to_camera'; expected {_CALIBRATION_LAYOUT}")
    return camera, transform


def _read_xyz(file: Path, layout: str) -> NumericTable:
    table = read_numeric(file, columns=4, what=layout, min_rows=2)
    check_increasing(table.time, table.lines, path=file, unit="s")
    return table


def _read_imu(iphone: Path, *, max_gap_s: float) -> tuple[ImuStream, dict[str, Any]]:
    acc_file = _first_existing(iphone, ("accelerometer.csv",), what=f"the accelerometer ({_ACC_LAYOUT})")
    gyro_file = _first_existing(iphone, ("gyro.csv", "gyroscope.csv"), what=f"the gyroscope ({_GYRO_LAYOUT})")
    acc = _read_xyz(acc_file, _ACC_LAYOUT)
    gyro = _read_xyz(gyro_file, _GYRO_LAYOUT)
    hint = gap_hint(max_gap_s)
    # the accelerometer is interpolated across its steps: a long gap there would be bridged silently
    check_increasing(acc.time, acc.lines, path=acc_file, unit="s", max_step=max_gap_s, max_step_hint=hint)
    median = float(np.median(np.linalg.norm(acc.values, axis=1))) * STANDARD_GRAVITY_MPS2
    if median > _MAX_MEDIAN_ACC_MPS2:
        raise ValueError(
            f"{acc_file}: median accelerometer magnitude {median:.3g} m/s^2 after the g -> m/s^2 conversion "
            f"exceeds {_MAX_MEDIAN_ACC_MPS2:g}; the file looks like it is already in m/s^2, expected units of g "
            "(about 1 at rest)"
        )
    # Resample onto the gyro clock: keep the gyro samples inside the accelerometer's span
    # (a contiguous run, because both clocks increase), interpolate the accelerometer linearly.
    inside = (gyro.time >= acc.time[0]) & (gyro.time <= acc.time[-1])
    keep = np.flatnonzero(inside)
    if keep.size < 2:
        raise ValueError(
            f"{gyro_file}: {keep.size} gyro samples lie within the accelerometer's span "
            f"[{acc.time[0]!r}, {acc.time[-1]!r}] s of {acc_file}; expected overlapping recordings"
        )
    first, last = int(keep[0]), int(keep[-1])
    t_s = gyro.time[first : last + 1]
    acc_g = np.stack([np.interp(t_s, acc.time, acc.values[:, j]) for j in range(3)], axis=1)
    check_increasing(
        t_s, gyro.lines[first : last + 1], path=gyro_file, unit="s", max_step=max_gap_s, max_step_hint=hint
    )
    imu = ImuStream(
        torch.from_numpy(t_s.copy()),
        torch.from_numpy(acc_g * STANDARD_GRAVITY_MPS2),
        torch.from_numpy(gyro.values[first : last + 1].copy()),
        name=str(gyro_file),
        max_gap_s=max_gap_s,
    )
    meta = {
        "method": "accelerometer linearly interpolated onto the gyro timestamps, then g -> m/s^2 (x 9.80665)",
        "accelerometer_file": str(acc_file),
        "gyro_file": str(gyro_file),
        "gyro_samples": len(gyro),
        "gyro_dropped_start": first,
        "gyro_dropped_end": len(gyro) - 1 - last,
        "accelerometer_samples": len(acc),
    }
    return imu, meta


def _read_frames(iphone: Path, *, check_files: bool) -> tuple[CameraFrames | None, dict[str, Any]]:
    csv_file = iphone / "frames.csv"
    if not csv_file.is_file():
        return None, {"frames": None}
    table = read_numeric(csv_file, columns=2, what=_FRAMES_LAYOUT)
    check_increasing(table.time, table.lines, path=csv_file, unit="s")
    numbers = table.values[:, 0]
    fractional = np.flatnonzero(numbers != np.round(numbers))
    if fractional.size:
        k = int(fractional[0])
        raise ValueError(
            f"{csv_file}: line {int(table.lines[k])}, column 2: frame number {numbers[k]!r} is not an integer; "
            f"expected {_FRAMES_LAYOUT}"
        )
    video = iphone / "frames.mov"
    meta: dict[str, Any] = {
        "frames": str(csv_file),
        "video": str(video),
        "video_index": "0-based row of frames.csv (as ADVIO's own tools read the video)",
        "frame_numbers_consecutive": bool(np.all(np.diff(numbers) == 1)),
    }
    if check_files:
        require_file(video, what=f"the iPhone video for {csv_file}")
        meta.update(_video_facts(video, rows=len(table), csv_file=csv_file))
    frames = CameraFrames(
        torch.from_numpy(table.time.copy()),
        video=video,
        indices=torch.arange(len(table)),
        name=str(csv_file),
        check_files=check_files,
    )
    return frames, meta


def _video_facts(video: Path, *, rows: int, csv_file: Path) -> dict[str, Any]:
    import cv2

    cap = cv2.VideoCapture(str(video))
    try:
        if not cap.isOpened():
            raise ValueError(f"{video}: OpenCV cannot open the video; expected an H.264 .mov ({csv_file} lists {rows} frames)")
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
    finally:
        cap.release()
    if 0 < count < rows:
        raise ValueError(f"{video}: {count} video frames for {rows} rows of {csv_file}; expected one frame per row")
    return {"video_frame_count": count, "video_size_wh": size}


def _read_gnss(iphone: Path) -> tuple[GnssStream | None, dict[str, Any]]:
    file = _optional(iphone, ("platform-location.csv", "platform-locations.csv"))
    if file is None:
        return None, {"gnss": None}
    table = read_numeric(file, columns=(6, 7), what=_LOCATION_LAYOUT)
    check_increasing(table.time, table.lines, path=file, unit="s")
    lat, lon, h_acc, alt, v_acc = (table.values[:, j] for j in range(5))
    # CoreLocation marks an invalid horizontal (vertical) fix by a negative accuracy:
    # such rows are not fixes. They are left out and listed, never repaired.
    valid = (h_acc > 0) & (v_acc > 0)
    meta: dict[str, Any] = {
        "gnss": str(file),
        "gnss_altitude_reference": "CoreLocation altitude (above mean sea level, not the WGS84 ellipsoid)",
        "gnss_invalid_rows": int((~valid).sum()),
        "gnss_invalid_lines": table.lines[~valid].tolist(),
    }
    if not valid.any():
        return None, meta
    gnss = GnssStream(
        torch.from_numpy(table.time[valid]),
        torch.from_numpy(lat[valid]),
        torch.from_numpy(lon[valid]),
        torch.from_numpy(alt[valid]),
        torch.from_numpy(h_acc[valid]),
        torch.from_numpy(v_acc[valid]),
        name=str(file),
    )
    return gnss, meta


def _read_groundtruth(folder: Path) -> tuple[PoseStream | None, dict[str, Any]]:
    file = _optional(folder / "ground-truth", ("pose.csv", "poses.csv"))
    if file is None:
        return None, {"groundtruth": None}
    table = read_numeric(file, columns=8, what=_POSE_LAYOUT)
    check_increasing(table.time, table.lines, path=file, unit="s")
    zero = np.flatnonzero(np.linalg.norm(table.values[:, 3:7], axis=1) == 0)
    if zero.size:
        raise ValueError(
            f"{file}: line {int(table.lines[zero[0]])}: zero quaternion; expected {_POSE_LAYOUT} with a unit quaternion"
        )
    pose = PoseStream(
        torch.from_numpy(table.time.copy()),
        torch.from_numpy(table.values[:, 0:3].copy()),
        torch.from_numpy(table.values[:, 3:7].copy()),
        name=str(file),
    )
    return pose, {"groundtruth": str(file), "groundtruth_frame": "as stored by ADVIO (README: 'camera pose'); unconverted"}


def read_advio(
    path: str | Path,
    *,
    calibration: str | Path | None = None,
    max_imu_gap_s: float = 0.2,
    check_frames: bool = True,
) -> Sequence:
    """Read one ADVIO sequence folder (``advio-NN``, containing ``iphone/``) into a :class:`Sequence`.

    IMU: ``accelerometer.csv`` (g) and ``gyro.csv`` (rad/s) have their own
    timestamps; the accelerometer is linearly interpolated onto the gyro
    timestamps and multiplied by 9.80665. Gyro samples before the first or after
    the last accelerometer sample cannot be interpolated and are dropped, at the
    two ends only (``metadata["imu_resampling"]`` counts them); nothing in the
    middle is dropped, and an accelerometer gap above ``max_imu_gap_s`` is an
    error rather than being bridged.

    Frames: ``frames.csv`` timestamps with the video ``frames.mov`` (video frame
    = 0-based row, as ADVIO's tools read it). GNSS: ``platform-location.csv``
    when present; rows with a non-positive accuracy (CoreLocation's "invalid")
    are left out and listed in ``metadata["gnss_invalid_lines"]``; altitudes are
    CoreLocation's (above mean sea level). Ground truth: ``ground-truth/pose.csv``
    (quaternion w-first). ``arkit.csv`` is not loaded; its path is
    ``metadata["arkit"]``. Times are ADVIO's (seconds since device boot), not
    shifted.

    Calibration: ``calibration`` (a flowins ``calibration.yaml``, see
    :func:`read_calibration`) or, by default, ADVIO's iPhone intrinsics of the
    recording batch of the sequence number at the end of the folder name
    (:data:`IPHONE_CALIBRATIONS`) with ADVIO's Kalibr ``T_cam_imu``
    (:data:`IPHONE_T_CAM_IMU`; see the module docstring for what is and is not
    verified about it).

    Raises ``ValueError`` naming the file and 1-based line for missing files,
    wrong column counts, non-numeric cells, non-increasing timestamps, IMU gaps
    and an accelerometer file already in m/s^2.
    """
    folder = Path(path)
    iphone = folder / "iphone"
    if not iphone.is_dir():
        raise ValueError(f"{iphone}: folder does not exist; expected an ADVIO sequence folder containing iphone/")
    if calibration is not None:
        camera, imu_to_camera = read_calibration(calibration)
        calibration_source = str(calibration)
    else:
        number = _sequence_number(folder)
        if number is None or not 1 <= number <= 23:
            raise ValueError(
                f"{folder}: cannot tell the ADVIO sequence number (1..23) from the folder name, which picks "
                "the calibration batch; name the folder advio-NN or pass calibration=<calibration.yaml>"
            )
        batch = default_calibration(number)
        camera = PinholeCamera(
            IPHONE_IMAGE_WIDTH, IPHONE_IMAGE_HEIGHT, batch.fx, batch.fy, batch.cx, batch.cy, batch.distortion,
            name=f"ADVIO iPhone ({batch.source})",
        )
        imu_to_camera = rigid_transform_from_matrix(IPHONE_T_CAM_IMU, where="ADVIO calibration/README.md T_cam_imu")
        calibration_source = f"AaltoVision/ADVIO {batch.source} (sequences {batch.sequences[0]}-{batch.sequences[1]})"
    imu, resampling = _read_imu(iphone, max_gap_s=max_imu_gap_s)
    frames, frame_meta = _read_frames(iphone, check_files=check_frames)
    gnss, gnss_meta = _read_gnss(iphone)
    groundtruth, gt_meta = _read_groundtruth(folder)
    arkit = iphone / "arkit.csv"
    metadata: dict[str, Any] = {
        "format": "advio",
        "sequence_number": _sequence_number(folder),
        "calibration": calibration_source,
        "accelerometer_unit": "g in the file, converted with 9.80665 m/s^2 per g",
        "imu_resampling": resampling,
        "arkit": str(arkit) if arkit.is_file() else None,
        **frame_meta,
        **gnss_meta,
        **gt_meta,
    }
    return Sequence(
        imu,
        name=folder.name,
        camera=camera,
        imu_to_camera=imu_to_camera,
        frames=frames,
        gnss=gnss,
        groundtruth=groundtruth,
        metadata=metadata,
        path=folder,
    )
