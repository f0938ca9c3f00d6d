"""The vehicle constraint: its Jacobian against autograd, and a simulated car through a GNSS outage."""
from __future__ import annotations

import dataclasses
import math
from functools import lru_cache

import pytest
import torch

from flowins.data.simulate.drive import AUTOMOTIVE_IMU, Drive, DriveConfig, drive_sequence
from flowins.geometry import quaternion as quat
from flowins.geometry.geodesy import LocalTangentPlane
from flowins.ins.mechanization import ProcessNoise
from flowins.measurements.vehicle import (
    VehicleConstraint,
    VehicleSettings,
    VehicleUpdate,
    body_velocity_jacobians,
    constraint_terms,
    gyro_at,
    platform_streams,
    vehicle_events,
)
from flowins.navigation import NavigationConfig, NavigationRun, navigate
from flowins.state import STATE

F64 = torch.float64
DRIVE = DriveConfig(duration_s=240.0, outage_s=60.0)  # outage 90..150 s


def test_the_body_velocity_and_its_jacobians_match_autograd():
    gen = torch.Generator().manual_seed(0)
    for _ in range(5):
        q = torch.randn(4, generator=gen, dtype=F64)  # not unit: the Jacobian includes the normalisation
        v = 10 * torch.randn(3, generator=gen, dtype=F64)
        v_b, d_v, d_q = body_velocity_jacobians(q, v)
        assert torch.allclose(v_b, quat.to_matrix(q / q.norm()).T @ v, atol=1e-12)
        f = lambda q_, v_: quat.to_matrix(q_ / q_.norm()).T @ v_  # noqa: E731
        jq, jv = torch.autograd.functional.jacobian(f, (q, v))
        assert torch.allclose(d_q, jq, atol=1e-10) and torch.allclose(d_v, jv, atol=1e-12)


MOUNTED = {"mount_pitch_rad": math.radians(2.0), "mount_yaw_rad": math.radians(3.0),
           "lever_forward_m": -1.0, "lever_left_m": 0.3, "lever_up_m": -0.4}


def test_the_constraint_and_its_jacobian_match_autograd_with_a_mounting_and_a_lever_arm():
    """``h(x)`` is the sideways and vertical velocity of the non-slipping point in the vehicle
    frame, ``S C_cb (C(q)ᵀ v + (ω̃ - b_w) × r_b)``, written here the long way (the lever arm
    turned into the IMU frame); ``H`` is its Jacobian in v, q and b_w, batched over (3, 2)."""
    gen = torch.Generator().manual_seed(1)
    settings = VehicleSettings(forward_axis="y", up_axis="-z", **MOUNTED)
    mean = torch.randn(3, 2, 26, generator=gen, dtype=F64)  # quaternions not unit: H includes the normalisation
    mean[..., STATE.v] *= 10.0
    mean[..., STATE.b_w] *= 0.05
    gyro = 0.5 * torch.randn(3, 2, 3, generator=gen, dtype=F64)
    C_cb = settings.vehicle_from_imu(mean)
    lever_c = settings.lever_arm(mean)
    h, H = constraint_terms(mean, gyro, C_cb, lever_c)

    def long_way(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        q = x[STATE.q] / x[STATE.q].norm()
        r_b = C_cb.T @ lever_c
        v_b = quat.to_matrix(q).T @ x[STATE.v] + torch.linalg.cross(w - x[STATE.b_w], r_b)
        return (C_cb @ v_b)[1:]

    for i in range(3):
        for j in range(2):
            assert torch.allclose(h[i, j], long_way(mean[i, j], gyro[i, j]), atol=1e-12)
            jac = torch.autograd.functional.jacobian(lambda x: long_way(x, gyro[i, j]), mean[i, j])
            assert torch.allclose(H[i, j], jac, atol=1e-10)
    assert H[..., STATE.b_w].abs().max() > 0.1  # the lever arm reaches the gyroscope's bias


def test_the_constraint_holds_exactly_on_a_simulated_car_with_its_imu_mounted_off_axis():
    """The simulator's IMU sits 3° off in yaw, 2° in pitch and away from the non-slipping point;
    with its true mounting and lever arm the constraint's h vanishes on the true state and the
    true rates, without them it is the car's speed times the turn."""
    config = DriveConfig(duration_s=60.0, outage_s=0.0, slip_per_lateral_rad=0.0, pitch_per_acceleration_rad=0.0,
                         bump_height_m=0.0, imu_mount_pitch_rad=MOUNTED["mount_pitch_rad"],
                         imu_mount_yaw_rad=MOUNTED["mount_yaw_rad"],
                         imu_lever_m=(MOUNTED["lever_forward_m"], MOUNTED["lever_left_m"], MOUNTED["lever_up_m"]))
    car = Drive(config)
    t = torch.linspace(1.0, 59.0, 40, dtype=F64)
    mean = torch.zeros(40, 26, dtype=F64)
    mean[:, STATE.q], mean[:, STATE.v] = car.quaternion(t), car.velocity(t)
    _, gyro = car.imu(t)
    settings = VehicleSettings(**MOUNTED)
    h, _ = constraint_terms(mean, gyro, settings.vehicle_from_imu(mean), settings.lever_arm(mean))
    assert h.abs().max() < 1e-12
    plain, _ = constraint_terms(mean, gyro, VehicleSettings().vehicle_from_imu(mean), None)
    speed = car.car_velocity(t).norm(dim=-1)
    assert plain[:, 0].abs().mean() > 0.8 * math.sin(MOUNTED["mount_yaw_rad"]) * float(speed.mean())
    # the IMU's velocity differs from the car's by the lever arm's turn; at t = 0 the car's point is
    # the origin and the IMU lies -C_wc r_c from it
    assert (car.velocity(t) - car.car_velocity(t)).norm(dim=-1).max() > 0.01
    zero = torch.zeros(1, dtype=F64)
    r_c = torch.tensor(config.imu_lever_m, dtype=F64)
    assert torch.allclose(car.position(zero)[0], -quat.to_matrix(car.car_quaternion(zero))[0] @ r_c, atol=1e-12)


def test_a_simulated_car_slips_in_turns_pitches_as_it_speeds_up_and_rides_over_bumps():
    """What the constraint's σ must allow for, in closed form: with only the slip, the body's
    sideways velocity is ``-v cos(grade) sin(k a_lat)``; with only the pitch, its vertical one is
    ``-v sin(k a_long)`` (nose up when speeding up, down when braking); the bumps move the car up
    and down by their height, and the position is the velocity's integral throughout."""
    from flowins.data.simulate.drive import _GRADE, _SPEED, _YAW_RATE, _wave_rate, _waves

    t = torch.linspace(1.0, 290.0, 3000, dtype=F64)
    off = {"slip_per_lateral_rad": 0.0, "pitch_per_acceleration_rad": 0.0, "bump_height_m": 0.0,
           "roll_per_lateral_rad": 0.0}
    speed = Drive(DriveConfig()).speed(t)
    lateral = speed * _waves(t, _YAW_RATE)

    def body_velocity(**changes):
        car = Drive(DriveConfig(**{**off, **changes}))
        return quat.rotate(quat.conjugate(car.car_quaternion(t)), car.car_velocity(t))

    slip = body_velocity(slip_per_lateral_rad=0.02)
    assert torch.allclose(slip[:, 1], -speed * torch.cos(_waves(t, _GRADE)) * torch.sin(0.02 * lateral), atol=1e-12)
    assert slip[:, 1].abs().max() > 0.2 and slip[:, 2].abs().max() < 1e-3  # the grade's share only
    pitch = body_velocity(pitch_per_acceleration_rad=0.02)
    assert torch.allclose(pitch[:, 2], -speed * torch.sin(0.02 * _wave_rate(t, _SPEED)), atol=1e-12)
    assert pitch[:, 2].abs().max() > 0.01 and pitch[:, 1].abs().max() < 1e-12
    car = Drive(DriveConfig(**{**off, "bump_height_m": 0.05, "bump_every_s": 10.0}))
    smooth = Drive(DriveConfig(**off))
    dz = car.car_position(t)[:, 2] - smooth.car_position(t)[:, 2]
    assert float(dz.max()) == pytest.approx(0.05, rel=1e-3) and float(dz.min()) > -1e-9
    h = 1e-4
    fd = (car.position(t + h) - car.position(t - h)) / (2 * h)
    assert torch.allclose(fd, car.velocity(t), atol=1e-5)
    with pytest.raises(ValueError, match="bump_every_s=0.0"):
        DriveConfig(bump_every_s=0.0)

def test_the_gyroscope_reading_of_an_update_is_the_sample_that_covers_its_time():
    t = torch.tensor([0.0, 0.1, 0.2, 0.3], dtype=F64)
    gyro = torch.arange(12, dtype=F64).reshape(4, 3)
    got = gyro_at(t, gyro, torch.tensor([0.05, 0.1, 0.25, 0.3], dtype=F64))
    assert got.tolist() == [gyro[1].tolist(), gyro[1].tolist(), gyro[3].tolist(), gyro[3].tolist()]


def test_settings_refuse_what_they_cannot_mean():
    with pytest.raises(ValueError, match=r"VehicleSettings\.mode='sometimes': expected one of auto, on, off"):
        VehicleSettings(mode="sometimes")
    with pytest.raises(ValueError, match="the same axis"):
        VehicleSettings(forward_axis="z", up_axis="-z")
    with pytest.raises(ValueError, match="lateral_sigma_mps=0.0"):
        VehicleSettings(lateral_sigma_mps=0.0)
    with pytest.raises(ValueError, match=r"mount_yaw_rad=0.7: expected a number < 0.5"):
        VehicleSettings(mount_yaw_rad=0.7)
    with pytest.raises(ValueError, match=r"noise_model='net': expected None or a network"):
        VehicleSettings(noise_model="net")
    E = VehicleSettings(forward_axis="y", up_axis="-z").rows()
    assert E.tolist() == [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]  # lateral x, up -z


def test_a_vehicle_platform_brings_the_constraint_and_mode_off_takes_it_away():
    assert platform_streams("vehicle") == {"vehicle": VehicleConstraint()} and platform_streams(None) == {}
    from flowins.measurements.registry import NavigationContext

    from flowins.data.streams import ImuStream

    t = torch.linspace(0.0, 3.0, 31, dtype=F64)
    imu = ImuStream(t, torch.zeros(31, 3, dtype=F64), t.unsqueeze(-1).expand(31, 3).clone())
    context = NavigationContext(t_start_s=1.0, t_end_s=3.0, frame=None, dtype=F64, imu=imu)
    events = vehicle_events(VehicleConstraint(), VehicleSettings(rate_hz=2.0), context)
    assert [e.time_s for e in events] == [1.5, 2.0, 2.5, 3.0]
    assert [float(e.gyro_rps[0]) for e in events] == pytest.approx([1.5, 2.0, 2.5, 3.0])
    with pytest.raises(ValueError, match="no IMU"):
        vehicle_events(VehicleConstraint(), VehicleSettings(), dataclasses.replace(context, imu=None))
    assert vehicle_events(VehicleConstraint(), VehicleSettings(mode="off"), context) == []


@lru_cache(maxsize=1)
def drive():
    return drive_sequence(DRIVE)[0]


def outage_error(result) -> float:
    """Mean horizontal error (m) over the last 20 s of the outage."""
    f = result.frame
    shift = LocalTangentPlane(*DRIVE.origin).to_enu(f.origin_lat_deg, f.origin_lon_deg, f.origin_alt_m)
    t = result.filter.t_s
    err = result.filter.node_mean[:, STATE.p] - (Drive(DRIVE).position(t) - shift)
    t0, t1 = DRIVE.outage()
    late = (t > t1 - 20.0) & (t < t1)
    return float(err[late, :2].norm(dim=-1).mean())


@pytest.mark.slow
def test_the_constraint_keeps_a_car_on_its_road_through_a_gnss_outage():
    """The simulated car's body x is along its velocity (no slip, no lift): its sideways and
    vertical body velocity are exactly zero. Through a 60 s outage the constraint holds the
    velocity's direction to the car's heading, and the error at the end of the outage falls
    to less than half of the INS's alone."""
    e = AUTOMOTIVE_IMU
    noise = ProcessNoise(acc_noise=e.acc_noise, gyro_noise=e.gyro_noise, acc_bias_walk=e.acc_bias_walk,
                         gyro_bias_walk=e.gyro_bias_walk)
    seq = drive()
    plain = navigate(NavigationRun(seq.imu, seq.gnss), config=NavigationConfig(noise=noise))
    on = NavigationConfig(noise=noise, measurements={"vehicle": VehicleSettings(mode="on")})
    held = navigate(NavigationRun(seq.imu, seq.gnss), config=on)
    assert [x for x in held.filter.log if x.get("kind") == "vehicle"]
    assert outage_error(held) < 0.5 * outage_error(plain), (outage_error(held), outage_error(plain))
    # auto: on only with the stream a vehicle platform brings
    auto = NavigationConfig(noise=noise, measurements={"vehicle": VehicleSettings()})
    by_platform = navigate(NavigationRun(seq.imu, seq.gnss, streams=platform_streams("vehicle")), config=auto)
    assert outage_error(by_platform) == pytest.approx(outage_error(held), rel=1e-9)
    none = navigate(NavigationRun(seq.imu, seq.gnss), config=auto)
    assert not [x for x in none.filter.log if x.get("kind") == "vehicle"]


def test_cars_constrained_in_one_batch_equal_each_car_alone():
    """The drive cut to 120 s and 80 s in one batched pass: the constraint's updates act on both
    rows at once, and each row's log and track are the run's alone (to rounding)."""
    from flowins.data.streams import GnssStream, ImuStream
    from flowins.navigation import navigate_batch

    e = AUTOMOTIVE_IMU
    config = NavigationConfig(noise=ProcessNoise(acc_noise=e.acc_noise, gyro_noise=e.gyro_noise),
                              measurements={"vehicle": VehicleSettings(mode="on")})
    seq = drive()
    runs = []
    for end_s in (120.0, 80.0):
        i, g = seq.imu.t_s <= end_s, seq.gnss.t_s <= end_s
        imu = ImuStream(seq.imu.t_s[i], seq.imu.acc_mps2[i], seq.imu.gyro_rps[i], name=seq.imu.name)
        gnss = GnssStream(seq.gnss.t_s[g], seq.gnss.lat_deg[g], seq.gnss.lon_deg[g], seq.gnss.alt_m[g],
                          seq.gnss.h_acc_m[g], seq.gnss.v_acc_m[g], name=seq.gnss.name)
        runs.append(NavigationRun(imu, gnss))
    sizes = []
    batch_update = VehicleUpdate.apply_batch.__func__

    def spy(cls, chain, rows, events):
        sizes.append(len(rows))
        return batch_update(cls, chain, rows, events)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(VehicleUpdate, "apply_batch", classmethod(spy))
        together = navigate_batch(runs, config=config)
    assert max(sizes) == 2
    for run, got in zip(runs, together):
        alone = navigate(run, config=config)
        assert [(x["t_s"], x.get("kind")) for x in got.filter.log] == [(x["t_s"], x.get("kind")) for x in alone.filter.log]
        vehicle = [x for x in alone.filter.log if x.get("kind") == "vehicle"]
        assert len(vehicle) >= 79  # every second of the shorter run's 80
        got_vehicle = [x for x in got.filter.log if x.get("kind") == "vehicle"]
        assert [x["nis"] for x in got_vehicle] == pytest.approx([x["nis"] for x in vehicle], rel=1e-6, abs=1e-9)
        torch.testing.assert_close(got.filter.node_mean, alone.filter.node_mean, rtol=1e-9, atol=1e-8)


def test_the_gradient_reaches_the_constraint_sigmas_as_finite_differences_say():
    """A 20 s drive with the constraint on: d(end position error²)/d(ln σ_lat) by autograd
    through the filter against a central difference."""
    config = DriveConfig(duration_s=20.0, outage_s=0.0)
    seq = drive_sequence(config)[0]
    e = AUTOMOTIVE_IMU
    noise = ProcessNoise(acc_noise=e.acc_noise, gyro_noise=e.gyro_noise, acc_bias_walk=e.acc_bias_walk,
                         gyro_bias_walk=e.gyro_bias_walk)

    def loss(log_sigma: torch.Tensor) -> torch.Tensor:
        settings = VehicleSettings(mode="on", lateral_sigma_mps=torch.exp(log_sigma), vertical_sigma_mps=0.5)
        result = navigate(NavigationRun(seq.imu, seq.gnss),
                          config=NavigationConfig(noise=noise, measurements={"vehicle": settings}))
        f = result.frame
        shift = LocalTangentPlane(*config.origin).to_enu(f.origin_lat_deg, f.origin_lon_deg, f.origin_alt_m)
        t_end = result.filter.t_s[-1:]
        err = result.filter.node_mean[-1, STATE.p] - (Drive(config).position(t_end)[0] - shift)
        return (err * err).sum()

    a = torch.tensor(-1.0, dtype=F64, requires_grad=True)
    (grad,) = torch.autograd.grad(loss(a), a)
    h = 1e-4
    with torch.no_grad():
        difference = (loss(torch.tensor(-1.0 + h, dtype=F64)) - loss(torch.tensor(-1.0 - h, dtype=F64))) / (2 * h)
    assert torch.isfinite(grad) and abs(float(grad)) > 1e-8
    assert float(grad) == pytest.approx(float(difference), rel=1e-4, abs=1e-9)


def test_from_next_to_nothing_the_constraint_sigmas_learn_down_on_a_car():
    """experiment=real_vehicle starts both σs at 10 m/s, next to nothing, and learns them. The
    simulated car's sideways and vertical body velocity are exactly zero, so the error late in a
    GNSS outage falls as the σs fall: at 10 m/s its gradient in ln σ is positive (training steps
    σ down), and at 1 m/s the error is below that at 10 m/s."""
    config = DriveConfig(duration_s=60.0, outage_s=30.0)  # outage 15..45 s
    seq = drive_sequence(config)[0]
    e = AUTOMOTIVE_IMU
    noise = ProcessNoise(acc_noise=e.acc_noise, gyro_noise=e.gyro_noise, acc_bias_walk=e.acc_bias_walk,
                         gyro_bias_walk=e.gyro_bias_walk)

    def late_outage_error(log_sigma: torch.Tensor) -> torch.Tensor:
        sigma = torch.exp(log_sigma)
        settings = VehicleSettings(mode="on", lateral_sigma_mps=sigma, vertical_sigma_mps=sigma)
        result = navigate(NavigationRun(seq.imu, seq.gnss),
                          config=NavigationConfig(noise=noise, measurements={"vehicle": settings}))
        f = result.frame
        shift = LocalTangentPlane(*config.origin).to_enu(f.origin_lat_deg, f.origin_lon_deg, f.origin_alt_m)
        t = result.filter.t_s
        late = (t > 35.0) & (t < 45.0)
        err = result.filter.node_mean[late, :2] - (Drive(config).position(t[late])[:, :2] - shift[:2])
        return (err * err).sum(-1).mean()

    start = torch.tensor(math.log(10.0), dtype=F64, requires_grad=True)
    at_start = late_outage_error(start)
    (grad,) = torch.autograd.grad(at_start, start)
    with torch.no_grad():
        at_one = late_outage_error(torch.tensor(0.0, dtype=F64))
    assert float(grad) > 0.0, float(grad)
    assert float(at_one) < float(at_start.detach()), (float(at_one), float(at_start.detach()))


@lru_cache(maxsize=1)
def mounted_drive():
    """300 s of a car whose IMU is turned 2° (pitch) and 3° (yaw), 1 m ahead of the non-slipping point;
    it does not slip (a slip in proportion to the lateral acceleration is, at a steady speed, what a
    lever arm along the car is: ``-k v² ω`` against ``ω r``)."""
    return drive_sequence(DriveConfig(duration_s=300.0, outage_s=0.0, slip_per_lateral_rad=0.0,
                                      imu_mount_pitch_rad=math.radians(2.0),
                                      imu_mount_yaw_rad=math.radians(3.0), imu_lever_m=(-1.0, 0.0, 0.0)))[0]


def automotive_noise() -> ProcessNoise:
    e = AUTOMOTIVE_IMU
    return ProcessNoise(acc_noise=e.acc_noise, gyro_noise=e.gyro_noise, acc_bias_walk=e.acc_bias_walk,
                        gyro_bias_walk=e.gyro_bias_walk)


def test_the_mounting_fit_finds_an_imu_mounted_off_the_cars_axes_from_the_smoothed_track():
    """A 300 s drive whose IMU is turned 2° (pitch) and 3° (yaw) from the car's axes, 1 m ahead of
    its non-slipping point: fitted on the smoothed track of a run without the constraint, the
    mounting comes within 0.5° of the truth and the lever arm's forward part within 0.3 m, and
    the constraint's residual falls to a fifth."""
    from flowins.measurements.vehicle import fit_mounting

    seq, noise = mounted_drive(), automotive_noise()
    smoothed = navigate(NavigationRun(seq.imu, seq.gnss), config=NavigationConfig(noise=noise)).smoother
    gyro = gyro_at(seq.imu.t_s, seq.imu.gyro_rps, torch.as_tensor(smoothed.t_s, dtype=F64))
    fit = fit_mounting(smoothed.node_mean, gyro)
    assert abs(math.degrees(fit.mount_pitch_rad) - 2.0) < 0.5 and abs(math.degrees(fit.mount_yaw_rad) - 3.0) < 0.5, fit
    assert abs(fit.lever_m[0] + 1.0) < 0.3, fit
    assert fit.rms_after_mps < 0.2 * fit.rms_before_mps and fit.samples > 1000
    assert "filter.measurements.vehicle.mount_yaw_rad=0.05" in " ".join(fit.overrides())
    with torch.inference_mode():  # as the jobs call it; forward-mode AD must still see the parameters
        again = fit_mounting(smoothed.node_mean, gyro)
    assert (again.mount_pitch_rad, again.mount_yaw_rad, *again.lever_m) == pytest.approx(
        (fit.mount_pitch_rad, fit.mount_yaw_rad, *fit.lever_m), abs=1e-9)
    with pytest.raises(ValueError, match="0 samples at 100.0 m/s or faster"):
        fit_mounting(smoothed.node_mean, gyro, min_speed_mps=100.0)
    broken = smoothed.node_mean.clone()
    broken[10, STATE.v] = float("nan")
    with pytest.raises(ValueError, match="not finite"):
        fit_mounting(broken, gyro)


@pytest.mark.slow
def test_mounting_fit_runs_a_first_pass_and_uses_the_fit_where_it_explains_the_track():
    """``mounting=fit``: the run's mounting comes from a first pass without the constraint, and
    the run equals one given those values; where the fit must explain more than it can
    (``fit_max_residual``) the configured mounting stays, and the record says why."""
    seq, noise = mounted_drive(), automotive_noise()
    run = NavigationRun(seq.imu, seq.gnss)
    fitted = navigate(run, config=NavigationConfig(noise=noise, measurements={
        "vehicle": VehicleSettings(mode="on", mounting="fit")}))
    record = fitted.vehicle_mounting
    assert record["used"] and record["residual_mps"][1] < 0.25 * record["residual_mps"][0], record
    assert abs(math.degrees(record["mount_yaw_rad"]) - 3.0) < 0.5, record
    lever = dict(zip(("lever_forward_m", "lever_left_m", "lever_up_m"), record["lever_m"]))
    given = navigate(run, config=NavigationConfig(noise=noise, measurements={"vehicle": VehicleSettings(
        mode="on", mount_pitch_rad=record["mount_pitch_rad"], mount_yaw_rad=record["mount_yaw_rad"], **lever)}))
    torch.testing.assert_close(fitted.filter.node_mean, given.filter.node_mean, rtol=0, atol=1e-9)
    assert given.vehicle_mounting is None
    strict = navigate(run, config=NavigationConfig(noise=noise, measurements={
        "vehicle": VehicleSettings(mode="on", mounting="fit", fit_max_residual=0.01)}))
    assert not strict.vehicle_mounting["used"] and "fit_max_residual=0.01" in strict.vehicle_mounting["reason"]
    plain = navigate(run, config=NavigationConfig(noise=noise, measurements={"vehicle": VehicleSettings(mode="on")}))
    torch.testing.assert_close(strict.filter.node_mean, plain.filter.node_mean, rtol=0, atol=1e-9)
