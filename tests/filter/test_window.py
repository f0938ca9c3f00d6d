"""A sliding window of N cloned poses (D = 19 + 7 N) through the filter core and the measurement
models: a run with N = 3 is the N = 1 run on the core and clone 0, the window shifts at each
frame, and the frame changes (heading alignment, GNSS reset) move every clone as clone 0."""
import dataclasses
import math

import pytest
import torch

from flowins.data.simulate.render import exact_flow, render
from flowins.data.simulate.scenario import CameraConfig, CameraTrajectory, SimulationConfig, simulate_imu
from flowins.data.simulate.world import build_city
from flowins.data.synthetic import Walk, WalkConfig
from flowins.filter import updater
from flowins.filter.augmentation import PoseAugmentation, augment_pose, copy_index, copy_matrices, with_window
from flowins.filter.chain import BatchChain
from flowins.filter.propagation import propagate_batched, propagate_reference
from flowins.filter.runner import FilterInput, run_filter, run_filters
from flowins.filter.smoother import rts_smooth
from flowins.flow.points import FlowPoints
from flowins.geometry import quaternion as quat
from flowins.ins.initialization import InitialUncertainty, initial_covariance
from flowins.ins.mechanization import ProcessNoise
from flowins.measurements.flow import FlowCamera, flow_measurements
from flowins.measurements.flow_update import FlowFrame, FlowUpdate
from flowins.measurements.gnss import GnssFix, GnssRecovery, gnss_fixes, reset_matrices
from flowins.measurements.gnss_heading import HeadingAlignment, HeadingFit, heading_noise, heading_transform
from flowins.measurements.selection import rotation_parallax_px
from flowins.measurements.zero_velocity import ZeroVelocity
from flowins.state import CORE_DIM, STATE, STATE_DIM, make_state, pose_slices, state_dim, symmetrize

F64 = torch.float64
CLONES = 3
DIM = state_dim(CLONES)  # 40


def _close(x, y, tol=1e-10):
    """``x`` and ``y`` agree to ``tol`` relative to the largest entry of ``y`` (at least 1)."""
    torch.testing.assert_close(x, y, rtol=0, atol=tol * max(1.0, float(y.abs().max())))


def _as_clone0(x: torch.Tensor, k: int) -> torch.Tensor:
    """The 26-dim state ``(..., 26)`` of ``x`` ``(..., D)`` with clone ``k``'s pose in clone 0's place."""
    p, q = pose_slices(x.shape[-1])[1 + k]
    return torch.cat((x[..., :CORE_DIM], x[..., p], x[..., q]), -1)


def _block_index(dim: int, k: int) -> torch.Tensor:
    """Indices of the core and clone ``k`` in a state of ``dim`` entries (26 of them)."""
    p, q = pose_slices(dim)[1 + k]
    return torch.cat((torch.arange(CORE_DIM), torch.arange(p.start, p.stop), torch.arange(q.start, q.stop)))


def _random_prior(gen: torch.Generator, *batch: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A 26-dim mean with unit quaternions and an SPD covariance, batch dims ``batch``."""
    r = lambda *s: torch.randn(*batch, *s, generator=gen, dtype=F64)
    q, q_prev = quat.normalize(r(4)), quat.normalize(r(4))
    mean = make_state(p=5 * r(3), v=r(3), q=q, b_a=0.1 * r(3), b_w=0.01 * r(3), T_a=1 + 0.01 * r(3),
                      p_prev=5 * r(3), q_prev=q_prev)
    A = r(STATE_DIM, STATE_DIM)
    return mean, symmetrize(A @ A.transpose(-1, -2) / STATE_DIM + 0.1 * torch.eye(STATE_DIM, dtype=F64))


@pytest.fixture(scope="module")
def scenario():
    """7 s of the simulated walk from t = 4 s (still until 5 s, at full pace from 8 s): exact flow +
    0.3 px noise at 40 near points per frame (10 Hz; the first frame, at the start, and those of the
    still device copy the pose only), zero-velocity updates while still, 4 Hz GNSS fixes (σ 0.5 m)
    that align an unknown heading (a prior yaw σ of 0.6 rad: well enough conditioned that the runs
    with 26 and 40 entries agree to 1e-12, not only 1e-10), then two fixes 60 m off that make the
    filter reset to the fixes (the recovery)."""
    walk = Walk(WalkConfig(duration_s=12.0))
    t, acc, gyro, _ = simulate_imu(walk, SimulationConfig(duration_s=12.0), torch.Generator().manual_seed(0))
    keep = (t >= 4.0) & (t <= 11.05)
    t, acc, gyro = t[keep], acc[keep], gyro[keep]
    t0, t_end = float(t[0]), float(t[-1])
    cc = CameraConfig(width=160, height=120)
    cam, T_ci = cc.intrinsics(), cc.imu_to_camera()
    camera = FlowCamera.from_calibration(cam, T_ci)
    city = build_city(walk, seed=0)
    times = t0 + 0.1 * torch.arange(int((t_end - t0) / 0.1) + 1, dtype=F64)
    R, P = CameraTrajectory(walk, T_ci).pose(times)
    gen = torch.Generator().manual_seed(3)
    frames, previous = [], None
    empty = torch.zeros(0, 2, dtype=F64)
    update = FlowUpdate(n_points=30, iterations=2)
    for i, ti in enumerate(times.tolist()):
        image = render(city, cam, R[i], P[i], ti)
        if previous is None or ti < 5.6:  # the first frame, and those of the still device: copies only
            frames.append(FlowFrame(ti, FlowPoints(empty, empty, empty), camera, update))
        else:
            truth = exact_flow(city, cam, previous[0], previous[1], (R[i], P[i], ti), image)
            ok = (truth.valid & truth.static & (truth.depth < 8.0)).nonzero()
            pick = ok[torch.randperm(ok.shape[0], generator=gen)[:40]]
            uv1 = torch.stack((pick[:, 1], pick[:, 0]), -1).to(F64)
            flow = truth.flow[pick[:, 0], pick[:, 1]].to(F64) + 0.3 * torch.randn(pick.shape[0], 2, generator=gen,
                                                                                   dtype=F64)
            frames.append(FlowFrame(ti, FlowPoints(uv1, flow, torch.full_like(flow, 0.3)), camera, update))
        previous = (image, (R[i], P[i], ti))
    t_gnss = torch.arange(t0 + 0.05, t_end, 0.25, dtype=F64)
    sigma = torch.tensor([0.5, 0.5, 0.75], dtype=F64).expand(t_gnss.shape[0], 3)
    enu = walk.position(t_gnss) + torch.randn(t_gnss.shape[0], 3, generator=gen, dtype=F64) * sigma
    enu[-3:-1, 0] += 60.0  # two fixes far off: rejected, then the reset to the second
    fixes = gnss_fixes(t_gnss, enu, torch.diag_embed(sigma**2),
                       heading=HeadingAlignment(baseline_m=3.0, max_sigma_rad=0.3, min_fixes=4),
                       recovery=GnssRecovery(after_rejections=2))
    zupts = [ZeroVelocity(t0 + 0.03 + 0.1 * k, 0.02) for k in range(int((4.9 - t0) / 0.1))]
    q0 = walk.quaternion(t[:1])[0]
    mean0 = make_state(p=walk.position(t[:1])[0], v=walk.velocity(t[:1])[0], q=q0)
    cov0 = initial_covariance(q0, InitialUncertainty(yaw_rad=0.6))
    return dict(t=t, acc=acc, gyro=gyro, mean0=mean0, cov0=cov0, events=frames + fixes + zupts, frames=frames,
                camera=camera)


def _run(s, clones, events=None, *, nugget_var=0.0):
    mean0, cov0 = with_window(s["mean0"], s["cov0"], clones, nugget_var=nugget_var)
    return run_filter(t_s=s["t"], acc_mps2=s["acc"], gyro_rps=s["gyro"], mean0=mean0, cov0=cov0, noise=ProcessNoise(),
                      events=s["events"] if events is None else events)


@pytest.fixture(scope="module")
def runs(scenario):
    """The filter with one cloned pose and with a window of three."""
    return {clones: _run(scenario, clones) for clones in (1, CLONES)}


def test_a_window_of_three_clones_is_the_one_clone_run_on_the_core_and_clone_0(runs):
    """Every event of the run (zero velocity, flow frames, the heading alignment, GNSS fixes and
    the reset) reads and moves the core and clone 0 alone, and so does the shift of the window:
    the N = 3 filter gives the N = 1 run's means, covariances and transitions there, at every node,
    and the smoother its covariances."""
    one, three = runs[1], runs[CLONES]
    kinds = {e.get("kind") for e in three.log}
    assert {"zero_velocity", "flow", "gnss", "heading", "gnss_reset"} <= kinds, kinds
    assert any(e.get("status") == "aligned" for e in three.log)
    assert sum(e["accepted"] for e in three.log if e.get("kind") == "flow") > 1000
    assert three.node_mean.shape[-1] == DIM and torch.equal(three.t_s, one.t_s)
    assert [e.get("accepted") for e in three.log] == [e.get("accepted") for e in one.log]
    core = slice(0, STATE_DIM)
    for name in ("node_mean", "pred_mean"):
        _close(getattr(three, name)[:, core], getattr(one, name))
    for name in ("node_cov", "pred_cov", "transition"):
        _close(getattr(three, name)[:, core, core], getattr(one, name))
    _close(rts_smooth(three).node_cov[:, core, core], rts_smooth(one).node_cov)


def test_the_smoother_of_a_window_is_the_one_clone_smoother_on_the_core_and_clone_0(scenario, monkeypatch):
    """The RTS smoother of the N = 3 run is the N = 1 smoother on the core and clone 0 (the further
    clones are nuisance states no measurement reads), with the updates' re-normalisation of the
    quaternions switched off: that is a step on the means alone, which the smoother takes for
    information, and each further clone's is one more (on this run the smoothed positions then
    differ by a few cm)."""
    monkeypatch.setattr(updater, "normalize_quaternions", lambda x: x)
    one, three = (rts_smooth(_run(scenario, clones)) for clones in (1, CLONES))
    core = slice(0, STATE_DIM)
    _close(three.node_mean[:, core], one.node_mean)
    _close(three.node_cov[:, core, core], one.node_cov)


def test_a_window_prior_with_a_nugget_keeps_the_smoother_exact_before_the_first_frame(scenario):
    """Updates before the first frame (zero velocity, GNSS fixes) meet the window prior as it is:
    with exact copies of clone 0 its predicted covariances are singular, with the prior's nugget
    on each further clone (``with_window(nugget_var=...)``) the smoother is the N = 1 one."""
    s = scenario
    events = [e for e in s["events"] if isinstance(e, ZeroVelocity)]
    events += [dataclasses.replace(e, heading=None) for e in s["events"] if isinstance(e, GnssFix)][:8]
    nugget = InitialUncertainty().augmentation_nugget_var
    exact = _run(s, CLONES, events)
    assert float(torch.linalg.eigvalsh(exact.pred_cov[1])[0]) <= 1e-15 * float(exact.pred_cov[1].diagonal().max())
    one, three = _run(s, 1, events), _run(s, CLONES, events, nugget_var=nugget)
    assert float(torch.linalg.eigvalsh(three.pred_cov).amin()) > 0.1 * nugget
    core = slice(0, STATE_DIM)
    _close(three.node_mean[:, core], one.node_mean)
    one, three = rts_smooth(one), rts_smooth(three)
    _close(three.node_mean[:, core], one.node_mean)
    _close(three.node_cov[:, core, core], one.node_cov)


def test_the_window_shifts_at_each_frame_and_the_covariance_stays_psd(runs):
    """At each frame's copy (the node it adds; an update at the same time may act on it after the
    copy) clone k takes clone k-1 and clone 0 the current pose exactly: the mean entries and the
    covariance rows and columns, plus the nugget. Every node's covariance is symmetric positive
    semi-definite."""
    track = runs[CLONES]
    T, Q = copy_matrices(1e-9, dtype=F64, dim=DIM)
    copies = [j for j in range(1, track.t_s.shape[0]) if torch.equal(track.transition[j], T)]
    assert len(copies) == 71  # one per frame
    poses = pose_slices(DIM)
    index = copy_index(torch.device("cpu"), DIM)
    for j in copies:
        before, after = track.node_mean[j - 1], track.pred_mean[j]
        assert torch.equal(after[:CORE_DIM], before[:CORE_DIM])
        for k in range(CLONES):
            (p_to, q_to), (p_from, q_from) = poses[1 + k], poses[k]
            assert torch.equal(after[p_to], before[p_from]) and torch.equal(after[q_to], before[q_from])
        assert torch.equal(track.pred_cov[j], track.node_cov[j - 1][index][:, index] + Q)
    for cov in (track.node_cov, track.pred_cov):
        assert torch.equal(cov, cov.transpose(-1, -2))
        eig = torch.linalg.eigvalsh(cov)
        assert bool((eig >= -1e-12 * eig.amax(-1, keepdim=True)).all())


def test_without_updates_clone_k_is_clone_0_of_k_frames_before(scenario):
    """IMU and frames only (no points, no fixes): the clones only ever move by the shift, so after
    frame i clone k holds the pose clone 0 took at frame i - k, which is the current pose just
    before that frame's copy."""
    s = scenario
    empty = torch.zeros(0, 2, dtype=F64)
    frames = [FlowFrame(f.time_s, FlowPoints(empty, empty, empty), f.camera) for f in s["frames"]]
    track = _run(s, CLONES, frames)
    mean0 = with_window(s["mean0"], s["cov0"], CLONES)[0]
    T, _ = copy_matrices(1e-9, dtype=F64, dim=DIM)
    copies = [j for j in range(1, track.t_s.shape[0]) if torch.equal(track.transition[j], T)]
    assert len(copies) == len(frames)
    poses = pose_slices(DIM)
    current = [torch.cat((track.node_mean[j - 1][poses[0][0]], track.node_mean[j - 1][poses[0][1]])) for j in copies]
    for i, j in enumerate(copies):
        for k in range(CLONES):
            p, q = poses[1 + k]
            held = torch.cat((track.node_mean[j][p], track.node_mean[j][q]))
            expected = current[i - k] if i >= k else torch.cat((mean0[poses[1][0]], mean0[poses[1][1]]))
            assert torch.equal(held, expected), (i, k)


@pytest.mark.parametrize("batch", [(), (1,), (3, 2)])
def test_with_window_copies_clone_0_into_every_clone_and_stays_psd(batch):
    """The extended prior is ``x ↦ T x`` with ``T`` rows of the identity: each further clone's mean,
    own block and cross-covariances are clone 0's, and the covariance stays PSD; N = 1 is the input."""
    mean, cov = _random_prior(torch.Generator().manual_seed(len(batch)), *batch)
    assert with_window(mean, cov, 1) == (mean, cov)
    wide_mean, wide_cov = with_window(mean, cov, 4)
    dim = state_dim(4)
    assert wide_mean.shape == (*batch, dim) and wide_cov.shape == (*batch, dim, dim)
    torch.testing.assert_close(wide_mean[..., :STATE_DIM], mean, rtol=0, atol=0)
    torch.testing.assert_close(wide_cov[..., :STATE_DIM, :STATE_DIM], cov, rtol=0, atol=0)
    clone0 = _block_index(dim, 0)
    for k in range(1, 4):
        index = _block_index(dim, k)
        # clone k, with the core, is clone 0 with the core: mean, own block and cross-covariances
        assert torch.equal(wide_mean[..., index], mean)
        assert torch.equal(wide_cov[..., index, :][..., index], cov)
        assert torch.equal(wide_cov[..., index, :][..., clone0], cov)
    assert torch.equal(wide_cov, wide_cov.transpose(-1, -2))
    eig = torch.linalg.eigvalsh(wide_cov)
    assert bool((eig >= -1e-12 * eig.amax(-1, keepdim=True)).all())
    # the nugget goes on the further clones' own variances only (clone 0 has the prior's own)
    nugget = with_window(mean, cov, 4, nugget_var=1e-3)[1] - wide_cov
    further = (torch.arange(dim) >= STATE_DIM).to(F64)
    torch.testing.assert_close(nugget, torch.diag_embed(1e-3 * further).expand_as(nugget), rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="N >= 1"):
        with_window(mean, cov, 0)
    with pytest.raises(ValueError, match="with_window"):
        with_window(wide_mean, wide_cov, 2)


def _heading_fit() -> HeadingFit:
    t = lambda *v: torch.tensor(v, dtype=F64) if len(v) > 1 else torch.tensor(v[0], dtype=F64)
    return HeadingFit(t(0.7), t(0.05), t(3.0, -1.0), t(-2.0, 5.0), t(0.3), torch.ones(5, dtype=torch.bool))


def _wide_state(gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """A 40-dim state with distinct clones and an SPD covariance."""
    mean, _ = _random_prior(gen)
    extra = []
    for _ in range(CLONES - 1):
        extra += [5 * torch.randn(3, generator=gen, dtype=F64), quat.normalize(torch.randn(4, generator=gen, dtype=F64))]
    x = torch.cat([mean, *extra])
    A = torch.randn(DIM, DIM, generator=gen, dtype=F64)
    return x, symmetrize(A @ A.T / DIM + 0.1 * torch.eye(DIM, dtype=F64))


def test_heading_transform_and_noise_move_every_clone_as_clone_0():
    """The 40-dim map and noise, read on the core and clone k, are the 26-dim ones applied to the
    state with clone k in clone 0's place."""
    fit = _heading_fit()
    x, P = _wide_state(torch.Generator().manual_seed(7))
    A, b = heading_transform(fit, dim=DIM)
    A26, b26 = heading_transform(fit)
    assert A.shape == (DIM, DIM) and b.shape == (DIM,)
    assert torch.equal(heading_transform(fit, dim=STATE_DIM)[0], A26)
    y, Q = A @ x + b, heading_noise(A @ x + b, fit)
    P_new = A @ P @ A.T + Q
    for k in range(CLONES):
        index = _block_index(DIM, k)
        x26 = _as_clone0(x, k)
        y26 = A26 @ x26 + b26
        _close(y[index], y26, 1e-14)
        Q26 = heading_noise(y26, fit)
        _close(Q[index][:, index], Q26, 1e-14)
        _close(P_new[index][:, index], A26 @ P[index][:, index] @ A26.T + Q26, 1e-13)


def test_reset_matrices_move_every_clone_as_clone_0():
    """The GNSS reset of a 40-dim state, read on the core and clone k, is the 26-dim reset of the
    state with clone k in clone 0's place: each clone keeps its offset from the position."""
    x, P = _wide_state(torch.Generator().manual_seed(8))
    fixes = [(0.0, torch.tensor([1.0, 2.0, 0.5], dtype=F64), 4.0 * torch.eye(3, dtype=F64)),
             (2.0, torch.tensor([3.0, 1.0, 0.7], dtype=F64), 9.0 * torch.eye(3, dtype=F64))]
    A, b, Q, with_velocity = reset_matrices(x, fixes, GnssRecovery())
    assert with_velocity and A.shape == (DIM, DIM)
    y, P_new = A @ x + b, A @ P @ A.T + Q
    for k in range(CLONES):
        index = _block_index(DIM, k)
        x26 = _as_clone0(x, k)
        A26, b26, Q26, _ = reset_matrices(x26, fixes, GnssRecovery())
        _close(y[index], A26 @ x26 + b26, 1e-14)
        _close(P_new[index][:, index], A26 @ P[index][:, index] @ A26.T + Q26, 1e-13)
        p = pose_slices(DIM)[1 + k][0]
        _close(y[p] - y[STATE.p], x[p] - x[STATE.p], 1e-14)


def test_propagation_of_a_window_keeps_the_clones_and_matches_the_reference():
    """Batched closed forms and the per-sample ``jacrev`` reference agree on a 40-dim state; its
    core and clone 0 are the 26-dim propagation and the further clones stay put (identity rows)."""
    gen = torch.Generator().manual_seed(9)
    x, P = _wide_state(gen)
    K = 12
    acc = torch.tensor([0.1, -0.2, 9.9], dtype=F64) + 0.3 * torch.randn(K, 3, generator=gen, dtype=F64)
    gyro = 0.2 * torch.randn(K, 3, generator=gen, dtype=F64)
    dt = torch.full((K,), 0.01, dtype=F64)
    nodes = torch.tensor([3, 7, K - 1])
    kw = dict(noise=ProcessNoise(), gravity_mps2=9.81)
    fast = propagate_batched(x, P, acc, gyro, dt, nodes, **kw)
    slow = propagate_reference(x, P, acc, gyro, dt, nodes, **kw)
    narrow = propagate_batched(x[:STATE_DIM], P[:STATE_DIM, :STATE_DIM], acc, gyro, dt, nodes, **kw)
    for a, b in zip(fast, slow):
        _close(a, b, 1e-9)
    assert fast.mean.shape == (3, DIM)
    torch.testing.assert_close(fast.mean[:, STATE_DIM:], x[STATE_DIM:].expand(3, -1), rtol=0, atol=0)
    torch.testing.assert_close(fast.transition[:, STATE_DIM:], torch.eye(DIM, dtype=F64)[STATE_DIM:].expand(3, -1, -1),
                               rtol=0, atol=0)
    core = slice(0, STATE_DIM)
    _close(fast.mean[:, core], narrow.mean, 1e-13)
    _close(fast.cov[:, core, core], narrow.cov, 1e-13)


@pytest.mark.parametrize("jacobians", ["analytic", "autodiff"])
@pytest.mark.parametrize("grad", [False, True])
def test_flow_measurements_of_a_window_are_the_26_dim_ones_padded(scenario, jacobians, grad):
    """The flow model reads the core and clone 0: H_x of a 40-dim state is the 26-dim one with zero
    columns for clones 1 and 2 (closed form and ``jacrev``, with and without a gradient to carry),
    and the point selection's parallax is the 26-dim one."""
    s = scenario
    frame = s["frames"][25]
    p, q = pose_slices(STATE_DIM)[0]
    x26 = make_state(p=s["mean0"][p] + torch.tensor([0.3, 0.1, 0.0], dtype=F64), v=s["mean0"][STATE.v],
                     q=s["mean0"][q], p_prev=s["mean0"][p], q_prev=s["mean0"][q])
    x40 = with_window(x26, torch.eye(STATE_DIM, dtype=F64), CLONES)[0].clone()
    x40[STATE_DIM:] += 0.5  # clones 1 and 2 differ from clone 0: they must not matter
    pts = frame.points
    args = (pts.flow_px.unsqueeze(0), pts.uv1_px.unsqueeze(0), s["camera"])
    with torch.set_grad_enabled(grad):
        wide = flow_measurements(x40.unsqueeze(0).requires_grad_(grad), *args, jacobians=jacobians)
        narrow = flow_measurements(x26.unsqueeze(0), *args, jacobians=jacobians)
    assert wide.H_x.shape[-1] == DIM and bool(narrow.valid.any())
    assert torch.equal(wide.valid, narrow.valid)
    _close(wide.residual.detach(), narrow.residual, 1e-13)
    _close(wide.H_x[..., :STATE_DIM].detach(), narrow.H_x, 1e-13)
    assert not bool(wide.H_x[..., STATE_DIM:].any())
    K, R_ci = s["camera"].K, s["camera"].R_ci
    _close(rotation_parallax_px(x40, pts, K, R_ci), rotation_parallax_px(x26, pts, K, R_ci), 1e-13)


def test_a_state_size_that_is_not_19_plus_7n_and_the_papers_augmentation_of_a_window_raise(scenario):
    """D = 30 is no window, a batch has one D, and the paper's forgetting + H⋆ update is written for
    the 26-dim state: each a ValueError that says so. The limit mode shifts the window."""
    s = scenario
    base = dict(t_s=s["t"][:20], acc_mps2=s["acc"][:20], gyro_rps=s["gyro"][:20], noise=ProcessNoise())
    with pytest.raises(ValueError, match="19 \\+ 7 N"):
        run_filter(mean0=torch.zeros(30, dtype=F64), cov0=torch.eye(30, dtype=F64), **base)
    wide_mean, wide_cov = with_window(s["mean0"], s["cov0"], CLONES)
    with pytest.raises(ValueError, match="one state size"):
        run_filters([FilterInput(s["t"][:20], s["acc"][:20], s["gyro"][:20], s["mean0"], s["cov0"]),
                     FilterInput(s["t"][:20], s["acc"][:20], s["gyro"][:20], wide_mean, wide_cov)], noise=ProcessNoise())
    with pytest.raises(ValueError, match="'paper'"):
        run_filter(mean0=wide_mean, cov0=wide_cov, events=[PoseAugmentation(float(s["t"][5]), mode="paper")], **base)
    with pytest.raises(ValueError, match="'paper'"):
        augment_pose(wide_mean, wide_cov, nugget_var=1e-9)
    # the limit mode shifts the window; the 26-dim state takes both modes as before
    chain = BatchChain(1)
    chain.add_nodes([[0.0]], torch.eye(DIM, dtype=F64)[None, None], wide_mean[None, None], wide_cov[None, None])
    PoseAugmentation(0.0, mode="limit").apply(chain.row(0))
    assert chain.mean.shape == (1, DIM)
    narrow = run_filter(mean0=s["mean0"], cov0=s["cov0"], events=[PoseAugmentation(float(s["t"][5]), mode="paper")],
                        **base)
    assert narrow.node_mean.shape[-1] == STATE_DIM and math.isfinite(float(narrow.node_cov.sum()))


def test_a_float32_window_run_mixes_no_dtypes(scenario, mixed_dtypes):
    """Every tensor the window builds (the prior's copies, the shift, the flow's padded Jacobians, the
    GNSS heading transform, its noise and the reset, the smoother) follows the state's dtype: float32
    with float64 as the default dtype mixes none (:class:`conftest.MixedDtypes`). The run stops after
    the first flow update: at the second, the float32 covariance of the nearly equal clones of the
    device that was still (the nugget is below float32's rounding) is indefinite beyond the update's
    jitter, as it is not with one clone (float32 is no filter dtype, ``filter.dtype``)."""
    s = scenario
    f32 = torch.float32
    mean0, cov0 = with_window(s["mean0"].to(f32), s["cov0"].to(f32), CLONES, nugget_var=1e-9)
    events = [e for e in s["events"] if e.time_s < 5.65]
    fit = HeadingFit(*(t.to(f32) for t in _heading_fit()[:5]), _heading_fit().used)
    x = _wide_state(torch.Generator().manual_seed(8))[0].to(f32)
    fixes = [(0.0, torch.tensor([1.0, 2.0, 0.5], dtype=f32), torch.eye(3, dtype=f32)),
             (2.0, torch.tensor([3.0, 1.0, 0.7], dtype=f32), torch.eye(3, dtype=f32))]
    with mixed_dtypes() as mode:
        track = run_filter(t_s=s["t"], acc_mps2=s["acc"], gyro_rps=s["gyro"], mean0=mean0, cov0=cov0,
                           noise=ProcessNoise(), events=events)
        smoothed = rts_smooth(track)
        A, b = heading_transform(fit, dtype=f32, dim=DIM)
        Q = heading_noise(A @ x + b, fit)
        reset = reset_matrices(x, fixes, GnssRecovery())
    assert mode.slips == {}, mode.slips
    assert {"flow", "zero_velocity", "gnss"} <= {e.get("kind") for e in track.log}
    assert sum(e["accepted"] for e in track.log if e.get("kind") == "flow") > 0
    assert track.node_mean.dtype == f32 and smoothed.node_cov.dtype == f32 and track.node_mean.shape[-1] == DIM
    assert all(t.dtype == f32 for t in (A, b, Q, *reset[:3])) and Q.shape == (DIM, DIM)
