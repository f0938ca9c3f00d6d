"""ADVIO reader: a tiny sequence folder with ADVIO's headerless CSV layouts and a real .mov.

The truth is what each test writes: linear accelerometer data (so linear
interpolation onto the gyro clock is exact), known frame brightness, known
fixes and poses. OpenCV here writes QuickTime .mov files (fourcc ``mp4v``), so
the fixture uses ADVIO's own name, ``frames.mov``.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from flowins.data.advio import IPHONE_T_CAM_IMU, read_advio, read_calibration

G = 9.80665
N_GYRO = 60
GYRO_T = 12.0 + 0.01 * np.arange(N_GYRO) + 0.0007 * np.sin(np.arange(N_GYRO))  # jittered 100 Hz
ACC_T = 12.0185 + 0.01 * np.arange(N_GYRO - 4)  # starts after gyro row 1, ends before the last 3 rows
ACC_C0 = np.array([0.05, -0.12, 0.98])  # [g]
ACC_C1 = np.array([0.02, 0.01, -0.03])  # [g/s]
VIDEO_W, VIDEO_H = 32, 48
FRAME_T = np.array([12.05, 12.1, 12.15, 12.2])
FRAME_LEVELS = (30, 90, 150, 210)
CALIBRATION_YAML = f"""camera:
  width: {VIDEO_W}
  height: {VIDEO_H}
  fx: 40.5
  fy: 41.0
  cx: 15.5
  cy: 23.5
  distortion: [0.01, -0.002, 0.0003, 0.0004]
imu_to_camera:
  rotation: [0.0, 1.0, 0.0, 0.0]   # 180 degrees about x: camera y, z opposite the device's
  translation: [0.01, 0.07, -0.005]
"""


def _acc_g(t):
    return ACC_C0 + np.outer(t - 12.0, ACC_C1)


def _csv(path: Path, rows) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(",".join(repr(float(v)) for v in row) + "\n" for row in rows))


def _write_sequence(folder: Path) -> dict:
    iphone = folder / "iphone"
    rng = np.random.default_rng(3)
    gyro = rng.normal(scale=0.2, size=(N_GYRO, 3))
    _csv(iphone / "gyro.csv", np.c_[GYRO_T, gyro])
    _csv(iphone / "accelerometer.csv", np.c_[ACC_T, _acc_g(ACC_T)])
    # frames.csv: time, frame number; the video holds one frame per row
    (iphone / "frames.csv").write_text("".join(f"{t!r},{k + 1}\n" for k, t in enumerate(FRAME_T.tolist())))
    writer = cv2.VideoWriter(str(iphone / "frames.mov"), cv2.VideoWriter_fourcc(*"mp4v"), 20, (VIDEO_W, VIDEO_H))
    assert writer.isOpened()
    for level in FRAME_LEVELS:
        writer.write(np.full((VIDEO_H, VIDEO_W, 3), level, np.uint8))
    writer.release()
    # platform-location.csv: t, lat, lon, horizontal accuracy, altitude, vertical accuracy, speed
    fixes = np.array(
        [
            [12.1, 60.1867, 24.8215, 5.0, 21.5, 3.0, 1.2],
            [12.3, 60.18671, 24.82152, -1.0, 21.4, 3.0, 1.1],  # invalid horizontal fix (CoreLocation: < 0)
            [12.5, 60.18672, 24.82154, 4.5, 21.3, 2.5, -1.0],
        ]
    )
    _csv(iphone / "platform-location.csv", fixes)
    pose_t = 12.0 + 0.01 * np.arange(20)
    pos = rng.normal(size=(20, 3))
    quat = rng.normal(size=(20, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    _csv(folder / "ground-truth" / "pose.csv", np.c_[pose_t, pos, quat])
    _csv(iphone / "arkit.csv", np.c_[pose_t, pos, quat])
    (folder / "calibration.yaml").write_text(CALIBRATION_YAML)
    return dict(gyro=gyro, fixes=fixes, pose_t=pose_t, pos=pos, quat=quat, iphone=iphone)


@pytest.fixture
def sequence_dir(tmp_path):
    folder = tmp_path / "advio-15"
    return folder, _write_sequence(folder)


def test_imu_resampled_onto_gyro_clock_in_mps2(sequence_dir):
    folder, truth = sequence_dir
    seq = read_advio(folder, calibration=folder / "calibration.yaml")
    inside = (GYRO_T >= ACC_T[0]) & (GYRO_T <= ACC_T[-1])
    assert inside.sum() == N_GYRO - 5 and inside[2:-3].all()  # the fixture drops 2 at the start, 3 at the end
    assert np.array_equal(seq.imu.t_s.numpy(), GYRO_T[inside])
    assert np.array_equal(seq.imu.gyro_rps.numpy(), truth["gyro"][inside])
    # linear data: interpolation is exact (to rounding); g -> m/s^2 with 9.80665
    np.testing.assert_allclose(seq.imu.acc_mps2.numpy(), _acc_g(GYRO_T[inside]) * G, rtol=0, atol=1e-12)
    resampling = seq.metadata["imu_resampling"]
    assert (resampling["gyro_dropped_start"], resampling["gyro_dropped_end"]) == (2, 3)
    assert resampling["gyro_samples"] == N_GYRO and resampling["accelerometer_samples"] == N_GYRO - 4


def test_frames_gnss_groundtruth_and_metadata(sequence_dir):
    folder, truth = sequence_dir
    seq = read_advio(folder, calibration=folder / "calibration.yaml")
    assert seq.name == "advio-15"
    assert seq.sources == ("imu", "frames", "gnss", "groundtruth")
    # frames: video + 0-based row indices, same clock as the IMU
    assert np.array_equal(seq.frames.t_s.numpy(), FRAME_T)
    assert seq.frames.video == truth["iphone"] / "frames.mov"
    assert seq.frames.indices.tolist() == [0, 1, 2, 3]
    for k in (2, 0, 3):  # random access
        image = seq.frames.read(k)
        assert image.shape == (VIDEO_H, VIDEO_W, 3)
        assert abs(float(image.float().mean()) - FRAME_LEVELS[k]) < 4  # lossy codec
    assert seq.metadata["video_frame_count"] == 4 and seq.metadata["video_size_wh"] == (VIDEO_W, VIDEO_H)
    assert seq.metadata["frame_numbers_consecutive"]
    # GNSS: columns t, lat, lon, h_acc, alt, v_acc, speed; the invalid fix is left out and listed
    fixes = truth["fixes"][[0, 2]]
    gnss = seq.gnss
    for got, column in ((gnss.t_s, 0), (gnss.lat_deg, 1), (gnss.lon_deg, 2), (gnss.h_acc_m, 3), (gnss.alt_m, 4), (gnss.v_acc_m, 5)):
        assert np.array_equal(got.numpy(), fixes[:, column])
    assert seq.metadata["gnss_invalid_rows"] == 1 and seq.metadata["gnss_invalid_lines"] == [2]
    # ground truth: t, x, y, z, qw, qx, qy, qz
    gt = seq.groundtruth
    assert np.array_equal(gt.t_s.numpy(), truth["pose_t"])
    assert np.array_equal(gt.pos_m.numpy(), truth["pos"])
    np.testing.assert_allclose(gt.quat_wxyz.numpy(), truth["quat"], rtol=0, atol=1e-15)
    assert seq.metadata["arkit"] == str(truth["iphone"] / "arkit.csv")
    assert seq.metadata["format"] == "advio"


def test_calibration_file_overrides_defaults(sequence_dir):
    folder, _ = sequence_dir
    camera, T = read_calibration(folder / "calibration.yaml")
    assert (camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy) == (32, 48, 40.5, 41.0, 15.5, 23.5)
    assert camera.distortion == (0.01, -0.002, 0.0003, 0.0004)
    # q = (0, 1, 0, 0): 180 degrees about x, so x_cam = (x, -y, -z) + t
    got = T.apply(torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)).numpy()
    np.testing.assert_allclose(got, [1.01, -1.93, -3.005], rtol=0, atol=1e-12)


def test_default_calibration_is_advios_batch(sequence_dir):
    folder, _ = sequence_dir
    seq = read_advio(folder)  # advio-15: batch 13-17, calibration/iphone-03.yaml
    cam = seq.camera
    assert (cam.width, cam.height) == (720, 1280)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (1082.4, 1084.4, 364.6778, 643.3080)
    assert cam.distortion == (0.0366, 0.0803, 0.000783, -0.000215)
    assert "iphone-03.yaml" in seq.metadata["calibration"]
    # imu_to_camera is ADVIO's Kalibr T_cam_imu: check by transforming a point with the matrix
    M = np.array(IPHONE_T_CAM_IMU)
    x = np.array([0.3, -0.2, 1.5])
    got = seq.imu_to_camera.apply(torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(got, M[:3, :3] @ x + M[:3, 3], rtol=0, atol=2e-5)  # the printed R is orthonormal to ~1e-5


def test_readme_file_names_are_accepted(sequence_dir):
    folder, truth = sequence_dir
    iphone = truth["iphone"]
    (iphone / "gyro.csv").rename(iphone / "gyroscope.csv")
    (folder / "ground-truth" / "pose.csv").rename(folder / "ground-truth" / "poses.csv")
    (iphone / "platform-location.csv").rename(iphone / "platform-locations.csv")
    seq = read_advio(folder, calibration=folder / "calibration.yaml")
    assert len(seq.imu) == N_GYRO - 5 and len(seq.groundtruth) == 20 and len(seq.gnss) == 2


def test_optional_parts_may_be_absent(sequence_dir):
    folder, truth = sequence_dir
    iphone = truth["iphone"]
    for name in ("frames.csv", "frames.mov", "platform-location.csv", "arkit.csv"):
        (iphone / name).unlink()
    (folder / "ground-truth" / "pose.csv").unlink()
    seq = read_advio(folder, calibration=folder / "calibration.yaml")
    assert seq.sources == ("imu",) and seq.metadata["arkit"] is None


# ------------------------------------------------------------------ bad input


def test_not_an_advio_folder(tmp_path):
    with pytest.raises(ValueError, match=r"iphone: folder does not exist; expected an ADVIO sequence folder"):
        read_advio(tmp_path)


def test_missing_accelerometer(sequence_dir):
    folder, truth = sequence_dir
    (truth["iphone"] / "accelerometer.csv").unlink()
    with pytest.raises(ValueError, match=r"accelerometer\.csv: file does not exist; expected the accelerometer"):
        read_advio(folder, calibration=folder / "calibration.yaml")


def test_missing_video(sequence_dir):
    folder, truth = sequence_dir
    (truth["iphone"] / "frames.mov").unlink()
    with pytest.raises(ValueError, match=r"frames\.mov: file does not exist; expected the iPhone video"):
        read_advio(folder, calibration=folder / "calibration.yaml")


def test_wrong_column_count(sequence_dir):
    folder, truth = sequence_dir
    file = truth["iphone"] / "gyro.csv"
    lines = file.read_text().splitlines()
    lines[6] += ",0.5"
    file.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"gyro\.csv: line 7: 5 columns; expected 4 \(t \[s\], wx"):
        read_advio(folder, calibration=folder / "calibration.yaml")


def test_non_numeric_cell(sequence_dir):
    folder, truth = sequence_dir
    file = truth["iphone"] / "accelerometer.csv"
    lines = file.read_text().splitlines()
    lines[2] = "12.0385,0.05,nope,0.98"
    file.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"accelerometer\.csv: line 3, column 3: 'nope' is not a number"):
        read_advio(folder, calibration=folder / "calibration.yaml")


def test_non_increasing_timestamps(sequence_dir):
    folder, truth = sequence_dir
    _csv(truth["iphone"] / "gyro.csv", np.c_[GYRO_T[[0, 1, 2, 4, 3, *range(5, N_GYRO)]], truth["gyro"]])
    with pytest.raises(ValueError, match=r"gyro\.csv: line 5: timestamp .* is not after the previous one .*line 4\)"):
        read_advio(folder, calibration=folder / "calibration.yaml")


def test_accelerometer_already_in_mps2(sequence_dir):
    folder, truth = sequence_dir
    _csv(truth["iphone"] / "accelerometer.csv", np.c_[ACC_T, _acc_g(ACC_T) * G])
    with pytest.raises(ValueError, match=r"median accelerometer magnitude 9\d\.\d m/s\^2 .*already in m/s\^2"):
        read_advio(folder, calibration=folder / "calibration.yaml")


def test_accelerometer_gap_is_not_bridged(sequence_dir):
    folder, truth = sequence_dir
    t = ACC_T.copy()
    t[30:] += 0.5
    _csv(truth["iphone"] / "accelerometer.csv", np.c_[t, _acc_g(t)])
    with pytest.raises(ValueError, match=r"accelerometer\.csv: line 31: gap of .* after line 30 exceeds 0\.2 s"):
        read_advio(folder, calibration=folder / "calibration.yaml")


def test_unknown_sequence_number_needs_a_calibration(tmp_path):
    folder = tmp_path / "my-recording"
    _write_sequence(folder)
    with pytest.raises(ValueError, match=r"cannot tell the ADVIO sequence number .* pass calibration="):
        read_advio(folder)
    assert read_advio(folder, calibration=folder / "calibration.yaml").camera.width == VIDEO_W


def test_bad_calibration_file(sequence_dir):
    folder, _ = sequence_dir
    bad = folder / "bad.yaml"
    bad.write_text(CALIBRATION_YAML.replace("rotation: [0.0, 1.0, 0.0, 0.0]", "rotation: [0.0, 1.0, 0.0]"))
    with pytest.raises(ValueError, match=r"bad\.yaml: line \d+: imu_to_camera\.rotation is \[0\.0, 1\.0, 0\.0\]; expected a list of 4 numbers"):
        read_advio(folder, calibration=bad)
    bad.write_text(CALIBRATION_YAML.replace("  fx: 40.5\n", ""))
    with pytest.raises(ValueError, match=r"bad\.yaml: .*camera has no 'fx'"):
        read_advio(folder, calibration=bad)
