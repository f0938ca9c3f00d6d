"""A sensor added in the registry's three places (model + events, settings, registration):
a toy barometer, checked against the simulated walk's truth and the scalar Kalman update."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import pytest
import torch
from torch import Tensor

from flowins.data.streams import ImuStream
from flowins.data.synthetic import synthetic_walk_recording
from flowins.filter.chain import ChainBuilder
from flowins.filter.updater import update
from flowins.measurements.registry import (
    MEASUREMENTS,
    MeasurementKind,
    NavigationContext,
    measurement_settings,
    register,
)
from flowins.batching import carries_gradient
from flowins.navigation import NavigationConfig, NavigationRun, navigate
from flowins.start import StartSettings, StillSettings
from flowins.state import STATE, STATE_DIM

F64 = torch.float64
UP = STATE.p.start + 2  # the up coordinate of the position


# --------------------------------------------------------------------------- the sensor


@dataclass(frozen=True)
class BarometerSettings:
    """``filter.measurements.barometer``."""

    #: the height noise σ (m)
    sigma_m: float | Tensor = 0.3


@dataclass(frozen=True)
class BarometerStream:
    """Heights above the ENU origin ``height_m (K,)`` (m) at ``t_s (K,)`` (s)."""

    t_s: Tensor
    height_m: Tensor


@dataclass(frozen=True)
class BarometerReading:
    """One height ``z = p_up + n``, ``n ~ N(0, σ²)``, as a filter event."""

    time_s: float
    height_m: Tensor
    sigma_m: float | Tensor
    name: str = "barometer"

    def apply(self, chain: ChainBuilder) -> None:
        mean = chain.mean
        H = torch.zeros(1, 1, mean.shape[-1], dtype=mean.dtype, device=mean.device)
        H[0, 0, UP] = 1.0
        sigma = torch.as_tensor(self.sigma_m, dtype=mean.dtype, device=mean.device)
        update(chain, H=H, residual=(self.height_m.to(mean) - mean[UP]).reshape(1, 1),
               noise_cov=(sigma**2).reshape(1, 1, 1), kind="barometer", name=self.name)


def barometer_events(stream: BarometerStream, settings: BarometerSettings,
                     context: NavigationContext) -> list[BarometerReading]:
    return [BarometerReading(float(t), stream.height_m[i], settings.sigma_m, f"barometer row {i}")
            for i, t in enumerate(stream.t_s.tolist()) if t >= context.t_start_s]


@pytest.fixture
def barometer():
    """The barometer registered for one test, and gone after it."""
    kind = register(MeasurementKind("barometer", BarometerSettings, barometer_events))
    yield kind
    del MEASUREMENTS["barometer"]


# --------------------------------------------------------------------------- the checks


@pytest.fixture(scope="module")
def walk():
    return synthetic_walk_recording(duration_s=20.0, seed=2)


def heights(walk, sigma_m: float, rate_hz: float = 5.0) -> BarometerStream:
    """The truth's up position at ``rate_hz`` within the IMU span, plus white noise of σ ``sigma_m``."""
    t = torch.arange(1.0 / rate_hz, float(walk.imu.t_s[-1]), 1.0 / rate_hz, dtype=F64)
    gen = torch.Generator().manual_seed(7)
    return BarometerStream(t, true_up(walk, t) + sigma_m * torch.randn(t.shape, generator=gen, dtype=F64))


def true_up(walk, t_s: Tensor) -> Tensor:
    """The walk's height above its start (the ENU origin of a run without GNSS) at ``t_s``."""
    return walk.walk.position(t_s)[:, 2] - walk.walk.position(walk.imu.t_s[:1])[0, 2]


def up_rmse(result, walk) -> float:
    error = result.filter.node_mean[:, UP] - true_up(walk, result.filter.t_s)
    return float(error.pow(2).mean().sqrt())


def test_a_barometer_bounds_the_vertical_drift_of_the_ins(barometer, walk):
    """INS alone (no GNSS), started from the ground truth so that no still phase calibrates
    the accelerometer: its bias and scale errors make the height drift by metres; 5 Hz
    heights of σ 0.3 m hold it within that σ of the truth."""
    # the ground-truth start without the still start's calibration (its min_s beyond the walk)
    config = NavigationConfig(start=StartSettings(mode="groundtruth", still=StillSettings(min_s=1000.0)),
                              measurements={"barometer": BarometerSettings(sigma_m=0.3)})
    stream = heights(walk, 0.3)
    alone = navigate(NavigationRun(walk.imu, truth=walk.truth), config=config)
    aided = navigate(NavigationRun(walk.imu, truth=walk.truth, streams={"barometer": stream}), config=config)
    readings = [e for e in aided.filter.log if e.get("kind") == "barometer"]
    assert len(readings) == len(stream.t_s) and not [e for e in alone.filter.log if e.get("kind") == "barometer"]
    assert up_rmse(aided, walk) < 0.3
    assert up_rmse(aided, walk) * 5.0 < up_rmse(alone, walk), (up_rmse(aided, walk), up_rmse(alone, walk))


def test_one_barometer_reading_is_the_scalar_kalman_update():
    """On a Gaussian prior whose quaternions are uncorrelated with the height (so their
    normalisation changes nothing): ``K = P h / (h P h + σ²)``, ``m⁺ = m + K (z - m_up)``,
    ``P⁺ = P - K h P``."""
    gen = torch.Generator().manual_seed(3)
    mean = torch.randn(STATE_DIM, generator=gen, dtype=F64)
    mean[STATE.q] = mean[STATE.q] / mean[STATE.q].norm()
    mean[STATE.q_prev] = mean[STATE.q_prev] / mean[STATE.q_prev].norm()
    quaternion = torch.zeros(STATE_DIM, dtype=torch.bool)
    quaternion[STATE.q] = quaternion[STATE.q_prev] = True
    # rows of A mix only within the quaternions or only within the rest: P is block-diagonal in the two
    A = torch.randn(STATE_DIM, STATE_DIM, generator=gen, dtype=F64) * (quaternion[:, None] == quaternion[None, :])
    cov = A @ A.T / STATE_DIM + 0.1 * torch.eye(STATE_DIM, dtype=F64)
    z, sigma = torch.tensor(1.7, dtype=F64), 0.4
    chain = ChainBuilder()
    chain.add_node(0.0, torch.eye(STATE_DIM, dtype=F64), mean, cov)
    BarometerReading(0.0, z, sigma).apply(chain)
    gain = cov[:, UP] / (cov[UP, UP] + sigma**2)
    assert torch.allclose(chain.mean, mean + gain * (z - mean[UP]), rtol=0.0, atol=1e-12)
    up_variance = cov[UP, UP] * sigma**2 / (cov[UP, UP] + sigma**2)
    assert abs(float(chain.cov[UP, UP] - up_variance)) < 1e-12
    assert torch.allclose(chain.cov, cov - torch.outer(gain, cov[UP]), rtol=0.0, atol=1e-12)
    assert chain.log[-1]["kind"] == "barometer" and chain.log[-1]["accepted"] == 1.0


def test_unknown_streams_and_keys_name_what_is_registered(barometer, walk):
    imu = ImuStream(walk.imu.t_s[:200], walk.imu.acc_mps2[:200], walk.imu.gyro_rps[:200], name="short IMU")
    with pytest.raises(ValueError, match=r"unknown measurement kind 'sonar'; registered kinds: barometer"):
        navigate(NavigationRun(imu, streams={"sonar": heights(walk, 0.3)}))
    with pytest.raises(ValueError, match="already registered"):
        register(MeasurementKind("barometer", BarometerSettings, barometer_events))
    # the config node filter.measurements builds each kind's settings, checked
    assert measurement_settings({"barometer": {"sigma_m": 0.2}}) == {"barometer": BarometerSettings(sigma_m=0.2)}
    assert measurement_settings({"barometer": None}) == {"barometer": BarometerSettings()}
    with pytest.raises(ValueError, match=r"filter\.measurements\.barometer\.sigma: unknown key"):
        measurement_settings({"barometer": {"sigma": 0.2}})
    with pytest.raises(ValueError, match=r"filter\.measurements\.sonar: .*registered kinds: barometer"):
        measurement_settings({"sonar": {}})


def test_a_settings_tensor_carries_its_gradient_through_the_filter(barometer, walk):
    """The registry's settings reach the graph: d(last up)/dσ by autograd equals central differences."""
    n = int((walk.imu.t_s <= 4.0).sum())
    imu = ImuStream(walk.imu.t_s[:n], walk.imu.acc_mps2[:n], walk.imu.gyro_rps[:n], name="4 s of the walk")
    stream = heights(walk, 0.3)
    keep = stream.t_s <= float(imu.t_s[-1])
    run = NavigationRun(imu, streams={"barometer": BarometerStream(stream.t_s[keep], stream.height_m[keep])})

    def last_up(sigma):
        config = NavigationConfig(measurements={"barometer": BarometerSettings(sigma_m=sigma)})
        return navigate(run, config=config).filter.node_mean[-1, UP]

    sigma = torch.tensor(0.3, dtype=F64, requires_grad=True)
    assert carries_gradient(run, NavigationConfig(measurements={"barometer": BarometerSettings(sigma)}))
    assert not carries_gradient(dataclasses.replace(run, streams={"barometer": stream}))
    (grad,) = torch.autograd.grad(last_up(sigma), sigma)
    eps = 1e-5
    fd = (last_up(0.3 + eps) - last_up(0.3 - eps)) / (2 * eps)
    assert abs(float(grad) - float(fd)) <= 1e-6 * max(1.0, abs(float(fd)))
