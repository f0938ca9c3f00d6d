"""The multi-view track update in the filter, on the synthetic walk with exact landmark tracks."""
from __future__ import annotations

import math

import pytest
import torch

from flowins.data.simulate.tracks import landmark_tracks, scatter_landmarks
from flowins.data.synthetic import Walk, WalkConfig, increment_imu
from flowins.filter.augmentation import with_window
from flowins.filter.ekf import Gate
from flowins.filter.runner import FilterInput, run_filters
from flowins.filter.smoother import rts_smooth
from flowins.geometry import quaternion as quat
from flowins.ins.mechanization import ProcessNoise
from flowins.measurements.flow import FlowCamera, camera_pose
from flowins.measurements.tracks import TrackUpdate, track_frames
from flowins.state import STATE, make_state, pose_slices, state_dim

K = torch.tensor([[460.0, 0.0, 376.0], [0.0, 455.0, 240.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
# the walk's body: x forward, y left, z up; the camera looks forward
R_CI = torch.tensor([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
CAMERA = FlowCamera(K, R_CI, torch.tensor([0.0, 0.03, -0.02], dtype=torch.float64))
T0, T1 = 6.0, 14.0


def _scene(seed: int = 0, noise_px: float = 0.0, imu_hz: int = 100):
    """The walk from T0 to T1 s: its IMU (exact attitude and velocity increments; the position's
    trapezoid error falls as 1/imu_hz²), a camera at 10 Hz, landmarks ahead and their tracks."""
    walk = Walk(WalkConfig(duration_s=T1 + 1.0))
    t_imu = torch.arange(T0 * imu_hz, T1 * imu_hz + 1, dtype=torch.float64) / imu_hz
    acc, gyro = increment_imu(walk, t_imu)
    t_cam = torch.arange(T0 * 10, T1 * 10 + 1, dtype=torch.float64) / 10.0
    R_wc, c_w = camera_pose(walk.quaternion(t_cam), walk.position(t_cam), CAMERA)
    g = torch.Generator().manual_seed(seed)
    ahead = walk.position(t_cam) + 6.0 * torch.cat((R_wc[:, :2, 2], torch.zeros(len(t_cam), 1, dtype=torch.float64)), -1)
    landmarks = scatter_landmarks(ahead, 3000, radius_m=6.0, height_m=(0.0, 4.0), generator=g)
    tracks = landmark_tracks(t_cam, R_wc, c_w, K, (480, 752), landmarks, noise_px=noise_px, generator=g)
    return walk, t_imu, acc, gyro, tracks


def _truth(walk: Walk, t: torch.Tensor) -> torch.Tensor:
    return make_state(p=walk.position(t), v=walk.velocity(t), q=walk.quaternion(t))


def _run(walk, t_imu, acc, gyro, events, *, window: int, velocity_error=(0.0, 0.0, 0.0), gyro_bias=0.0):
    t0 = t_imu[:1]
    mean0 = _truth(walk, t0)[0]
    mean0[STATE.v] += torch.tensor(velocity_error, dtype=torch.float64)
    sigma = torch.zeros(26, dtype=torch.float64)
    sigma[STATE.p], sigma[STATE.v], sigma[STATE.q] = 1e-3, 0.5, 1e-3
    sigma[STATE.b_a], sigma[STATE.b_w], sigma[STATE.T_a] = 0.05, 2e-3, 1e-3
    sigma[STATE.p_prev], sigma[STATE.q_prev] = 1e-3, 1e-3
    cov0 = torch.diag(sigma**2)
    cov0[STATE.p_prev, STATE.p] = cov0[STATE.p, STATE.p_prev] = torch.diag(sigma[STATE.p] ** 2)
    mean0, cov0 = with_window(mean0, cov0, window)
    noise = ProcessNoise(acc_noise=1e-3, gyro_noise=1e-4, acc_bias_walk=1e-4, gyro_bias_walk=1e-5)
    gyro = gyro + gyro_bias
    run = FilterInput(t_imu, acc, gyro, mean0, cov0, events)
    return run_filters([run], noise=noise, output_every=round(0.1 / float(t_imu[1] - t_imu[0])))[0]


def _errors(track, walk):
    t = track.t
    truth = _truth(walk, t)
    position = torch.linalg.vector_norm(track.mean[:, STATE.p] - truth[:, STATE.p], dim=-1)
    attitude = quat.angle_between(track.mean[:, STATE.q], truth[:, STATE.q])
    return position, attitude


def test_exact_tracks_keep_a_filter_started_at_the_truth_there():
    """Exact tracks, an exact 1 kHz IMU (inertial navigation alone is off by its position step's
    approximation: 1.4 mm after 8 s), the filter started at the truth: it stays within that."""
    walk, t_imu, acc, gyro, tracks = _scene(imu_hz=1000)
    update = TrackUpdate(window=5, sigma_px=0.5)
    events = track_frames(tracks, CAMERA, update, t_min_s=T0, t_max_s=T1)
    track = _run(walk, t_imu, acc, gyro, events, window=5)
    position, attitude = _errors(track, walk)
    log = [e for e in track.log if e["kind"] == "tracks"]
    assert sum(e["valid"] for e in log) > 20 * len(log)  # the scene gives the update tracks to use
    assert sum(e["accepted"] for e in log) >= 0.99 * sum(e["valid"] for e in log)
    assert float(position.max()) < 3e-3 and float(attitude.max()) < 2e-4
    alone, _ = _errors(_run(walk, t_imu, acc, gyro, [], window=1), walk)
    assert float(position[-1]) < float(alone[-1])


def test_tracks_correct_a_wrong_velocity_and_a_gyro_bias_that_inertial_navigation_keeps():
    walk, t_imu, acc, gyro, tracks = _scene(seed=1, noise_px=0.3)
    update = TrackUpdate(window=5, sigma_px=0.3)
    bad = dict(velocity_error=(0.3, -0.2, 0.1), gyro_bias=2e-3)
    alone = _run(walk, t_imu, acc, gyro, [], window=1, **bad)
    with_tracks = _run(walk, t_imu, acc, gyro, track_frames(tracks, CAMERA, update, t_min_s=T0, t_max_s=T1),
                       window=5, **bad)
    p_alone, _ = _errors(alone, walk)
    p_tracks, _ = _errors(with_tracks, walk)
    assert float(p_alone[-1]) > 2.0
    assert float(p_tracks[-1]) < 0.05 * float(p_alone[-1])
    b_w = with_tracks.mean[-1, STATE.b_w]
    assert float(torch.linalg.vector_norm(b_w - 2e-3)) < 0.5e-3  # the bias is learned from the tracks
    smoothed = rts_smooth(with_tracks)
    truth = _truth(walk, smoothed.t)
    p_smooth = torch.linalg.vector_norm(smoothed.mean[:, STATE.p] - truth[:, STATE.p], dim=-1)
    assert float(p_smooth.mean()) <= float(p_tracks.mean())


@pytest.mark.parametrize("window", [1, 3])
def test_every_window_size_keeps_its_clones_where_the_frames_were(window):
    walk, t_imu, acc, gyro, tracks = _scene(seed=2, imu_hz=1000)
    update = TrackUpdate(window=window, sigma_px=0.5)
    track = _run(walk, t_imu, acc, gyro, track_frames(tracks, CAMERA, update, t_min_s=T0, t_max_s=T1), window=window)
    assert track.node_mean.shape[-1] == state_dim(window)
    position, _ = _errors(track, walk)
    assert float(position.max()) < 3e-3
    # after the last frame's shift, clone a - 1 holds the pose a frames back (at 10 Hz)
    last = track.node_mean[-1]
    for age, (p, q) in enumerate(pose_slices(last.shape[-1])[1:], start=1):
        t = torch.tensor([T1 - 0.1 * (age - 1)], dtype=torch.float64)
        assert float(torch.linalg.vector_norm(last[p] - walk.position(t)[0])) < 3e-3
        assert float(quat.angle_between(last[q], walk.quaternion(t)[0])) < 2e-4
    variances = track.node_cov.diagonal(dim1=-2, dim2=-1)
    assert bool(torch.isfinite(track.node_cov).all()) and float(variances.min()) >= 0.0


@pytest.mark.parametrize("heading_transport", [False, True])
def test_gradient_of_the_track_noise_matches_finite_differences(heading_transport):
    """The track update is in the torch graph: d(position error²)/d(σ_px) through the filter
    (4 s of the walk, window 3) against a central difference, with and without the heading transport."""
    walk, t_imu, acc, gyro, tracks = _scene(seed=3, noise_px=0.3)
    keep = t_imu <= T0 + 4.0
    t_imu, acc, gyro = t_imu[keep], acc[keep], gyro[keep]

    def loss(sigma):
        update = TrackUpdate(window=3, sigma_px=sigma, gate=Gate(mode="off"), heading_transport=heading_transport)
        events = track_frames(tracks, CAMERA, update, t_min_s=T0, t_max_s=float(t_imu[-1]))
        track = _run(walk, t_imu, acc, gyro, events, window=3, velocity_error=(0.2, 0.0, 0.0))
        truth = _truth(walk, track.t)
        return ((track.mean[:, STATE.p] - truth[:, STATE.p]) ** 2).sum()

    sigma = torch.tensor(0.4, dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(loss(sigma), sigma)
    h = 1e-5
    with torch.no_grad():
        numeric = (loss(torch.tensor(0.4 + h, dtype=torch.float64)) - loss(torch.tensor(0.4 - h, dtype=torch.float64))) / (2 * h)
    assert abs(float(grad)) > 1e-6
    torch.testing.assert_close(grad, numeric, rtol=1e-4, atol=0)


def test_gradient_of_the_soft_track_gate_matches_finite_differences():
    """The track gate is learnable (``train.py``'s ``tracks_gate_scale``, ``tracks_gate_softness``):
    with the soft gate ``sigmoid((scale χ²_dof(p) - NIS) / softness)`` and a scale that puts the
    threshold among the tracks' NIS (so that the weights are neither 0 nor 1), d(position error²)
    with respect to the scale and the softness through the filter against central differences."""
    walk, t_imu, acc, gyro, tracks = _scene(seed=3, noise_px=0.3)
    keep = t_imu <= T0 + 4.0
    t_imu, acc, gyro = t_imu[keep], acc[keep], gyro[keep]

    def loss(scale, softness):
        gate = Gate(mode="soft", probability=0.5, scale=scale, softness=softness)
        update = TrackUpdate(window=3, sigma_px=0.3, gate=gate)
        events = track_frames(tracks, CAMERA, update, t_min_s=T0, t_max_s=float(t_imu[-1]))
        track = _run(walk, t_imu, acc, gyro, events, window=3, velocity_error=(0.2, 0.0, 0.0))
        truth = _truth(walk, track.t)
        return ((track.mean[:, STATE.p] - truth[:, STATE.p]) ** 2).sum()

    point = torch.tensor([0.8, 2.0], dtype=torch.float64, requires_grad=True)
    grad = torch.autograd.grad(loss(point[0], point[1]), point)[0]
    h = 1e-5
    with torch.no_grad():
        numeric = torch.stack([(loss(*(point + h * e)) - loss(*(point - h * e))) / (2 * h)
                               for e in torch.eye(2, dtype=torch.float64)])
    assert bool((grad.abs() > 1e-7).all()), grad
    torch.testing.assert_close(grad, numeric, rtol=1e-4, atol=0)


def test_the_track_update_on_another_device_is_the_cpu_run(fake_device):
    """Track frames (window 3), their window shifts and the smoother on the fake device of
    ``conftest.FakeDevice``: no op meets a CPU tensor there, the filter's pass reads nothing back
    from the device until it ends, and the numbers are the CPU run's."""
    walk, t_imu, acc, gyro, tracks = _scene(seed=4, noise_px=0.3)
    keep = t_imu <= T0 + 2.0
    t_imu, acc, gyro = t_imu[keep], acc[keep], gyro[keep]
    update = TrackUpdate(window=3, sigma_px=0.3)
    events = track_frames(tracks, CAMERA, update, t_min_s=T0, t_max_s=float(t_imu[-1]))
    cpu = _run(walk, t_imu, acc, gyro, events, window=3)
    mean0, cov0 = cpu.node_mean[0], cpu.node_cov[0]
    noise = ProcessNoise(acc_noise=1e-3, gyro_noise=1e-4, acc_bias_walk=1e-4, gyro_bias_walk=1e-5)
    copies = []
    for frames in (len(events) // 2, len(events) // 2, len(events)):  # the first builds the device's constants
        with fake_device() as mode:
            run = FilterInput(t_imu, acc, gyro, mean0.to("meta"), cov0.to("meta"), events[:frames])
            moved = run_filters([run], noise=noise, output_every=10)[0]
            reads = dict(mode.reads)
        copies.append(mode.copies)
    assert copies[1] == copies[2], copies[1:]  # the views, steps and plans move once a pass, not once a frame
    with fake_device() as mode:
        smoothed = rts_smooth(moved)
        assert moved.node_mean.device.type == "meta" and smoothed.node_cov.device.type == "meta"
    assert mode.slips == {}, mode.slips
    assert sum(reads.values()) <= 2 and all(" at flowins/filter/chain.py" in key for key in reads), reads
    assert sum(e["valid"] for e in moved.log if e["kind"] == "tracks") > 0
    assert torch.equal(moved.node_mean, cpu.node_mean) and torch.equal(smoothed.node_cov, rts_smooth(cpu).node_cov)


@pytest.mark.parametrize("window", [1, 5])
def test_tracks_do_not_turn_a_yaw_they_cannot_observe(window):
    """The IMU and the camera do not observe the yaw: the tracks, with a wrong start velocity and a
    gyroscope bias to correct, must leave the track's reference direction where the start put it
    (here the truth's). With the reference σ (``InitialUncertainty.reference_yaw_rad``) the yaw stays
    within 10 mrad of the truth over the 8 s (the bias alone, uncorrected, turns it by 16 mrad); a yaw
    σ of π lets the linearised updates turn it by 1.1 and 1.8 rad."""
    from flowins.ins.initialization import InitialUncertainty, initial_covariance, start_uncertainty

    walk, t_imu, acc, gyro, tracks = _scene(seed=1, noise_px=0.3)
    mean0 = _truth(walk, t_imu[:1])[0]
    mean0[STATE.v] += torch.tensor((0.3, -0.2, 0.1), dtype=torch.float64)
    errors = {}
    for name, u in (("reference", InitialUncertainty(velocity_mps=0.5, acc_bias_mps2=0.05, acc_scale=1e-3)),
                    ("pi", InitialUncertainty(velocity_mps=0.5, acc_bias_mps2=0.05, acc_scale=1e-3, reference_yaw_rad=math.pi))):
        cov0 = initial_covariance(mean0[STATE.q], start_uncertainty(u, reference=True))
        m0, c0 = with_window(mean0, cov0, window)
        events = track_frames(tracks, CAMERA, TrackUpdate(window=window, sigma_px=0.3), t_min_s=T0, t_max_s=T1)
        noise = ProcessNoise(acc_noise=1e-3, gyro_noise=1e-4, acc_bias_walk=1e-4, gyro_bias_walk=1e-5)
        track = run_filters([FilterInput(t_imu, acc, gyro + 2e-3, m0, c0, events)], noise=noise, output_every=10)[0]
        dq = quat.multiply(track.mean[:, STATE.q], quat.conjugate(_truth(walk, track.t)[:, STATE.q]))
        errors[name] = float((2 * torch.atan2(dq[:, 3], dq[:, 0])).abs().max())  # about the world's vertical
    assert errors["reference"] < 0.01
    assert errors["pi"] > 0.3  # what the reference σ prevents
