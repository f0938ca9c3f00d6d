"""Validation of the sensor streams: each bad input names the stream and the row."""
from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
import torch

from flowins.data import GnssStream, ImuStream, PoseStream

F64 = torch.float64


def _imu_arrays(n: int = 20, dt: float = 0.01):
    t = np.arange(n, dtype=np.float64) * dt + 100.0
    rng = np.random.default_rng(0)
    acc = rng.normal(size=(n, 3)) + np.array([0.0, 0.0, 9.81])
    gyro = rng.normal(scale=0.1, size=(n, 3))
    return t, acc, gyro


def _gnss_arrays(g: int = 5):
    t = np.arange(g, dtype=np.float64)
    lat = 60.17 + 1e-5 * np.arange(g)
    lon = 24.94 + 1e-5 * np.arange(g)
    alt = 20.0 + np.arange(g, dtype=np.float64)
    h = np.full(g, 2.5)
    v = np.full(g, 4.0)
    return [t, lat, lon, alt, h, v]


# --------------------------------------------------------------------- ImuStream


def test_imu_valid_keeps_every_sample_and_converts_to_float64():
    t, acc, gyro = _imu_arrays()
    t[5:] += 0.003  # non-uniform sampling is fine
    imu = ImuStream(t, acc.tolist(), torch.tensor(gyro, dtype=torch.float32))
    assert len(imu) == 20
    for x in (imu.t_s, imu.acc_mps2, imu.gyro_rps):
        assert x.dtype == F64 and x.device.type == "cpu"
    assert np.array_equal(imu.t_s.numpy(), t)
    assert np.array_equal(imu.acc_mps2.numpy(), acc)
    assert np.allclose(imu.gyro_rps.numpy(), gyro, atol=1e-7)  # float32 input, converted
    np.testing.assert_allclose(imu.dt_s.numpy(), np.diff(t))
    assert imu.duration_s == pytest.approx(t[-1] - t[0])
    assert imu.rate_hz == pytest.approx(100.0)


def test_imu_is_immutable_and_does_not_alias_input():
    t, acc, gyro = _imu_arrays()
    imu = ImuStream(t, acc, gyro)
    acc[0, 0] = 1e9
    assert imu.acc_mps2[0, 0] != 1e9
    with pytest.raises(dataclasses.FrozenInstanceError):
        imu.t_s = torch.zeros(3)  # type: ignore[misc]


def test_imu_nan_in_acc_names_array_row_and_column():
    t, acc, gyro = _imu_arrays()
    acc[7, 1] = np.nan
    with pytest.raises(ValueError, match=r"^IMU: acc_mps2 .*row 7 \(0-based\), column 1"):
        ImuStream(t, acc, gyro)


def test_imu_inf_in_gyro_names_array():
    t, acc, gyro = _imu_arrays()
    gyro[12, 2] = np.inf
    with pytest.raises(ValueError, match=r"gyro_rps .*row 12 \(0-based\), column 2"):
        ImuStream(t, acc, gyro, name="imu0.csv")


def test_imu_non_increasing_time_names_row_and_both_timestamps():
    t, acc, gyro = _imu_arrays()
    t[3] = t[2]
    with pytest.raises(ValueError) as err:
        ImuStream(t, acc, gyro, name="imu0.csv")
    msg = str(err.value)
    assert msg.startswith("imu0.csv:")
    assert "row 3 (0-based)" in msg
    assert f"t_s[2]={float(t[2])!r}" in msg and f"t_s[3]={float(t[3])!r}" in msg


def test_imu_decreasing_time_reports_first_offending_row():
    t, acc, gyro = _imu_arrays()
    t[10] -= 1.0  # rows 10 (t drops) and 11 (t jumps back, too big a gap) are both wrong
    with pytest.raises(ValueError, match=r"not strictly increasing at row 10 \(0-based\)"):
        ImuStream(t, acc, gyro)


def test_imu_gap_is_reported_with_rows_and_hint():
    t, acc, gyro = _imu_arrays(n=120)
    t[100:] += 0.72  # dt between rows 99 and 100 becomes 0.73 s
    with pytest.raises(ValueError) as err:
        ImuStream(t, acc, gyro)
    msg = str(err.value)
    assert re.search(r"^IMU: gap of 0\.73 s between rows 99 and 100", msg), msg
    assert "max_imu_gap_s=0.2" in msg and "raise sequence.max_imu_gap_s" in msg
    # ...and the hint works: the same data is accepted, unchanged, with a larger bound.
    imu = ImuStream(t, acc, gyro, max_gap_s=1.0)
    assert len(imu) == 120 and np.array_equal(imu.t_s.numpy(), t)


@pytest.mark.parametrize(
    ("acc_shape", "gyro_shape", "bad"),
    [((20, 2), (20, 3), "acc_mps2"), ((20, 3), (19, 3), "gyro_rps"), ((20,), (20, 3), "acc_mps2")],
)
def test_imu_shape_mismatch(acc_shape, gyro_shape, bad):
    t = np.arange(20) * 0.01
    with pytest.raises(ValueError, match=rf"^IMU: {bad} has shape .*expected \(20, 3\)"):
        ImuStream(t, np.zeros(acc_shape), np.zeros(gyro_shape))


def test_imu_time_must_be_1d():
    with pytest.raises(ValueError, match=r"^IMU: t_s has shape \(4, 1\)"):
        ImuStream(np.zeros((4, 1)), np.zeros((4, 3)), np.zeros((4, 3)))


def test_imu_empty_and_single_sample():
    with pytest.raises(ValueError, match=r"^IMU: stream is empty"):
        ImuStream([], np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(ValueError, match=r"^IMU: stream has 1 sample"):
        ImuStream([0.0], np.zeros((1, 3)), np.zeros((1, 3)))


def test_imu_bad_max_gap():
    t, acc, gyro = _imu_arrays()
    with pytest.raises(ValueError, match="max_gap_s"):
        ImuStream(t, acc, gyro, max_gap_s=0.0)


def test_imu_slice_time_is_inclusive_and_keeps_data():
    t, acc, gyro = _imu_arrays()
    imu = ImuStream(t, acc, gyro, name="imu0.csv")
    part = imu.slice_time(t[4], t[9])
    assert len(part) == 6 and part.name == "imu0.csv" and part.max_gap_s == imu.max_gap_s
    assert np.array_equal(part.t_s.numpy(), t[4:10])
    assert np.array_equal(part.acc_mps2.numpy(), acc[4:10])
    assert np.array_equal(part.gyro_rps.numpy(), gyro[4:10])


def test_imu_slice_time_too_short():
    t, acc, gyro = _imu_arrays()
    imu = ImuStream(t, acc, gyro)
    with pytest.raises(ValueError, match=r"^IMU: slice_time.*keeps 1 of 20 samples"):
        imu.slice_time(t[4], t[4] + 0.001)
    with pytest.raises(ValueError, match=r"expected t0_s <= t1_s"):
        imu.slice_time(t[9], t[4])


# --------------------------------------------------------------------- GnssStream


def test_gnss_valid_keeps_every_fix():
    arrays = _gnss_arrays()
    gnss = GnssStream(*arrays)
    assert len(gnss) == 5
    for key, x in zip(("t_s", "lat_deg", "lon_deg", "alt_m", "h_acc_m", "v_acc_m"), arrays):
        got = getattr(gnss, key)
        assert got.dtype == F64 and np.array_equal(got.numpy(), x)


def test_gnss_single_fix_is_allowed():
    gnss = GnssStream(*[a[:1] for a in _gnss_arrays()])
    assert len(gnss) == 1


def test_gnss_missing_h_acc_names_array_and_row():
    arrays = _gnss_arrays()
    arrays[4][2] = np.nan
    with pytest.raises(ValueError, match=r"^GNSS: h_acc_m .*row 2 \(0-based\).*missing accuracy"):
        GnssStream(*arrays)


def test_gnss_missing_v_acc_names_array_and_row():
    arrays = _gnss_arrays()
    arrays[5][3] = np.nan
    with pytest.raises(ValueError, match=r"^fix\.csv: v_acc_m .*row 3 \(0-based\)"):
        GnssStream(*arrays, name="fix.csv")


def test_gnss_latitude_out_of_range():
    arrays = _gnss_arrays()
    arrays[1][1] = 95.0
    with pytest.raises(ValueError, match=r"^GNSS: lat_deg=95\.0 at row 1 \(0-based\); expected .*\[-90, 90\]"):
        GnssStream(*arrays)


def test_gnss_longitude_out_of_range():
    arrays = _gnss_arrays()
    arrays[2][4] = -180.5
    with pytest.raises(ValueError, match=r"lon_deg=-180\.5 at row 4 \(0-based\)"):
        GnssStream(*arrays)


@pytest.mark.parametrize(("col", "key", "value"), [(4, "h_acc_m", -1.0), (5, "v_acc_m", 0.0)])
def test_gnss_non_positive_accuracy(col, key, value):
    arrays = _gnss_arrays()
    arrays[col][3] = value
    with pytest.raises(ValueError, match=rf"^GNSS: {key}=-?{abs(value)} at row 3 \(0-based\); expected .*> 0"):
        GnssStream(*arrays)


def test_gnss_non_increasing_time():
    arrays = _gnss_arrays()
    arrays[0][4] = arrays[0][3]
    with pytest.raises(ValueError, match=r"^GNSS: timestamps are not strictly increasing at row 4 \(0-based\)"):
        GnssStream(*arrays)


def test_gnss_empty_and_shape_mismatch():
    with pytest.raises(ValueError, match=r"^GNSS: stream is empty"):
        GnssStream(*[np.zeros(0)] * 6)
    arrays = _gnss_arrays()
    arrays[3] = arrays[3][:4]
    with pytest.raises(ValueError, match=r"^GNSS: alt_m has shape \(4,\); expected \(5,\)"):
        GnssStream(*arrays)


# --------------------------------------------------------------------- PoseStream


def test_pose_without_orientation():
    t = np.arange(4.0)
    pos = np.arange(12.0).reshape(4, 3)
    pose = PoseStream(t, pos)
    assert pose.quat_wxyz is None and len(pose) == 4
    assert pose.name == "ground truth" and np.array_equal(pose.pos_m.numpy(), pos)


def test_pose_quaternion_is_normalised_not_clipped():
    t = np.arange(3.0)
    quat = np.array([[2.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0], [-0.5, 0.1, 0.2, 0.3]])
    pose = PoseStream(t, np.zeros((3, 3)), quat)
    expected = quat / np.linalg.norm(quat, axis=1, keepdims=True)  # sign kept (w < 0 in row 2)
    np.testing.assert_allclose(pose.quat_wxyz.numpy(), expected, rtol=0, atol=1e-15)


def test_pose_zero_quaternion_row():
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (5, 1))
    quat[3] = 0.0
    with pytest.raises(ValueError, match=r"^ground truth: quat_wxyz row 3 \(0-based\) is the zero quaternion"):
        PoseStream(np.arange(5.0), np.zeros((5, 3)), quat)


def test_pose_bad_inputs():
    t = np.arange(5.0)
    pos = np.zeros((5, 3))
    pos[2, 0] = np.nan
    with pytest.raises(ValueError, match=r"^gt\.csv: pos_m .*row 2 \(0-based\), column 0"):
        PoseStream(t, pos, name="gt.csv")
    with pytest.raises(ValueError, match=r"quat_wxyz has shape \(5, 3\); expected \(5, 4\)"):
        PoseStream(t, np.zeros((5, 3)), np.ones((5, 3)))
    t_bad = t.copy()
    t_bad[3] = 1.5
    with pytest.raises(ValueError, match=r"not strictly increasing at row 3 \(0-based\)"):
        PoseStream(t_bad, np.zeros((5, 3)))
    with pytest.raises(ValueError, match=r"^ground truth: stream is empty"):
        PoseStream(np.zeros(0), np.zeros((0, 3)))
