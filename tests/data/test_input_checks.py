"""Implausible input stops with an error naming the file and row, or runs with a printed
change: the cases of a corrupted-recording battery, each against the value it corrupts."""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from flowins.data.folder import read_folder
from flowins.data.sequence import CameraFrames, PinholeCamera, Sequence, Tracks, within_imu_span
from flowins.data.streams import GnssStream, ImuStream, PoseStream
from flowins.geometry.camera import RigidTransform
from flowins.ins.imu_model import ImuModel
from flowins.ins.initialization import StillSettings, still_interval
from flowins.evaluation.metrics import truth_extent_problem

H, W = 6, 8
CALIBRATION = """\
camera:
  width: 8
  height: 6
  fx: {fx}
  fy: 5.5
  cx: {cx}
  cy: 2.5
imu_to_camera:
  rotation: [1.0, 0.0, 0.0, 0.0]
  translation: [0.0, 0.0, 0.0]
"""


def _folder(tmp_path: Path, *, fx: float = 5.0, cx: float = 3.5, tracks: str | None = None,
            frame_times: tuple[float, ...] = (0.1, 0.2, 0.3)) -> Path:
    folder = tmp_path / "rec"
    (folder / "frames").mkdir(parents=True)
    t = np.arange(0.0, 1.0, 0.01)
    rows = "\n".join(f"{float(x)!r},0.0,0.0,9.81,0.0,0.0,0.0" for x in t)
    (folder / "imu.csv").write_text("t,ax,ay,az,wx,wy,wz\n" + rows + "\n")
    (folder / "calibration.yaml").write_text(CALIBRATION.format(fx=fx, cx=cx))
    names = []
    for i, _ in enumerate(frame_times):
        cv2.imwrite(str(folder / "frames" / f"{i}.png"), np.zeros((H, W, 3), np.uint8))
        names.append(f"{i}.png")
    (folder / "frames.csv").write_text("t,file\n" + "\n".join(f"{t!r},{n}" for t, n in zip(frame_times, names)) + "\n")
    if tracks is not None:
        (folder / "tracks.csv").write_text("t,track_id,u,v\n" + tracks)
    return folder


# --- calibration: principal point and field of view -------------------------------------------


def test_a_principal_point_outside_the_image_names_the_file_and_key(tmp_path):
    with pytest.raises(ValueError, match=r"calibration\.yaml.*principal point cx=5000 px is outside the image"):
        read_folder(_folder(tmp_path, cx=5000.0))


@pytest.mark.parametrize("fx, fov", [(0.02, 179.4), (60.0, 7.6)])
def test_a_focal_length_giving_an_implausible_field_of_view_is_refused(tmp_path, fx, fov):
    assert math.degrees(2 * math.atan(W / 2 / fx)) == pytest.approx(fov, abs=0.1)  # the truth the message states
    with pytest.raises(ValueError, match=rf"calibration\.yaml.*fx={fx:g} px over an image width of 8 px is a {fov}°"):
        read_folder(_folder(tmp_path, fx=fx))


def test_the_field_of_view_limits_are_inclusive_of_real_cameras():
    # EuRoC cam0 (752x480, fx 458.654): 78.7°; KITTI (1242x375, fx 721.5): 81.4°; a phone's 1920 px at fx 1500: 65°
    for w, h, f in ((752, 480, 458.654), (1242, 375, 721.5377), (1920, 1080, 1500.0)):
        PinholeCamera(w, h, f, f, w / 2, h / 2)


# --- tracks: on the image, on the frame clock --------------------------------------------------


def test_a_track_point_outside_the_image_names_the_line(tmp_path):
    tracks = "0.1,0,1.0,1.0\n0.1,1,2000.0,3.0\n0.2,0,1.5,1.0\n"
    with pytest.raises(ValueError, match=r"tracks\.csv: line 3: point \(u, v\) = \(2000, 3\) px is outside the 8x6 image"):
        read_folder(_folder(tmp_path, tracks=tracks))


def test_a_track_point_on_the_edge_within_the_margin_is_kept(tmp_path):
    seq = read_folder(_folder(tmp_path, tracks="0.1,0,-1.5,0.0\n0.2,0,8.5,5.5\n"))
    assert seq.tracks.uv_px[:, 0].tolist() == [-1.5, 8.5]


def test_track_times_off_the_frame_times_name_the_line(tmp_path):
    tracks = "0.1,0,1.0,1.0\n0.233,0,1.5,1.0\n"  # 33 ms after the frame at 0.2 s
    with pytest.raises(ValueError, match=r"tracks\.csv: line 3: time 0\.233 s is 33\.000 ms from the nearest frame time"):
        read_folder(_folder(tmp_path, tracks=tracks))


def test_without_frames_the_tracks_times_are_the_frame_clock():
    tracks = Tracks(torch.tensor([0.1, 0.133], dtype=torch.float64), torch.tensor([0, 0]), torch.tensor([[1.0, 1.0], [1.5, 1.0]]),
                    image_size=(H, W))
    assert tracks.frame_times.tolist() == [0.1, 0.133]


# --- one time-span policy for every input stream ------------------------------------------------


def _sequence(*, frames_t=None, gnss_t=None) -> Sequence:
    t = torch.arange(0.0, 10.0, 0.01, dtype=torch.float64)
    imu = ImuStream(t, torch.tensor([0.0, 0.0, 9.81]).expand(len(t), 3), torch.zeros(len(t), 3), name="imu.csv")
    camera = transform = frames = gnss = None
    if frames_t is not None:
        frames = CameraFrames(torch.tensor(frames_t, dtype=torch.float64), files=tuple(Path(f"{i}.png") for i in range(len(frames_t))),
                              name="frames.csv", check_files=False)
        camera = PinholeCamera(W, H, 5.0, 5.0, 3.5, 2.5)
        transform = RigidTransform(torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    if gnss_t is not None:
        n = len(gnss_t)
        gnss = GnssStream(torch.tensor(gnss_t, dtype=torch.float64), torch.full((n,), 60.0), torch.full((n,), 25.0),
                          torch.zeros(n), torch.ones(n), torch.ones(n), name="gnss.csv")
    return Sequence(imu, camera=camera, imu_to_camera=transform, frames=frames, gnss=gnss,
                    groundtruth=PoseStream(t, torch.zeros(len(t), 3)))


def test_frames_after_the_imu_are_an_error_naming_the_row_and_both_spans():
    frames_t = [float(x) for x in np.arange(3.0, 13.0, 0.1)]  # 3 s later than the IMU's 10 s
    with pytest.raises(ValueError, match=r"frames\.csv: row 70 \(0-based\) at t = 10\.000 s is outside the IMU's time "
                                         r"span \[0\.000, 9\.990\] s \(frames span \[3\.000, 12\.900\] s; 0 rows before, 30 "
                                         r"after\).*sequence\.crop=true"):
        within_imu_span(_sequence(frames_t=frames_t))


def test_gnss_6_ms_early_is_the_same_error_and_crop_crops_every_stream_and_says_so():
    frames_t = [float(x) for x in np.arange(3.0, 13.0, 0.1)]
    seq = _sequence(frames_t=frames_t, gnss_t=[-0.006, 1.0, 2.0])
    with pytest.raises(ValueError, match=r"gnss\.csv: row 0 \(0-based\) at t = -0\.006 s is outside"):
        within_imu_span(_sequence(gnss_t=[-0.006, 1.0, 2.0]))
    cropped, notes = within_imu_span(seq, crop=True)
    assert cropped.frames.t_s.tolist() == frames_t[:70] and cropped.gnss.t_s.tolist() == [1.0, 2.0]
    assert notes == [
        "frames.csv: cropped 0 rows before and 30 after the IMU span [0.000, 9.990] s (sequence.crop=true); 70 of 100 kept",
        "gnss.csv: cropped 1 rows before and 0 after the IMU span [0.000, 9.990] s (sequence.crop=true); 2 of 3 kept",
    ]
    assert within_imu_span(_sequence(gnss_t=[0.0, 9.99])) [1] == []  # the span's ends are inside


# --- IMU readings within the sensor's range ----------------------------------------------------


def _imu(acc=None, gyro=None, n=500) -> ImuStream:
    t = torch.arange(n, dtype=torch.float64) * 0.01
    a = torch.tensor([0.0, 0.0, 9.81]).expand(n, 3).clone() if acc is None else acc
    w = torch.zeros(n, 3) if gyro is None else gyro
    return ImuStream(t, a, w, name="imu.csv")


PHONE = ImuModel("phone", 1e-3, 1e-4, acc_range_mps2=156.9, gyro_range_rps=34.9)


def test_one_accelerometer_sample_of_1e6_names_the_sample_and_the_key():
    acc = torch.tensor([0.0, 0.0, 9.81]).expand(500, 3).clone()
    acc[123, 0] = 1e6
    with pytest.raises(ValueError, match=r"imu\.csv: sample 123 \(0-based, t = 1\.230 s\): accelerometer reading 1e\+06 "
                                         r"m/s² beyond the sensor's range ±156\.9 m/s² \(imu\.acc_range_mps2, preset phone\)"):
        PHONE.check_readings(_imu(acc=acc))


def test_readings_at_the_range_pass_and_null_leaves_them_unchecked():
    acc = torch.tensor([0.0, 0.0, 9.81]).expand(500, 3).clone()
    acc[7, 1] = 156.9  # a saturated reading: at the range, not beyond it
    PHONE.check_readings(_imu(acc=acc))
    acc[7, 1] = 1e6
    ImuModel("free", 1e-3, 1e-4).check_readings(_imu(acc=acc))


def test_a_gyroscope_in_deg_per_s_is_named_as_such():
    t = torch.arange(500, dtype=torch.float64) * 0.01
    walk_rps = torch.stack([0.8 * torch.sin(2 * t), 1.2 * torch.sin(3 * t + 1), 0.3 * torch.cos(t)], -1)
    with pytest.raises(ValueError, match=r"gyroscope reading .* rad/s beyond .*imu\.gyro_range_rps.*look like deg/s"):
        PHONE.check_readings(_imu(gyro=torch.rad2deg(walk_rps)))
    PHONE.check_readings(_imu(gyro=walk_rps))  # the same motion in rad/s passes


def test_a_still_detector_stopped_by_the_gyroscope_alone_suggests_deg_per_s():
    t = torch.arange(1000, dtype=torch.float64) * 0.01
    acc = torch.tensor([0.0, 0.0, 9.80665]).expand(1000, 3)
    gyro = torch.zeros(1000, 3)
    gyro[600:, 2] = math.degrees(0.01)  # a 0.01 rad/s bias step, read in deg/s: 0.57
    still = still_interval(t, acc, gyro, StillSettings())
    assert "low-passed rate moved" in still.reason and "deg/s" in still.reason
    acc2 = acc.clone()
    acc2[600:, 0] = 2.0  # the specific force moves too: a real motion, no unit hint
    assert "deg/s" not in still_interval(t, acc2, gyro, StillSettings()).reason


# --- ground truth that does not move -----------------------------------------------------------


def test_a_ground_truth_that_does_not_move_is_named_before_the_run():
    t = torch.arange(100, dtype=torch.float64) * 0.1
    still = PoseStream(t, 0.003 * torch.randn(100, 3, dtype=torch.float64), name="groundtruth.csv")
    moving = PoseStream(t, torch.stack([t, 0 * t, 0 * t], -1), name="groundtruth.csv")
    assert "groundtruth.csv: the ground truth stays within" in truth_extent_problem(still)
    assert truth_extent_problem(moving) is None and truth_extent_problem(None) is None
