"""The flowins folder format: exact round trips, hand-written files, and every bad input."""
from __future__ import annotations

import sys
import types
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml

from flowins.data.folder import read_folder, write_folder, write_frame_images
from flowins.data.read import detect_format, read_sequence
from flowins.data.sequence import CameraFrames, PinholeCamera, Sequence, Tracks
from flowins.data.streams import GnssStream, ImuStream, PoseStream
from flowins.geometry.camera import RigidTransform

H, W = 6, 8

CALIBRATION = """\
camera:
  width: 8
  height: 6
  fx: 5.0
  fy: 5.5
  cx: 3.5
  cy: 2.5
imu_to_camera:
  rotation: [1.0, 0.0, 0.0, 0.0]
  translation: [0.0, 0.0, 0.0]
"""

IMU = """\
t,ax,ay,az,wx,wy,wz
0.0,0.1,0.2,9.81,0.01,0.02,0.03
0.01,0.1,0.2,9.8,0.01,0.02,0.03
0.02,0.1,0.2,9.79,0.01,0.02,0.03
"""


def _image(seed: int, h: int = H, w: int = W) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def _make_sequence(tmp_path: Path, *, with_quat: bool = True, n_imu: int = 50) -> Sequence:
    """A sequence with every part; awkward floats (1/3, 0.1, tiny, huge) everywhere."""
    g = torch.Generator().manual_seed(0)
    t = 1e9 + torch.cumsum(torch.full((n_imu,), 0.005, dtype=torch.float64) + 1e-4 * torch.rand(n_imu, generator=g, dtype=torch.float64), 0)
    acc = torch.randn(n_imu, 3, generator=g, dtype=torch.float64) + torch.tensor([0.0, 0.0, 9.81])
    acc[0] = torch.tensor([1.0 / 3.0, 1e-300, 9.81])
    gyro = 0.1 * torch.randn(n_imu, 3, generator=g, dtype=torch.float64)
    imu = ImuStream(t, acc, gyro)
    src = tmp_path / "src_images"
    src.mkdir()
    files = []
    for i in range(4):
        f = src / f"img_{i}.png"
        cv2.imwrite(str(f), _image(i))
        files.append(f)
    t_frames = t[[1, 10, 20, 30]]
    frames = CameraFrames(t_frames, files=tuple(files))
    tracks = Tracks(
        torch.cat([t_frames[:2].repeat_interleave(3), t_frames[2:3]]),
        torch.tensor([0, 5, 7, 0, 5, 9, 11]),
        torch.rand(7, 2, generator=g, dtype=torch.float64) * torch.tensor([W - 1.0, H - 1.0]),
    )
    gnss = GnssStream(
        t[[0, 25]], torch.tensor([60.1699, -33.9]), torch.tensor([24.9384, 151.2]),
        torch.tensor([12.3456789, -1.0 / 7.0]), torch.tensor([3.0, 2.5]), torch.tensor([5.0, 4.1]),
    )
    quat = torch.randn(n_imu, 4, generator=g, dtype=torch.float64) if with_quat else None
    groundtruth = PoseStream(t, torch.randn(n_imu, 3, generator=g, dtype=torch.float64) * 100, quat)
    camera = PinholeCamera(W, H, 5.123456789012345, 5.5, 3.5 + 1 / 3, 2.5, (0.1, -0.02, 1e-4, -2e-4, 1 / 3))
    q_ic = torch.randn(4, generator=g, dtype=torch.float64)
    transform = RigidTransform(q_ic / q_ic.norm(), torch.tensor([0.01, -0.2, 1 / 3], dtype=torch.float64))
    metadata = {"device": "test", "rate": torch.tensor(200.0), "noise": np.array([0.1, 0.2]), "nested": {"k": (1, 2)}}
    return Sequence(
        imu, name="synthetic", camera=camera, imu_to_camera=transform, frames=frames, tracks=tracks,
        gnss=gnss, groundtruth=groundtruth, metadata=metadata,
    )


def _write_minimal(folder: Path, imu: str = IMU, **files: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "imu.csv").write_text(imu)
    for name, text in files.items():
        (folder / name.replace("_csv", ".csv").replace("_yaml", ".yaml")).write_text(text)
    return folder


# ---------------------------------------------------------------------------
# Round trips (independent truth: the in-memory arrays written)
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("with_quat", [True, False])
def test_round_trip_is_bit_exact(tmp_path, with_quat):
    seq = _make_sequence(tmp_path, with_quat=with_quat)
    out = write_folder(seq, tmp_path / "out")
    back = read_folder(out)

    assert torch.equal(back.imu.t_s, seq.imu.t_s)
    assert torch.equal(back.imu.acc_mps2, seq.imu.acc_mps2)
    assert torch.equal(back.imu.gyro_rps, seq.imu.gyro_rps)
    for key in ("t_s", "lat_deg", "lon_deg", "alt_m", "h_acc_m", "v_acc_m"):
        assert torch.equal(getattr(back.gnss, key), getattr(seq.gnss, key)), key
    assert torch.equal(back.groundtruth.t_s, seq.groundtruth.t_s)
    assert torch.equal(back.groundtruth.pos_m, seq.groundtruth.pos_m)
    if with_quat:
        assert torch.equal(back.groundtruth.quat_wxyz, seq.groundtruth.quat_wxyz)
    else:
        assert back.groundtruth.quat_wxyz is None
        assert (out / "groundtruth.csv").read_text().splitlines()[1].endswith(",,,,")
    assert torch.equal(back.tracks.t_s, seq.tracks.t_s)
    assert torch.equal(back.tracks.track_id, seq.tracks.track_id)
    assert torch.equal(back.tracks.uv_px, seq.tracks.uv_px)
    assert torch.equal(back.frames.t_s, seq.frames.t_s)
    assert [f.name for f in back.frames.files] == [f.name for f in seq.frames.files]
    for i in range(len(seq.frames)):
        assert torch.equal(back.frames.read(i), seq.frames.read(i))
    assert back.camera == seq.camera
    assert torch.equal(back.imu_to_camera.rotation_wxyz, seq.imu_to_camera.rotation_wxyz)
    assert torch.equal(back.imu_to_camera.translation_m, seq.imu_to_camera.translation_m)
    assert back.metadata == {"device": "test", "rate": 200.0, "noise": [0.1, 0.2], "nested": {"k": [1, 2]}}
    assert back.name == "out" and back.sources == seq.sources


def test_round_trip_of_a_video(tmp_path):
    seq = _make_sequence(tmp_path)
    video = tmp_path / "movie.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (W, H))
    assert writer.isOpened()
    for i in range(5):
        writer.write(np.full((H, W, 3), 40 * i, dtype=np.uint8))
    writer.release()
    frames = CameraFrames(seq.frames.t_s[:3], video=video, indices=torch.tensor([0, 2, 4]))
    seq = Sequence(seq.imu, camera=seq.camera, imu_to_camera=seq.imu_to_camera, frames=frames)
    out = write_folder(seq, tmp_path / "out")
    assert (out / "frames.mp4").read_bytes() == video.read_bytes()
    assert (out / "frames.csv").read_text().splitlines()[0] == "t,index"
    back = read_folder(out)
    assert torch.equal(back.frames.t_s, frames.t_s)
    assert torch.equal(back.frames.indices, torch.tensor([0, 2, 4]))
    assert abs(int(back.frames.read(1).float().mean()) - 80) <= 3  # video frame 2 is gray 80 (lossy codec)


def test_clashing_frame_names_are_renumbered(tmp_path):
    seq = _make_sequence(tmp_path)
    files = []
    for i in range(4):
        (tmp_path / f"d{i}").mkdir()
        f = tmp_path / f"d{i}" / "frame.png"
        cv2.imwrite(str(f), _image(10 + i))
        files.append(f)
    frames = CameraFrames(seq.frames.t_s, files=tuple(files))
    seq = Sequence(seq.imu, camera=seq.camera, imu_to_camera=seq.imu_to_camera, frames=frames)
    back = read_folder(write_folder(seq, tmp_path / "out"))
    assert [f.name for f in back.frames.files] == ["000000.png", "000001.png", "000002.png", "000003.png"]
    for i in range(4):
        assert torch.equal(back.frames.read(i), torch.from_numpy(cv2.cvtColor(_image(10 + i), cv2.COLOR_BGR2RGB)))


def test_write_frame_images_then_write_folder_in_place(tmp_path):
    images = [_image(i) for i in range(3)]  # RGB
    t = torch.tensor([0.005, 0.01, 0.015], dtype=torch.float64)
    out = tmp_path / "sim"
    frames = write_frame_images(out, iter(images), t)
    assert (out / "frames.csv").read_text().splitlines() == ["t,file", "0.005,000000.png", "0.01,000001.png", "0.015,000002.png"]
    bgr = cv2.imread(str(out / "frames" / "000001.png"))
    assert np.array_equal(bgr[:, :, ::-1], images[1])  # stored as a normal (BGR-on-disk) PNG
    imu = ImuStream(torch.linspace(0, 0.02, 5, dtype=torch.float64), torch.tensor([[0, 0, 9.81]] * 5), torch.zeros(5, 3))
    camera = PinholeCamera(W, H, 5.0, 5.0, 3.5, 2.5)
    seq = Sequence(imu, camera=camera, imu_to_camera=RigidTransform.identity(), frames=frames)
    write_folder(seq, out, overwrite=True)  # the images are the sequence's own: they stay
    back = read_folder(out)
    for i in range(3):
        assert torch.equal(back.frames.read(i), torch.from_numpy(images[i]))


def test_no_copy_keeps_frames_already_in_the_folder(tmp_path):
    out = tmp_path / "sim"
    (out / "frames").mkdir(parents=True)
    images = [_image(20 + i) for i in range(2)]  # BGR as written by cv2
    files = []
    for i, image in enumerate(images):
        files.append(out / "frames" / f"{i:06d}.png")
        cv2.imwrite(str(files[-1]), image)
    (out / "flow").mkdir()  # not the format's: stays
    imu = ImuStream(torch.linspace(0, 0.02, 5, dtype=torch.float64), torch.tensor([[0, 0, 9.81]] * 5), torch.zeros(5, 3))
    frames = CameraFrames(torch.tensor([0.0, 0.01], dtype=torch.float64), files=tuple(files))
    seq = Sequence(imu, camera=PinholeCamera(W, H, 5.0, 5.0, 3.5, 2.5), imu_to_camera=RigidTransform.identity(), frames=frames)
    write_folder(seq, out, overwrite=True, copy_frames=False)
    assert sorted(p.name for p in out.iterdir()) == ["calibration.yaml", "flow", "frames", "frames.csv", "imu.csv"]
    back = read_folder(out)
    for i in range(2):
        assert torch.equal(back.frames.read(i), torch.from_numpy(cv2.cvtColor(images[i], cv2.COLOR_BGR2RGB)))


def test_write_frame_images_checks_counts(tmp_path):
    with pytest.raises(ValueError, match="2 images for 3 timestamps"):
        write_frame_images(tmp_path / "a", [_image(0), _image(1)], [0.0, 0.1, 0.2])
    with pytest.raises(ValueError, match=r"image 0 has shape \(6, 8\)"):
        write_frame_images(tmp_path / "b", [_image(0)[:, :, 0]], [0.0])


def test_write_refuses_a_non_empty_folder_and_overwrite_removes_stale_parts(tmp_path):
    seq = _make_sequence(tmp_path)
    out = write_folder(seq, tmp_path / "out")
    small = Sequence(seq.imu)
    with pytest.raises(ValueError, match="not empty; pass overwrite=True"):
        write_folder(small, out)
    write_folder(small, out, overwrite=True)
    assert sorted(p.name for p in out.iterdir()) == ["imu.csv"]
    assert read_folder(out).sources == ("imu",)


def test_no_frames_keeps_the_calibration(tmp_path):
    seq = _make_sequence(tmp_path)
    out = write_folder(seq, tmp_path / "out", copy_frames=False)
    assert not (out / "frames.csv").exists() and not (out / "frames").exists()
    back = read_folder(out)
    assert back.frames is None and back.camera == seq.camera and back.tracks is not None


def test_write_checks_before_removing_anything(tmp_path):
    seq = _make_sequence(tmp_path)
    out = write_folder(seq, tmp_path / "out", copy_frames=False)
    before = sorted(p.name for p in out.iterdir())
    seq.frames.files[2].unlink()
    with pytest.raises(ValueError, match=r"frame source .*img_2\.png \(row 2, 0-based\) does not exist"):
        write_folder(seq, out, overwrite=True)
    bad = Sequence(seq.imu, metadata={"ok": 1, "sub": {"bad": object()}})
    with pytest.raises(ValueError, match=r"metadata\.sub\.bad: value of type object"):
        write_folder(bad, out, overwrite=True)
    assert sorted(p.name for p in out.iterdir()) == before


def test_metadata_dates_round_trip(tmp_path):
    import datetime

    seq = Sequence(_make_sequence(tmp_path).imu, metadata={"recorded": datetime.date(2020, 5, 17), "path": tmp_path})
    back = read_folder(write_folder(seq, tmp_path / "out"))
    assert back.metadata == {"recorded": datetime.date(2020, 5, 17), "path": str(tmp_path)}


# ---------------------------------------------------------------------------
# Reading hand-written files (independent truth: the literal text)
# ---------------------------------------------------------------------------


def test_reads_hand_written_folder(tmp_path):
    folder = _write_minimal(
        tmp_path / "seq",
        gnss_csv="t,lat,lon,alt,h_acc,v_acc\n0.01,60.5,25.25,10.0,3.0,5.0\n",
        groundtruth_csv="t,px,py,pz,qw,qx,qy,qz\n0.0,1,2,3,,,,\n\n0.02,4,5,6,,,,\n",
        metadata_yaml="device: phone\nrate_hz: 100\n",
    )
    seq = read_folder(folder)
    assert torch.equal(seq.imu.t_s, torch.tensor([0.0, 0.01, 0.02], dtype=torch.float64))
    assert torch.equal(seq.imu.acc_mps2[:, 2], torch.tensor([9.81, 9.8, 9.79], dtype=torch.float64))
    assert torch.equal(seq.imu.gyro_rps[1], torch.tensor([0.01, 0.02, 0.03], dtype=torch.float64))
    assert float(seq.gnss.lat_deg[0]) == 60.5 and float(seq.gnss.v_acc_m[0]) == 5.0
    assert seq.groundtruth.quat_wxyz is None
    assert torch.equal(seq.groundtruth.pos_m, torch.tensor([[1.0, 2, 3], [4, 5, 6]], dtype=torch.float64))
    assert seq.metadata == {"device": "phone", "rate_hz": 100}
    assert seq.sources == ("imu", "gnss", "groundtruth")


# ---------------------------------------------------------------------------
# Bad input: file, line and what was expected
# ---------------------------------------------------------------------------


def test_missing_imu(tmp_path):
    (tmp_path / "seq").mkdir()
    with pytest.raises(ValueError, match=r"imu\.csv: missing; expected imu\.csv \(t,ax,ay,az,wx,wy,wz\)"):
        read_folder(tmp_path / "seq")


def test_misnamed_columns(tmp_path):
    folder = _write_minimal(tmp_path / "seq", IMU.replace("t,ax", "time,ax", 1))
    with pytest.raises(ValueError, match=r"imu\.csv: line 1: header is 'time,ax,ay,az,wx,wy,wz'; expected 't,ax,ay,az,wx,wy,wz'"):
        read_folder(folder)


def test_non_numeric_cell(tmp_path):
    folder = _write_minimal(tmp_path / "seq", IMU.replace("9.8,", "9.8x,"))
    with pytest.raises(ValueError, match=r"imu\.csv: line 3: column 'az' is '9\.8x'; expected a number \(m/s²\)"):
        read_folder(folder)


def test_wrong_column_count(tmp_path):
    folder = _write_minimal(tmp_path / "seq", IMU + "0.03,0.1,0.2,9.8,0.01,0.02\n")
    with pytest.raises(ValueError, match=r"imu\.csv: line 5: 6 comma-separated cells; expected 7"):
        read_folder(folder)


def test_non_increasing_timestamps_name_file_and_line(tmp_path):
    folder = _write_minimal(tmp_path / "seq", IMU.replace("\n0.02,", "\n0.01,"))
    with pytest.raises(ValueError, match=r"imu\.csv: timestamps are not strictly increasing at line 4"):
        read_folder(folder)
    gnss = "t,lat,lon,alt,h_acc,v_acc\n0.01,60,25,1,3,5\n\n0.005,60,25,1,3,5\n"
    folder = _write_minimal(tmp_path / "seq2", gnss_csv=gnss)
    with pytest.raises(ValueError, match=r"gnss\.csv: timestamps are not strictly increasing at line 4"):
        read_folder(folder)


def test_imu_gap_names_lines(tmp_path):
    folder = _write_minimal(tmp_path / "seq", IMU.replace("\n0.02,", "\n0.5,"))
    with pytest.raises(ValueError, match=r"imu\.csv: gap of 0\.49 s between lines 3 and 4"):
        read_folder(folder)
    assert len(read_folder(folder, max_imu_gap_s=1.0).imu) == 3


def test_gnss_out_of_range_names_line(tmp_path):
    folder = _write_minimal(tmp_path / "seq", gnss_csv="t,lat,lon,alt,h_acc,v_acc\n0.0,95,25,1,3,5\n")
    with pytest.raises(ValueError, match=r"gnss\.csv: lat_deg=95\.0 at line 2; expected a value in \[-90, 90\]"):
        read_folder(folder)


def test_non_finite_value_names_line(tmp_path):
    folder = _write_minimal(tmp_path / "seq", IMU.replace(",9.8,", ",nan,"))
    with pytest.raises(ValueError, match=r"imu\.csv: acc_mps2 has a non-finite value \(nan\) at line 3, column 2"):
        read_folder(folder)


def test_non_unit_quaternions_are_normalised(tmp_path):
    gt = "t,px,py,pz,qw,qx,qy,qz\n0.0,1,2,3,2,0,0,0\n0.01,1,2,3,1,0,0,0\n0.02,1,2,3,0,3,0,4\n"
    seq = read_folder(_write_minimal(tmp_path / "seq", groundtruth_csv=gt))
    expected = torch.tensor([[1.0, 0, 0, 0], [1, 0, 0, 0], [0, 0.6, 0, 0.8]], dtype=torch.float64)
    assert torch.equal(seq.groundtruth.quat_wxyz, expected)


def test_mixed_empty_quaternions(tmp_path):
    gt = "t,px,py,pz,qw,qx,qy,qz\n0.0,1,2,3,1,0,0,0\n0.01,1,2,3,,,,\n"
    folder = _write_minimal(tmp_path / "seq", groundtruth_csv=gt)
    with pytest.raises(ValueError, match=r"groundtruth\.csv: line 3 has no orientation but line 2 has"):
        read_folder(folder)
    gt = "t,px,py,pz,qw,qx,qy,qz\n0.0,1,2,3,1,0,,0\n"
    folder = _write_minimal(tmp_path / "seq2", groundtruth_csv=gt)
    with pytest.raises(ValueError, match=r"groundtruth\.csv: line 2: some of qw,qx,qy,qz are empty"):
        read_folder(folder)


def test_units_look_like_g(tmp_path):
    in_g = "\n".join(["t,ax,ay,az,wx,wy,wz"] + [f"{0.01 * k},0.01,0.02,1.0,0,0,0" for k in range(5)]) + "\n"
    folder = _write_minimal(tmp_path / "seq", in_g)
    with pytest.raises(ValueError, match=r"imu\.csv: accelerometer magnitude median 1; expected m/s² \(≈9\.81 at rest\); the file looks like it is in g"):
        read_folder(folder)
    assert len(read_folder(folder, check_units=False).imu) == 5
    huge = in_g.replace(",1.0,", ",981.0,")
    with pytest.raises(ValueError, match=r"accelerometer magnitude median 981; expected m/s²"):
        read_folder(_write_minimal(tmp_path / "seq2", huge))


def test_units_look_like_deg_per_s(tmp_path):
    deg = "\n".join(["t,ax,ay,az,wx,wy,wz"] + [f"{0.01 * k},0,0,9.81,30,0,0" for k in range(5)]) + "\n"
    with pytest.raises(ValueError, match=r"imu\.csv: gyroscope magnitude median 30; expected rad/s; the file looks like it is in deg/s"):
        read_folder(_write_minimal(tmp_path / "seq", deg))


def _frames_folder(tmp_path: Path, image_size=(H, W), frames_csv="t,file\n0.0,a.png\n0.01,b.png\n") -> Path:
    folder = _write_minimal(tmp_path / "seq", frames_csv=frames_csv, calibration_yaml=CALIBRATION)
    (folder / "frames").mkdir()
    for name in ("a.png", "b.png"):
        cv2.imwrite(str(folder / "frames" / name), _image(0, *image_size))
    return folder


def test_frames_read_with_calibration(tmp_path):
    seq = read_folder(_frames_folder(tmp_path))
    assert seq.camera == PinholeCamera(8, 6, 5.0, 5.5, 3.5, 2.5)
    assert torch.equal(seq.imu_to_camera.rotation_wxyz, torch.tensor([1.0, 0, 0, 0], dtype=torch.float64))
    expected = torch.from_numpy(cv2.cvtColor(_image(0), cv2.COLOR_BGR2RGB))
    assert torch.equal(seq.frames.read(1), expected)


def test_missing_frame_names_file_and_line(tmp_path):
    folder = _frames_folder(tmp_path, frames_csv="t,file\n0.0,a.png\n0.01,c.png\n")
    with pytest.raises(ValueError, match=r"frames\.csv: line 3: image file .*c\.png does not exist"):
        read_folder(folder)
    assert read_folder(folder, check_frames=False).frames.files[1].name == "c.png"


def test_missing_video(tmp_path):
    folder = _frames_folder(tmp_path, frames_csv="t,index\n0.0,0\n0.01,1\n")
    with pytest.raises(ValueError, match=r"frames\.csv: header 't,index' needs the video .*frames\.mp4"):
        read_folder(folder)


def test_image_size_disagrees_with_calibration(tmp_path):
    folder = _frames_folder(tmp_path, image_size=(H + 1, W))
    with pytest.raises(ValueError, match=r"frames\.csv: .*a\.png is 8x7 \(WxH\); the calibration expects 8x6"):
        read_folder(folder)


def test_frames_need_calibration(tmp_path):
    folder = _frames_folder(tmp_path)
    (folder / "calibration.yaml").unlink()
    with pytest.raises(ValueError, match=r"frames\.csv: needs the camera calibration, but calibration\.yaml is missing"):
        read_folder(folder)


@pytest.mark.parametrize(
    "old, new, message",
    [
        ("  fx: 5.0", "  fx: five", r"calibration\.yaml: line 4: camera\.fx is 'five'; expected a number"),
        ("  fy: 5.5\n", "", r"calibration\.yaml: line 1: camera has no 'fy'"),
        ("  cy: 2.5\n", "  cy: 2.5\n  distorsion: [0, 0, 0, 0]\n", r"calibration\.yaml: line 8: camera has unknown key 'distorsion'"),
        ("[1.0, 0.0, 0.0, 0.0]", "[1.0, 0.0, 0.0]", r"calibration\.yaml: line 9: imu_to_camera\.rotation is \[1\.0, 0\.0, 0\.0\]; expected a list of 4 numbers"),
        ("[1.0, 0.0, 0.0, 0.0]", "[2.0, 0.0, 0.0, 0.0]", r"calibration\.yaml: line 9: RigidTransform: rotation quaternion .* unit norm"),
        ("  width: 8", "  width: -8", r"calibration\.yaml: line 1: camera: width=-8; expected a positive integer"),
        ("  width: 8", "  width: [8", r"calibration\.yaml: line \d+: not valid YAML"),
    ],
)
def test_bad_calibration(tmp_path, old, new, message):
    folder = _frames_folder(tmp_path)
    assert old in CALIBRATION
    (folder / "calibration.yaml").write_text(CALIBRATION.replace(old, new))
    with pytest.raises(ValueError, match=message):
        read_folder(folder)


def test_tracks_bad_id_and_duplicate(tmp_path):
    folder = _write_minimal(tmp_path / "seq", tracks_csv="t,track_id,u,v\n0.0,1,2.5,3.5\n0.0,1.5,2,3\n", calibration_yaml=CALIBRATION)
    with pytest.raises(ValueError, match=r"tracks\.csv: line 3: column 'track_id' is '1\.5'; expected a non-negative integer"):
        read_folder(folder)
    (folder / "tracks.csv").write_text("t,track_id,u,v\n0.0,1,2.5,3.5\n0.0,1,2,3\n")
    with pytest.raises(ValueError, match=r"tracks\.csv: line 3: track_id 1 appears twice"):
        read_folder(folder)


def test_metadata_must_be_a_mapping(tmp_path):
    folder = _write_minimal(tmp_path / "seq", metadata_yaml="- a\n- b\n")
    with pytest.raises(ValueError, match=r"metadata\.yaml: line 1: the document is a list; expected a mapping"):
        read_folder(folder)


def test_empty_and_header_only_files(tmp_path):
    with pytest.raises(ValueError, match=r"imu\.csv: the file is empty; expected a header row"):
        read_folder(_write_minimal(tmp_path / "a", ""))
    with pytest.raises(ValueError, match=r"imu\.csv: no data rows after the header \(line 1\)"):
        read_folder(_write_minimal(tmp_path / "b", "t,ax,ay,az,wx,wy,wz\n"))


# ---------------------------------------------------------------------------
# read_sequence dispatch
# ---------------------------------------------------------------------------


def test_read_sequence_dispatches_flowins_folder(tmp_path):
    folder = _write_minimal(tmp_path / "seq")
    assert detect_format(folder) == "flowins"
    seq = read_sequence(folder, max_imu_gap_s=0.5)
    assert torch.equal(seq.imu.t_s, torch.tensor([0.0, 0.01, 0.02], dtype=torch.float64))
    assert seq.imu.max_gap_s == 0.5


@pytest.mark.parametrize("layout, module, function", [
    (("mav0",), "flowins.data.euroc", "read_euroc"),
    (("imu0", "cam0"), "flowins.data.euroc", "read_euroc"),
    (("iphone",), "flowins.data.advio", "read_advio"),
])
def test_read_sequence_dispatches_other_layouts(tmp_path, monkeypatch, layout, module, function):
    for name in layout:
        (tmp_path / name).mkdir()
    calls = []
    fake = types.ModuleType(module)
    setattr(fake, function, lambda path, **kw: calls.append((Path(path), kw)) or "sequence")
    monkeypatch.setitem(sys.modules, module, fake)
    assert read_sequence(tmp_path, check_frames=False) == "sequence"
    assert calls == [(tmp_path, {"check_frames": False})]


def test_read_sequence_unknown_layout(tmp_path):
    (tmp_path / "cam0").mkdir()
    with pytest.raises(ValueError, match=r"unknown sequence layout; looked for imu\.csv .*mav0/, or imu0/ and cam0/ .*iphone/"):
        read_sequence(tmp_path)
    with pytest.raises(ValueError, match="not a folder"):
        read_sequence(tmp_path / "nothing")


# ---------------------------------------------------------------------------
# camera_to_imu: the inverse of imu_to_camera (independent truth: Rodrigues' formula)
# ---------------------------------------------------------------------------

_AXIS = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
_ANGLE = 1.9
_Q_CAM_IN_IMU = [np.cos(_ANGLE / 2), *(np.sin(_ANGLE / 2) * _AXIS)]  # camera's orientation in the IMU frame
_T_CAM_IN_IMU = np.array([0.05, -0.02, 0.11])  # camera's position in the IMU frame [m]


def _rodrigues(axis, angle):
    Kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * Kx + (1 - np.cos(angle)) * Kx @ Kx


def _extrinsic_yaml(key, q, t, digits=None):
    fmt = (lambda v: repr(float(v))) if digits is None else (lambda v: f"{float(v):.{digits}f}")
    return f"{key}:\n  rotation: [{', '.join(map(fmt, q))}]\n  translation: [{', '.join(map(fmt, t))}]\n"


def _camera_yaml():
    return CALIBRATION.split("imu_to_camera:")[0]


def test_camera_to_imu_alone_is_inverted(tmp_path):
    folder = _frames_folder(tmp_path)
    (folder / "calibration.yaml").write_text(_camera_yaml() + _extrinsic_yaml("camera_to_imu", _Q_CAM_IN_IMU, _T_CAM_IN_IMU))
    seq = read_folder(folder)
    points_cam = np.random.default_rng(0).normal(size=(20, 3))
    points_imu = points_cam @ _rodrigues(_AXIS, _ANGLE).T + _T_CAM_IN_IMU  # x_imu = R x_cam + t
    mapped = seq.imu_to_camera.apply(torch.from_numpy(points_imu))
    assert torch.allclose(mapped, torch.from_numpy(points_cam), rtol=0, atol=1e-12)


@pytest.mark.parametrize("digits", [None, 6])  # exact, and printed with six decimals
def test_camera_to_imu_and_imu_to_camera_that_agree(tmp_path, digits):
    R = _rodrigues(_AXIS, _ANGLE)
    q_inverse = [_Q_CAM_IN_IMU[0], *(-np.asarray(_Q_CAM_IN_IMU[1:]))]
    text = (_camera_yaml() + _extrinsic_yaml("imu_to_camera", q_inverse, -R.T @ _T_CAM_IN_IMU, digits)
            + _extrinsic_yaml("camera_to_imu", _Q_CAM_IN_IMU, _T_CAM_IN_IMU, digits))
    folder = _frames_folder(tmp_path)
    (folder / "calibration.yaml").write_text(text)
    written = yaml.safe_load(text)["imu_to_camera"]
    transform = read_folder(folder).imu_to_camera  # imu_to_camera, as written
    assert torch.equal(transform.translation_m, torch.tensor(written["translation"], dtype=torch.float64))
    assert torch.allclose(transform.rotation_wxyz, torch.tensor(written["rotation"], dtype=torch.float64), rtol=0, atol=1e-6)


@pytest.mark.parametrize("rotation_error, translation_error, message", [
    # no rotation error: 0 up to rounding (numpy and torch versions round it to 0 or ~1e-16)
    (0.0, 1e-3, r"by (0|[0-9.]+e-1[5-7]) rad \((0|[0-9.]+e-1[3-5]) deg\) in rotation and 0\.001 m in translation"),
    (1e-3, 0.0, r"by 0\.001 rad \(0\.0573 deg\) in rotation and 4\.44e-05 m in translation"),  # 1e-3 x |t ⊥ axis|
])
def test_camera_to_imu_and_imu_to_camera_that_disagree(tmp_path, rotation_error, translation_error, message):
    R = _rodrigues(_AXIS, _ANGLE)
    q_inverse = [_Q_CAM_IN_IMU[0], *(-np.asarray(_Q_CAM_IN_IMU[1:]))]
    q_off = [np.cos(_ANGLE / 2 + rotation_error / 2), *(np.sin(_ANGLE / 2 + rotation_error / 2) * _AXIS)]
    text = (_camera_yaml() + _extrinsic_yaml("imu_to_camera", q_inverse, -R.T @ _T_CAM_IN_IMU)
            + _extrinsic_yaml("camera_to_imu", q_off, _T_CAM_IN_IMU + [0.0, translation_error, 0.0]))
    folder = _frames_folder(tmp_path)
    (folder / "calibration.yaml").write_text(text)
    with pytest.raises(ValueError, match=r"calibration\.yaml: line 11: imu_to_camera and camera_to_imu disagree: .*" + message
                       + r".*within 1e-05 rad and 1e-05 m"):
        read_folder(folder)
