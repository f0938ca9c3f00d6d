"""The optical-flow measurement model against simulated geometry and finite differences."""
import pytest
import torch

from flowins.data.simulate.render import exact_flow, render
from flowins.data.simulate.scenario import CameraConfig, CameraTrajectory
from flowins.data.simulate.world import build_city
from flowins.data.synthetic import Walk, WalkConfig
from flowins.geometry import quaternion as quat
from flowins.measurements.flow import FlowCamera, flow_measurements, flow_residual
from flowins.state import STATE, make_state

F64 = torch.float64


@pytest.fixture(scope="module")
def frame_pair():
    """A rendered pair with exact flow, the true state and 200 static, visible points."""
    config = CameraConfig()
    walk = Walk(WalkConfig())
    city = build_city(walk, seed=0)
    cam = config.intrinsics()
    T_ci = config.imu_to_camera()
    trajectory = CameraTrajectory(walk, T_ci)
    t1, t2 = 60.0, 60.1
    R, p = trajectory.pose(torch.tensor([t1, t2], dtype=F64))
    r1 = render(city, cam, R[0], p[0], t1)
    r2 = render(city, cam, R[1], p[1], t2)
    truth = exact_flow(city, cam, r1, (R[0], p[0], t1), (R[1], p[1], t2), r2)
    ok = (truth.valid & truth.static).nonzero()
    pick = ok[torch.linspace(0, ok.shape[0] - 1, 200).long()]
    uv1 = torch.stack((pick[:, 1], pick[:, 0]), -1).to(F64)
    flow = truth.flow[pick[:, 0], pick[:, 1]].to(F64)
    tt = torch.tensor([t1, t2], dtype=F64)
    pos, q = walk.position(tt), walk.quaternion(tt)
    x = make_state(p=pos[1], v=walk.velocity(tt[1:])[0], q=q[1], p_prev=pos[0], q_prev=q[0])
    return x, flow, uv1, FlowCamera.from_calibration(cam, T_ci)


def test_exact_flow_at_the_true_state_has_zero_residual(frame_pair):
    x, flow, uv1, camera = frame_pair
    m = flow_measurements(x, flow, uv1, camera)
    assert bool(m.valid.all()) and m.n_degenerate == 0 and m.n_behind == 0
    assert float(m.residual.abs().max()) < 2e-3  # the renderer's flow is float32
    # a wrong pose is inconsistent with the flow
    x_bad = x.clone()
    x_bad[STATE.p] += torch.tensor([0.0, 0.0, 0.2], dtype=F64)
    bad = flow_measurements(x_bad, flow, uv1, camera)
    assert float(bad.residual.abs().max()) > 0.1


def test_jacobians_match_central_finite_differences(frame_pair):
    x, flow, uv1, camera = frame_pair
    idx = torch.tensor([3, 77, 150])
    noisy = flow[idx] + 0.3  # off the exact flow, so h != 0 and nothing cancels
    m = flow_measurements(x, noisy, uv1[idx], camera)
    eps = 1e-6
    for i in range(3):
        def h_of_x(x_):
            return flow_residual(x_, noisy[i], uv1[idx][i], camera)[0]

        fd = torch.stack([(h_of_x(x + eps * e) - h_of_x(x - eps * e)) / (2 * eps) for e in torch.eye(26, dtype=F64)], -1)
        torch.testing.assert_close(m.H_x[i], fd, rtol=1e-5, atol=1e-6)

        def h_of_d(d_):
            return flow_residual(x, d_, uv1[idx][i], camera)[0]

        fd_r = torch.stack([(h_of_d(noisy[i] + eps * e) - h_of_d(noisy[i] - eps * e)) / (2 * eps) for e in torch.eye(2, dtype=F64)], -1)
        torch.testing.assert_close(m.H_r[i], fd_r, rtol=1e-5, atol=1e-6)
    assert float(m.H_x[:, :, STATE.v].abs().max()) == 0.0  # flow says nothing about velocity directly


def test_analytic_jacobians_equal_the_torch_func_reference(frame_pair):
    """The closed-form batched linearisation against vmap(jacrev) through the triangulation, on every
    point of a frame, at a state off the truth."""
    x, flow, uv1, camera = frame_pair
    x0 = x.clone()
    x0[STATE.p] += torch.tensor([0.05, -0.02, 0.03], dtype=F64)
    x0[STATE.q] = quat.multiply(x0[STATE.q], quat.from_rotation_vector(torch.tensor([0.01, -0.02, 0.005], dtype=F64)))
    noisy = flow + 0.3
    fast = flow_measurements(x0, noisy, uv1, camera)
    ref = flow_measurements(x0, noisy, uv1, camera, jacobians="autodiff")
    assert torch.equal(fast.valid, ref.valid) and bool(fast.valid.all())
    torch.testing.assert_close(fast.residual, ref.residual, rtol=0, atol=1e-10)
    torch.testing.assert_close(fast.H_r, ref.H_r, rtol=0, atol=1e-9)
    scale = float(ref.H_x.abs().max())
    torch.testing.assert_close(fast.H_x, ref.H_x, rtol=0, atol=1e-11 * scale)
    # only the two camera poses enter
    others = [i for i in range(26) if i not in STATE.indices("p", "q", "p_prev", "q_prev").tolist()]
    assert float(fast.H_x[..., others].abs().max()) == 0.0


def test_analytic_jacobians_carry_the_same_second_derivatives(frame_pair):
    """Training differentiates through H_x: the gradient of a function of H_x with respect to
    the state is the same through the closed form as through torch.func."""
    x, flow, uv1, camera = frame_pair
    noisy = (flow + 0.3)[:20]
    weights = torch.randn(20, 2, 26, generator=torch.Generator().manual_seed(2), dtype=F64)
    grads = []
    for method in ("analytic", "autodiff"):
        x_ = x.clone().requires_grad_(True)
        m = flow_measurements(x_, noisy, uv1[:20], camera, jacobians=method)
        (grad,) = torch.autograd.grad((m.H_x * weights).sum() + m.residual.sum(), x_)
        grads.append(grad)
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-8, atol=1e-8 * float(grads[1].abs().max()))


def test_one_pass_without_gradients_equals_the_tracked_two_passes(frame_pair):
    """Inference screens and linearises in one pass; with a gradient to carry it screens
    first and differentiates the valid points only (gathered, so in batches of another
    shape). Same numbers to rounding (ε / conditioning², and H_x sums products of that
    size), same counts."""
    x, flow, uv1, camera = frame_pair
    still = x.clone()
    still[STATE.p_prev] = still[STATE.p]
    still[STATE.q_prev] = still[STATE.q]
    for state in (x, still):
        with torch.no_grad():
            fast = flow_measurements(state, flow + 0.2, uv1, camera)
        tracked = flow_measurements(state.clone().requires_grad_(True), flow + 0.2, uv1, camera)
        assert torch.equal(fast.valid, tracked.valid) and fast.n_degenerate == tracked.n_degenerate
        for a, b in ((fast.residual, tracked.residual), (fast.H_x, tracked.H_x), (fast.H_r, tracked.H_r)):
            assert torch.isfinite(a).all()
            torch.testing.assert_close(a, b.detach(), rtol=0, atol=1e-11 * max(1.0, float(a.abs().max())))


def test_dominant_direction_is_the_first_left_singular_vector():
    from flowins.measurements.flow import dominant_direction

    gen = torch.Generator().manual_seed(4)
    H = torch.randn(50, 2, 2, generator=gen, dtype=F64)
    H[:10] = torch.randn(10, 2, 1, generator=gen, dtype=F64) * torch.randn(10, 1, 2, generator=gen, dtype=F64)  # rank one
    w = dominant_direction(H)
    U = torch.linalg.svd(H).U[..., :, 0]
    torch.testing.assert_close((w * U).sum(-1).abs(), torch.ones(50, dtype=F64), rtol=0, atol=1e-10)


def test_no_translation_is_degenerate_and_finite(frame_pair):
    x, flow, uv1, camera = frame_pair
    still = x.clone()
    still[STATE.p_prev] = still[STATE.p]
    still[STATE.q_prev] = still[STATE.q]
    m = flow_measurements(still, flow, uv1, camera)
    assert not bool(m.valid.any()) and m.n_degenerate + m.n_behind == flow.shape[0]
    for t in (m.residual, m.H_x, m.H_r):
        assert torch.isfinite(t).all() and float(t.abs().max()) == 0.0


def test_pure_rotation_is_degenerate_and_finite(frame_pair):
    x, flow, uv1, camera = frame_pair
    from flowins.measurements.flow import camera_pose

    rotated = x.clone()
    rotated[STATE.q_prev] = quat.multiply(rotated[STATE.q], quat.from_rotation_vector(torch.tensor([0.0, 0.0, 0.05], dtype=F64)))
    # the same camera centre (the IMU moves along the lever arm), different orientations
    _, c_now = camera_pose(rotated[STATE.q], rotated[STATE.p], camera)
    _, c_prev = camera_pose(rotated[STATE.q_prev], rotated[STATE.p], camera)
    rotated[STATE.p_prev] = rotated[STATE.p] + (c_now - c_prev)
    m = flow_measurements(rotated, flow, uv1, camera)
    assert torch.isfinite(m.residual).all() and torch.isfinite(m.H_x).all()
    assert not bool(m.valid.any())


def test_points_behind_the_second_camera_are_counted(frame_pair):
    """Camera 2 stands 20 m ahead of camera 1, beyond points 5-15 m in front of camera 1:
    the rays meet exactly, behind camera 2 (its projection formula still gives pixels)."""
    from flowins.geometry.camera import project
    from flowins.measurements.flow import camera_pose

    x, _, _, camera = frame_pair
    state = x.clone()
    state[STATE.q] = state[STATE.q_prev]
    R1, c1 = camera_pose(state[STATE.q_prev], state[STATE.p_prev], camera)
    state[STATE.p] = state[STATE.p_prev] + 20.0 * R1[:, 2]  # along the optical axis
    R2, c2 = camera_pose(state[STATE.q], state[STATE.p], camera)
    gen = torch.Generator().manual_seed(0)
    depth = 5.0 + 10.0 * torch.rand(20, generator=gen, dtype=F64)
    lateral = torch.randn(20, 2, generator=gen, dtype=F64)
    X = c1 + depth[:, None] * R1[:, 2] + lateral[:, :1] * R1[:, 0] + lateral[:, 1:] * R1[:, 1]
    K = camera.K
    uv1 = project((X - c1) @ R1, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    uv2 = project((X - c2) @ R2, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    m = flow_measurements(state, uv2 - uv1, uv1, camera)
    assert m.n_behind == 20 and not bool(m.valid.any())
    assert torch.isfinite(m.H_x).all() and torch.isfinite(m.residual).all()


def _prior(x):
    x0 = x.clone()
    x0[STATE.p] += torch.tensor([0.0, 0.0, 0.02], dtype=F64)  # off by 2 cm, across the baseline
    P = torch.diag(torch.cat((torch.full((3,), 0.05**2), torch.full((3,), 0.1**2), torch.full((4,), 0.01**2),
                              torch.full((9,), 1e-4), torch.full((3,), 1e-6), torch.full((4,), 1e-8)))).to(F64)
    return x0, P


def test_flow_noise_jacobian_has_rank_one_and_the_literal_2d_update_diverges(frame_pair):
    """Why flowins updates with the epipolar component: ∂h/∂δ is rank one."""
    from flowins.filter.ekf import ekf_update

    x, flow, uv1, camera = frame_pair
    x0, P = _prior(x)
    m = flow_measurements(x0, flow[:60], uv1[:60], camera)
    s = torch.linalg.svdvals(m.H_r)
    assert float((s[:, 1] / s[:, 0]).max()) < 1e-2
    literal = ekf_update(x0, P, innovation=-m.residual, H=m.H_x, noise_cov=m.H_r @ (0.25 * torch.eye(2, dtype=F64)) @ m.H_r.transpose(-1, -2))
    before = float(flow_measurements(x0, flow[:60], uv1[:60], camera).residual.norm())
    after = float(flow_measurements(literal.mean, flow[:60], uv1[:60], camera).residual.norm())
    assert after > before  # the near-singular noise direction wrecks the literal update


@pytest.mark.parametrize("sigma", [0.0, 0.5])
def test_sequential_and_batched_epipolar_updates_agree_and_fit_the_flow(frame_pair, sigma):
    """The paper's per-point EKF update and one stacked update of all points of a frame."""
    from flowins.filter.ekf import ekf_update
    from flowins.measurements.flow import epipolar_update

    x, flow, uv1, camera = frame_pair
    gen = torch.Generator().manual_seed(1)
    noisy = flow[:60] + sigma * torch.randn(60, 2, generator=gen, dtype=F64)
    x0, P = _prior(x)
    m = flow_measurements(x0, noisy, uv1[:60], camera)
    upd = epipolar_update(m, torch.full((60, 2), 0.5, dtype=F64))
    assert upd.H.shape == (60, 1, 26)
    kwargs = dict(innovation=upd.innovation, H=upd.H, noise_cov=upd.noise_cov)
    batched = ekf_update(x0, P, **kwargs)
    sequential = ekf_update(x0, P, sequential=True, **kwargs)
    # the update makes the state agree with the exact flow and moves the position to the truth
    before = float(flow_measurements(x0, flow[:60], uv1[:60], camera).residual.norm())
    after = float(flow_measurements(batched.mean, flow[:60], uv1[:60], camera).residual.norm())
    assert after < 0.3 * before
    assert float((batched.mean[STATE.p] - x[STATE.p]).norm()) < 0.6 * float((x0[STATE.p] - x[STATE.p]).norm())
    torch.testing.assert_close(sequential.mean, batched.mean, rtol=0, atol=1e-10)
    torch.testing.assert_close(sequential.cov, batched.cov, rtol=0, atol=1e-12)


def test_low_parallax_points_are_left_out_and_counted(frame_pair):
    """Parallax = focal length x the angle between the world-frame viewing rays; points
    below the threshold are left out (zero Jacobian) and counted."""
    x, flow, uv1, camera = frame_pair
    m = flow_measurements(x, flow, uv1, camera)
    assert m.parallax_px is not None and bool((m.parallax_px > 0).all())
    threshold = float(m.parallax_px.median())
    gated = flow_measurements(x, flow, uv1, camera, min_parallax_px=threshold)
    low = m.parallax_px < threshold
    assert gated.n_low_parallax == int(low.sum()) and torch.equal(gated.valid, ~low)
    assert float(gated.H_x[low].abs().max()) == 0.0 and float(gated.H_x[~low].abs().max()) > 0.0


def test_the_camera_s_kept_tensors_made_in_inference_mode_serve_a_later_run_with_gradients(frame_pair):
    """A validation runs in inference mode and a training step after it, on the same camera. What
    the camera keeps from the first (its float32 copy, the flow update's stand-in point) must be a
    plain tensor, or the training step could not save it for backward."""
    from flowins.measurements.flow import _stand_in

    x, _, _, camera = frame_pair
    camera = FlowCamera(camera.K.clone(), camera.R_ci.clone(), camera.t_ci.clone())  # nothing kept yet
    rows = x.expand(3, -1)
    with torch.inference_mode():
        copy = camera.to(rows.float())
        stand_in = _stand_in(camera, rows)
    assert camera.to(rows.float()) is copy and _stand_in(camera, rows)[0]._base is stand_in[0]._base
    kept = (copy.K, copy.R_ci, copy.t_ci, *stand_in)
    assert not any(t.is_inference() for t in kept)
    w = torch.tensor(2.0, dtype=F64, requires_grad=True)
    (grad,) = torch.autograd.grad(sum((w * w * t.to(F64)).sum() for t in kept), w)
    assert float(grad) == pytest.approx(2 * 2.0 * sum(float(t.to(F64).sum()) for t in kept), rel=1e-12)
