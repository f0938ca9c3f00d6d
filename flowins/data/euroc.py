"""Reader for the EuRoC MAV datasets in ETH's ASL folder format.

Burri et al., "The EuRoC micro aerial vehicle datasets", IJRR 2016. One
sequence, as unpacked from its ``.zip``::

    MH_01_easy/mav0/
      imu0/data.csv        #timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y,w_RS_S_z,a_RS_S_x [m s^-2],a_RS_S_y,a_RS_S_z
      imu0/sensor.yaml     T_BS (16 numbers, row-major), rate_hz, gyroscope_noise_density, ...
      cam0/data.csv        #timestamp [ns],filename       (images in cam0/data/)
      cam0/sensor.yaml     T_BS, resolution: [w, h], camera_model: pinhole,
                           intrinsics: [fu, fv, cu, cv], distortion_model: radial-tangential,
                           distortion_coefficients: [k1, k2, p1, p2]
      state_groundtruth_estimate0/data.csv
                           #timestamp, p_RS_R_x [m], p_RS_R_y, p_RS_R_z, q_RS_w [], q_RS_x, q_RS_y, q_RS_z,
                           v_RS_R_x [m s^-1], ..., b_w_RS_S_x [rad s^-1], ..., b_a_RS_S_x [m s^-2], ...  (17 columns)
      leica0/data.csv      #timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m]        (Machine Hall)
      vicon0/data.csv      #timestamp [ns], p_RS_R_x [m], ..., q_RS_w [], ... q_RS_z []  (Vicon Room)

Each sensor's ``T_BS`` maps the sensor frame S into the body frame B:
``x_B = T_BS x_S``; in EuRoC the body frame is the IMU's (``imu0``'s ``T_BS`` is
the identity). The layouts were checked against ETH's published sample
``sensor.yaml`` files and the headers of the released ``data.csv`` files as
quoted by public EuRoC loaders (column names above).

Time: every stream's nanosecond timestamps have the *first IMU timestamp*
subtracted as exact integers, then are converted to float64 seconds, so all
streams share one clock that starts at 0 s at the first IMU sample; the
subtracted value is ``metadata["time_offset_ns"]`` (add it back, as an integer,
to recover EuRoC's absolute time).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from flowins.data.csvio import (
    check_increasing,
    read_numeric,
    read_rows,
    read_yaml,
    require_file,
    rigid_transform_from_matrix,
    yaml_numbers,
)
from flowins.data.sequence import CameraFrames, PinholeCamera, Sequence
from flowins.data.streams import gap_hint, ImuStream, PoseStream
from flowins.geometry.camera import RigidTransform

__all__ = ["read_euroc"]

_IMU_LAYOUT = "timestamp [ns], w_RS_S_x, w_RS_S_y, w_RS_S_z [rad/s], a_RS_S_x, a_RS_S_y, a_RS_S_z [m/s^2]"
_CAM_LAYOUT = "timestamp [ns], filename"
_STATE_LAYOUT = "timestamp [ns], p_RS_R xyz [m], q_RS wxyz, v_RS_R xyz [m/s], b_w_RS_S xyz [rad/s], b_a_RS_S xyz [m/s^2]"
_POSITION_LAYOUT = "timestamp [ns], p_RS_R_x, p_RS_R_y, p_RS_R_z [m] (vicon0 may add q_RS_w, q_RS_x, q_RS_y, q_RS_z)"
_IMU_NOISE_KEYS = (
    "rate_hz",
    "gyroscope_noise_density",
    "gyroscope_random_walk",
    "accelerometer_noise_density",
    "accelerometer_random_walk",
)
# Below this median |a| [m/s^2] the accelerometer must be in units of g (1 g at rest).
_MIN_MEDIAN_ACC_MPS2 = 2.0


def _mav0(path: Path) -> Path:
    path = Path(path)
    if (path / "mav0").is_dir():
        return path / "mav0"
    if (path / "imu0").is_dir():
        return path
    raise ValueError(
        f"{path}: neither {path / 'mav0'} nor {path / 'imu0'} is a folder; expected an EuRoC sequence "
        "(the folder containing mav0/, or mav0/ itself)"
    )


def _seconds(t_ns: np.ndarray, offset_ns: int) -> torch.Tensor:
    """Exact integer subtraction, then float64 seconds."""
    return torch.from_numpy((t_ns - np.int64(offset_ns)).astype(np.float64) / 1e9)


def _sensor_transform(data: dict[str, Any], *, path: Path) -> RigidTransform:
    """``T_BS`` (sensor -> body) of a ``sensor.yaml``."""
    values = yaml_numbers(data, "T_BS.data", count=16, path=path, what="T_BS: {data: [16 numbers, row-major]}")
    return rigid_transform_from_matrix(np.reshape(values, (4, 4)), where=f"{path}: T_BS")


def _read_imu(mav0: Path, *, max_gap_s: float) -> tuple[np.ndarray, ImuStream, dict[str, Any]]:
    file = mav0 / "imu0" / "data.csv"
    table = read_numeric(file, columns=7, what=_IMU_LAYOUT, integer_time=True, min_rows=2)
    check_increasing(
        table.time,
        table.lines,
        path=file,
        unit="ns",
        max_step=int(round(max_gap_s * 1e9)),
        max_step_hint=gap_hint(max_gap_s),
    )
    acc = table.values[:, 3:6]
    median = float(np.median(np.linalg.norm(acc, axis=1)))
    if median < _MIN_MEDIAN_ACC_MPS2:
        raise ValueError(
            f"{file}: median accelerometer magnitude {median:.3g} is below {_MIN_MEDIAN_ACC_MPS2:g}; the "
            "columns a_RS_S_x..z look like units of g, expected m/s^2 (about 9.81 at rest)"
        )
    offset_ns = int(table.time[0])
    imu = ImuStream(
        _seconds(table.time, offset_ns),
        torch.from_numpy(acc.copy()),
        torch.from_numpy(table.values[:, 0:3].copy()),
        name=str(file),
        max_gap_s=max_gap_s,
    )
    meta: dict[str, Any] = {}
    yaml_file = mav0 / "imu0" / "sensor.yaml"
    if yaml_file.is_file():
        data = read_yaml(yaml_file, what="the IMU's sensor.yaml (T_BS, rate_hz, noise densities)")
        noise = {}
        for key in _IMU_NOISE_KEYS:
            if key in data:
                value = data[key]
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
                    raise ValueError(f"{yaml_file}: {key} = {value!r}; expected a finite number")
                noise[key] = float(value)
        meta["imu_noise"] = noise
        meta["imu_T_BS"] = _sensor_transform(data, path=yaml_file) if "T_BS" in data else None
    return table.time, imu, meta


def _read_camera(mav0: Path, camera: str) -> tuple[PinholeCamera, RigidTransform]:
    file = mav0 / camera / "sensor.yaml"
    data = read_yaml(file, what=f"the calibration of {camera} (T_BS, resolution, intrinsics, distortion)")
    model = data.get("camera_model", "pinhole")
    if model != "pinhole":
        raise ValueError(f"{file}: camera_model = {model!r}; expected 'pinhole'")
    distortion_model = data.get("distortion_model", "radial-tangential")
    if distortion_model not in ("radial-tangential", "radtan"):
        raise ValueError(
            f"{file}: distortion_model = {distortion_model!r}; expected 'radial-tangential' "
            "(flowins' pinhole camera has no other lens model)"
        )
    width, height = yaml_numbers(data, "resolution", count=2, path=file, what="resolution: [width, height]")
    fx, fy, cx, cy = yaml_numbers(data, "intrinsics", count=4, path=file, what="intrinsics: [fu, fv, cu, cv]")
    distortion = ()
    if "distortion_coefficients" in data:
        distortion = yaml_numbers(
            data, "distortion_coefficients", count=(4, 5), path=file, what="distortion_coefficients: [k1, k2, p1, p2]"
        )
    pinhole = PinholeCamera(width, height, fx, fy, cx, cy, distortion, name=str(file))
    return pinhole, _sensor_transform(data, path=file)


def _read_frames(mav0: Path, camera: str, offset_ns: int, *, check_files: bool) -> CameraFrames:
    file = mav0 / camera / "data.csv"
    rows = read_rows(file, columns=2, what=_CAM_LAYOUT)
    t_ns = np.empty(len(rows), dtype=np.int64)
    for k, (row, line) in enumerate(zip(rows.cells, rows.lines.tolist())):
        try:
            t_ns[k] = int(row[0])
        except ValueError:
            raise ValueError(
                f"{file}: line {line}, column 1: {row[0]!r} is not an integer; expected {_CAM_LAYOUT}"
            ) from None
        if not row[1]:
            raise ValueError(f"{file}: line {line}, column 2: empty file name; expected {_CAM_LAYOUT}")
    check_increasing(t_ns, rows.lines, path=file, unit="ns")
    images = mav0 / camera / "data"
    files = tuple(images / row[1] for row in rows.cells)
    if check_files:
        for f, line in zip(files, rows.lines.tolist()):
            if not f.is_file():
                raise ValueError(f"{file}: line {line}: image {f} does not exist")
    return CameraFrames(_seconds(t_ns, offset_ns), files=files, name=str(file), check_files=False)


def _read_groundtruth(mav0: Path, offset_ns: int) -> tuple[PoseStream | None, dict[str, Any]]:
    state = mav0 / "state_groundtruth_estimate0" / "data.csv"
    if state.is_file():
        table = read_numeric(state, columns=17, what=_STATE_LAYOUT, integer_time=True)
        check_increasing(table.time, table.lines, path=state, unit="ns")
        pose = PoseStream(
            _seconds(table.time, offset_ns),
            torch.from_numpy(table.values[:, 0:3].copy()),
            torch.from_numpy(table.values[:, 3:7].copy()),
            name=str(state),
        )
        return pose, {"groundtruth_source": "state_groundtruth_estimate0", "groundtruth_frame": "body (IMU)"}
    for sensor in ("leica0", "vicon0"):
        file = mav0 / sensor / "data.csv"
        if not file.is_file():
            continue
        table = read_numeric(file, columns=(4, 8), what=_POSITION_LAYOUT, integer_time=True)
        check_increasing(table.time, table.lines, path=file, unit="ns")
        pose = PoseStream(_seconds(table.time, offset_ns), torch.from_numpy(table.values[:, 0:3].copy()), name=str(file))
        meta: dict[str, Any] = {
            "groundtruth_source": sensor,
            "groundtruth_frame": f"{sensor} target (positions only; not moved to the IMU: see {sensor}_T_BS)",
        }
        yaml_file = mav0 / sensor / "sensor.yaml"
        if yaml_file.is_file():
            meta[f"{sensor}_T_BS"] = _sensor_transform(read_yaml(yaml_file, what=f"{sensor}'s T_BS"), path=yaml_file)
        return pose, meta
    return None, {"groundtruth_source": None}


def read_euroc(
    path: str | Path,
    *,
    camera: str | None = "cam0",
    max_imu_gap_s: float = 0.2,
    check_frames: bool = True,
) -> Sequence:
    """Read one EuRoC sequence (ASL folder format) into a :class:`Sequence`.

    Args:
        path: the sequence folder (containing ``mav0/``) or ``mav0/`` itself.
        camera: which camera folder to read (``"cam0"`` or ``"cam1"``), or
            ``None`` for IMU and ground truth only.
        max_imu_gap_s: largest allowed step between IMU samples [s].
        check_frames: check that every image listed in ``<camera>/data.csv``
            exists (images are read lazily either way).

    Returns a sequence whose streams all share one clock: seconds since the first
    IMU sample (``metadata["time_offset_ns"]`` holds that sample's EuRoC
    timestamp). IMU columns are reordered to ``acc_mps2, gyro_rps``.
    ``imu_to_camera`` is ``T_cam_imu = T_BS(camera)^-1 T_BS(imu)``
    (``x_cam = R x_imu + t``; ``T_BS(imu)`` is the identity when
    ``imu0/sensor.yaml`` is absent). Ground truth is
    ``state_groundtruth_estimate0`` (body = IMU pose, quaternion w-first), else
    the positions of ``leica0`` or ``vicon0`` (the tracked prism / marker, not
    moved to the IMU), else none.

    ``metadata``: ``format``, ``time_offset_ns``, ``camera``, ``imu_noise`` (the
    numbers of ``imu0/sensor.yaml``: ``rate_hz``, ``*_noise_density``,
    ``*_random_walk``), ``groundtruth_source``, ``groundtruth_frame``.

    Raises ``ValueError`` naming the file and 1-based line for a missing file, a
    wrong column count, a non-numeric cell, non-increasing timestamps, an IMU gap
    above ``max_imu_gap_s`` or an accelerometer in units of g.
    """
    mav0 = _mav0(Path(path))
    require_file(mav0 / "imu0" / "data.csv", what=f"the IMU samples ({_IMU_LAYOUT})")
    t_imu_ns, imu, imu_meta = _read_imu(mav0, max_gap_s=max_imu_gap_s)
    offset_ns = int(t_imu_ns[0])
    metadata: dict[str, Any] = {
        "format": "euroc",
        "imu": "adis16448",  # the IMU preset (configs/imu) of the EuRoC MAV's sensor
        "time_offset_ns": offset_ns,
        "camera": camera,
        "imu_noise": imu_meta.get("imu_noise", {}),
    }
    pinhole = imu_to_camera = frames = None
    if camera is not None:
        if not (mav0 / camera).is_dir():
            found = sorted(p.name for p in mav0.glob("cam*") if p.is_dir())
            raise ValueError(f"{mav0 / camera}: camera folder does not exist; found {found or 'no cam* folders'}")
        pinhole, T_b_cam = _read_camera(mav0, camera)
        T_b_imu = imu_meta.get("imu_T_BS") or RigidTransform.identity()
        imu_to_camera = T_b_cam.inverse().compose(T_b_imu)
        frames = _read_frames(mav0, camera, offset_ns, check_files=check_frames)
    groundtruth, gt_meta = _read_groundtruth(mav0, offset_ns)
    metadata.update(gt_meta)
    name = mav0.parent.name if mav0.name == "mav0" else mav0.name
    return Sequence(
        imu,
        name=name,
        camera=pinhole,
        imu_to_camera=imu_to_camera,
        frames=frames,
        groundtruth=groundtruth,
        metadata=metadata,
        path=mav0,
    )
