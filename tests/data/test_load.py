"""A part of a recording (``start_s``, ``end_s``): every stream cropped to the IMU samples kept."""
import pytest
import torch

from flowins.data.load import Recording, time_window
from flowins.data.sequence import Sequence
from flowins.data.synthetic import synthetic_walk_recording


@pytest.fixture(scope="module")
def recording():
    walk = synthetic_walk_recording(duration_s=20.0, seed=1)
    return Recording(Sequence(walk.imu, name="walk", gnss=walk.gnss, groundtruth=walk.truth))


def test_a_window_keeps_the_imu_samples_inside_it_and_crops_every_stream_to_them(recording):
    t0 = float(recording.imu.t_s[0])
    part = time_window(recording, 6.0, 14.5)
    imu_t = recording.imu.t_s
    inside = (imu_t >= t0 + 6.0) & (imu_t <= t0 + 14.5)
    assert torch.equal(part.imu.t_s, imu_t[inside])
    assert torch.equal(part.imu.acc_mps2, recording.imu.acc_mps2[inside])
    lo, hi = float(part.imu.t_s[0]), float(part.imu.t_s[-1])
    for full, cut in ((recording.gnss.t_s, part.gnss.t_s), (recording.truth.t_s, part.truth.t_s)):
        expected = full[(full >= lo) & (full <= hi)]  # a naive filter of the whole stream
        assert expected.numel() > 0 and torch.equal(cut, expected)
    gnss_rows = (recording.gnss.t_s >= lo) & (recording.gnss.t_s <= hi)
    assert torch.equal(part.gnss.lat_deg, recording.gnss.lat_deg[gnss_rows])
    truth_rows = (recording.truth.t_s >= lo) & (recording.truth.t_s <= hi)
    assert torch.equal(part.truth.pos_m, recording.truth.pos_m[truth_rows])


def test_open_ends_and_no_window(recording):
    assert time_window(recording, None, None) is recording
    tail = time_window(recording, 12.0, None)
    assert float(tail.imu.t_s[-1]) == float(recording.imu.t_s[-1])
    head = time_window(recording, None, 5.0)
    assert float(head.imu.t_s[0]) == float(recording.imu.t_s[0])
    assert float(head.imu.t_s[-1]) <= float(recording.imu.t_s[0]) + 5.0


def test_a_window_outside_the_recording_is_refused_naming_the_keys(recording):
    with pytest.raises(ValueError, match=r"walk: start_s=8.0, end_s=4.0 .*expected 0 <= start_s < end_s"):
        time_window(recording, 8.0, 4.0)
    with pytest.raises(ValueError, match=r"walk: start_s=30.0 .*past its 20"):
        time_window(recording, 30.0, None)
