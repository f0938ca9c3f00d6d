"""The gyroscope against the accelerometer: exact readings of known motions, and deg/s named."""
import math

import pytest
import torch

from flowins.data.streams import ImuStream
from flowins.data.synthetic import Walk, WalkConfig, body_readings
from flowins.geometry import quaternion as quat
from flowins.ins.consistency import gyro_consistency
from flowins.sensor import check_gyro_consistency, resolve_imu

F64 = torch.float64


def walk_readings(duration_s: float = 40.0, seed: int = 0):
    """A walk's exact readings (sway ±3° at 0.9 Hz) plus white noise of a phone-class IMU."""
    t = torch.arange(0.0, duration_s, 0.01, dtype=F64)
    acc, gyro = Walk(WalkConfig(duration_s=duration_s, stationary_s=2.0, ramp_s=2.0)).imu(t)
    gen = torch.Generator().manual_seed(seed)
    acc = acc + 0.02 * torch.randn(acc.shape, generator=gen, dtype=F64)
    gyro = gyro + 0.002 * torch.randn(gyro.shape, generator=gen, dtype=F64)
    return t, acc, gyro


def rocking_readings(amplitude_rad: float = math.radians(10.0), hz: float = 0.25, duration_s: float = 40.0):
    """A platform rocking in roll about a fixed point, no translation: the specific force is
    gravity in the body frame, so its direction follows the roll exactly."""
    t = torch.arange(0.0, duration_s, 0.01, dtype=F64)

    def rotation(tau):
        roll = amplitude_rad * torch.sin(2 * math.pi * hz * tau)
        return quat.to_matrix(quat.from_euler(roll, torch.zeros_like(roll), torch.zeros_like(roll)))

    acc, gyro = body_readings(rotation, lambda tau: torch.zeros(3, dtype=F64) * tau, t)
    return t, acc, gyro


def test_a_rocking_platform_is_explained_by_its_gyroscope():
    t, acc, gyro = rocking_readings()
    result = gyro_consistency(t, acc, gyro)
    assert result.consistent and result.fix is None
    assert result.windows >= 40
    # the gyroscope predicts each tilt change to within a small fraction of the change itself
    # (what is left comes from averaging a turning vector over 0.5 s)
    assert result.gyro_error_rad < 0.1 * result.still_error_rad
    assert result.still_error_rad > math.radians(5.0)
    # roll read as pitch: the predicted tilt goes the wrong way, worse than predicting none,
    # yet within the margin: the check does not claim to catch a swapped pair of axes
    swapped = gyro_consistency(t, acc, gyro[:, [1, 0, 2]])
    assert swapped.gyro_error_rad > swapped.still_error_rad and swapped.consistent


def test_a_walk_passes_and_the_same_walk_in_deg_per_s_is_named():
    t, acc, gyro = walk_readings()
    clean = gyro_consistency(t, acc, gyro)
    assert clean.consistent
    wrong = gyro_consistency(t, acc, gyro * (180.0 / math.pi))
    assert not wrong.consistent and wrong.fix == "deg/s"
    assert wrong.gyro_error_rad > 2 * wrong.still_error_rad + math.radians(3.0)


def test_a_rocking_platform_in_deg_per_s_is_named_too():
    t, acc, gyro = rocking_readings(amplitude_rad=math.radians(2.0))
    assert gyro_consistency(t, acc, gyro).consistent
    wrong = gyro_consistency(t, acc, gyro * (180.0 / math.pi))
    assert not wrong.consistent and wrong.fix == "deg/s"


def test_no_tilt_or_too_short_gives_no_verdict():
    t = torch.arange(0.0, 30.0, 0.01, dtype=F64)
    acc = torch.tensor([0.0, 0.0, 9.81], dtype=F64).expand(t.shape[0], 3)
    gyro = torch.zeros(t.shape[0], 3, dtype=F64)
    still = gyro_consistency(t, acc, gyro)
    assert still.consistent and still.windows == 0
    assert gyro_consistency(t[:50], acc[:50], gyro[:50] + 5.0).consistent  # shorter than a window and its averages


def test_the_job_names_the_stream_deg_per_s_and_the_key_to_skip_the_check():
    t, acc, gyro = walk_readings(duration_s=25.0)
    stream = ImuStream(t, acc, gyro * (180.0 / math.pi), name="walk/imu.csv")
    with pytest.raises(ValueError, match=r"walk/imu\.csv: the gyroscope.*deg/s.*imu\.check_consistency=false"):
        check_gyro_consistency(stream)
    check_gyro_consistency(ImuStream(t, acc, gyro, name="walk/imu.csv"))  # the clean one passes

    class Rec:
        imu = stream
        sensor = None

    preset = {"name": "phone", "acc_noise": 1e-3, "gyro_noise": 1e-4, "check_consistency": True}
    with pytest.raises(ValueError, match="deg/s"):
        resolve_imu(preset, [Rec()], recorded=True)
    assert resolve_imu(preset | {"check_consistency": False}, [Rec()], recorded=True).name == "phone"
    with pytest.raises(ValueError, match="imu.check_consistency='no': expected true or false"):
        resolve_imu(preset | {"check_consistency": "no"}, [Rec()], recorded=True)


def test_a_simulated_car_drive_passes_and_in_deg_per_s_is_named():
    """A car tilts little (road grade, roll in the turns): the hardest case for deg/s."""
    import dataclasses

    from flowins.data.simulate.drive import DriveConfig, drive_sequence

    imu = drive_sequence(dataclasses.replace(DriveConfig(), seed=2))[0].imu
    assert gyro_consistency(imu.t_s, imu.acc_mps2, imu.gyro_rps).consistent
    wrong = gyro_consistency(imu.t_s, imu.acc_mps2, imu.gyro_rps * (180.0 / math.pi))
    assert not wrong.consistent and wrong.fix == "deg/s"


@pytest.mark.parametrize("bias", [(0.08, 0.0, 0.0), (0.0, -0.08, 0.0), (-0.002, 0.021, 0.077)])
def test_a_constant_bias_is_no_fault_and_is_recovered(bias):
    """A still start, then a walk: the readings as they are fail (a 0.08 rad/s bias tilts the
    prediction by 4.6° a second), less the bias they pass, and the bias removed is the true one."""
    t, acc, gyro = walk_readings(duration_s=60.0)
    b = torch.tensor(bias, dtype=F64)
    result = gyro_consistency(t, acc, gyro + b)
    assert result.consistent and result.fix is None
    if result.bias_rps is not None:  # a bias about gravity (z on a walk) tilts nothing: no verdict needed
        assert "still start" in result.bias_source
        # the horizontal axes are seen by the tilt; z (about gravity) only by the still start
        assert torch.allclose(torch.tensor(result.bias_rps, dtype=F64)[:2], b[:2], atol=3e-3)
    wrong = gyro_consistency(t, acc, (gyro + b) * (180.0 / math.pi))
    assert not wrong.consistent and wrong.fix == "deg/s"


def test_the_bias_is_fitted_without_a_still_start():
    """A platform rocking from its first sample (no still start) with a bias on every axis: the
    fit over the windows alone finds the bias that tilts gravity (x, y; gravity is z)."""
    t, acc, gyro = rocking_readings(amplitude_rad=math.radians(3.0))
    b = torch.tensor([0.09, -0.07, 0.0], dtype=F64)
    result = gyro_consistency(t, acc, gyro + b)
    assert result.consistent and result.fix is None
    # bias_rps set: the readings as they are failed, and the verdict is on them less the bias
    assert result.bias_rps is not None and result.bias_source == "fitted over every window"
    assert torch.allclose(torch.tensor(result.bias_rps, dtype=F64)[:2], b[:2], atol=2e-3)


def test_the_fitted_bias_matches_the_truth_under_white_noise():
    """fit_gyro_bias against the bias that was added, from a start of zero, on the walk's noisy
    readings: within 2 mrad/s on the axes the tilt sees."""
    from flowins.ins.consistency import _Windows, fit_gyro_bias

    t, acc, gyro = walk_readings(duration_s=60.0, seed=3)
    b = torch.tensor([-0.05, 0.06, 0.0], dtype=F64)
    fitted = fit_gyro_bias(t, acc, gyro + b, _Windows(50, 100, 50), start_rps=torch.zeros(3, dtype=F64))
    assert torch.allclose(fitted[:2], b[:2], atol=2e-3)
    # the readings without bias: the fit stays at zero
    assert fit_gyro_bias(t, acc, gyro, _Windows(50, 100, 50), start_rps=torch.zeros(3, dtype=F64))[:2].abs().max() < 2e-3
