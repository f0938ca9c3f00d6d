"""The χ² gate of the flow update rejects the flow of a moving car and keeps the static scene."""
import torch

from flowins.data.simulate.render import exact_flow, render
from flowins.data.simulate.scenario import CameraConfig, CameraTrajectory
from flowins.data.simulate.world import build_city
from flowins.data.synthetic import Walk, WalkConfig
from flowins.filter.ekf import Gate, ekf_update
from flowins.ins.initialization import augmented_covariance
from flowins.measurements.flow import FlowCamera, epipolar_update, flow_measurements
from flowins.state import STATE, make_state

F64 = torch.float64


def test_gate_rejects_a_moving_car_and_accepts_the_static_scene():
    t1, t2 = 171.0, 171.1  # a car crosses the view of the default walk here
    walk = Walk(WalkConfig())
    city = build_city(walk, seed=0)
    cc = CameraConfig()
    cam, T_ci = cc.intrinsics(), cc.imu_to_camera()
    R, P = CameraTrajectory(walk, T_ci).pose(torch.tensor([t1, t2], dtype=F64))
    r1, r2 = render(city, cam, R[0], P[0], t1), render(city, cam, R[1], P[1], t2)
    truth = exact_flow(city, cam, r1, (R[0], P[0], t1), (R[1], P[1], t2), r2)
    gen = torch.Generator().manual_seed(0)

    def sample(mask, n):
        idx = mask.nonzero()
        return idx[torch.randperm(idx.shape[0], generator=gen)[:n]]

    near = truth.depth < 15.0
    static = sample(truth.valid & truth.static & near, 150)
    moving = sample(truth.valid & ~truth.static, 60)
    assert moving.shape[0] == 60  # the car is in view
    pix = torch.cat((static, moving))
    uv1 = torch.stack((pix[:, 1], pix[:, 0]), -1).to(F64)
    sigma = torch.full((pix.shape[0], 2), 0.2, dtype=F64)
    flow = truth.flow[pix[:, 0], pix[:, 1]].to(F64) + 0.2 * torch.randn(pix.shape[0], 2, generator=gen, dtype=F64)

    tt = torch.tensor([t1, t2], dtype=F64)
    x = make_state(p=walk.position(tt[1:])[0], v=walk.velocity(tt[1:])[0], q=walk.quaternion(tt[1:])[0]).clone()
    x[STATE.p_prev], x[STATE.q_prev] = walk.position(tt[:1])[0], walk.quaternion(tt[:1])[0]
    sd = torch.zeros(19, dtype=F64)
    sd[STATE.p], sd[STATE.v], sd[STATE.q] = 0.01, 0.05, 1e-3
    sd[STATE.b_a], sd[STATE.b_w], sd[STATE.T_a] = 0.05, 0.01, 0.02
    cov = augmented_covariance(torch.diag(sd**2), 1e-9)
    cov[STATE.p, STATE.p] += 1e-4 * torch.eye(3, dtype=F64)  # the current pose is uncertain relative to the previous
    cov[STATE.q, STATE.q] += 1e-7 * torch.eye(4, dtype=F64)

    m = flow_measurements(x, flow, uv1, FlowCamera.from_calibration(cam, T_ci))
    upd = epipolar_update(m, sigma)
    result = ekf_update(x, cov, innovation=upd.innovation, H=upd.H, noise_cov=upd.noise_cov, gate=Gate(probability=0.999))
    # every point has a row (the invalid ones add nothing); judge the valid ones
    moving_rows = torch.arange(pix.shape[0]) >= static.shape[0]
    is_moving, is_static = m.valid & moving_rows, m.valid & ~moving_rows
    accepted = result.weight > 0.5
    static_kept = float(accepted[is_static].float().mean())
    moving_kept = float(accepted[is_moving].float().mean())
    assert int(is_moving.sum()) >= 40 and int(is_static.sum()) >= 140
    assert static_kept >= 0.97, static_kept
    # a mover whose flow stays on its epipolar line (moving along the viewing direction) can't be
    # told from a static point by two views; this car crosses the view, and most of it is rejected
    assert moving_kept <= 0.25, moving_kept
    # the accepted points alone keep the state at the truth; with the car it would be pulled away
    off = ekf_update(x, cov, innovation=upd.innovation, H=upd.H, noise_cov=upd.noise_cov, gate=Gate(mode="off"))
    err_gated = (result.mean[STATE.p] - x[STATE.p]).norm()
    err_all = (off.mean[STATE.p] - x[STATE.p]).norm()
    assert err_gated < 0.5 * err_all, (float(err_gated), float(err_all))
