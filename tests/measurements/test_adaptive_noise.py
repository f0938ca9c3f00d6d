"""Adaptive noise: the IMU windows, the bounded factors, the gradient through the filter and a checkpoint."""
from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from flowins.data.simulate.drive import AUTOMOTIVE_IMU, DriveConfig, drive_sequence
from flowins.geometry import quaternion as quat
from flowins.ins.mechanization import ProcessNoise
from flowins.measurements.adaptive_noise import RECENT_SAMPLES, AdaptiveNoise, imu_windows, steady_window
from flowins.measurements.vehicle import VehicleSettings
from flowins.navigation import NavigationConfig, NavigationRun, navigate
from flowins.state import STATE

F64 = torch.float64


def test_a_window_holds_the_samples_up_to_the_one_that_covers_its_time():
    t = torch.arange(10, dtype=F64) * 0.1
    gyro = torch.arange(30, dtype=F64).reshape(10, 3)
    acc = -gyro
    w = imu_windows(t, acc, gyro, torch.tensor([0.25, 0.05], dtype=F64), samples=4)
    assert w.shape == (2, 6, 4)
    assert w[0, 0].tolist() == [0.0, 3.0, 6.0, 9.0]  # samples 0..3; sample 3 covers (0.2, 0.3]
    assert w[1, 0].tolist() == [0.0, 0.0, 0.0, 3.0]  # before the first sample it repeats
    assert torch.allclose(w[0, 3:], -w[0, :3] / 9.80665)


def test_the_factors_start_at_one_and_stay_within_their_decades():
    net = AdaptiveNoise(decades=0.5)
    windows = torch.randn(7, 6, 100, dtype=F64, generator=torch.Generator().manual_seed(0))
    assert torch.equal(net(windows), torch.ones(7, 2, dtype=F64))
    with torch.no_grad():
        for p in net.parameters():
            p.normal_(0.0, 30.0, generator=torch.Generator().manual_seed(1))
    s = net(windows)
    assert s.min() >= 10 ** -0.5 * (1 - 1e-12) and s.max() <= 10 ** 0.5 * (1 + 1e-12) and s.std() > 0.1


@pytest.fixture(scope="module")
def short_drive():
    return drive_sequence(DriveConfig(duration_s=20.0, outage_s=0.0))[0]


def _loss(seq, net: AdaptiveNoise) -> torch.Tensor:
    e = AUTOMOTIVE_IMU
    noise = ProcessNoise(acc_noise=e.acc_noise, gyro_noise=e.gyro_noise)
    settings = VehicleSettings(mode="on", rate_hz=5.0, lateral_sigma_mps=0.3, noise_model=net)
    result = navigate(NavigationRun(seq.imu, seq.gnss), config=NavigationConfig(noise=noise,
                                                                                 measurements={"vehicle": settings}))
    return result.filter.node_mean[-1, STATE.v].pow(2).sum()


def test_an_untrained_network_is_the_constant_sigmas_and_its_gradient_is_the_finite_difference(short_drive):
    """Through the filter: with the head at zero the run equals the constant σs'; d(loss)/d(head
    bias) by autograd equals a central difference, for a loss on the last velocity."""
    net = AdaptiveNoise()
    e = AUTOMOTIVE_IMU
    constant = navigate(NavigationRun(short_drive.imu, short_drive.gnss), config=NavigationConfig(
        noise=ProcessNoise(acc_noise=e.acc_noise, gyro_noise=e.gyro_noise),
        measurements={"vehicle": VehicleSettings(mode="on", rate_hz=5.0, lateral_sigma_mps=0.3)}))
    with torch.no_grad():
        assert float(_loss(short_drive, net)) == pytest.approx(float(constant.filter.node_mean[-1, STATE.v].pow(2).sum()),
                                                               rel=1e-12)
    with torch.no_grad():  # away from the start, where the ReLUs and tanh are all in play
        net.head.weight.normal_(0.0, 0.5, generator=torch.Generator().manual_seed(2))
        net.head.bias.copy_(torch.tensor([0.3, -0.2], dtype=F64))
    loss = _loss(short_drive, net)
    (grad,) = torch.autograd.grad(loss, net.head.bias)
    h = 1e-5
    for i in range(2):
        with torch.no_grad():
            net.head.bias[i] += h
            up = float(_loss(short_drive, net))
            net.head.bias[i] -= 2 * h
            down = float(_loss(short_drive, net))
            net.head.bias[i] += h
        assert float(grad[i]) == pytest.approx((up - down) / (2 * h), rel=1e-4, abs=1e-12), i
    assert grad.abs().max() > 0


def test_a_checkpoint_keeps_the_network_and_evaluate_uses_it(tmp_path, short_drive):
    from flowins.training.module import FilterLearner
    from flowins.training.parameters import FilterParameters, starting_values

    params = FilterParameters(starting_values(NavigationConfig()), learn=["acc_noise"], adaptive=["vehicle"])
    assert all(p.requires_grad for p in params.adaptive.parameters())
    with torch.no_grad():
        for p in params.adaptive.parameters():
            p.normal_(0.0, 0.3, generator=torch.Generator().manual_seed(3))
    path = tmp_path / "adaptive.ckpt"
    torch.save({"state_dict": FilterLearner(params, NavigationConfig(), methods=["ins"]).state_dict()}, path)
    loaded = FilterParameters.from_checkpoint(path)
    windows = torch.randn(5, 6, 100, dtype=F64, generator=torch.Generator().manual_seed(4))
    assert torch.equal(loaded.adaptive["vehicle"](windows), params.adaptive["vehicle"](windows).detach())
    assert not any(p.requires_grad for p in loaded.adaptive.parameters())
    config = loaded.apply(NavigationConfig(measurements={"vehicle": VehicleSettings(mode="on")}), training=False)
    assert config.measurements["vehicle"].noise_model is loaded.adaptive["vehicle"]
    # a checkpoint without it has none
    plain = FilterParameters(starting_values(NavigationConfig()), learn=["acc_noise"])
    torch.save({"state_dict": FilterLearner(plain, NavigationConfig(), methods=["ins"]).state_dict()}, path)
    assert len(FilterParameters.from_checkpoint(path).adaptive) == 0
    with pytest.raises(ValueError, match="model.adaptive: \\['zupt'\\]; expected kinds from \\['vehicle'\\]"):
        from flowins.training.parameters import ModelSettings
        ModelSettings(adaptive=("zupt",))
    assert math.isfinite(float(_loss(short_drive, loaded.adaptive["vehicle"]).detach()))


# ------------------------------------------------------------------ the mounting's angles
def test_angles_start_at_zero_stay_within_their_bound_and_vanish_on_the_steady_window():
    net = AdaptiveNoise(angles=2, angle_bound_rad=0.03)
    windows = torch.randn(7, 6, 100, dtype=F64, generator=torch.Generator().manual_seed(5))
    factors, angles = net(windows)
    assert torch.equal(factors, torch.ones(7, 2, dtype=F64)) and torch.equal(angles, torch.zeros(7, 2, dtype=F64))
    with torch.no_grad():
        for p in net.parameters():
            p.normal_(0.0, 30.0, generator=torch.Generator().manual_seed(6))
    _, angles = net(windows)
    assert angles.abs().max() <= 0.03 and angles.std() > 1e-3
    up = torch.tensor([0.1, -0.2, 0.97], dtype=F64)
    steady = steady_window(up)
    assert steady.shape == (1, 6, 100) and torch.equal(steady[0, 3:, 0], up) and not steady[0, :3].any()
    _, at_steady = net(steady.expand(3, 6, 100), steady)
    assert torch.equal(at_steady, torch.zeros(3, 2, dtype=F64))  # whatever the weights
    moderate = AdaptiveNoise(angles=2, angle_bound_rad=0.03)
    with torch.no_grad():
        for p in moderate.parameters():
            p.normal_(0.0, 0.01, generator=torch.Generator().manual_seed(6))
    _, absolute = moderate(windows)
    _, relative = moderate(windows, steady)
    assert not torch.allclose(relative, absolute)


def test_the_recent_path_is_a_linear_map_of_the_last_readings_mean():
    """With the convolutions' head at zero the angles are A tanh(W r / A), r the mean of the last
    RECENT_SAMPLES readings: a closed form."""
    net = AdaptiveNoise(angles=2, angle_bound_rad=0.05)
    W = torch.tensor([[0.0, 0.0, 0.0, -0.1, 0.0, 0.0], [0.0, 0.0, 0.2, 0.0, 0.05, 0.0]], dtype=F64)
    with torch.no_grad():
        net.recent.weight.copy_(W)
        for p in (*net.conv1.parameters(), *net.conv2.parameters()):
            p.normal_(0.0, 1.0, generator=torch.Generator().manual_seed(7))
    windows = torch.randn(4, 6, 100, dtype=F64, generator=torch.Generator().manual_seed(8))
    r = windows[..., -RECENT_SAMPLES:].mean(-1)
    _, angles = net(windows)
    assert torch.allclose(angles, 0.05 * torch.tanh(r @ W.T / 0.05), rtol=0, atol=1e-15)


def _drive_loss(seq, model, **settings) -> torch.Tensor:
    e = AUTOMOTIVE_IMU
    noise = ProcessNoise(acc_noise=e.acc_noise, gyro_noise=e.gyro_noise)
    vehicle = VehicleSettings(mode="on", rate_hz=5.0, lateral_sigma_mps=0.05, vertical_sigma_mps=0.05,
                              noise_model=model, **settings)
    result = navigate(NavigationRun(seq.imu, seq.gnss), config=NavigationConfig(noise=noise,
                                                                                 measurements={"vehicle": vehicle}))
    return result.filter.node_mean[-1, STATE.v].pow(2).sum()


def test_constant_angles_from_the_network_are_the_mounting_they_add_to(short_drive):
    """An offset of (pitch, yaw) at every update runs as the mounting turned by it: the same
    filter, by another code path (one matrix per update against the settings' one)."""
    offset = torch.tensor([0.02, -0.03], dtype=F64)

    def constant(windows, steady=None):
        return torch.ones(len(windows), 2, dtype=F64), offset.expand(len(windows), 2)

    with torch.no_grad():
        by_offset = _drive_loss(short_drive, constant, mount_pitch_rad=0.01)
        by_mounting = _drive_loss(short_drive, None, mount_pitch_rad=0.03, mount_yaw_rad=-0.03)
        plain = _drive_loss(short_drive, None, mount_pitch_rad=0.01)
    assert float(by_offset) == pytest.approx(float(by_mounting), rel=1e-10)
    assert float(by_offset) != pytest.approx(float(plain), rel=1e-3)


@pytest.mark.parametrize("compensate, entries, seed", [(False, ((0, 3), (1, 4), (1, 2)), 9),
                                                     (True, ((0, 3), (1, 4), (0, 5), (1, 2)), 15)])
def test_the_angles_gradient_through_the_filter_is_the_finite_difference(short_drive, compensate, entries, seed):
    """d(loss)/d(the linear path's weights) by autograd equals a central difference, also where the
    angles read the filter's attitude, bias and scale at each update (``compensate_gravity``)."""
    net = AdaptiveNoise(angles=2, angle_bound_rad=0.05, compensate_gravity=compensate)
    with torch.no_grad():
        net.recent.weight.normal_(0.0, 0.05, generator=torch.Generator().manual_seed(seed))
    loss = _drive_loss(short_drive, net, lever_forward_m=-1.2)
    (grad,) = torch.autograd.grad(loss, net.recent.weight)
    h = 1e-6
    for i, j in entries:
        with torch.no_grad():
            net.recent.weight[i, j] += h
            up = float(_drive_loss(short_drive, net, lever_forward_m=-1.2))
            net.recent.weight[i, j] -= 2 * h
            down = float(_drive_loss(short_drive, net, lever_forward_m=-1.2))
            net.recent.weight[i, j] += h
        assert float(grad[i, j]) == pytest.approx((up - down) / (2 * h), rel=1e-4, abs=1e-12), (i, j)
    assert grad[:, 3:].abs().min() > 0


def test_a_checkpoint_keeps_the_angles_and_their_bound(tmp_path):
    from flowins.config import build
    from flowins.training.module import FilterLearner
    from flowins.training.parameters import FilterParameters, ModelSettings, starting_values

    params = FilterParameters(starting_values(NavigationConfig()), learn=["acc_noise"], adaptive=["vehicle"],
                              adaptive_angles_rad=0.04)
    with torch.no_grad():
        for p in params.adaptive.parameters():
            p.normal_(0.0, 0.3, generator=torch.Generator().manual_seed(10))
    path = tmp_path / "angles.ckpt"
    torch.save({"state_dict": FilterLearner(params, NavigationConfig(), methods=["ins"]).state_dict()}, path)
    loaded = FilterParameters.from_checkpoint(path).adaptive["vehicle"]
    assert loaded.angles == 2 and float(loaded.angle_bound_rad) == 0.04
    windows = torch.randn(5, 6, 100, dtype=F64, generator=torch.Generator().manual_seed(11))
    for a, b in zip(loaded(windows), params.adaptive["vehicle"](windows)):
        assert torch.equal(a, b.detach())
    state = torch.load(path, weights_only=True)
    state["state_dict"]["params.adaptive.vehicle.angle_bound_rad"] = torch.tensor(2.0, dtype=F64)
    torch.save(state, path)
    with pytest.raises(ValueError, match=r"angle_bound_rad=.*expected one number in \(0, 0.5\] rad"):
        FilterParameters.from_checkpoint(path)
    with pytest.raises(ValueError, match="model.adaptive_angles_rad"):
        build(ModelSettings, {"adaptive_angles_rad": 0.7}, "model")


# ------------------------------------------------------------------ angles from the car's acceleration

def test_the_acceleration_is_the_specific_force_less_gravity_in_the_imus_axes():
    """On a simulated car on a sloped road, with the true attitude: the specific force less gravity
    is the velocity's rate in the IMU's axes (a central difference), for the filter's gravity."""
    from flowins.data.simulate.drive import Drive
    from flowins.measurements.adaptive_noise import acceleration_g

    car = Drive(DriveConfig(grade_scale=3.0, imu_mount_pitch_rad=0.03, imu_mount_yaw_rad=-0.02))
    t = torch.linspace(5.0, 200.0, 60, dtype=F64)
    g = 9.79
    force, _ = car.imu(t, gravity_mps2=g)
    h = 1e-5
    rate = (car.velocity(t + h) - car.velocity(t - h)) / (2 * h)
    q = car.quaternion(t)
    expected = quat.rotate(quat.conjugate(q), rate) / 9.80665
    got = acceleration_g(force / 9.80665, q, g)
    assert torch.allclose(got, expected, rtol=0, atol=1e-8)  # a difference's error: 2e-9 at h = 1e-5 s
    slope_part = quat.rotate(quat.conjugate(q), torch.tensor([0.0, 0.0, g], dtype=F64).expand(60, 3))[:, 0]
    assert slope_part.abs().max() > 0.2  # the specific force's forward part holds g sin(slope): not small
    batch = acceleration_g((force / 9.80665).reshape(3, 20, 3), q.reshape(3, 20, 4), g)
    assert torch.allclose(batch.reshape(60, 3), got, rtol=0, atol=1e-15)
    # an accelerometer that reads f / T_a + b_a (the mechanization's model), corrected by both
    bias = torch.tensor([0.05, -0.03, 0.08], dtype=F64)
    scale = torch.tensor([1.01, 0.98, 1.02], dtype=F64)
    measured = (force / scale + bias) / 9.80665
    corrected = acceleration_g(measured, q, g, acc_bias_mps2=bias.expand(60, 3), acc_scale=scale.expand(60, 3))
    assert torch.allclose(corrected, got, rtol=0, atol=1e-14)
    assert (acceleration_g(measured, q, g) - got).abs().max() > 1e-3


def _acceleration_network(bound: float = 0.05, seed: int = 12) -> AdaptiveNoise:
    net = AdaptiveNoise(angles=2, angle_bound_rad=bound, compensate_gravity=True)
    with torch.no_grad():
        for p in net.parameters():
            p.normal_(0.0, 0.1, generator=torch.Generator().manual_seed(seed))
    return net


def test_an_acceleration_network_adds_the_acceleration_where_the_specific_force_was():
    """Closed form: angles ``A tanh((y_head + W_w ω̄ + W_f a) / A)`` relative to the steady car's
    (whose acceleration is 0); ``split`` then ``bounded_angles`` is ``forward``; without the
    acceleration it refuses."""
    net = _acceleration_network()
    assert net.compensates_gravity and not AdaptiveNoise(angles=2).compensates_gravity
    windows = torch.randn(5, 6, 100, dtype=F64, generator=torch.Generator().manual_seed(13))
    accel = torch.randn(5, 3, dtype=F64, generator=torch.Generator().manual_seed(14)) * 0.2
    steady = steady_window(torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    factors, angles = net(windows, steady, accel)
    plain = AdaptiveNoise(angles=2, angle_bound_rad=0.05)
    plain.load_state_dict({k: v for k, v in net.state_dict().items() if k != "compensate_gravity"})
    W = net.recent.weight.detach()
    with torch.no_grad():  # the head's part (unbounded), by the network without its linear path
        plain.recent.weight.zero_()
        head_factors, head = plain.split(windows, steady)
    gyro_mean = windows[:, :3, -RECENT_SAMPLES:].mean(-1)
    y = head + gyro_mean @ W[:, :3].T + accel @ W[:, 3:].T
    assert torch.allclose(angles, 0.05 * torch.tanh(y / 0.05), rtol=0, atol=1e-12)
    assert torch.equal(factors, head_factors) and head.abs().min() > 1e-3
    f, y_split = net.split(windows, steady)
    assert torch.equal(net.bounded_angles(y_split, accel), angles) and torch.equal(f, factors)
    _, at_steady = net(steady.expand(2, 6, 100), steady, torch.zeros(2, 3, dtype=F64))
    assert torch.equal(at_steady, torch.zeros(2, 2, dtype=F64))
    with pytest.raises(ValueError, match="expected acceleration"):
        net(windows, steady)
    with pytest.raises(ValueError, match="compensate_gravity=True without angles"):
        AdaptiveNoise(compensate_gravity=True)


def _law_network(slip: float, pitch: float, *, compensate: bool) -> AdaptiveNoise:
    """The simulated car's slip and pitch law on the recent force (g) along x (forward), y (left)."""
    net = AdaptiveNoise(angles=2, angle_bound_rad=0.1, compensate_gravity=compensate)
    with torch.no_grad():
        net.recent.weight[0, 3] = -pitch * 9.80665
        net.recent.weight[1, 4] = slip * 9.80665
    return net


def test_on_a_sloped_road_the_acceleration_law_sets_the_cars_own_pitch_through_the_filter():
    """Through the filter on a car whose pitch follows its forward acceleration, on a sloped road:
    the law read from the acceleration at each update (the filter's attitude) is the simulated
    car's pitch, ``-k a_forward``, within 1.5 mrad RMS (the filter's attitude and bias errors, the
    IMU's noise), with an accelerometer 0.2 m/s² off too (the filter's bias estimate corrects
    it); read from the specific force, the slope (up to 0.09 rad here, ``k g sin(slope)``: up to
    18 mrad) throws it off by more than 6."""
    from flowins.data.simulate.drive import _SPEED, _wave_rate
    from flowins.measurements.adaptive_noise import AdaptiveNoise as Net

    from flowins.data.synthetic import Imperfections

    config = DriveConfig(duration_s=90.0, outage_s=0.0, grade_scale=3.0, slip_per_lateral_rad=0.0,
                         pitch_per_acceleration_rad=0.02, bump_height_m=0.0)
    sequences = {"plain": drive_sequence(config)[0],  # and an accelerometer off by 0.2 m/s² forward
                 "biased": drive_sequence(dataclasses.replace(
                     config, imperfections=Imperfections(acc_bias_mps2=(0.2, 0.0, 0.0))))[0]}
    seen: list[torch.Tensor] = []
    original = Net.bounded_angles

    def spy(self, y, acceleration=None):
        out = original(self, y, acceleration)
        seen.append(out.detach())
        return out

    e = AUTOMOTIVE_IMU
    noise = ProcessNoise(acc_noise=e.acc_noise, gyro_noise=e.gyro_noise)
    errors = {}
    for case, compensate in (("plain", True), ("plain", False), ("biased", True)):
        seq = sequences[case]
        seen.clear()
        vehicle = VehicleSettings(mode="on", rate_hz=1.0, lateral_sigma_mps=0.1, vertical_sigma_mps=0.1,
                                  noise_model=_law_network(0.0, 0.02, compensate=compensate))
        with pytest.MonkeyPatch.context() as mp, torch.no_grad():
            mp.setattr(Net, "bounded_angles", spy)
            navigate(NavigationRun(seq.imu, seq.gnss), config=NavigationConfig(noise=noise,
                                                                              measurements={"vehicle": vehicle}))
        pitch = torch.cat(seen)[:, 0]
        t = torch.arange(1, len(pitch) + 1, dtype=F64) + float(seq.imu.t_s[0])
        truth = -0.02 * _wave_rate(t - 0.1, _SPEED)  # the last 0.2 s's mean: at its middle
        errors[case, compensate] = (pitch - truth)[20:].pow(2).mean().sqrt()  # once the filter has settled
    assert errors["plain", True] < 1.5e-3 and errors["plain", False] > 6e-3, errors
    assert errors["biased", True] < 1.5e-3, errors  # the filter's bias estimate taken out (4 mrad if not)


def test_a_checkpoint_keeps_an_acceleration_network_and_settings_refuse_it_without_angles(tmp_path):
    from flowins.training.module import FilterLearner
    from flowins.training.parameters import FilterParameters, ModelSettings, starting_values

    params = FilterParameters(starting_values(NavigationConfig()), learn=["acc_noise"], adaptive=["vehicle"],
                              adaptive_angles_rad=0.04, adaptive_compensate_gravity=True)
    network = params.adaptive["vehicle"]
    assert network.compensates_gravity
    with torch.no_grad():
        for p in params.adaptive.parameters():
            p.normal_(0.0, 0.3, generator=torch.Generator().manual_seed(16))
    path = tmp_path / "acceleration.ckpt"
    torch.save({"state_dict": FilterLearner(params, NavigationConfig(), methods=["ins"]).state_dict()}, path)
    loaded = FilterParameters.from_checkpoint(path).adaptive["vehicle"]
    assert loaded.compensates_gravity and float(loaded.angle_bound_rad) == 0.04
    windows = torch.randn(5, 6, 100, dtype=F64, generator=torch.Generator().manual_seed(17))
    accel = torch.randn(5, 3, dtype=F64, generator=torch.Generator().manual_seed(18)) * 0.1
    for a, b in zip(loaded(windows, None, accel), network(windows, None, accel)):
        assert torch.equal(a, b.detach())
    state = torch.load(path, weights_only=True)
    for key in [k for k in state["state_dict"] if k.endswith(("angle_bound_rad", "recent.weight"))]:
        del state["state_dict"][key]
    torch.save(state, tmp_path / "broken.ckpt")
    with pytest.raises(ValueError, match=r"broken.ckpt: the adaptive network for vehicle reads the car's acceleration"):
        FilterParameters.from_checkpoint(tmp_path / "broken.ckpt")
    plain = FilterParameters(starting_values(NavigationConfig()), learn=[], adaptive=["vehicle"], adaptive_angles_rad=0.04)
    assert not plain.adaptive["vehicle"].compensates_gravity
    for bad in ({"adaptive": ("vehicle",)}, {"adaptive_angles_rad": 0.05}):
        with pytest.raises(ValueError, match="model.adaptive_compensate_gravity=true: it acts on the angles"):
            ModelSettings(adaptive_compensate_gravity=True, **bad)
    ModelSettings(adaptive=("vehicle",), adaptive_angles_rad=0.05, adaptive_compensate_gravity=True)
