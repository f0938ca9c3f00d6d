"""Gradients of the filter's output with respect to the learned parameters.

The scenario is built by hand: a constant velocity with a constant yaw rate (so the
IMU readings are exact for the midpoint mechanization), a pinhole camera on the IMU
with the simulator's mounting, and flow points projected exactly from a known point
cloud at the true camera poses. Everything the filter sees that depends on a learned
parameter is written by :meth:`FilterParameters.apply` (and
:meth:`FlowPoints.at_dropout_rate`), so the gradient flows from the raw parameters.
"""
import itertools
import math

import pytest
import torch
from torch import nn
from torch.func import functional_call

from flowins.data.simulate.scenario import CameraConfig
from flowins.data.synthetic import (
    ImuErrors,
    Walk,
    WalkConfig,
    corrupt_imu,
    increment_imu,
)
from flowins.filter.ekf import Gate
from flowins.measurements.flow_update import FlowFrame, FlowUpdate
from flowins.measurements.gnss import GnssFix
from flowins.filter.runner import run_filter
from flowins.flow.points import FlowPoints
from flowins.geometry import quaternion as quat
from flowins.ins.initialization import InitialUncertainty, still_prior
from flowins.ins.mechanization import STANDARD_GRAVITY_MPS2
from flowins.measurements.flow import FlowCamera
from flowins.measurements.gnss import gnss_noise
from flowins.navigation import NavigationConfig
from flowins.state import STATE, make_state
from flowins.training.parameters import NAMES, FilterParameters, starting_values

F64 = torch.float64
G = STANDARD_GRAVITY_MPS2
EMPTY = torch.zeros(0, 2, dtype=F64)


# ----------------------------------------------------------------------------- scenario helpers


def make_camera() -> FlowCamera:
    """fx = fy = 250, principal point (160, 120); the simulator's IMU->camera mounting
    (camera z = body x forward, a small misalignment and a lever arm)."""
    K = torch.tensor([[250.0, 0.0, 160.0], [0.0, 250.0, 120.0], [0.0, 0.0, 1.0]], dtype=F64)
    T_ci = CameraConfig().imu_to_camera()
    return FlowCamera(K, T_ci.rotation_matrix.to(F64), T_ci.translation_m.to(F64))


def camera_in_world(R_wb: torch.Tensor, p_wb: torch.Tensor, camera: FlowCamera) -> tuple[torch.Tensor, torch.Tensor]:
    """``(R_wc, c_w)`` written out from ``x_c = R_ci x_b + t_ci`` (independent of the library's helper)."""
    R_ic = camera.R_ci.T
    return R_wb @ R_ic, p_wb - R_wb @ R_ic @ camera.t_ci


def pixels(X_w: torch.Tensor, R_wc: torch.Tensor, c_w: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Pinhole projection ``(M, 2)`` of world points ``(M, 3)`` (no check of the side)."""
    x_c = (X_w - c_w) @ R_wc  # rows: R_wcᵀ (X - c)
    return torch.stack((K[0, 0] * x_c[:, 0] / x_c[:, 2] + K[0, 2], K[1, 1] * x_c[:, 1] / x_c[:, 2] + K[1, 2]), -1)


def cloud(R_wc, c_w, n, gen, *, near=3.0, far=8.0):
    """``n`` points in front of a camera, spread over the image, at depths in ``[near, far]``."""
    xy = torch.rand(n, 2, generator=gen, dtype=F64) * torch.tensor([1.1, 0.85], dtype=F64) - torch.tensor([0.55, 0.43], dtype=F64)
    depth = near + (far - near) * torch.rand(n, 1, generator=gen, dtype=F64)
    return c_w + (torch.cat((xy, torch.ones(n, 1, dtype=F64)), -1) * depth) @ R_wc.T


def exact_points(X_w, pose1, pose2, camera) -> FlowPoints:
    """Flow points of world points between two IMU poses ``(R_wb, p_wb)``."""
    R1, c1 = camera_in_world(*pose1, camera)
    R2, c2 = camera_in_world(*pose2, camera)
    uv1 = pixels(X_w, R1, c1, camera.K)
    uv2 = pixels(X_w, R2, c2, camera.K)
    return FlowPoints(uv1, uv2 - uv1, torch.full_like(uv1, 0.5))


class ConstantMotion:
    """``p(t) = p0 + v t``, ``R(t) = Rz(ω t)``: the specific force is ``+g`` on body z."""

    def __init__(self, p0, v, yaw_rate):
        self.p0, self.v, self.w = torch.as_tensor(p0, dtype=F64), torch.as_tensor(v, dtype=F64), float(yaw_rate)

    def q(self, t: float) -> torch.Tensor:
        return quat.from_rotation_vector(torch.tensor([0.0, 0.0, self.w * t], dtype=F64))

    def pose(self, t: float):
        return quat.to_matrix(self.q(t)), self.p0 + self.v * t

    def imu(self, t_s: torch.Tensor):
        n = t_s.shape[0]
        acc = torch.tensor([0.0, 0.0, G], dtype=F64).expand(n, 3).clone()
        gyro = torch.tensor([0.0, 0.0, self.w], dtype=F64).expand(n, 3).clone()
        return acc, gyro


def prior_covariance(q: torch.Tensor, initial: InitialUncertainty) -> torch.Tensor:
    """The covariance :func:`still_prior` gives a device still at orientation ``q`` (fed still
    samples whose specific force is gravity seen at ``q``)."""
    R = quat.to_matrix(q)
    acc = (R.T @ torch.tensor([0.0, 0.0, G], dtype=F64)).expand(12, 3)
    yaw = math.atan2(float(R[1, 0]), float(R[0, 0]))
    mean, cov = still_prior(acc, torch.zeros(12, 3, dtype=F64), yaw_rad=yaw, uncertainty=initial)
    # the prior's orientation is q's (up to the sign of the quaternion)
    assert min(float((mean[STATE.q] - q).norm()), float((mean[STATE.q] + q).norm())) < 1e-9
    return cov


class Written(nn.Module):
    """``params.apply(base, training=True)`` as a module call, for ``torch.func.functional_call``."""

    def __init__(self, params: FilterParameters):
        super().__init__()
        self.params = params

    def forward(self, base: NavigationConfig):
        return self.params.apply(base, training=True), self.params.value("dropout_p")


# ----------------------------------------------------------------------------- gradcheck

GRADCHECK_NAMES = (
    "acc_noise", "gyro_noise", "gnss_noise_scale", "flow_sigma_scale", "flow_sigma_floor_px", "sigma_p0",
    "flow_gate_threshold", "flow_gate_softness", "dropout_p", "initial_velocity_mps", "gnss_gate_threshold",
)  # fmt: skip


@pytest.fixture(scope="module")
def frames():
    """Eight IMU samples at 100 Hz; camera frames at 0.01 s (augments only), 0.04 s and 0.07 s
    (30 points each, projected exactly from a cloud 1.5-4 m away, +0.4 px noise); a GNSS fix
    0.5 m off the truth at the last frame. The prior is 5 cm/s off in velocity."""
    gen = torch.Generator().manual_seed(3)
    motion = ConstantMotion([1.0, 2.0, 1.5], [1.5, 0.8, 0.1], yaw_rate=0.5)
    camera = make_camera()
    t = torch.arange(8, dtype=F64) * 0.01
    acc, gyro = motion.imu(t)
    times = (0.01, 0.04, 0.07)
    pairs = []
    for ta, tb in itertools.pairwise(times):
        R1, c1 = camera_in_world(*motion.pose(ta), camera)
        X = cloud(R1, c1, 30, gen, near=1.5, far=4.0)
        exact = exact_points(X, motion.pose(ta), motion.pose(tb), camera)
        flow = exact.flow_px + 0.4 * torch.randn(30, 2, generator=gen, dtype=F64)
        # dropout moments: σ(p) = max(sqrt(p / (1 - p)) unit, floor), the unit term dominating
        unit = 0.8 + 0.4 * torch.rand(30, 2, generator=gen, dtype=F64)
        pairs.append(FlowPoints(exact.uv1_px, flow, torch.full_like(flow, 0.5), unit, torch.full_like(flow, 0.1)))
    x0 = make_state(p=motion.p0, v=motion.v + torch.tensor([0.05, -0.03, 0.0], dtype=F64), q=motion.q(0.0))
    gnss_z = motion.pose(times[-1])[1] + torch.tensor([0.3, -0.2, 0.4], dtype=F64)
    return dict(t=t, acc=acc, gyro=gyro, times=times, camera=camera, pairs=pairs, x0=x0, gnss_z=gnss_z,
                q0=motion.q(0.0))


def base_config(parallax_inflation: bool = True) -> NavigationConfig:
    """What is not learned: every point used, no parallax limit, the paper's pose forgetting."""
    update = FlowUpdate(n_points=None, min_parallax_sigma=0.0, parallax_inflation=parallax_inflation,
                        augmentation_mode="paper", gate=Gate(mode="soft"))
    return NavigationConfig(initial=InitialUncertainty(position_m=0.3, yaw_rad=0.05), gnss_gate=Gate(mode="soft"),
                            flow_update=update)


def gradcheck_start() -> dict[str, float]:
    """Starting values where every checked parameter has a visible effect: gates in their
    transition (NIS ~ threshold), forgetting variances comparable to the pose's."""
    start = starting_values(base_config())
    start.update(acc_bias_walk=1e-3, gyro_bias_walk=1e-4, acc_scale_walk=1e-4, acc_noise=0.3, gyro_noise=0.02,
                 sigma_p0=1.5, sigma_q0=0.5, flow_gate_threshold=1.5, flow_gate_softness=1.2, gnss_gate_threshold=3.0,
                 gnss_gate_softness=2.0, gnss_noise_scale=1.3, flow_sigma_scale=1.1, flow_sigma_floor_px=0.2,
                 dropout_p=0.2)
    return start


def filter_outputs(params: FilterParameters, s: dict, raw: dict[str, torch.Tensor], *, n_pairs: int,
                   parallax_inflation: bool) -> tuple[torch.Tensor, list]:
    """The final mean ``(26,)`` and six covariance entries as a function of the raw parameters
    ``raw`` (the others at ``params``' values), and the filter's log. ``n_pairs``: flow frames
    with points after the first frame; the GNSS fix comes at the last one."""
    written = functional_call(Written(params), {f"params.raw.{k}": v for k, v in raw.items()},
                              (base_config(parallax_inflation),))
    config, p = written
    cov0 = prior_covariance(s["q0"], config.initial)
    times = s["times"][: n_pairs + 1]
    events = [FlowFrame(times[0], FlowPoints(EMPTY, EMPTY, EMPTY), s["camera"], config.flow_update, "frame 0")]
    events += [FlowFrame(tk, s["pairs"][k].at_dropout_rate(p), s["camera"], config.flow_update, f"frame {k + 1}")
               for k, tk in enumerate(times[1:])]
    h_acc = torch.tensor(0.5, dtype=F64)
    events.append(GnssFix(times[-1], s["gnss_z"], gnss_noise(h_acc, 1.5 * h_acc, config.gnss_noise_scale), config.gnss_gate))
    n = int(torch.searchsorted(s["t"], torch.tensor(times[-1], dtype=F64) - 1e-9)) + 1  # the IMU up to the last event
    track = run_filter(t_s=s["t"][:n], acc_mps2=s["acc"][:n], gyro_rps=s["gyro"][:n], mean0=s["x0"], cov0=cov0,
                       noise=config.noise, events=events, output_every=2)
    mean, cov = track.node_mean[-1], track.node_cov[-1]
    entries = torch.stack((cov[0, 0], cov[1, 4], cov[3, 3], cov[6, 7], cov[STATE.p_prev][0, 0], cov[13, 13]))
    return torch.cat((mean, entries)), track.log


@pytest.mark.parametrize(
    ("n_pairs", "parallax_inflation"),
    [
        (1, True),  # one frame: its parallax depends on no parameter
        (2, False),
        (2, True),  # the second frame's parallax, and with it the noise inflation, depends on the parameters
    ],
)
def test_gradcheck_through_predict_flow_gnss_forgetting_and_augmentation(frames, n_pairs, parallax_inflation):
    params = FilterParameters(gradcheck_start())
    names = GRADCHECK_NAMES
    raw0 = tuple(params.raw[n].detach().clone().requires_grad_(True) for n in names)
    kw = dict(n_pairs=n_pairs, parallax_inflation=parallax_inflation)

    def f(*raw):
        return filter_outputs(params, frames, dict(zip(names, raw)), **kw)[0]

    # the scenario is informative: all points valid, gates in their transition region
    _, log = filter_outputs(params, frames, dict(zip(names, raw0)), **kw)
    flow = [e for e in log if e.get("kind") == "flow"]
    gnss = [e for e in log if e.get("kind") == "gnss"]
    assert len(flow) == n_pairs and len(gnss) == 1
    for entry in flow:
        assert entry["valid"] == 30 and entry["degenerate"] == 0, entry
        assert 3.0 < entry["accepted"] < 27.0, entry  # a sum of 30 soft weights: neither all 0 nor all 1
    assert 0.05 < gnss[0]["accepted"] < 0.95, gnss[0]
    assert torch.autograd.gradcheck(f, raw0, eps=1e-6, atol=1e-5, rtol=1e-3)


@pytest.mark.parametrize(
    "parallax_inflation", [False, True]
)
def test_flow_noise_jacobian_with_respect_to_the_state_matches_finite_differences(parallax_inflation):
    """The epipolar noise ``wᵀ H_r R H_rᵀ w`` (times the inflation ``p² / (p² - σ²)``) of points
    8-15 m away seen over a 6 cm baseline (parallax 1-2 px, σ = 0.5 px, so the inflation is
    1.1-1.5): its autograd Jacobian with respect to the state against central differences."""
    from flowins.measurements.flow import epipolar_update, flow_measurements

    gen = torch.Generator().manual_seed(5)
    motion = ConstantMotion([1.0, 2.0, 1.5], [0.3, 2.0, 0.1], yaw_rate=0.5)  # sideways: camera x
    camera = make_camera()
    pose1, pose2 = motion.pose(0.0), motion.pose(0.03)
    R1, c1 = camera_in_world(*pose1, camera)
    exact = exact_points(cloud(R1, c1, 12, gen, near=8.0, far=15.0), pose1, pose2, camera)
    flow = exact.flow_px + 0.1 * torch.randn(12, 2, generator=gen, dtype=F64)
    sigma = torch.full_like(flow, 0.5)
    x = make_state(p=pose2[1], v=motion.v, q=motion.q(0.03), p_prev=pose1[1], q_prev=motion.q(0.0))

    def noise(x_):
        m = flow_measurements(x_, flow, exact.uv1_px, camera)
        assert bool(m.valid.all())
        return epipolar_update(m, sigma, parallax_inflation=parallax_inflation).noise_cov.reshape(-1)

    m = flow_measurements(x, flow, exact.uv1_px, camera)
    inflation = m.parallax_px**2 / (m.parallax_px**2 - 0.25)
    assert float(inflation.min()) > 1.05 and float(inflation.max()) < 3.0  # the inflation matters, and is finite
    analytic = torch.autograd.functional.jacobian(noise, x)
    eps = 1e-6
    numeric = torch.stack([(noise(x + eps * e) - noise(x - eps * e)) / (2 * eps) for e in torch.eye(26, dtype=F64)], -1)
    assert float(numeric.abs().max()) > 1e-3  # the noise does depend on the state
    torch.testing.assert_close(analytic, numeric, rtol=1e-4, atol=1e-6)


# ----------------------------------------------------------------------------- long unroll


@pytest.fixture(scope="module")
def walk_segment():
    """3 s (300 IMU steps at 100 Hz) of the synthetic walk at full speed, exact increment IMU
    readings with iPad-grade errors (biases, scale, noise), flow frames every 10 steps with 25
    exact points each from a fresh cloud 3-10 m in front of the camera, GNSS fixes at 1 s."""
    gen = torch.Generator().manual_seed(11)
    walk = Walk(WalkConfig(duration_s=30.0))
    t = 10.0 + 0.01 * torch.arange(301, dtype=F64)
    acc, gyro = increment_imu(walk, t)
    acc, gyro, _ = corrupt_imu(t, acc, gyro, ImuErrors(), gen)
    camera = make_camera()
    R, p = walk.rotation(t), walk.position(t)
    frames = []
    for k in range(0, 301, 10):
        if k == 0:
            frames.append((float(t[k]), FlowPoints(EMPTY, EMPTY, EMPTY)))
            continue
        j = k - 10
        R1, c1 = camera_in_world(R[j], p[j], camera)
        X = cloud(R1, c1, 25, gen, near=3.0, far=10.0)
        exact = exact_points(X, (R[j], p[j]), (R[k], p[k]), camera)
        unit = 0.4 + 0.4 * torch.rand(25, 2, generator=gen, dtype=F64)
        frames.append((float(t[k]), FlowPoints(exact.uv1_px, exact.flow_px, exact.sigma_px, unit, torch.full_like(unit, 0.05))))
    gnss = [(float(t[k]), p[k] + 2.0 * torch.randn(3, generator=gen, dtype=F64)) for k in (100, 200, 300)]
    x0 = make_state(p=p[0], v=walk.velocity(t[:1])[0], q=walk.quaternion(t[:1])[0])
    return dict(t=t, acc=acc, gyro=gyro, camera=camera, frames=frames, gnss=gnss, x0=x0, q0=x0[STATE.q],
                p_end=p[-1])


def unroll_loss(params: FilterParameters, s: dict, parallax_inflation: bool = True,
                innovation: bool = False) -> tuple[torch.Tensor, list]:
    """Squared final position error of the filter over the walk segment (soft gates, learned values);
    ``innovation``: the summed innovation negative log-likelihood instead (and the track, not its
    log), with the gates (and the flow recheck) off."""
    off = {"gate": Gate(mode="off"), "recheck": Gate(mode="off")} if innovation else {}
    base = NavigationConfig(initial=InitialUncertainty(yaw_rad=0.05), gnss_gate=off.get("gate", Gate()),
                            flow_update=FlowUpdate(parallax_inflation=parallax_inflation, **off))
    config = params.apply(base, training=True)
    p = params.value("dropout_p")
    events = [FlowFrame(t, pts if len(pts) == 0 else pts.at_dropout_rate(p), s["camera"], config.flow_update, f"frame {t:.2f}")
              for t, pts in s["frames"]]
    h_acc = torch.tensor(2.0, dtype=F64)
    events += [GnssFix(t, z, gnss_noise(h_acc, h_acc, config.gnss_noise_scale), config.gnss_gate, name=f"fix {t:.0f}")
               for t, z in s["gnss"]]
    track = run_filter(t_s=s["t"], acc_mps2=s["acc"], gyro_rps=s["gyro"], mean0=s["x0"],
                       cov0=prior_covariance(s["q0"], config.initial), noise=config.noise, events=events,
                       likelihood=innovation)
    if innovation:
        return track.nll, track
    err = track.node_mean[-1, STATE.p] - s["p_end"]
    return (err * err).sum(), track.log


def unroll_start() -> dict[str, float]:
    start = starting_values(NavigationConfig())
    start.update(acc_bias_walk=1e-4, gyro_bias_walk=1e-5, acc_scale_walk=1e-5)  # configs/model/filter.yaml
    return start


def directional_derivatives(grads: dict, h: float, *, seed: int, loss) -> tuple[float, float]:
    """Along a random direction of the raw parameters in ``grads``: the derivative from those
    gradients and the central difference of ``loss(FilterParameters)`` from :func:`unroll_start`."""
    gen = torch.Generator().manual_seed(seed)
    direction = {n: float(torch.randn((), generator=gen, dtype=F64)) for n in grads}

    def shifted(sign):
        moved = FilterParameters(unroll_start())
        with torch.no_grad():
            for n, d in direction.items():
                moved.raw[n].add_(sign * h * d)
            return float(loss(moved))

    return sum(float(grads[n]) * d for n, d in direction.items()), (shifted(+1) - shifted(-1)) / (2 * h)


def test_gradients_are_finite_through_a_300_step_unroll(walk_segment):
    """The default flow update (parallax inflation on, limit pose step), soft gates."""
    params = FilterParameters(unroll_start())
    loss, log = unroll_loss(params, walk_segment)
    flows = [e for e in log if e.get("kind") == "flow"]
    assert len(flows) == 30 and sum(e["valid"] for e in flows) >= 0.95 * 30 * 25  # the flow is used
    assert 1e-6 < float(loss.detach()) < 25.0  # the IMU errors leave a real, bounded error
    loss.backward()
    grads = {n: params.raw[n].grad for n in params.learned}
    # the default pose step is the σ -> ∞ limit ("limit"): the forgetting variances take no part,
    # a walk is no vehicle: the vehicle constraint's σs neither; dense flow, no tracks: nor the tracks' σ
    assert {n for n, g in grads.items() if g is None} == {"sigma_p0", "sigma_q0", "vehicle_lateral_sigma_mps",
                                                          "vehicle_vertical_sigma_mps", "tracks_sigma_px",
                                                          "tracks_gate_scale", "tracks_gate_softness"}
    grads = {n: g for n, g in grads.items() if g is not None}
    assert all(bool(torch.isfinite(g)) for g in grads.values()), grads
    assert sum(float(g.abs()) > 1e-12 for g in grads.values()) >= 10, grads
    assert all(params.raw[n].grad is None for n in NAMES if n not in params.learned)  # frozen ones get none


@pytest.mark.parametrize(
    "parallax_inflation", [False, True]
)
def test_unroll_gradient_is_the_finite_difference_of_the_loss(walk_segment, parallax_inflation):
    """The directional derivative of the 300-step loss along a random direction of all learned
    raw parameters, autograd against a central difference (h = 1e-5 in log space)."""
    params = FilterParameters(unroll_start())
    loss, _ = unroll_loss(params, walk_segment, parallax_inflation)
    loss.backward()
    grads = {n: params.raw[n].grad for n in params.learned if params.raw[n].grad is not None}
    assert len(grads) >= 15
    analytic, numeric = directional_derivatives(grads, 1e-5, seed=0, loss=lambda moved: unroll_loss(
        moved, walk_segment, parallax_inflation)[0])
    assert abs(numeric) > 1e-4  # a real slope
    assert analytic == pytest.approx(numeric, rel=1e-4), (analytic, numeric)


def test_innovation_likelihood_gradient_is_its_finite_difference(walk_segment):
    """The summed innovation NLL of the flow points and fixes over the 300-step walk: its count is
    the gate-accepted valid points plus 3 per accepted fix (from the log), and its directional
    derivative along a random direction of all learned raw parameters is the central difference.
    The gates are off: the likelihood takes their weights as constants, so with soft gates its
    gradient is, by design, not the total derivative."""
    params = FilterParameters(unroll_start())
    nll, track = unroll_loss(params, walk_segment, innovation=True)
    flows = [e for e in track.log if e.get("kind") == "flow"]
    fixes = [e for e in track.log if e.get("kind") == "gnss"]
    assert len(fixes) == 3
    expected_count = sum(e["accepted"] for e in flows) + 3.0 * sum(e["accepted"] for e in fixes)
    assert track.nll_count == pytest.approx(expected_count, rel=1e-12)
    nll.backward()
    grads = {n: params.raw[n].grad for n in params.learned if params.raw[n].grad is not None}
    assert {"acc_noise", "gyro_noise", "flow_sigma_scale", "gnss_noise_scale", "dropout_p"} <= set(grads)
    assert track.nll_count == sum(e["valid"] for e in flows) + 9.0  # the gates are off
    analytic, numeric = directional_derivatives(grads, 1e-6, seed=1, loss=lambda moved: unroll_loss(
        moved, walk_segment, innovation=True)[0])
    assert abs(numeric) > 1e-2  # a real slope
    assert analytic == pytest.approx(numeric, rel=1e-4), (analytic, numeric)


# ----------------------------------------------------------------------------- degenerate geometry


def degenerate_scenario(case: str):
    """Eleven IMU samples, frames at 0.02 s and 0.1 s, a GNSS fix 0.5 m off the truth at 0.1 s.

    ``standstill``: no motion at all (the filter knows it: zero velocity), 20 points with zero flow.
    ``infinity``: 20 points at infinity (flow of the rotation alone) and 10 ordinary points.
    ``behind``: 5 points 2-6 cm in front of camera 1, which camera 2 passes (12 cm forward),
    and 10 ordinary points.
    Returns the scenario and the expected (valid, bad) point counts of frame 2.
    """
    gen = torch.Generator().manual_seed(7)
    still = case == "standstill"
    motion = ConstantMotion([1.0, 2.0, 1.5], [0.0, 0.0, 0.0] if still else [1.5, 0.8, 0.1], 0.0 if still else 0.5)
    camera = make_camera()
    t = torch.arange(11, dtype=F64) * 0.01
    acc, gyro = motion.imu(t)
    t1, t2 = 0.02, 0.1
    pose1, pose2 = motion.pose(t1), motion.pose(t2)
    R1, c1 = camera_in_world(*pose1, camera)
    R2, c2 = camera_in_world(*pose2, camera)
    good = exact_points(cloud(R1, c1, 10, gen), pose1, pose2, camera)
    if still:
        pts = exact_points(cloud(R1, c1, 20, gen), pose1, pose2, camera)
        assert float(pts.flow_px.abs().max()) < 1e-9
        points, expect = pts, (0, 20)
    else:
        if case == "infinity":
            d = cloud(R1, torch.zeros(3, dtype=F64), 20, gen, near=1.0, far=1.0)  # directions
            uv1, uv2 = pixels(d, R1, torch.zeros(3, dtype=F64), camera.K), pixels(d, R2, torch.zeros(3, dtype=F64), camera.K)
            bad = FlowPoints(uv1, uv2 - uv1, torch.full_like(uv1, 0.5))
        else:
            assert float((c2 - c1) @ R1[:, 2]) > 0.1  # camera 2 is >10 cm ahead along camera 1's axis
            X = cloud(R1, c1, 5, gen, near=0.02, far=0.06)
            assert bool((((X - c2) @ R2)[:, 2] < 0).all())  # behind camera 2
            bad = exact_points(X, pose1, pose2, camera)
        points = FlowPoints(*(torch.cat((a, b)) for a, b in zip(good[:3], bad[:3])))
        expect = (10, len(bad))
    x0 = make_state(p=motion.p0, v=motion.v, q=motion.q(0.0))
    return dict(t=t, acc=acc, gyro=gyro, t1=t1, t2=t2, camera=camera, points=points, x0=x0, q0=motion.q(0.0),
                gnss_z=pose2[1] + torch.tensor([0.3, -0.4, 0.2], dtype=F64), p_end=pose2[1]), expect


@pytest.mark.parametrize("case", ["standstill", "infinity", "behind"])
def test_gradients_stay_finite_through_degenerate_flow_geometry(case):
    s, (n_valid, n_bad) = degenerate_scenario(case)
    params = FilterParameters(unroll_start())
    config = params.apply(NavigationConfig(initial=InitialUncertainty(position_m=0.3, yaw_rad=0.05)), training=True)
    h_acc = torch.tensor(0.5, dtype=F64)
    events = [
        FlowFrame(s["t1"], FlowPoints(EMPTY, EMPTY, EMPTY), s["camera"], config.flow_update, "frame 1"),
        FlowFrame(s["t2"], s["points"], s["camera"], config.flow_update, "frame 2"),
        GnssFix(s["t2"], s["gnss_z"], gnss_noise(h_acc, h_acc, config.gnss_noise_scale), config.gnss_gate),
    ]
    track = run_filter(t_s=s["t"], acc_mps2=s["acc"], gyro_rps=s["gyro"], mean0=s["x0"],
                       cov0=prior_covariance(s["q0"], config.initial), noise=config.noise, events=events)
    (frame,) = [e for e in track.log if e.get("kind") == "flow"]
    assert frame["candidates"] == n_valid + n_bad and frame["valid"] == n_valid, frame
    assert frame["degenerate"] + frame["behind"] + frame["low_parallax"] == n_bad, frame
    which = {"standstill": "degenerate", "infinity": "low_parallax", "behind": "behind"}[case]
    assert frame[which] == n_bad, frame
    err = track.node_mean[-1, STATE.p] - s["p_end"]
    loss = (err * err).sum()
    assert torch.isfinite(track.node_mean).all() and torch.isfinite(track.node_cov).all()
    loss.backward()
    grads = {n: params.raw[n].grad for n in params.learned}
    # no path: the limit pose step (σ_p0, σ_q0), no dropout moments, no vehicle constraint; with no valid
    # point, the flow noise and gate (the frame's update is computed and not taken: a zero gradient)
    unused = {"sigma_p0", "sigma_q0", "dropout_p", "vehicle_lateral_sigma_mps", "vehicle_vertical_sigma_mps",
              "tracks_sigma_px", "tracks_gate_scale", "tracks_gate_softness"}
    assert {n for n, g in grads.items() if g is None} == unused
    flow = {"flow_sigma_scale", "flow_sigma_floor_px", "flow_gate_threshold", "flow_gate_softness"}
    assert {n for n in flow if float(grads[n].abs()) == 0.0} == (flow if n_valid == 0 else set())
    grads = {n: g for n, g in grads.items() if g is not None}
    assert all(bool(torch.isfinite(g)) for g in grads.values()), grads
    assert float(grads["gnss_noise_scale"].abs()) > 1e-8  # the loss does depend on the parameters
    if n_valid:  # the ordinary points still inform the filter
        assert float(grads["flow_sigma_scale"].abs()) > 1e-10


def test_a_gradient_after_an_inference_run_in_the_same_process(frames):
    """``navigate`` runs in inference mode when nothing needs a gradient. The constant tensors
    a run builds once (:mod:`flowins.constants`) must still serve a later run with gradients:
    the same gradient as when they were first built with gradients on."""
    from flowins.constants import clear_constants

    params = FilterParameters(gradcheck_start())
    kw = dict(n_pairs=2, parallax_inflation=True)

    def gradient():
        raw = tuple(params.raw[n].detach().clone().requires_grad_(True) for n in GRADCHECK_NAMES)
        out = filter_outputs(params, frames, dict(zip(GRADCHECK_NAMES, raw)), **kw)[0]
        return torch.autograd.grad(out.sum(), raw)

    clear_constants()
    with torch.inference_mode():
        filter_outputs(params, frames, {n: params.raw[n].detach() for n in GRADCHECK_NAMES}, **kw)
    after_inference = gradient()
    clear_constants()
    for a, b in zip(after_inference, gradient(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
