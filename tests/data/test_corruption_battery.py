"""A battery of corrupted recordings: every input file of the folder format, each with the
corruptions a real recording shows. Each must stop with a ValueError that names the file
and, for a row, its line, and nothing in a file may run code.

The truth of each case is the corruption itself: the test writes it at a known line.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from flowins.data.folder import read_folder

H, W = 6, 8
N_IMU = 200  # 2 s at 100 Hz
FRAME_T = (0.5, 0.6, 0.7)


def _valid(folder: Path) -> dict[str, str]:
    """The text of each file of a small valid recording."""
    imu = ["t,ax,ay,az,wx,wy,wz"] + [f"{0.01 * i!r},0.0,0.1,9.81,0.001,0.0,0.0" for i in range(N_IMU)]
    frames = ["t,file"] + [f"{t!r},{i}.png" for i, t in enumerate(FRAME_T)]
    tracks = ["t,track_id,u,v"] + [f"{t!r},{k},{1.0 + k},{2.0 + 0.1 * i}" for i, t in enumerate(FRAME_T) for k in range(3)]
    gnss = ["t,lat,lon,alt,h_acc,v_acc"] + [f"{0.1 + 0.5 * i!r},60.0,25.0,10.0,3.0,5.0" for i in range(3)]
    truth = ["t,px,py,pz,qw,qx,qy,qz"] + [f"{0.01 * i!r},{0.01 * i!r},0.0,0.0,1.0,0.0,0.0,0.0" for i in range(N_IMU)]
    calibration = ("camera:\n  width: 8\n  height: 6\n  fx: 5.0\n  fy: 5.5\n  cx: 3.5\n  cy: 2.5\n"
                   "imu_to_camera:\n  rotation: [1.0, 0.0, 0.0, 0.0]\n  translation: [0.0, 0.0, 0.0]\n")
    (folder / "frames").mkdir(parents=True, exist_ok=True)
    for i in range(len(FRAME_T)):
        cv2.imwrite(str(folder / "frames" / f"{i}.png"), np.full((H, W, 3), 40 * i, np.uint8))
    return {"imu.csv": "\n".join(imu) + "\n", "frames.csv": "\n".join(frames) + "\n",
            "tracks.csv": "\n".join(tracks) + "\n", "gnss.csv": "\n".join(gnss) + "\n",
            "groundtruth.csv": "\n".join(truth) + "\n", "calibration.yaml": calibration,
            "metadata.yaml": "device: test\n"}


def _line(text: str, n: int, new: str) -> str:
    lines = text.splitlines()
    lines[n - 1] = new
    return "\n".join(lines) + "\n"


def _cell(text: str, n: int, column: int, value: str) -> str:
    cells = text.splitlines()[n - 1].split(",")
    cells[column] = value
    return _line(text, n, ",".join(cells))


#: (file, corruption of its valid text, the message expected: file and line or key named)
CASES = {
    "imu: a word for a number": ("imu.csv", lambda s: _cell(s, 5, 1, "abc"), r"imu\.csv: line 5: column 'ax'"),
    "imu: NaN": ("imu.csv", lambda s: _cell(s, 7, 4, "nan"), r"imu\.csv.*line 7"),
    "imu: inf": ("imu.csv", lambda s: _cell(s, 9, 6, "inf"), r"imu\.csv.*line 9"),
    "imu: a time twice": ("imu.csv", lambda s: _cell(s, 11, 0, "0.08"), r"imu\.csv.*line 11"),
    "imu: time going back": ("imu.csv", lambda s: _cell(s, 21, 0, "0.05"), r"imu\.csv.*line 21"),
    "imu: a 1 s gap": ("imu.csv", lambda s: "\n".join(s.splitlines()[:50] + s.splitlines()[150:]) + "\n",
                       r"imu\.csv.*lines 50 and 51.*sequence\.max_imu_gap_s"),
    "imu: a missing column": ("imu.csv", lambda s: s.replace(",wz", "", 1), r"imu\.csv.*wz"),
    "imu: header only": ("imu.csv", lambda s: s.splitlines()[0] + "\n", r"imu\.csv"),
    "imu: in g": ("imu.csv", lambda s: s.replace(",9.81,", ",1.0,"), r"imu\.csv.*looks like it is in g"),
    "imu: a short row": ("imu.csv", lambda s: _line(s, 4, "0.02,0.0,0.1"), r"imu\.csv: line 4"),
    "frames: a missing image": ("frames.csv", lambda s: _cell(s, 3, 1, "gone.png"), r"frames\.csv: line 3.*gone\.png"),
    "frames: time going back": ("frames.csv", lambda s: _cell(s, 4, 0, "0.55"), r"frames\.csv.*line 4"),
    "frames: a word for a time": ("frames.csv", lambda s: _cell(s, 2, 0, "x"), r"frames\.csv: line 2"),
    "tracks: a fractional id": ("tracks.csv", lambda s: _cell(s, 3, 1, "1.5"), r"tracks\.csv: line 3"),
    "tracks: NaN pixel": ("tracks.csv", lambda s: _cell(s, 4, 2, "nan"), r"tracks\.csv.*line 4"),
    "tracks: a point off the image": ("tracks.csv", lambda s: _cell(s, 5, 2, "2000"), r"tracks\.csv: line 5: point"),
    "tracks: a time between frames": ("tracks.csv", lambda s: _cell(s, 10, 0, "0.733"), r"tracks\.csv: line 10: time 0\.733"),
    "tracks: an id twice in a frame": ("tracks.csv", lambda s: _cell(s, 3, 1, "0"), r"tracks\.csv: line 3: track_id 0 appears twice"),
    "gnss: latitude 200": ("gnss.csv", lambda s: _cell(s, 3, 1, "200"), r"gnss\.csv: lat_deg=200\.0 at line 3"),
    "gnss: accuracy 0": ("gnss.csv", lambda s: _cell(s, 2, 4, "0"), r"gnss\.csv.*line 2"),
    "gnss: accuracy missing": ("gnss.csv", lambda s: _cell(s, 4, 5, ""), r"gnss\.csv: line 4"),
    "gnss: time going back": ("gnss.csv", lambda s: _cell(s, 4, 0, "0.2"), r"gnss\.csv.*line 4"),
    "groundtruth: a zero quaternion": ("groundtruth.csv", lambda s: _line(s, 8, "0.06,0.06,0.0,0.0,0.0,0.0,0.0,0.0"),
                                       r"groundtruth\.csv.*line 8.*zero quaternion"),
    "groundtruth: mixed rows with and without q": ("groundtruth.csv", lambda s: _line(s, 9, "0.07,0.07,0.0,0.0,,,,"),
                                                   r"groundtruth\.csv"),
    "groundtruth: NaN": ("groundtruth.csv", lambda s: _cell(s, 12, 2, "nan"), r"groundtruth\.csv.*line 12"),
    "calibration: cx off the image": ("calibration.yaml", lambda s: s.replace("cx: 3.5", "cx: 5000"),
                                      r"calibration\.yaml.*principal point cx=5000"),
    "calibration: fx for another image size": ("calibration.yaml", lambda s: s.replace("fx: 5.0", "fx: 458.7"),
                                               r"calibration\.yaml.*fx=458\.7 px over an image width of 8 px"),
    "calibration: a word for fx": ("calibration.yaml", lambda s: s.replace("fx: 5.0", "fx: five"),
                                   r"calibration\.yaml.*line 4.*camera\.fx is 'five'"),
    "calibration: a typo key": ("calibration.yaml", lambda s: s.replace("  cy: 2.5\n", "  cy: 2.5\n  distorsion: []\n"),
                                r"calibration\.yaml.*distorsion"),
    "calibration: not a rotation": ("calibration.yaml", lambda s: s.replace("[1.0, 0.0, 0.0, 0.0]", "[0.0, 0.0, 0.0, 0.0]"),
                                    r"calibration\.yaml.*rotation"),
    "calibration: no camera": ("calibration.yaml", lambda s: s.split("imu_to_camera")[0].replace("camera:", "cam:"),
                               r"calibration\.yaml|frames\.csv"),
    "metadata: a list": ("metadata.yaml", lambda s: "- a\n- b\n", r"metadata\.yaml.*expected a mapping"),
    "metadata: a python object tag runs nothing": (
        "metadata.yaml", lambda s: "x: !!python/object/apply:os.system ['touch RAN']\n", r"metadata\.yaml"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_each_corruption_stops_with_the_file_and_line_named(tmp_path, case, monkeypatch):
    file, corrupt, message = CASES[case]
    folder = tmp_path / "rec"
    texts = _valid(folder)
    texts[file] = corrupt(texts[file])
    assert texts[file] != _valid(tmp_path / "clean")[file]  # the case changes the file
    for name, text in texts.items():
        (folder / name).write_text(text)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError, match=message):
        read_folder(folder)
    assert not (tmp_path / "RAN").exists()  # nothing in a file ran


def test_the_valid_recording_reads(tmp_path):
    folder = tmp_path / "rec"
    for name, text in _valid(folder).items():
        (folder / name).write_text(text)
    seq = read_folder(folder)
    assert len(seq.imu) == N_IMU and len(seq.frames) == 3 and len(seq.tracks) == 9 and len(seq.gnss) == 3
