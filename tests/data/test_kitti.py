"""KITTI raw reader: a tiny drive written from a closed-form trajectory.

The truth is independent of flowins: the trajectory (a circle driven with a
banked, pitched body), its exact specific force and body rates, WGS84
coordinates computed here with the closed-form ellipsoid formulas (not PROJ),
rotations built from elementary matrices, and the KITTI devkit's projection
``y = P_rect_0i R_rect_00 T_cam0_velo T_velo_imu x``.
"""
from __future__ import annotations

import datetime
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from flowins.data.kitti import read_kitti_raw
from flowins.data.read import detect_format, read_sequence
from flowins.geometry import quaternion as quat
from flowins.geometry.camera import project

G = 9.80665
ORIGIN = (49.011, 8.423, 112.5)  # Karlsruhe-ish lat [deg], lon [deg], height [m]
T0_NS = 1_317_042_145_964_389_445  # 2011-09-26 13:02:25.964389445 (as UTC)
DT_NS = 100_000_000  # 10 Hz, a sync drive
WIDTH, HEIGHT = 8, 6


# ---------------------------------------------------------------------------
# Independent truth
# ---------------------------------------------------------------------------


def _rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _ecef(lat, lon, h):
    a, f = 6378137.0, 1 / 298.257223563
    e2 = f * (2 - f)
    phi, lam = np.radians(lat), np.radians(lon)
    n = a / np.sqrt(1 - e2 * np.sin(phi) ** 2)
    return np.stack([(n + h) * np.cos(phi) * np.cos(lam), (n + h) * np.cos(phi) * np.sin(lam), (n * (1 - e2) + h) * np.sin(phi)], -1)


def _geodetic(enu):
    """ENU about ORIGIN -> (lat, lon, h), by the textbook fixed-point iteration on the WGS84 ellipsoid."""
    a, f = 6378137.0, 1 / 298.257223563
    e2 = f * (2 - f)
    phi0, lam0 = math.radians(ORIGIN[0]), math.radians(ORIGIN[1])
    M = np.array([
        [-math.sin(lam0), math.cos(lam0), 0],
        [-math.sin(phi0) * math.cos(lam0), -math.sin(phi0) * math.sin(lam0), math.cos(phi0)],
        [math.cos(phi0) * math.cos(lam0), math.cos(phi0) * math.sin(lam0), math.sin(phi0)],
    ])
    x, y, z = (_ecef(*ORIGIN) + enu @ M).T
    lon, p = np.arctan2(y, x), np.hypot(x, y)
    lat = np.arctan2(z, p * (1 - e2))
    for _ in range(20):
        n = a / np.sqrt(1 - e2 * np.sin(lat) ** 2)
        h = p / np.cos(lat) - n
        lat = np.arctan2(z, p * (1 - e2 * n / (n + h)))
    n = a / np.sqrt(1 - e2 * np.sin(lat) ** 2)
    return np.degrees(lat), np.degrees(lon), p / np.cos(lat) - n


def _drive(n=30, *, radius=20.0, speed=5.0, roll=0.04, pitch=-0.06, yaw0=2.9, climb=0.3):
    """A circle (counter-clockwise) with a constant climb; the body is banked by roll, pitched by pitch."""
    t = np.arange(n) * DT_NS / 1e9
    w = speed / radius
    yaw = yaw0 + w * t
    enu = np.stack([radius * (np.sin(yaw) - math.sin(yaw0)), -radius * (np.cos(yaw) - math.cos(yaw0)), climb * t], -1)
    acc_world = np.stack([-radius * w * w * np.sin(yaw), radius * w * w * np.cos(yaw), 0 * t], -1)
    R = np.stack([_rz(y) @ _ry(pitch) @ _rx(roll) for y in yaw])
    f_body = np.einsum("nji,nj->ni", R, acc_world + [0, 0, G])
    w_body = np.einsum("nji,j->ni", R, [0, 0, w])
    yaw_wrapped = (yaw + math.pi) % (2 * math.pi) - math.pi
    rpy = np.stack([np.full(n, roll), np.full(n, pitch), yaw_wrapped], -1)
    return {"t_ns": T0_NS + DT_NS * np.arange(n, dtype=np.int64), "enu": enu, "R": R, "rpy": rpy, "acc": f_body, "gyro": w_body}


# ---------------------------------------------------------------------------
# Writing a drive
# ---------------------------------------------------------------------------


def _stamp(t_ns: int) -> str:
    seconds, fraction = divmod(int(t_ns), 1_000_000_000)
    day = datetime.datetime(1970, 1, 1) + datetime.timedelta(seconds=seconds)
    return f"{day:%Y-%m-%d %H:%M:%S}.{fraction:09d}"


def _write_drive(root: Path, truth: dict, *, pos_accuracy=None) -> Path:
    drive = root / "2011_09_26" / "2011_09_26_drive_0001_sync"
    (drive / "oxts" / "data").mkdir(parents=True)
    (drive / "oxts" / "timestamps.txt").write_text("".join(_stamp(t) + "\n" for t in truth["t_ns"]))
    lat, lon, alt = _geodetic(truth["enu"])
    n = len(truth["t_ns"])
    pos_accuracy = np.linspace(0.0, 0.5, n) if pos_accuracy is None else pos_accuracy
    for k in range(n):
        values = [lat[k], lon[k], alt[k], *truth["rpy"][k], 1.0, 2.0, 3.0, 0.1, 0.2, *truth["acc"][k],
                  0.5, 0.6, 9.7, *truth["gyro"][k], 0.01, 0.02, 0.03, pos_accuracy[k], 0.05, 4, 10, 4, 4, 0]
        (drive / "oxts" / "data" / f"{k:010d}.txt").write_text(" ".join(repr(float(v)) for v in values) + "\n")
    return drive


def _homogeneous(R, t):
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, t
    return M


T_VELO_IMU = _homogeneous(_rz(0.0075) @ _rx(-0.002), [-0.8086759, 0.3195559, -0.7997231])
T_CAM0_VELO = _homogeneous(_rx(-math.pi / 2) @ _rz(-math.pi / 2) @ _ry(0.01), [-0.004069766, -0.07631618, -0.2717806])
R_RECT_00 = _rz(0.0098) @ _ry(-0.0074)
# KITTI's 1242x375 rectified camera, scaled to the WIDTH x HEIGHT test images
SCALE = np.diag([WIDTH / 1242.0, HEIGHT / 375.0, 1.0])
K = SCALE @ np.array([[721.5377, 0.0, 609.5593], [0.0, 721.5377, 172.854], [0.0, 0.0, 1.0]])
P_RECT = {i: np.hstack([K, SCALE @ p[:, None]]) for i, p in {
    0: np.zeros(3), 1: np.array([-387.5744, 0.0, 0.0]), 2: np.array([44.85728, 0.2163791, 0.002745884]),
    3: np.array([-339.5242, 2.199936, 0.002729905]),
}.items()}


def _numbers(values) -> str:
    return " ".join(f"{float(v):.17g}" for v in np.ravel(values))


def _write_calibration(folder: Path) -> None:
    lines = ["calib_time: 09-Jan-2012 13:57:47", "corner_dist: 9.950000e-02"]
    for i in range(4):
        lines += [f"S_rect_0{i}: {WIDTH}.0 {HEIGHT}.0", f"P_rect_0{i}: {_numbers(P_RECT[i])}"]
    lines.insert(3, f"R_rect_00: {_numbers(R_RECT_00)}")
    (folder / "calib_cam_to_cam.txt").write_text("\n".join(lines) + "\n")
    for name, M in (("calib_imu_to_velo.txt", T_VELO_IMU), ("calib_velo_to_cam.txt", T_CAM0_VELO)):
        text = f"calib_time: 25-May-2012 16:47:16\nR: {_numbers(M[:3, :3])}\nT: {_numbers(M[:3, 3])}\n"
        (folder / name).write_text(text + ("delta_f: 0 0\n" if "velo_to_cam" in name else ""))


def _write_images(drive: Path, camera: int, t_ns) -> None:
    folder = drive / f"image_0{camera}"
    (folder / "data").mkdir(parents=True)
    (folder / "timestamps.txt").write_text("".join(_stamp(t) + "\n" for t in t_ns))
    rng = np.random.default_rng(camera)
    for k in range(len(t_ns)):
        cv2.imwrite(str(folder / "data" / f"{k:010d}.png"), rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8))


# ---------------------------------------------------------------------------
# Streams
# ---------------------------------------------------------------------------


def test_streams_equal_the_written_trajectory(tmp_path):
    truth = _drive()
    seq = read_kitti_raw(_write_drive(tmp_path, truth))
    assert torch.equal(seq.imu.t_s, torch.from_numpy((truth["t_ns"] - T0_NS) / 1e9))
    assert torch.equal(seq.imu.acc_mps2, torch.from_numpy(truth["acc"]))
    assert torch.equal(seq.imu.gyro_rps, torch.from_numpy(truth["gyro"]))
    gt = seq.groundtruth
    assert torch.equal(gt.t_s, seq.imu.t_s)
    assert float((gt.pos_m - torch.from_numpy(truth["enu"])).abs().max()) < 1e-6  # metres (well below a mm)
    assert torch.allclose(quat.to_matrix(gt.quat_wxyz), torch.from_numpy(truth["R"]), atol=1e-12)
    pos_accuracy = np.linspace(0.0, 0.5, len(truth["t_ns"]))
    assert torch.equal(seq.gnss.h_acc_m, torch.from_numpy(np.maximum(pos_accuracy, 0.02)))
    assert torch.equal(seq.gnss.v_acc_m, 1.5 * seq.gnss.h_acc_m)
    lat, lon, alt = _geodetic(truth["enu"])
    assert torch.allclose(seq.gnss.lat_deg, torch.from_numpy(lat), rtol=0, atol=1e-12)
    assert torch.allclose(seq.gnss.alt_m, torch.from_numpy(alt), rtol=0, atol=1e-9)
    assert seq.metadata["imu"] == "oxts_rt3003" and seq.metadata["source"] == "KITTI raw"
    assert seq.metadata["time_offset_ns"] == T0_NS and seq.metadata["start_time"] == "2011-09-26 13:02:25.964389445"
    assert seq.metadata["gnss_floored_rows"] == int((pos_accuracy < 0.02).sum()) == 2
    assert seq.frames is None and seq.camera is None


def test_imu_obeys_the_navigation_equations_of_the_groundtruth(tmp_path):
    """R(q) f + g = d²p/dt² (second differences of the ENU positions) and q_{k+1} = q_k ⊙ exp(ω dt)."""
    seq = read_kitti_raw(_write_drive(tmp_path, _drive()))
    dt = DT_NS / 1e9
    p, q = seq.groundtruth.pos_m, seq.groundtruth.quat_wxyz
    acc_fd = (p[2:] - 2 * p[1:-1] + p[:-2]) / dt**2
    acc_imu = quat.rotate(q[1:-1], seq.imu.acc_mps2[1:-1]) - torch.tensor([0.0, 0.0, G], dtype=torch.float64)
    assert float((acc_imu - acc_fd).abs().max()) < 1e-3  # m/s^2; a wrong gravity or axis convention is ~0.5
    q_next = quat.multiply(q[:-1], quat.from_rotation_vector(seq.imu.gyro_rps[:-1] * dt))
    assert float(quat.angle_between(q_next, q[1:]).max()) < 1e-9


def test_still_vehicle_on_a_slope_measures_gravity_upwards(tmp_path):
    seq = read_kitti_raw(_write_drive(tmp_path, _drive(speed=0.0, climb=0.0, roll=0.05, pitch=-0.08)))
    norm = torch.linalg.vector_norm(seq.imu.acc_mps2, dim=-1)
    assert torch.allclose(norm, torch.full_like(norm, G), atol=1e-12)
    up = quat.rotate(seq.groundtruth.quat_wxyz, seq.imu.acc_mps2)
    assert torch.allclose(up, torch.tensor([0.0, 0.0, G], dtype=torch.float64).expand_as(up), atol=1e-12)


@pytest.mark.parametrize("rpy, axis, expected", [
    ((0.0, 0.3, 0.0), 0, "front down: forward axis points below the horizon"),
    ((0.3, 0.0, 0.0), 1, "left side up: left axis points above the horizon"),
    ((0.0, 0.0, 0.0), 0, "yaw 0: forward is east"),
    ((0.0, 0.0, math.pi / 2), 0, "yaw +90 deg (counter-clockwise): forward is north"),
])
def test_orientation_follows_the_devkit_readme(tmp_path, rpy, axis, expected):
    truth = _drive(n=3, speed=0.0, climb=0.0)
    truth["rpy"] = np.tile(rpy, (3, 1))
    seq = read_kitti_raw(_write_drive(tmp_path, truth))
    body_axis = quat.to_matrix(seq.groundtruth.quat_wxyz[0])[:, axis].numpy()
    if expected.startswith("front down"):
        assert body_axis[2] == pytest.approx(-math.sin(0.3))
    elif expected.startswith("left side up"):
        assert body_axis[2] == pytest.approx(math.sin(0.3))
    elif "east" in expected:
        assert body_axis == pytest.approx([1.0, 0.0, 0.0])
    else:
        assert body_axis == pytest.approx([0.0, 1.0, 0.0], abs=1e-15)


def test_accelerations_without_gravity_are_an_error(tmp_path):
    truth = _drive()
    truth["acc"] = truth["acc"] - np.einsum("nji,j->ni", truth["R"], [0, 0, G])
    with pytest.raises(ValueError, match=r"oxts/data: median \|\(ax, ay, az\)\| is .* below 2; expected specific force"):
        read_kitti_raw(_write_drive(tmp_path, truth))


# ---------------------------------------------------------------------------
# Bad files
# ---------------------------------------------------------------------------


def _edit_timestamps(drive: Path, line: int, text: str) -> None:
    file = drive / "oxts" / "timestamps.txt"
    lines = file.read_text().splitlines()
    lines[line - 1] = text
    file.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("copy_from", [3, 2])  # a repeated packet time; a step backwards
def test_non_increasing_timestamp_names_file_and_lines(tmp_path, copy_from):
    drive = _write_drive(tmp_path, _drive())
    _edit_timestamps(drive, 4, (drive / "oxts" / "timestamps.txt").read_text().splitlines()[copy_from - 1])
    with pytest.raises(ValueError, match=r"oxts/timestamps\.txt: line 4: timestamp \d+ ns is not after the previous one "
                                         r"\(\d+ ns, line 3\); expected strictly increasing"):
        read_kitti_raw(drive)


def test_bad_timestamp_text_names_line(tmp_path):
    drive = _write_drive(tmp_path, _drive())
    _edit_timestamps(drive, 5, "2011-09-26 13:02:26,364389445")
    with pytest.raises(ValueError, match=r"timestamps\.txt: line 5: '2011-09-26 13:02:26,364389445' is not a timestamp"):
        read_kitti_raw(drive)
    _edit_timestamps(drive, 5, "2011-09-31 13:02:26.364389445")
    with pytest.raises(ValueError, match=r"timestamps\.txt: line 5: .* is not a valid date and time"):
        read_kitti_raw(drive)


def test_gap_names_lines(tmp_path):
    truth = _drive()
    truth["t_ns"][10:] += 1_000_000_000
    drive = _write_drive(tmp_path, truth)
    with pytest.raises(ValueError, match=r"timestamps\.txt: line 11: gap of 1100000000 ns after line 10 .*max_imu_gap_s=0\.2"):
        read_kitti_raw(drive)
    assert read_kitti_raw(drive, max_imu_gap_s=1.2).imu.t_s[10] == pytest.approx(2.0)


def test_wrong_column_count_names_file_and_line(tmp_path):
    drive = _write_drive(tmp_path, _drive())
    file = drive / "oxts" / "data" / "0000000003.txt"
    file.write_text("\n" + " ".join(file.read_text().split()[:29]) + "\n")
    with pytest.raises(ValueError, match=r"0000000003\.txt: line 2: 29 values; expected one line of 30 space-separated"):
        read_kitti_raw(drive)


def test_non_numeric_value_names_column(tmp_path):
    drive = _write_drive(tmp_path, _drive())
    file = drive / "oxts" / "data" / "0000000007.txt"
    cells = file.read_text().split()
    cells[12] = "nan"
    file.write_text(" ".join(cells))
    with pytest.raises(ValueError, match=r"0000000007\.txt: line 1, column 13 \(ay\): 'nan' is not a finite number"):
        read_kitti_raw(drive)


def test_packet_files_must_match_the_timestamps(tmp_path):
    drive = _write_drive(tmp_path, _drive())
    (drive / "oxts" / "data" / "0000000029.txt").unlink()
    with pytest.raises(ValueError, match=r"oxts/data: 29 packet files for the 30 timestamps .*0000000029\.txt is missing"):
        read_kitti_raw(drive)


# ---------------------------------------------------------------------------
# Camera
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("camera", [0, 2])
@pytest.mark.parametrize("calibration_in", ["date folder", "drive folder"])
def test_camera_calibration_projects_as_the_devkit(tmp_path, camera, calibration_in):
    truth = _drive()
    drive = _write_drive(tmp_path, truth)
    _write_calibration(drive.parent if calibration_in == "date folder" else drive)
    t_frames = truth["t_ns"][2:20:3] + 12_345
    _write_images(drive, camera, t_frames)
    seq = read_kitti_raw(drive, camera=camera)
    assert (seq.camera.width, seq.camera.height, seq.camera.distortion) == (WIDTH, HEIGHT, ())
    assert (seq.camera.fx, seq.camera.fy, seq.camera.cx, seq.camera.cy) == (K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    points_imu = np.random.default_rng(0).uniform([-5, -10, -2], [40, 10, 3], size=(50, 3)) + [10, 0, 0]
    rect = np.eye(4)
    rect[:3, :3] = R_RECT_00
    y = (P_RECT[camera] @ rect @ T_CAM0_VELO @ T_VELO_IMU @ np.c_[points_imu, np.ones(50)].T).T
    points_cam = seq.imu_to_camera.apply(torch.from_numpy(points_imu))
    uv = project(points_cam, seq.camera.fx, seq.camera.fy, seq.camera.cx, seq.camera.cy)
    assert torch.allclose(uv, torch.from_numpy(y[:, :2] / y[:, 2:]), rtol=0, atol=1e-8)  # pixels
    assert torch.allclose(points_cam[:, 2], torch.from_numpy(y[:, 2]), rtol=0, atol=1e-9)  # depth, metres
    assert torch.equal(seq.frames.t_s, torch.from_numpy((t_frames - T0_NS) / 1e9))
    assert seq.frames.files[1] == drive / f"image_0{camera}" / "data" / "0000000001.png"
    assert tuple(seq.frames.read(0).shape) == (HEIGHT, WIDTH, 3)
    assert seq.metadata["camera"] == f"image_0{camera}"


def test_images_without_calibration_name_what_was_looked_for(tmp_path):
    truth = _drive()
    drive = _write_drive(tmp_path, truth)
    _write_calibration(drive.parent)
    (drive.parent / "calib_velo_to_cam.txt").unlink()
    _write_images(drive, 0, truth["t_ns"][:3])
    with pytest.raises(ValueError, match=r"the images need the KITTI calibration; looked for calib_cam_to_cam\.txt, "
                                         r"calib_imu_to_velo\.txt, calib_velo_to_cam\.txt in .* and did not find calib_velo_to_cam\.txt"):
        read_kitti_raw(drive)
    assert read_kitti_raw(drive, camera=None).frames is None


def test_missing_camera_or_calibration_key(tmp_path):
    truth = _drive()
    drive = _write_drive(tmp_path, truth)
    _write_calibration(drive.parent)
    _write_images(drive, 2, truth["t_ns"][:3])
    with pytest.raises(ValueError, match=r"image_00: folder does not exist, but image_02 do; pass camera="):
        read_kitti_raw(drive)
    file = drive.parent / "calib_cam_to_cam.txt"
    file.write_text(file.read_text().replace("P_rect_02: ", "P_rect_02: x"))
    with pytest.raises(ValueError, match=r"calib_cam_to_cam\.txt: line \d+: P_rect_02:.*expected 12 finite numbers"):
        read_kitti_raw(drive, camera=2)


def test_read_sequence_detects_a_kitti_drive(tmp_path):
    drive = _write_drive(tmp_path, _drive())
    assert detect_format(drive) == "kitti"
    seq = read_sequence(drive, max_imu_gap_s=0.5)
    assert seq.imu.max_gap_s == 0.5 and seq.metadata["format"] == "kitti"
