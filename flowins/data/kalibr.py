"""Kalibr's camera-IMU calibration, ``camchain-imucam.yaml``, as flowins' camera and extrinsics.

``kalibr_calibrate_imu_camera`` writes one mapping per camera::

    cam0:
      T_cam_imu:                      # 4 x 4, x_cam = T_cam_imu x_imu (flowins' imu_to_camera)
      - [r11, r12, r13, tx]
      - [r21, r22, r23, ty]
      - [r31, r32, r33, tz]
      - [0.0, 0.0, 0.0, 1.0]
      camera_model: pinhole           # flowins reads pinhole only
      intrinsics: [fu, fv, pu, pv]    # pixels
      distortion_model: radtan        # radtan (k1, k2, r1, r2 = OpenCV k1, k2, p1, p2) or none
      distortion_coeffs: [k1, k2, r1, r2]
      resolution: [width, height]
      rostopic: /cam0/image_raw
      timeshift_cam_imu: 0.0          # t_imu = t_cam + timeshift_cam_imu [s]

Other lens models (``equidistant``, ``fov``) and camera models (``omni``,
``eucm``, ``ds``) are errors: flowins' :class:`PinholeCamera` has the
radial-tangential model only.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from flowins.data.csvio import read_yaml, rigid_transform_from_matrix, yaml_numbers
from flowins.data.sequence import PinholeCamera
from flowins.geometry.camera import RigidTransform

__all__ = ["CAMCHAIN", "read_kalibr_camchain", "read_kalibr_timeshift"]

#: The file name Kalibr gives the camera-IMU calibration.
CAMCHAIN = "camchain-imucam.yaml"
_WHAT = "Kalibr's camchain-imucam.yaml (cam0: {T_cam_imu, intrinsics, distortion_model, distortion_coeffs, resolution})"
_DISTORTION_COUNTS = {"radtan": 4, "none": 0}


def _camera_node(file: Path, camera: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(whole file, file[camera])``."""
    data = read_yaml(file, what=_WHAT)
    node = data.get(camera)
    if not isinstance(node, dict):
        cameras = sorted(str(k) for k, v in data.items() if isinstance(v, dict))
        raise ValueError(f"{file}: no camera {camera!r} (a mapping); found {cameras or 'none'}; expected {_WHAT}")
    return data, node


def _matrix(rows: Any, key: str, *, file: Path) -> np.ndarray:
    if not (
        isinstance(rows, list)
        and len(rows) == 4
        and all(isinstance(r, list) and len(r) == 4 for r in rows)
        and all(isinstance(v, (int, float)) and not isinstance(v, bool) for r in rows for v in r)
    ):
        raise ValueError(f"{file}: {key} = {rows!r}; expected 4 rows of 4 numbers (a homogeneous transform)")
    return np.asarray(rows, dtype=np.float64)


def _distortion(data: dict[str, Any], node: dict[str, Any], camera: str, *, file: Path) -> tuple[float, ...]:
    model = node.get("distortion_model")
    if model not in _DISTORTION_COUNTS:
        raise ValueError(
            f"{file}: {camera}.distortion_model = {model!r}; supported: radtan (k1, k2, r1, r2) and none "
            "(flowins' pinhole camera has no equidistant/fisheye or fov lens model: undistort the images first)"
        )
    count = _DISTORTION_COUNTS[model]
    if count == 0 and node.get("distortion_coeffs") in (None, []):
        return ()
    what = f"distortion_coeffs for distortion_model {model}"
    return yaml_numbers(data, f"{camera}.distortion_coeffs", count=count, path=file, what=what)


def read_kalibr_camchain(file: str | Path, camera: str = "cam0") -> tuple[PinholeCamera, RigidTransform]:
    """``(camera intrinsics, imu_to_camera)`` of ``camera`` in a Kalibr ``camchain-imucam.yaml``.

    ``T_cam_imu`` maps IMU points into the camera, ``x_cam = R x_imu + t``: it is
    flowins' ``imu_to_camera`` as it is. Its rotation block must be orthonormal
    with determinant +1 and its last row ``0 0 0 1``, to within 1e-3
    (:func:`~flowins.data.csvio.rigid_transform_from_matrix`). The time shift is
    not part of the result: see :func:`read_kalibr_timeshift`.

    Raises:
        ValueError: naming the file and key: a missing camera or key, a camera
            model other than pinhole, a lens model other than radtan or none, a
            ``T_cam_imu`` that is not a rigid transform.
    """
    file = Path(file)
    data, node = _camera_node(file, camera)
    model = node.get("camera_model")
    if model != "pinhole":
        raise ValueError(f"{file}: {camera}.camera_model = {model!r}; expected 'pinhole' (flowins' only camera model)")
    distortion = _distortion(data, node, camera, file=file)
    fx, fy, cx, cy = yaml_numbers(data, f"{camera}.intrinsics", count=4, path=file, what="intrinsics: [fu, fv, pu, pv]")
    width, height = yaml_numbers(data, f"{camera}.resolution", count=2, path=file, what="resolution: [width, height]")
    try:
        pinhole = PinholeCamera(width, height, fx, fy, cx, cy, distortion, name=f"{file}: {camera}")
    except ValueError as exc:
        raise ValueError(f"{exc} (intrinsics, resolution)") from None
    if "T_cam_imu" not in node:
        raise ValueError(
            f"{file}: key '{camera}.T_cam_imu' is missing; expected the output of kalibr_calibrate_imu_camera "
            "(camchain-imucam.yaml, not the camera-only camchain.yaml)"
        )
    matrix = _matrix(node["T_cam_imu"], f"{camera}.T_cam_imu", file=file)
    return pinhole, rigid_transform_from_matrix(matrix, where=f"{file}: {camera}.T_cam_imu")


def read_kalibr_timeshift(file: str | Path, camera: str = "cam0") -> float:
    """``timeshift_cam_imu`` [s] of ``camera`` (``t_imu = t_cam + shift``); 0 when the key is absent."""
    file = Path(file)
    _, node = _camera_node(file, camera)
    value = node.get("timeshift_cam_imu", 0.0)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise ValueError(f"{file}: {camera}.timeshift_cam_imu = {value!r}; expected a finite number of seconds")
    return float(value)
