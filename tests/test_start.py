"""Starts and recovery on whole simulated recordings, against their exact truth: a car that
drives from the first sample with a GNSS outage, a filter locked out by its gate, and a
walk whose IMU vibrates on the ground before it moves."""
from __future__ import annotations

import math
from functools import lru_cache

import pytest
import torch

from flowins.data.simulate.drive import AUTOMOTIVE_IMU, Drive, DriveConfig, drive_sequence
from flowins.data.synthetic import Vibration, WalkConfig, synthetic_walk_recording
from flowins.measurements.gnss import GnssRecovery
from flowins.geometry import quaternion as quat
from flowins.geometry.geodesy import LocalTangentPlane
from flowins.ins.initialization import InitialUncertainty
from flowins.ins.mechanization import ProcessNoise
from flowins.navigation import NavigationConfig, NavigationRun, navigate
from flowins.start import choose_start
from flowins.state import STATE, split

DRIVE = DriveConfig()  # 300 s, outage 120..180 s


@lru_cache(maxsize=1)
def drive():
    return drive_sequence(DRIVE)[0]


def noise(scale: float = 1.0) -> ProcessNoise:
    e = AUTOMOTIVE_IMU
    return ProcessNoise(acc_noise=scale * e.acc_noise, gyro_noise=scale * e.gyro_noise,
                        acc_bias_walk=scale * e.acc_bias_walk, gyro_bias_walk=scale * e.gyro_bias_walk)


def errors(result, truth_position, origin):
    """``(t (N,), error (N, 3), sigma (N, 3))`` of the filter against the truth, in the filter's frame."""
    f = result.frame
    shift = LocalTangentPlane(*origin).to_enu(f.origin_lat_deg, f.origin_lon_deg, f.origin_alt_m)
    t = result.filter.t_s
    err = result.filter.node_mean[:, STATE.p] - (truth_position(t) - shift)
    sigma = result.filter.node_cov[:, STATE.p, STATE.p].diagonal(dim1=-2, dim2=-1).sqrt()
    return t, err, sigma


def mean_error(t, err, t0: float, t1: float) -> float:
    return float(err.norm(dim=-1)[(t >= t0) & (t < t1)].mean())


def test_a_car_starts_moving_stays_consistent_through_the_outage_and_recovers():
    result = navigate(NavigationRun(drive().imu, drive().gnss), config=NavigationConfig(noise=noise()))
    assert result.start.mode == "moving" and result.start.index == 0
    t, err, sigma = errors(result, Drive(DRIVE).position, DRIVE.origin)
    t0, t1 = DRIVE.outage()
    assert mean_error(t, err, 20.0, t0) < 3.0  # fixes of 1 m σ, correlated over 10 s
    in_outage = (t > t0) & (t < t1)
    assert mean_error(t, err, t1 - 2, t1) > 10.0  # the outage matters ...
    assert float((err.abs() / sigma)[in_outage].max()) < 4.0  # ... and the filter knows how much
    assert mean_error(t, err, t1 + 10, t1 + 11) < 5.0  # 10 s after the fixes return
    assert not [e for e in result.filter.log if e.get("kind") == "gnss_reset"]


@pytest.mark.parametrize("recover", [False, True])
def test_a_filter_that_drifts_off_in_the_outage_is_reset_instead_of_locked_out(recover):
    """IMU noise 10x and bias priors 100x too small: the filter drifts far beyond its σ in
    the outage, and its gate then rejects every later fix, unless it is reset."""
    config = NavigationConfig(noise=noise(0.1), initial=InitialUncertainty(acc_bias_mps2=3e-4, gyro_bias_rps=1e-5),
                              gnss_recovery=GnssRecovery(after_rejections=3 if recover else 0, nis_window=0))
    result = navigate(NavigationRun(drive().imu, drive().gnss), config=config)
    t, err, _ = errors(result, Drive(DRIVE).position, DRIVE.origin)
    t1 = DRIVE.outage()[1]
    fixes = [e for e in result.filter.log if e.get("kind") == "gnss" and e["t_s"] > t1]
    resets = [e for e in result.filter.log if e.get("kind") == "gnss_reset"]
    if not recover:
        assert sum(e["accepted"] < 0.5 for e in fixes) == len(fixes) and not resets
        assert mean_error(t, err, 290.0, 300.0) > 1000.0
    else:
        assert resets and all(e["why"] == "rejected" and e["rejected"] == 3 for e in resets)
        back = [e for e in resets if e["t_s"] > t1]
        assert back and back[0]["t_s"] < t1 + 5.0 and back[0]["offset_m"] > 50.0
        assert mean_error(t, err, t1 + 10, t1 + 11) < 10.0
        assert mean_error(t, err, 290.0, 300.0) < 5.0


@pytest.mark.slow
def test_inconsistent_innovations_reset_a_filter_whose_gate_is_off():
    """With the gate off nothing is rejected; the NIS of the returning fixes tells."""
    from flowins.filter.ekf import Gate

    base = dict(noise=noise(0.1), initial=InitialUncertainty(acc_bias_mps2=3e-4, gyro_bias_rps=1e-5),
                gnss_gate=Gate(mode="off"))
    run = NavigationRun(drive().imu, drive().gnss)
    quiet = navigate(run, config=NavigationConfig(**base, gnss_recovery=GnssRecovery(nis_window=0)))
    reset = navigate(run, config=NavigationConfig(**base, gnss_recovery=GnssRecovery(nis_window=10)))
    resets = [e for e in reset.filter.log if e.get("kind") == "gnss_reset"]
    t1 = DRIVE.outage()[1]
    assert resets and all(e["why"] == "inconsistent" for e in resets)
    assert [e for e in resets if t1 < e["t_s"] < t1 + 10.0]
    t, err_reset, _ = errors(reset, Drive(DRIVE).position, DRIVE.origin)
    _, err_quiet, _ = errors(quiet, Drive(DRIVE).position, DRIVE.origin)
    late = slice(int((t < 200.0).sum()), None)
    assert float(err_reset[late].norm(dim=-1).mean()) < 0.5 * float(err_quiet[late].norm(dim=-1).mean())


@pytest.mark.parametrize("seed", [0, 1])
def test_a_vibrating_standstill_is_found_and_starts_the_walk_level(seed):
    """Rotor-like vibration (0.5 m/s², 0.04 rad/s RMS in the readings, 50–200 Hz) until the
    walk sets off at 5 s: the still start ends within 0.4 s after it, where the walk has
    moved less than a millimetre, and roll and pitch come out as without the vibration
    (within 0.05°; both are off the truth by the accelerometer bias and scale, under 1°)."""
    walk = WalkConfig(duration_s=30.0)
    rec = synthetic_walk_recording(duration_s=30.0, seed=seed, walk=walk,
                                   vibration=Vibration(0.5, 0.04, until_s=walk.stationary_s))
    assert float(rec.imu.acc_mps2[:400].std(0).min()) > 0.4  # the readings do shake
    start = choose_start(rec.imu)
    assert start.mode == "still"
    end = start.facts["still_end_s"]
    assert walk.stationary_s - 0.1 < end < walk.stationary_s + 0.4
    t_end = torch.tensor([0.0, end], dtype=torch.float64)
    assert float((rec.walk.position(t_end)[1] - rec.walk.position(t_end)[0]).norm()) < 1e-3
    quiet = choose_start(synthetic_walk_recording(duration_s=30.0, seed=seed, walk=walk).imu)
    shaken, still = quat.to_euler(split(start.mean).q), quat.to_euler(split(quiet.mean).q)
    truth = quat.to_euler(rec.walk.quaternion(torch.zeros((), dtype=torch.float64)))
    for k in (0, 1):  # roll, pitch
        assert abs(float(shaken[k] - still[k])) < math.radians(0.05)
        assert abs(float(shaken[k] - truth[k])) < math.radians(1.0)


def test_a_still_window_longer_than_the_recording_says_the_recording_is_shorter():
    from flowins.data.streams import ImuStream
    from flowins.ins.initialization import StillSettings
    from flowins.start import StartSettings

    t = torch.arange(2500, dtype=torch.float64) * 0.01  # 25 s, still throughout
    imu = ImuStream(t, torch.tensor([0.0, 0.0, 9.80665]).expand(2500, 3), torch.zeros(2500, 3))
    settings = StartSettings(mode="still", still=StillSettings(min_s=30.0))
    with pytest.raises(ValueError, match=r"the recording lasts 24\.99 s, shorter than filter\.init\.still\.min_s=30\.0"):
        choose_start(imu, settings=settings)
    assert choose_start(imu, settings=StartSettings(mode="still", still=StillSettings(min_s=20.0))).mode == "still"


def _gt_case(seed: int = 0):
    """A tilted walk (pitch -12°) that starts still for 5 s, a gyroscope bias of 0.01 rad/s σ,
    and a ground truth at 20 Hz with 2 mm and 2 mrad of noise of its own."""
    from dataclasses import replace

    from flowins.data.synthetic import noisy_truth

    rec = synthetic_walk_recording(duration_s=20.0, seed=seed, truth_rate_hz=20.0, walk=WalkConfig(duration_s=20.0))
    noisy = noisy_truth(rec.truth, position_sigma_m=0.002, attitude_sigma_rad=0.002,
                        generator=torch.Generator().manual_seed(100 + seed), name="gt")
    truth = rec.truth
    return replace(rec, truth=noisy), truth


@pytest.mark.parametrize("seed", [0, 1])
def test_a_ground_truth_start_on_a_still_recording_is_as_good_as_the_still_start(seed):
    """INS alone over a 20 s walk: started from the ground truth it learns the gyroscope bias
    and takes the zero-velocity updates of the still start as the still start does, so its
    error is no worse; without them (the still start not recognised) it drifts far more."""
    from flowins.evaluation import trajectory_errors
    from flowins.start import StartSettings, StillSettings

    rec, exact = _gt_case(seed)

    def rmse(settings: StartSettings):
        result = navigate(NavigationRun(rec.imu, truth=rec.truth), config=NavigationConfig(start=settings))
        track = result.filter
        return result.start, trajectory_errors(track.t, track.mean[:, STATE.p], exact.t_s, exact.pos_m,
                                               align="se3").rmse_m

    gt_start, gt = rmse(StartSettings(mode="groundtruth"))
    _, still = rmse(StartSettings(mode="still"))
    _, blind = rmse(StartSettings(mode="groundtruth", still=StillSettings(min_s=100.0)))
    assert gt_start.mode == "groundtruth" and gt_start.zupt_times_s and gt_start.facts["still_s"] > 4.5
    assert float((split(gt_start.mean).b_w - rec.imu_errors["b_w"][0]).norm()) < 2e-3
    assert gt <= 1.1 * still + 0.05
    assert blind > 3.0 * gt


def test_a_moving_start_waits_for_sparse_fixes_and_says_how_long():
    """Fixes every 6 s; the recording starts 4 s into the drive, so its first 10 s hold one fix
    (at 5 s). The start waits for it, fits it and the next (6 s later), starts there and
    drives on as well as a start fitted over 20 s from the first row; without the wait
    (max_wait_s below the 5 s it needs) it stops with the error that names fit_s."""
    from dataclasses import replace

    from flowins.data.streams import GnssStream, ImuStream
    from flowins.start import MovingSettings, StartSettings

    config = DriveConfig(duration_s=120.0, gnss_rate_hz=1.0 / 6.0, outage_s=0.0)
    seq = drive_sequence(config)[0]
    i, g = seq.imu.t_s >= 4.0, seq.gnss.t_s >= 4.0
    imu = ImuStream(seq.imu.t_s[i], seq.imu.acc_mps2[i], seq.imu.gyro_rps[i], name="imu")
    gnss = GnssStream(*(getattr(seq.gnss, k)[g] for k in ("t_s", "lat_deg", "lon_deg", "alt_m", "h_acc_m", "v_acc_m")),
                      name="gnss")
    assert 4.9 < float(gnss.t_s[0] - imu.t_s[0]) < 5.1 and int((gnss.t_s <= float(imu.t_s[0]) + 10.0).sum()) == 1
    moving = StartSettings(mode="moving")  # at a steady 12 m/s the IMU alone looks still
    result = navigate(NavigationRun(imu, gnss), config=NavigationConfig(noise=noise(), start=moving))
    start = result.start
    assert start.mode == "moving" and abs(start.facts["waited_s"] - 5.0) < 0.05
    assert "waited 5.0 s for two GNSS fixes" in start.reason and abs(start.t_s - float(gnss.t_s[0])) < 0.02
    t, err, _ = errors(result, Drive(config).position, config.origin)
    assert float(t[0]) >= start.t_s - 1e-9  # nothing filtered before the start
    long_fit = NavigationConfig(noise=noise(), start=replace(moving, moving=replace(MovingSettings(), fit_s=20.0)))
    t_l, err_l, _ = errors(navigate(NavigationRun(imu, gnss), config=long_fit), Drive(config).position, config.origin)
    assert mean_error(t, err, 30.0, 120.0) < 1.5 * mean_error(t_l, err_l, 30.0, 120.0) + 0.5
    assert mean_error(t, err, 30.0, 120.0) < 6.0  # fixes of 1 m σ every 6 s, correlated over 10 s
    early = NavigationConfig(noise=noise(), start=replace(moving, moving=replace(MovingSettings(), max_wait_s=4.0)))
    with pytest.raises(ValueError, match="filter.init.mode=moving without GNSS fixes at the start"):
        navigate(NavigationRun(imu, gnss), config=early)
