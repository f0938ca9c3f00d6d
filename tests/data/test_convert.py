"""The converter CLI: ``python -m flowins.data.convert SRC OUT [--overwrite] [--no-frames]``."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

from flowins.data.convert import main
from flowins.data.folder import read_folder

IMU_ROWS = [(0.0, 0.1, -0.2, 9.81, 0.01, 0.0, -0.03), (0.1, 0.2, -0.1, 9.79, 0.02, 0.0, -0.02), (0.2, 1 / 3, 0.0, 9.8, 0.0, 0.0, 0.0)]


def _source(folder: Path) -> Path:
    """A hand-written flowins folder: IMU, two frames with calibration, positions-only ground truth."""
    (folder / "frames").mkdir(parents=True)
    (folder / "imu.csv").write_text("t,ax,ay,az,wx,wy,wz\n" + "".join(",".join(map(repr, r)) + "\n" for r in IMU_ROWS))
    (folder / "frames.csv").write_text("t,file\n0.05,a.png\n0.15,b.png\n")
    for name, value in (("a.png", 10), ("b.png", 200)):
        cv2.imwrite(str(folder / "frames" / name), np.full((4, 6, 3), value, dtype=np.uint8))
    (folder / "calibration.yaml").write_text(
        "camera: {width: 6, height: 4, fx: 3.0, fy: 3.0, cx: 2.5, cy: 1.5}\n"
        "imu_to_camera: {rotation: [0.0, 1.0, 0.0, 0.0], translation: [0.1, 0.0, 0.0]}\n"
    )
    (folder / "groundtruth.csv").write_text("t,px,py,pz,qw,qx,qy,qz\n0.0,1.5,2.5,3.5,,,,\n0.2,1.5,2.5,3.75,,,,\n")
    return folder


def test_convert_round_trip(tmp_path, capsys):
    src = _source(tmp_path / "src")
    assert main([str(src), str(tmp_path / "out")]) == 0
    summary = capsys.readouterr().out.strip().splitlines()
    assert summary == ["out: IMU 3 samples over 0.2 s (10 Hz), 2 frames (10.0 fps, 6x4), 2 ground-truth positions"]
    back = read_folder(tmp_path / "out")
    assert torch.equal(back.imu.t_s, torch.tensor([r[0] for r in IMU_ROWS], dtype=torch.float64))
    assert torch.equal(back.imu.acc_mps2, torch.tensor([r[1:4] for r in IMU_ROWS], dtype=torch.float64))
    assert torch.equal(back.imu.gyro_rps, torch.tensor([r[4:] for r in IMU_ROWS], dtype=torch.float64))
    assert torch.equal(back.groundtruth.pos_m, torch.tensor([[1.5, 2.5, 3.5], [1.5, 2.5, 3.75]], dtype=torch.float64))
    assert back.groundtruth.quat_wxyz is None
    assert torch.equal(back.frames.t_s, torch.tensor([0.05, 0.15], dtype=torch.float64))
    assert int(back.frames.read(1)[0, 0, 0]) == 200
    assert torch.equal(back.imu_to_camera.rotation_wxyz, torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=torch.float64))
    assert (back.camera.width, back.camera.height, back.camera.cx) == (6, 4, 2.5)


def test_convert_overwrite_and_no_frames(tmp_path, capsys):
    src = _source(tmp_path / "src")
    out = tmp_path / "out"
    assert main([str(src), str(out)]) == 0
    assert main([str(src), str(out), "--no-frames"]) == 2
    assert "not empty; pass overwrite=True (--overwrite)" in capsys.readouterr().err
    assert main([str(src), str(out), "--no-frames", "--overwrite"]) == 0
    assert not (out / "frames").exists() and not (out / "frames.csv").exists()
    assert capsys.readouterr().out.strip() == "out: IMU 3 samples over 0.2 s (10 Hz), 2 ground-truth positions"


def test_convert_bad_input_exits_2_without_traceback(tmp_path):
    src = _source(tmp_path / "src")
    (src / "imu.csv").write_text("t,ax,ay,az,wx,wy,wz\n0.0,0,0,9.8,0,0,0\n0.1,0,0,oops,0,0,0\n")
    result = subprocess.run(
        [sys.executable, "-m", "flowins.data.convert", str(src), str(tmp_path / "out")],
        capture_output=True, text=True, timeout=60,
    )
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert result.stderr.startswith("error: ") and "imu.csv: line 3: column 'az' is 'oops'" in result.stderr
    assert not (tmp_path / "out").exists()
