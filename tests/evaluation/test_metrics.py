"""Association, interpolation and trajectory errors against naive and closed-form truths."""
import math

import numpy as np
import pytest
import torch

from flowins.evaluation import (
    associate,
    interpolate_positions,
    interpolate_quaternions,
    position_rmse,
    segment_errors,
    trajectory_errors,
)
from flowins.geometry import quaternion

F64 = torch.float64


def naive_associate(t_est, t_ref, max_dt):
    """Reference implementation: plain Python loops over lists of floats."""
    out = []
    for j, tau in enumerate(t_ref):
        if tau < t_est[0] or tau > t_est[-1]:
            continue
        k = max(i for i in range(len(t_est) - 1) if t_est[i] <= tau)
        nearest = min(tau - t_est[k], t_est[k + 1] - tau)
        if nearest <= max_dt:
            out.append((j, k, (tau - t_est[k]) / (t_est[k + 1] - t_est[k])))
    return out


def random_times(gen, n, start, gaps=()):
    dt = 0.01 + 0.09 * torch.rand(n, generator=gen, dtype=F64)
    for i in gaps:
        dt[i] = 1.0  # a hole in the data
    return start + torch.cumsum(dt, 0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_associate_and_interpolate_match_naive_loop(seed):
    gen = torch.Generator().manual_seed(seed)
    t_est = random_times(gen, 200, 0.0, gaps=(50, 120))
    t_ref = random_times(gen, 150, -0.5, gaps=(30,))
    max_dt = 0.04
    a = associate(t_est, t_ref, max_dt_s=max_dt)
    truth = naive_associate(t_est.tolist(), t_ref.tolist(), max_dt)
    assert len(truth) < len(t_ref)  # the gaps and span really exclude some
    assert a.ref_index.tolist() == [j for j, _, _ in truth]
    assert a.est_left.tolist() == [k for _, k, _ in truth]
    assert np.allclose(a.weight.numpy(), [w for _, _, w in truth], atol=1e-12, rtol=0)

    pos = torch.randn(200, 3, generator=gen, dtype=F64)
    p = pos.tolist()
    expected = [[(1 - w) * p[k][d] + w * p[k + 1][d] for d in range(3)] for _, k, w in truth]
    assert np.allclose(interpolate_positions(pos, a).numpy(), expected, atol=1e-12, rtol=0)


def test_linear_motion_is_interpolated_exactly():
    gen = torch.Generator().manual_seed(3)
    t_est = random_times(gen, 100, 0.0)
    t_ref = torch.linspace(0.2, float(t_est[-1]) - 0.1, 37, dtype=F64)
    v = torch.tensor([1.5, -0.5, 0.25], dtype=F64)
    p0 = torch.tensor([10.0, 20.0, 30.0], dtype=F64)
    a = associate(t_est, t_ref, max_dt_s=1.0)
    assert a.ref_index.tolist() == list(range(37))
    got = interpolate_positions(p0 + t_est[:, None] * v, a)
    assert torch.allclose(got, p0 + t_ref[:, None] * v, atol=1e-12, rtol=0)


def test_tolerance_excludes_far_reference_times():
    t_est = torch.tensor([0.0, 1.0, 2.0, 10.0, 11.0], dtype=F64)
    t_ref = torch.tensor([-0.1, 1.3, 2.4, 5.0, 9.7, 11.0, 11.2], dtype=F64)
    a = associate(t_est, t_ref, max_dt_s=0.4)
    # -0.1 and 11.2 lie outside the span, 5.0 is 3 s from any sample.
    assert a.ref_index.tolist() == [1, 2, 4, 5]
    assert a.est_left.tolist() == [1, 2, 2, 3]
    assert np.allclose(a.weight.numpy(), [0.3, 0.05, 0.9625, 1.0])
    assert associate(t_est, t_ref, max_dt_s=0.35).ref_index.tolist() == [1, 4, 5]


def test_no_association_reports_the_time_spans():
    t_est = torch.tensor([0.0, 1.0, 2.0], dtype=F64)
    t_ref = torch.tensor([5.0, 6.0], dtype=F64)
    with pytest.raises(ValueError, match=r"estimate covers \[0\.0+, 2\.0+\] s, reference covers \[5\.0+, 6\.0+\] s, none within 0\.05 s"):
        associate(t_est, t_ref, max_dt_s=0.05)


def test_times_must_increase_strictly():
    good = torch.tensor([0.0, 1.0, 2.0, 3.0], dtype=F64)
    bad = torch.tensor([0.0, 1.0, 1.0, 3.0], dtype=F64)
    with pytest.raises(ValueError, match=r"t_ref_s must be strictly increasing; first bad row is t_ref_s\[2\]"):
        associate(good, bad, max_dt_s=0.1)
    with pytest.raises(ValueError, match=r"t_est_s must be strictly increasing; first bad row is t_est_s\[2\]"):
        associate(bad, good, max_dt_s=0.1)
    with pytest.raises(ValueError, match="max_dt_s"):
        associate(good, good, max_dt_s=-1.0)


def test_quaternion_interpolation_follows_constant_rate_rotation():
    # q(t) = 𝒬{ω t} rotates at a constant rate, so slerp between samples is exact.
    gen = torch.Generator().manual_seed(4)
    omega = torch.tensor([0.3, -0.8, 0.5], dtype=F64)
    t_est = random_times(gen, 60, 0.0)
    t_ref = torch.linspace(0.1, float(t_est[-1]) - 0.05, 41, dtype=F64)
    q_est = quaternion.from_rotation_vector(t_est[:, None] * omega)
    q_est[::2] = -q_est[::2]  # the sign of a quaternion must not matter
    a = associate(t_est, t_ref, max_dt_s=1.0)
    assert a.ref_index.tolist() == list(range(41))
    got = interpolate_quaternions(q_est, a)
    truth = quaternion.from_rotation_vector(t_ref[:, None] * omega)
    assert quaternion.angle_between(got, truth).max().item() < 1e-9
    assert torch.allclose(got.norm(dim=-1), torch.ones(41, dtype=F64), atol=1e-12)


def test_position_rmse_matches_numpy():
    gen = torch.Generator().manual_seed(5)
    a = torch.randn(20, 3, generator=gen, dtype=F64)
    b = torch.randn(20, 3, generator=gen, dtype=F64)
    expected = math.sqrt(np.mean(np.sum((a.numpy() - b.numpy()) ** 2, axis=1)))
    assert position_rmse(a, b).item() == pytest.approx(expected, rel=1e-12)


def ground_truth(t):
    """A 3-D figure-of-eight-ish path (m)."""
    return torch.stack((20 * torch.sin(0.2 * t), 10 * torch.sin(0.4 * t), 0.5 * t), dim=-1)


def rigid(seed):
    gen = torch.Generator().manual_seed(seed)
    R = quaternion.to_matrix(quaternion.from_rotation_vector(torch.tensor([0.2, -0.4, 1.1], dtype=F64)))
    return R, torch.tensor([100.0, -50.0, 3.0], dtype=F64), gen


def test_se3_alignment_leaves_only_the_noise():
    R, t, gen = rigid(6)
    t_est = torch.arange(0, 3000, dtype=F64) * 0.01  # 100 Hz
    t_ref = t_est[::5].clone()  # 20 Hz on the same grid: interpolation is exact
    sigma = 1e-3
    noise = sigma * torch.randn(3000, 3, generator=gen, dtype=F64)
    pos_est = ground_truth(t_est) @ R.T + t + noise
    res = trajectory_errors(t_est, pos_est, t_ref, ground_truth(t_ref), max_dt_s=0.005)
    assert res.num_associated == 600
    assert torch.equal(res.t_s, t_ref)
    noise_rmse = noise[::5].square().sum(-1).mean().sqrt().item()
    # The true transform is a candidate, so the optimum is no worse than the noise alone.
    assert res.rmse_m <= noise_rmse
    assert res.rmse_m > 0.9 * noise_rmse
    assert torch.allclose(res.alignment.rotation, R.T, atol=1e-5)
    assert res.errors_m.shape == (600,)
    assert res.rmse_m == pytest.approx(res.errors_m.square().mean().sqrt().item(), rel=1e-12)


def test_no_alignment_gives_the_raw_error():
    R, t, gen = rigid(7)
    t_est = torch.arange(0, 1000, dtype=F64) * 0.01
    t_ref = t_est[::4] + 0.0025  # a quarter of the way between samples
    pos_est = ground_truth(t_est) @ R.T + t
    res = trajectory_errors(t_est[:-1], pos_est[:-1], t_ref, ground_truth(t_ref), align="none", max_dt_s=0.01)
    # Independent: interpolate by hand with numpy and subtract the reference.
    e = pos_est.numpy()
    expected_est = 0.75 * e[0:-1:4] + 0.25 * e[1::4]
    expected_err = np.linalg.norm(expected_est - ground_truth(t_ref).numpy(), axis=1)
    assert res.num_associated == 250
    assert np.allclose(res.errors_m.numpy(), expected_err, atol=1e-9, rtol=0)
    assert res.rmse_m == pytest.approx(math.sqrt(np.mean(expected_err**2)), rel=1e-12)
    assert res.rmse_m > 50.0
    assert torch.equal(res.alignment.rotation, torch.eye(3, dtype=F64))


def test_sim3_and_orientations():
    R, t, _ = rigid(8)
    c = 0.8
    t_s = torch.arange(0, 500, dtype=F64) * 0.02
    q_ref = quaternion.from_rotation_vector(torch.stack((0.1 * t_s, 0.05 * torch.cos(t_s), 0.2 * t_s), -1))
    q_R = quaternion.from_matrix(R)
    pos_est = c * ground_truth(t_s) @ R.T + t
    q_est = quaternion.multiply(q_R.expand(500, 4), q_ref)

    res = trajectory_errors(t_s, pos_est, t_s, ground_truth(t_s), align="sim3", q_est=q_est, q_ref=q_ref)
    assert res.rmse_m < 1e-9
    assert res.alignment.scale.item() == pytest.approx(1 / c, rel=1e-10)
    assert res.orientation_rmse_rad < 1e-7

    raw = trajectory_errors(t_s, pos_est, t_s, ground_truth(t_s), align="none", q_est=q_est, q_ref=q_ref)
    angle_R = quaternion.to_rotation_vector(q_R).norm().item()
    assert raw.orientation_rmse_rad == pytest.approx(angle_R, abs=1e-9)
    assert res.orientation_errors_rad.shape == (500,)


def test_trajectory_errors_argument_checks():
    t = torch.arange(10, dtype=F64)
    p = torch.randn(10, 3, dtype=F64)
    with pytest.raises(ValueError, match="align must be one of"):
        trajectory_errors(t, p, t, p, align="SE3")
    with pytest.raises(ValueError, match="q_est and q_ref"):
        trajectory_errors(t, p, t, p, q_est=torch.zeros(10, 4, dtype=F64))
    with pytest.raises(ValueError, match="t_est_s has 10 samples but pos_est has 9 rows"):
        trajectory_errors(t, p[:9], t, p)
    with pytest.raises(ValueError, match="at least 3 associated points"):
        trajectory_errors(t, p, torch.tensor([0.5, 4.0], dtype=F64), p[:2], max_dt_s=0.6)


# ---------------------------------------------------------------- segment errors
def _circle_walk(n: int = 401, rate: float = 0.2, radius: float = 10.0):
    """40 s on a circle, body x axis along the velocity (heading = angle + π/2)."""
    t = torch.linspace(0.0, 40.0, n, dtype=torch.float64)
    angle = rate * t
    pos = torch.stack((radius * torch.cos(angle), radius * torch.sin(angle), torch.zeros_like(t)), -1)
    yaw = angle + math.pi / 2
    zero = torch.zeros_like(yaw)
    return t, pos, quaternion.from_euler(zero, zero, yaw)


def test_segment_errors_of_a_scale_error_on_a_straight_line():
    """Every displacement is s times the truth: the error is |s - 1| v L for each duration L."""
    t = torch.linspace(0.0, 30.0, 301, dtype=torch.float64)
    ref = torch.stack((1.5 * t, torch.zeros_like(t), torch.zeros_like(t)), -1)
    out = segment_errors(t, 1.02 * ref, ref, [5.0, 10.0, 25.0, 40.0])
    assert out.lengths_s == (5.0, 10.0, 25.0)  # no 40 s segment in 30 s
    assert out.counts == (251, 201, 51)
    assert torch.allclose(out.rmse_m, 0.02 * 1.5 * torch.tensor([5.0, 10.0, 25.0], dtype=torch.float64), rtol=1e-9)
    assert out.heading_rmse_rad is None


def test_segment_errors_in_heading_frames_need_no_alignment():
    """The truth turned by 0.7 rad about the vertical and moved: positions, headings and all.
    Relative errors in each segment's own heading frame are zero without any alignment."""
    t, pos, q = _circle_walk()
    turn = quaternion.from_euler(*(torch.tensor(v, dtype=torch.float64) for v in (0.0, 0.0, 0.7)))
    est = pos @ quaternion.to_matrix(turn).T + torch.tensor([3.0, -2.0, 1.0], dtype=torch.float64)
    q_est = quaternion.multiply(turn.expand_as(q), q)
    out = segment_errors(t, est, pos, [5.0, 20.0], q_est=q_est, q_ref=q)
    assert float(out.rmse_m.max()) < 2e-6 and float(out.heading_rmse_rad.max()) < 1e-7  # the sqrt floors
    world = segment_errors(t, est, pos, [5.0, 20.0])  # world frame: the turn is an error there
    assert float(world.rmse_m.min()) > 1.0


def test_segment_errors_of_a_heading_offset_and_a_heading_drift_match_the_closed_form():
    """Positions exact; the estimated heading off by a constant β: each displacement is turned
    by -β, an error of 2 sin(β/2) times the chord 2 r sin(ωL/2), and the heading change is exact.
    With a heading drifting at δ rad/s instead, the heading-change error is δ L."""
    rate, radius, beta, drift = 0.2, 10.0, 0.05, 0.003
    t, pos, q = _circle_walk(rate=rate, radius=radius)
    zero = torch.zeros_like(t)
    offset = quaternion.from_euler(zero, zero, zero + beta)
    out = segment_errors(t, pos, pos, [5.0, 20.0], q_est=quaternion.multiply(offset, q), q_ref=q)
    lengths = torch.tensor([5.0, 20.0], dtype=torch.float64)
    chord = 2 * radius * torch.sin(rate * lengths / 2)
    assert torch.allclose(out.rmse_m, 2 * math.sin(beta / 2) * chord, rtol=1e-9)
    assert float(out.heading_rmse_rad.max()) < 1e-7
    drifting = quaternion.from_euler(zero, zero, drift * t)
    out = segment_errors(t, pos, pos, [5.0, 20.0], q_est=quaternion.multiply(drifting, q), q_ref=q)
    assert torch.allclose(out.heading_rmse_rad, drift * lengths, rtol=1e-6)


def test_segment_errors_gradient_matches_finite_differences():
    t, pos, q = _circle_walk(n=81)
    gen = torch.Generator().manual_seed(0)
    est = (pos + 0.1 * torch.randn(pos.shape, generator=gen, dtype=torch.float64)).requires_grad_(True)
    q_est = (q + 0.01 * torch.randn(q.shape, generator=gen, dtype=torch.float64)).requires_grad_(True)

    def f(e, qe):
        out = segment_errors(t, e, pos, [5.0, 20.0], q_est=qe, q_ref=q)
        return out.rmse_m.sum() + out.heading_rmse_rad.sum()

    assert torch.autograd.gradcheck(f, (est, q_est), eps=1e-6, atol=1e-6)


def test_segment_errors_refuse_bad_input():
    t, pos, q = _circle_walk(n=11)
    with pytest.raises(ValueError, match="durations? must be > 0"):
        segment_errors(t, pos, pos, [0.0])
    with pytest.raises(ValueError, match="together"):
        segment_errors(t, pos, pos, [1.0], q_est=q)
    with pytest.raises(ValueError, match="expected t_s"):
        segment_errors(t, pos[:5], pos, [1.0])


def test_chunk_rmse_aligns_each_piece_on_its_own_and_measures_a_scale_error_in_closed_form():
    """chunk_rmse: a track that is the truth turned by another yaw and moved by another offset in
    each 10 s piece has zero error per piece (each piece aligned on its own); a track 10 % too
    long on a straight line has, in each piece of uniform samples, RMSE 0.1·v·√((n²-1)/12)·dt;
    a 2 s tail joins the piece before; the pieces need >= 3 samples."""
    from flowins.evaluation.metrics import chunk_rmse

    t = torch.arange(0.0, 32.0 + 1e-9, 0.1, dtype=torch.float64)  # 0 .. 32 s: pieces 0-10, 10-20, 20-32
    s = torch.sin(0.3 * t)
    truth = torch.stack((3.0 * t, 5.0 * s, 0.1 * t), -1)
    est = truth.clone()
    for k, (a, b) in enumerate(((0, 10), (10, 20), (20, 33))):
        m = (t >= a) & (t < b)
        yaw = 0.4 + 0.7 * k
        c, sn = math.cos(yaw), math.sin(yaw)
        R = torch.tensor([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
        est[m] = truth[m] @ R.T + torch.tensor([10.0 * k, -3.0, 2.0 * k], dtype=torch.float64)
    pieces = chunk_rmse(t, est, t, truth, 10.0)
    assert [(a, b) for a, b, _ in pieces] == [(0.0, 10.0), (10.0, 20.0), (20.0, pytest.approx(32.0))]
    assert max(r for _, _, r in pieces) < 1e-9
    # the whole run aligned once is not zero: the pieces' own alignments are what made it so
    assert float(trajectory_errors(t, est, t, truth, align="se3").rmse_m) > 1.0

    line = torch.stack((2.0 * t, torch.zeros_like(t), torch.zeros_like(t)), -1)
    pieces = chunk_rmse(t, 1.1 * line, t, line, 10.0)
    for a, b, rmse in pieces:
        n = int(((t >= a - 1e-9) & (t < b - 1e-9)).sum()) + (1 if b == pieces[-1][1] else 0)
        assert rmse == pytest.approx(0.1 * 2.0 * 0.1 * math.sqrt((n * n - 1) / 12.0), rel=1e-9)
    assert chunk_rmse(t[:2], line[:2], t[:2], line[:2], 10.0) == []
    with pytest.raises(ValueError, match="chunk_s"):
        chunk_rmse(t, line, t, line, 0.0)
