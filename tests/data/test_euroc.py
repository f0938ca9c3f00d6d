"""EuRoC (ASL folder format) reader: a tiny sequence written with the real headers.

The truth is what each test writes: the numbers in the CSV files, the known
T_BS matrices and the pixels of the PNGs.
"""
from __future__ import annotations

import math
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from flowins.data.euroc import read_euroc

T0_NS = 1403636579758555392  # an EuRoC-sized nanosecond timestamp (beyond float64's exact integers)
IMU_STEP_NS = 5_000_000  # 200 Hz
N_IMU = 40
IMU_HEADER = (
    "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
    "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
)
GT_HEADER = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
    "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
    "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
)
WIDTH, HEIGHT = 8, 6
INTRINSICS = (4.58654, 4.57296, 3.215, 2.375)  # EuRoC cam0 scaled to the 8x6 test images
DISTORTION = (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)


def _rotation(axis, angle):
    """Rodrigues' formula (numpy, independent of flowins' quaternions)."""
    k = np.asarray(axis, dtype=np.float64)
    k = k / np.linalg.norm(k)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _homogeneous(R, t):
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = t
    return M


T_BS_CAM = _homogeneous(_rotation([0.3, -0.2, 1.0], 1.6), [-0.0216, -0.0647, 0.0098])
T_BS_IMU = _homogeneous(_rotation([1.0, 0.5, 0.0], 0.2), [0.01, 0.02, -0.03])


def _yaml_matrix(M):
    return "T_BS:\n  cols: 4\n  rows: 4\n  data: [" + ", ".join(repr(float(v)) for v in M.reshape(-1)) + "]\n"


def _write(path: Path, text: str, newline: str = "\n") -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline=newline) as f:
        f.write(text)


def _imu_rows():
    rng = np.random.default_rng(1)
    t_ns = T0_NS + IMU_STEP_NS * np.arange(N_IMU, dtype=np.int64)
    gyro = rng.normal(scale=0.1, size=(N_IMU, 3))
    acc = rng.normal(scale=0.3, size=(N_IMU, 3)) + np.array([9.1, 0.2, -3.4])
    return t_ns, gyro, acc


def _imu_text(t_ns, gyro, acc):
    lines = [IMU_HEADER]
    for t, w, a in zip(t_ns.tolist(), gyro, acc):
        lines.append(",".join([str(t)] + [repr(float(v)) for v in (*w, *a)]))
    return "\n".join(lines) + "\n"


def _write_sequence(root: Path, *, imu_identity: bool = False):
    """A complete EuRoC sequence under ``root/mav0``; returns the written truth."""
    mav0 = root / "mav0"
    t_ns, gyro, acc = _imu_rows()
    _write(mav0 / "imu0" / "data.csv", _imu_text(t_ns, gyro, acc))
    T_imu = np.eye(4) if imu_identity else T_BS_IMU
    _write(
        mav0 / "imu0" / "sensor.yaml",
        "#Default imu sensor yaml file\nsensor_type: imu\ncomment: VI-Sensor IMU (ADIS16448)\n\n"
        "# Sensor extrinsics wrt. the body-frame.\n" + _yaml_matrix(T_imu) + "rate_hz: 200\n\n"
        "# inertial sensor noise model parameters (static)\n"
        "gyroscope_noise_density: 1.6968e-04     # [ rad / s / sqrt(Hz) ]   ( gyro \"white noise\" )\n"
        "gyroscope_random_walk: 1.9393e-05       # [ rad / s^2 / sqrt(Hz) ] ( gyro bias diffusion )\n"
        "accelerometer_noise_density: 2.0000e-3  # [ m / s^2 / sqrt(Hz) ]   ( accel \"white noise\" )\n"
        "accelerometer_random_walk: 3.0000e-3    # [ m / s^3 / sqrt(Hz) ].  ( accel bias diffusion )\n",
    )
    _write(
        mav0 / "cam0" / "sensor.yaml",
        "# General sensor definitions.\nsensor_type: camera\ncomment: VI-Sensor cam0 (MT9M034)\n\n"
        "# Sensor extrinsics wrt. the body-frame.\n" + _yaml_matrix(T_BS_CAM) + "\n# Camera specific definitions.\n"
        f"rate_hz: 20\nresolution: [{WIDTH}, {HEIGHT}]\ncamera_model: pinhole\n"
        f"intrinsics: [{', '.join(map(repr, INTRINSICS))}] #fu, fv, cu, cv\n"
        "distortion_model: radial-tangential\n"
        f"distortion_coefficients: [{', '.join(map(repr, DISTORTION))}]\n",
    )
    frame_ns = T0_NS + 3 * IMU_STEP_NS + 10 * IMU_STEP_NS * np.arange(3, dtype=np.int64)
    images = []
    for k, t in enumerate(frame_ns.tolist()):
        image = (np.arange(HEIGHT * WIDTH, dtype=np.uint8).reshape(HEIGHT, WIDTH) * 5 + 40 * k).astype(np.uint8)
        (mav0 / "cam0" / "data").mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(mav0 / "cam0" / "data" / f"{t}.png"), image)
        images.append(image)
    # EuRoC's cam0/data.csv is written with Windows line endings
    _write(
        mav0 / "cam0" / "data.csv",
        "#timestamp [ns],filename\n" + "".join(f"{t},{t}.png\n" for t in frame_ns.tolist()),
        newline="\r\n",
    )
    gt_ns = T0_NS + 2 * IMU_STEP_NS + IMU_STEP_NS * np.arange(10, dtype=np.int64)
    rng = np.random.default_rng(2)
    pos = rng.normal(size=(10, 3))
    quat = rng.normal(size=(10, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    rest = rng.normal(size=(10, 9))
    gt_lines = [GT_HEADER] + [
        ", ".join([str(t)] + [repr(float(v)) for v in (*p, *q, *r)]) for t, p, q, r in zip(gt_ns.tolist(), pos, quat, rest)
    ]
    _write(mav0 / "state_groundtruth_estimate0" / "data.csv", "\n".join(gt_lines) + "\n")
    return dict(
        t_ns=t_ns, gyro=gyro, acc=acc, frame_ns=frame_ns, images=images, gt_ns=gt_ns, pos=pos, quat=quat, mav0=mav0
    )


@pytest.fixture
def sequence_dir(tmp_path):
    root = tmp_path / "MH_00_test"
    return root, _write_sequence(root)


def test_reads_every_value_written(sequence_dir):
    root, truth = sequence_dir
    seq = read_euroc(root)
    assert seq.name == "MH_00_test"
    assert seq.metadata["format"] == "euroc"
    assert seq.metadata["time_offset_ns"] == T0_NS
    # ns -> s after subtracting the first IMU timestamp as an exact integer
    expected_t = (truth["t_ns"] - T0_NS).astype(np.float64) / 1e9
    assert np.array_equal(seq.imu.t_s.numpy(), expected_t)
    assert seq.imu.t_s[0] == 0.0 and seq.imu.t_s[1] == pytest.approx(0.005, abs=0)
    # columns reordered: acc then gyro, values bit-exact
    assert np.array_equal(seq.imu.acc_mps2.numpy(), truth["acc"])
    assert np.array_equal(seq.imu.gyro_rps.numpy(), truth["gyro"])
    # frames: same clock, files in cam0/data
    assert np.array_equal(seq.frames.t_s.numpy(), (truth["frame_ns"] - T0_NS).astype(np.float64) / 1e9)
    assert [f.name for f in seq.frames.files] == [f"{t}.png" for t in truth["frame_ns"].tolist()]
    for k, image in enumerate(truth["images"]):
        rgb = seq.frames.read(k).numpy()
        assert rgb.shape == (HEIGHT, WIDTH, 3)
        for c in range(3):
            assert np.array_equal(rgb[:, :, c], image)
    # camera
    cam = seq.camera
    assert (cam.width, cam.height) == (WIDTH, HEIGHT)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == INTRINSICS
    assert cam.distortion == DISTORTION
    # ground truth: body pose, quaternion w-first, same clock
    gt = seq.groundtruth
    assert np.array_equal(gt.t_s.numpy(), (truth["gt_ns"] - T0_NS).astype(np.float64) / 1e9)
    assert np.array_equal(gt.pos_m.numpy(), truth["pos"])
    np.testing.assert_allclose(gt.quat_wxyz.numpy(), truth["quat"], rtol=0, atol=1e-15)
    assert seq.metadata["groundtruth_source"] == "state_groundtruth_estimate0"
    # IMU noise densities from imu0/sensor.yaml
    assert seq.metadata["imu_noise"] == {
        "rate_hz": 200.0,
        "gyroscope_noise_density": 1.6968e-04,
        "gyroscope_random_walk": 1.9393e-05,
        "accelerometer_noise_density": 2.0e-3,
        "accelerometer_random_walk": 3.0e-3,
    }
    assert seq.sources == ("imu", "frames", "groundtruth")


def test_imu_to_camera_composes_both_T_BS(sequence_dir):
    root, _ = sequence_dir
    seq = read_euroc(root)
    points_imu = np.array([[1.0, 2.0, 3.0], [-0.5, 0.25, 4.0], [0.0, 0.0, 0.0]])
    # x_body = T_BS_imu x_imu; x_cam = T_BS_cam^-1 x_body (plain 4 x 4 algebra)
    homog = np.c_[points_imu, np.ones(3)].T
    expected = (np.linalg.inv(T_BS_CAM) @ T_BS_IMU @ homog)[:3].T
    got = seq.imu_to_camera.apply(torch.from_numpy(points_imu)).numpy()
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)


def test_identity_imu_T_BS_gives_inverse_of_camera_T_BS(tmp_path):
    root = tmp_path / "V1_00"
    _write_sequence(root, imu_identity=True)
    (root / "mav0" / "imu0" / "sensor.yaml").unlink()  # no imu yaml: identity T_BS, no noise numbers
    seq = read_euroc(root / "mav0")  # mav0 itself is accepted too
    assert seq.name == "V1_00"
    assert seq.metadata["imu_noise"] == {}
    np.testing.assert_allclose(seq.imu_to_camera.matrix().numpy(), np.linalg.inv(T_BS_CAM), rtol=0, atol=1e-12)


def test_leica_positions_when_state_estimate_is_absent(sequence_dir):
    root, truth = sequence_dir
    mav0 = truth["mav0"]
    shutil.rmtree(mav0 / "state_groundtruth_estimate0")
    t_ns = T0_NS + np.array([7_000_000, 70_000_000, 140_000_000], dtype=np.int64)
    pos = np.array([[4.6, -1.8, 0.79], [4.61, -1.79, 0.8], [4.62, -1.78, 0.81]])
    _write(
        mav0 / "leica0" / "data.csv",
        "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m]\n"
        + "".join(f"{t},{p[0]!r},{p[1]!r},{p[2]!r}\n" for t, p in zip(t_ns.tolist(), pos.tolist())),
    )
    seq = read_euroc(root)
    assert seq.metadata["groundtruth_source"] == "leica0"
    assert seq.groundtruth.quat_wxyz is None
    assert np.array_equal(seq.groundtruth.pos_m.numpy(), pos)
    assert np.array_equal(seq.groundtruth.t_s.numpy(), (t_ns - T0_NS) / 1e9)
    shutil.rmtree(mav0 / "leica0")
    seq = read_euroc(root)
    assert seq.groundtruth is None and seq.metadata["groundtruth_source"] is None


def test_camera_none_reads_imu_only(sequence_dir):
    root, _ = sequence_dir
    seq = read_euroc(root, camera=None)
    assert seq.frames is None and seq.camera is None and seq.imu_to_camera is None


# ------------------------------------------------------------------ bad input


def _imu_file(truth) -> Path:
    return truth["mav0"] / "imu0" / "data.csv"


def _replace_line(path: Path, line: int, text: str) -> None:
    lines = path.read_text().splitlines()
    lines[line - 1] = text
    path.write_text("\n".join(lines) + "\n")


def test_not_a_sequence_folder(tmp_path):
    with pytest.raises(ValueError, match="expected an EuRoC sequence"):
        read_euroc(tmp_path)


def test_missing_imu_file(sequence_dir):
    root, truth = sequence_dir
    _imu_file(truth).unlink()
    with pytest.raises(ValueError, match=r"imu0/data\.csv: file does not exist; expected the IMU samples"):
        read_euroc(root)


def test_missing_camera_yaml(sequence_dir):
    root, truth = sequence_dir
    (truth["mav0"] / "cam0" / "sensor.yaml").unlink()
    with pytest.raises(ValueError, match=r"cam0/sensor\.yaml: file does not exist"):
        read_euroc(root)


def test_missing_camera_folder_lists_the_ones_found(sequence_dir):
    root, _ = sequence_dir
    with pytest.raises(ValueError, match=r"cam1: camera folder does not exist; found \['cam0'\]"):
        read_euroc(root, camera="cam1")


def test_wrong_column_count_names_line(sequence_dir):
    root, truth = sequence_dir
    _replace_line(_imu_file(truth), 4, f"{T0_NS + 2 * IMU_STEP_NS},0.1,0.2,0.3,9.8,0.1")
    with pytest.raises(ValueError, match=r"data\.csv: line 4: 6 columns; expected 7 \(timestamp \[ns\]"):
        read_euroc(root)


def test_non_numeric_cell_names_line_and_column(sequence_dir):
    root, truth = sequence_dir
    _replace_line(_imu_file(truth), 6, f"{T0_NS + 4 * IMU_STEP_NS},0.1,0.2,abc,9.8,0.1,0.2")
    with pytest.raises(ValueError, match=r"line 6, column 4: 'abc' is not a number"):
        read_euroc(root)


def test_fractional_timestamp_is_an_error(sequence_dir):
    root, truth = sequence_dir
    _replace_line(_imu_file(truth), 3, "1.4e18,0.1,0.2,0.3,9.8,0.1,0.2")
    with pytest.raises(ValueError, match=r"line 3, column 1: '1.4e18' is not an integer"):
        read_euroc(root)


def test_non_increasing_imu_timestamps(sequence_dir):
    root, truth = sequence_dir
    _replace_line(_imu_file(truth), 10, f"{T0_NS + 7 * IMU_STEP_NS},0.1,0.2,0.3,9.8,0.1,0.2")  # line 9 has step 7
    with pytest.raises(ValueError, match=r"line 10: timestamp .* is not after the previous one .*line 9\)"):
        read_euroc(root)


def test_non_increasing_frame_timestamps(sequence_dir):
    root, truth = sequence_dir
    file = truth["mav0"] / "cam0" / "data.csv"
    t = truth["frame_ns"].tolist()
    file.write_text(f"#timestamp [ns],filename\n{t[0]},{t[0]}.png\n{t[2]},{t[2]}.png\n{t[1]},{t[1]}.png\n")
    with pytest.raises(ValueError, match=r"cam0/data\.csv: line 4: timestamp"):
        read_euroc(root)


def test_imu_gap_names_lines(sequence_dir):
    root, truth = sequence_dir
    file = _imu_file(truth)
    t_ns, gyro, acc = _imu_rows()
    t_ns[20:] += 300_000_000  # 0.3 s gap between data rows 19 and 20 (lines 21 and 22)
    file.write_text(_imu_text(t_ns, gyro, acc))
    with pytest.raises(ValueError, match=r"line 22: gap of 305000000 ns after line 21 exceeds 200000000 ns"):
        read_euroc(root)
    assert len(read_euroc(root, max_imu_gap_s=0.5).imu) == N_IMU


def test_accelerometer_in_g_is_rejected(sequence_dir):
    root, truth = sequence_dir
    t_ns, gyro, acc = _imu_rows()
    _imu_file(truth).write_text(_imu_text(t_ns, gyro, acc / 9.81))
    with pytest.raises(ValueError, match=r"median accelerometer magnitude 0\.9\d* is below 2; .*look like units of g"):
        read_euroc(root)


def test_missing_image(sequence_dir):
    root, truth = sequence_dir
    t = truth["frame_ns"][1]
    (truth["mav0"] / "cam0" / "data" / f"{t}.png").unlink()
    with pytest.raises(ValueError, match=rf"cam0/data\.csv: line 3: image .*{t}\.png does not exist"):
        read_euroc(root)
    assert len(read_euroc(root, check_frames=False).frames) == 3  # lazily loaded: listed, not checked


def test_bad_T_BS_is_rejected(sequence_dir):
    root, truth = sequence_dir
    file = truth["mav0"] / "cam0" / "sensor.yaml"
    bad = T_BS_CAM.copy()
    bad[0, 0] += 0.1
    text = re.sub(r"T_BS:\n(.*\n){3}", _yaml_matrix(bad), file.read_text())
    file.write_text(text)
    with pytest.raises(ValueError, match=r"sensor\.yaml: T_BS: rotation block is not a rotation"):
        read_euroc(root)
