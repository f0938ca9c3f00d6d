"""Kalibr's camchain-imucam.yaml: known numbers written in Kalibr's layout, read back.

The truth is what each test writes: a ``T_cam_imu`` built from Rodrigues' formula
(x_cam = R x_imu + t, checked by mapping points with numpy), the intrinsics and
the distortion coefficients.
"""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from flowins.data.folder import read_folder, write_folder
from flowins.data.kalibr import read_kalibr_camchain, read_kalibr_timeshift
from flowins.data.read import read_sequence
from flowins.data.sequence import PinholeCamera

INTRINSICS = (4.58654, 4.57296, 3.5, 2.5)  # EuRoC cam0 scaled to the 8x6 test images
DISTORTION = (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
WIDTH, HEIGHT = 8, 6


def _rotation(axis, angle):
    k = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


T_CAM_IMU = np.eye(4)
T_CAM_IMU[:3, :3] = _rotation([0.2, -1.0, 0.4], 1.7)
T_CAM_IMU[:3, 3] = [0.0652, -0.0207, -0.0081]


def _camera_yaml(name: str, T: np.ndarray, *, model="pinhole", distortion_model="radtan", distortion=DISTORTION,
                 intrinsics=INTRINSICS, extra="") -> str:
    rows = "".join(f"  - [{', '.join(repr(float(v)) for v in row)}]\n" for row in T)
    return (
        f"{name}:\n  T_cam_imu:\n{rows}"
        f"  cam_overlaps: []\n  camera_model: {model}\n"
        f"  distortion_coeffs: [{', '.join(map(repr, distortion))}]\n  distortion_model: {distortion_model}\n"
        f"  intrinsics: [{', '.join(map(repr, intrinsics))}]\n  resolution: [{WIDTH}, {HEIGHT}]\n"
        f"  rostopic: /{name}/image_raw\n{extra}"
    )


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_reads_back_the_written_calibration(tmp_path):
    other = T_CAM_IMU.copy()
    other[:3, 3] += [0.11, 0.0, 0.0]
    file = _write(tmp_path / "camchain-imucam.yaml", _camera_yaml("cam0", T_CAM_IMU) + _camera_yaml("cam1", other))
    camera, transform = read_kalibr_camchain(file)
    assert camera == PinholeCamera(WIDTH, HEIGHT, *INTRINSICS, DISTORTION, name=f"{file}: cam0")
    points_imu = np.random.default_rng(0).normal(size=(20, 3))
    expected = points_imu @ T_CAM_IMU[:3, :3].T + T_CAM_IMU[:3, 3]  # x_cam = R x_imu + t
    assert torch.allclose(transform.apply(torch.from_numpy(points_imu)), torch.from_numpy(expected), rtol=0, atol=1e-12)
    _, transform1 = read_kalibr_camchain(file, camera="cam1")
    assert torch.allclose(transform1.translation_m, torch.from_numpy(other[:3, 3]), rtol=0, atol=1e-15)
    assert read_kalibr_timeshift(file) == 0.0


def test_no_distortion(tmp_path):
    file = _write(tmp_path / "c.yaml", _camera_yaml("cam0", T_CAM_IMU, distortion_model="none", distortion=()))
    assert read_kalibr_camchain(file)[0].distortion == ()


def _bad(T=T_CAM_IMU, **kwargs):
    return _camera_yaml("cam0", T, **kwargs)


_NOT_ORTHONORMAL = T_CAM_IMU.copy()
_NOT_ORTHONORMAL[0, :3] *= 1.01
_REFLECTION = T_CAM_IMU.copy()
_REFLECTION[:3, 0] *= -1
_BOTTOM = T_CAM_IMU.copy()
_BOTTOM[3, 0] = 0.5


@pytest.mark.parametrize("text, message", [
    (_bad(_NOT_ORTHONORMAL), r"c\.yaml: cam0\.T_cam_imu: rotation block is not a rotation \(\|R R\^T - I\| = 0\.02"),
    (_bad(_REFLECTION), r"c\.yaml: cam0\.T_cam_imu: rotation block is not a rotation .*det = -1"),
    (_bad(_BOTTOM), r"c\.yaml: cam0\.T_cam_imu: bottom row \[0\.5, 0\.0, 0\.0, 1\.0\]; expected \[0, 0, 0, 1\]"),
    (_bad(T_CAM_IMU[:3]), r"c\.yaml: cam0\.T_cam_imu = .*; expected 4 rows of 4 numbers"),
    (_bad(distortion_model="equidistant"), r"c\.yaml: cam0\.distortion_model = 'equidistant'; supported: radtan .* and none"),
    (_bad(model="omni"), r"c\.yaml: cam0\.camera_model = 'omni'; expected 'pinhole'"),
    (_bad(distortion=(0.1, 0.2, 0.3)), r"c\.yaml: cam0\.distortion_coeffs = \[0\.1, 0\.2, 0\.3\]; expected a list of 4 numbers"),
    (_bad(intrinsics=(-1.0, 5.0, 3.0, 2.0)), r"c\.yaml: cam0: focal lengths fx=-1\.0, fy=5\.0; expected > 0 pixels"),
    (_bad().replace("cam0:", "cam1:"), r"c\.yaml: no camera 'cam0' \(a mapping\); found \['cam1'\]"),
    (_bad().replace("T_cam_imu", "T_cn_cnm1"),
     r"c\.yaml: key 'cam0\.T_cam_imu' is missing; expected the output of kalibr_calibrate_imu_camera"),
])
def test_bad_camchain_names_file_and_key(tmp_path, text, message):
    with pytest.raises(ValueError, match=message):
        read_kalibr_camchain(_write(tmp_path / "c.yaml", text))


# ---------------------------------------------------------------------------
# In the flowins folder format
# ---------------------------------------------------------------------------


def _folder(tmp_path: Path, camchain: str) -> Path:
    folder = tmp_path / "seq"
    _write(folder / "imu.csv", "t,ax,ay,az,wx,wy,wz\n" + "".join(f"{0.01 * k},0.1,0.2,9.81,0,0,0\n" for k in range(5)))
    _write(folder / "frames.csv", "t,file\n0.0,a.png\n0.02,b.png\n")
    (folder / "frames").mkdir()
    for name in ("a.png", "b.png"):
        cv2.imwrite(str(folder / "frames" / name), np.zeros((HEIGHT, WIDTH, 3), dtype=np.uint8))
    _write(folder / "camchain-imucam.yaml", camchain)
    return folder


def test_folder_with_a_camchain_instead_of_calibration_yaml(tmp_path):
    folder = _folder(tmp_path, _camera_yaml("cam0", T_CAM_IMU, extra="  timeshift_cam_imu: 0.0\n"))
    seq = read_sequence(folder)
    assert seq.camera == PinholeCamera(WIDTH, HEIGHT, *INTRINSICS, DISTORTION, name=f"{folder / 'camchain-imucam.yaml'}: cam0")
    assert torch.allclose(seq.imu_to_camera.matrix(), torch.from_numpy(T_CAM_IMU), rtol=0, atol=1e-12)
    out = write_folder(seq, tmp_path / "seq", overwrite=True)  # in place: calibration.yaml replaces the camchain
    assert not (out / "camchain-imucam.yaml").exists()
    again = read_folder(out)
    assert again.camera == PinholeCamera(WIDTH, HEIGHT, *INTRINSICS, DISTORTION)
    assert torch.equal(again.imu_to_camera.translation_m, seq.imu_to_camera.translation_m)


def test_folder_with_both_calibrations_is_an_error(tmp_path):
    folder = _folder(tmp_path, _camera_yaml("cam0", T_CAM_IMU))
    _write(folder / "calibration.yaml", "camera: {width: 8, height: 6, fx: 5.0, fy: 5.0, cx: 3.5, cy: 2.5}\n")
    with pytest.raises(ValueError, match=r"seq: holds both calibration\.yaml and camchain-imucam\.yaml; expected one of them"):
        read_folder(folder)


def test_folder_camchain_with_a_time_shift_is_an_error(tmp_path):
    folder = _folder(tmp_path, _camera_yaml("cam0", T_CAM_IMU, extra="  timeshift_cam_imu: -0.0023\n"))
    with pytest.raises(ValueError, match=r"camchain-imucam\.yaml: cam0\.timeshift_cam_imu = -0\.0023 s; .*add the shift"):
        read_folder(folder)
    assert read_kalibr_timeshift(folder / "camchain-imucam.yaml") == -0.0023
