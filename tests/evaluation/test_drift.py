"""Drift metrics against closed forms: a scale error is a constant translational drift, a
heading-rate error a constant rotational drift and a known chord error, and neither depends
on the estimate's world frame."""
import math

import pytest
import torch

from flowins.evaluation.drift import kitti_drift, path_length, rpe

F64 = torch.float64


def rot_z(angle: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    R = torch.zeros(*angle.shape, 3, 3, dtype=F64)
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1], R[..., 2, 2] = c, -s, s, c, 1.0
    return R


def straight(duration_s=1000.0, rate_hz=10.0, speed=1.0):
    """The truth: along x at ``speed``, body axes the world's."""
    t = torch.arange(0.0, duration_s + 0.5 / rate_hz, 1.0 / rate_hz, dtype=F64)
    p = torch.stack((speed * t, torch.zeros_like(t), torch.zeros_like(t)), -1)
    return t, torch.eye(3, dtype=F64).expand(t.shape[0], 3, 3), p


def turning(t, omega, speed=1.0):
    """An estimate whose heading turns at ``omega`` and that moves along its heading."""
    R = rot_z(omega * t)
    p = torch.stack((speed * torch.sin(omega * t) / omega, speed * (1 - torch.cos(omega * t)) / omega,
                     torch.zeros_like(t)), -1)
    return R, p


def test_a_scale_error_is_a_constant_translational_drift_and_no_rotational_one():
    t, R, p = straight()
    drift = kitti_drift(R, p, R, 1.01 * p)
    # each segment ends at the first sample beyond L: at most one 0.1 m step longer than L
    assert abs(drift.translation_pct - 1.0) < 1e-3
    assert drift.rotation_deg_per_m == 0.0
    assert set(drift.per_length) == {100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0}
    # from every 10th of 10001 samples, a segment of L while L fits: 1000 - 100 L / 100 + ... starts
    for L, (pct, _, count) in drift.per_length.items():
        assert count == sum(1 for i in range(0, 10001, 10) if 0.1 * i + L < 1000.0 - 1e-9)
        assert abs(pct - 1.0) < 1e-3


def test_a_heading_rate_error_is_its_rate_per_metre_and_the_chord_of_its_arc():
    omega = 1e-3  # rad/s, at 1 m/s: 1e-3 rad/m
    t, R_ref, p_ref = straight()
    R_est, p_est = turning(t, omega)
    drift = kitti_drift(R_ref, p_ref, R_est, p_est)
    assert abs(drift.rotation_deg_per_m - math.degrees(omega)) < 1e-3 * math.degrees(omega)
    T = 100.0
    result = rpe(t, R_ref, p_ref, R_est, p_est, delta=T, unit="s")
    chord = math.hypot(math.sin(omega * T) / omega - T, (1 - math.cos(omega * T)) / omega)
    assert result.pairs == 10  # 0-100 s, 100-200 s, ..., 900-1000 s, each starting where the last ended
    assert result.translation_rmse_m == pytest.approx(chord, rel=1e-9)
    assert result.translation_median_m == pytest.approx(chord, rel=1e-9)
    assert result.rotation_rmse_rad == pytest.approx(omega * T, rel=1e-9)
    every = rpe(t, R_ref, p_ref, R_est, p_est, delta=T, unit="s", all_pairs=True)
    assert every.pairs == 9001 and every.translation_mean_m == pytest.approx(chord, rel=1e-6)
    # on a path at 1 m/s, 100 m of it and 1000 samples are those 100 s
    for delta, unit in ((100.0, "m"), (1000, "f")):
        other = rpe(t, R_ref, p_ref, R_est, p_est, delta=delta, unit=unit)
        assert other.pairs == 10 and other.translation_rmse_m == pytest.approx(chord, rel=1e-6)


def test_the_estimates_world_frame_does_not_matter():
    """A turn and a shift of the estimate's world frame (an INS's unknown heading and origin)
    change no relative error."""
    t, R_ref, p_ref = straight(duration_s=300.0)
    R_est, p_est = turning(t, 2e-3)
    p_est = 1.02 * p_est
    R0 = rot_z(torch.tensor(1.1, dtype=F64)) @ torch.tensor([[1.0, 0, 0], [0, math.cos(0.3), -math.sin(0.3)],
                                                              [0, math.sin(0.3), math.cos(0.3)]], dtype=F64)
    moved_R, moved_p = R0 @ R_est, p_est @ R0.T + torch.tensor([5.0, -3.0, 2.0], dtype=F64)
    a = kitti_drift(R_ref, p_ref, R_est, p_est, lengths_m=(50.0, 100.0))
    b = kitti_drift(R_ref, p_ref, moved_R, moved_p, lengths_m=(50.0, 100.0))
    assert b.translation_pct == pytest.approx(a.translation_pct, rel=1e-9)
    assert b.rotation_deg_per_m == pytest.approx(a.rotation_deg_per_m, rel=1e-9)
    assert a.translation_pct > 1.0  # the scale and the turn do cost


def test_a_short_path_has_no_kitti_segment_and_no_pair():
    t, R, p = straight(duration_s=50.0)
    assert kitti_drift(R, p, R, p) is None
    with pytest.raises(ValueError, match="no pair of samples 60 s apart"):
        rpe(t, R, p, R, p, delta=60.0)
    with pytest.raises(ValueError, match="unit='x'"):
        rpe(t, R, p, R, p, delta=1.0, unit="x")
    assert path_length(p)[-1] == pytest.approx(50.0)


def test_drift_metrics_match_a_track_at_its_own_rate_to_the_truth():
    """A track at 10 Hz against a truth at 50 Hz (a straight walk, 1 % long): linear
    interpolation is exact on it, so KITTI's drift is that 1 % and the 10 s RPE is 0.1 m per pair."""
    from flowins.evaluation.drift import drift_metrics
    from flowins.geometry import quaternion

    t_ref, R_ref, p_ref = straight(duration_s=400.0, rate_hz=50.0)
    t_est, _, p_est = straight(duration_s=400.0, rate_hz=10.0)
    q_ref = quaternion.from_matrix(R_ref)
    q_est = quaternion.from_matrix(torch.eye(3, dtype=F64).expand(t_est.shape[0], 3, 3))
    m = drift_metrics(t_est, 1.01 * p_est, q_est, t_ref, p_ref, q_ref)
    assert m["rpe_pairs"] == 40 and m["rpe_translation_rmse_m"] == pytest.approx(0.1, rel=1e-6)
    assert m["rpe_rotation_rmse_deg"] == pytest.approx(0.0, abs=1e-9)
    assert abs(m["kitti_translation_pct"] - 1.0) < 1e-3 and m["kitti_segments"] > 0
    assert m["scale_pct"] == pytest.approx(1.0, rel=1e-9)
    short = drift_metrics(t_est[:51], p_est[:51], q_est[:51], t_ref[:251], p_ref[:251], q_ref[:251])
    assert short["kitti_translation_pct"] is None and short["rpe_pairs"] == 0


def test_the_scale_error_is_the_similarity_that_maps_the_track_onto_the_truth():
    """A turning 3-D track that is the truth made 2.5 % larger about a point of its own, turned and
    moved (an estimate's frame is its own): +2.5 %; 2 % smaller: -2 %; and a truth that never
    moves has no scale (None), not an error."""
    from flowins.evaluation.drift import scale_error_pct

    t = torch.linspace(0.0, 60.0, 601, dtype=F64)
    _, p = turning(t, 0.1)
    p = p + torch.stack((torch.zeros_like(t), torch.zeros_like(t), 0.3 * torch.sin(0.2 * t)), -1)
    turn = rot_z(torch.tensor(0.7, dtype=F64))
    for factor, want in ((1.025, 2.5), (0.98, -2.0)):
        est = (factor * (p - p[17]) + p[17]) @ turn.T + torch.tensor([4.0, -2.0, 1.0], dtype=F64)
        assert scale_error_pct(est, p) == pytest.approx(want, rel=1e-9)
    still = torch.ones(50, 3, dtype=F64)
    assert scale_error_pct(still + 0.1 * torch.randn(50, 3, dtype=F64), still) is None


def _devkit_drift(T_gt, T_est, lengths, step=10):
    """The KITTI odometry devkit's ``calcSequenceErrors`` as its C++ writes it, in plain loops
    over 4 x 4 poses: ``dist`` the truth's path length, from every ``step``-th first frame and
    each length the first frame whose distance exceeds the first's by more than the length,
    ``pose_error = inverse(Δ_result) Δ_gt``, the rotation error ``acos(clamp((tr - 1) / 2))``
    and the translation error's norm, each over the length; returned as their means."""
    dist = [0.0]
    for i in range(1, len(T_gt)):
        dist.append(dist[-1] + float(torch.linalg.vector_norm(T_gt[i][:3, 3] - T_gt[i - 1][:3, 3])))
    r_errs, t_errs = [], []
    for first in range(0, len(T_gt), step):
        for length in lengths:
            last = next((i for i in range(first, len(dist)) if dist[i] > dist[first] + length), -1)
            if last == -1:
                continue
            delta_gt = torch.linalg.inv(T_gt[first]) @ T_gt[last]
            delta_result = torch.linalg.inv(T_est[first]) @ T_est[last]
            error = torch.linalg.inv(delta_result) @ delta_gt
            d = 0.5 * (float(error[0, 0] + error[1, 1] + error[2, 2]) - 1.0)
            r_errs.append(math.acos(max(min(d, 1.0), -1.0)) / length)
            t_errs.append(float(torch.linalg.vector_norm(error[:3, 3])) / length)
    return sum(t_errs) / len(t_errs), sum(r_errs) / len(r_errs), len(t_errs)


def test_kitti_drift_is_the_devkit_s_on_a_three_dimensional_drive():
    """A wavy 3-D drive (turning, climbing, rolling) and an estimate off it by a slowly growing
    rotation and a wandering translation: flowins' drift equals the devkit's computation written
    out as its C++ does it (:func:`_devkit_drift`), segment count included."""
    from flowins.geometry import quaternion as quat

    t = torch.arange(0.0, 600.0, 0.5, dtype=F64)
    p = torch.stack((10.0 * t, 80.0 * torch.sin(t / 40.0), 5.0 * torch.sin(t / 15.0)), -1)
    R = quat.to_matrix(quat.from_rotation_vector(torch.stack((0.05 * torch.sin(t / 7.0), 0.03 * torch.cos(t / 11.0),
                                                              0.4 * torch.sin(t / 40.0)), -1)))
    R_est = R @ quat.to_matrix(quat.from_rotation_vector(torch.stack((1e-4 * t, -2e-4 * t, 3e-4 * t), -1)))
    p_est = p + torch.stack((0.01 * t, 2.0 * torch.sin(t / 30.0), 0.002 * t**1.2), -1)
    lengths = (100.0, 200.0, 400.0, 800.0)

    def poses(R, p):
        T = torch.eye(4, dtype=F64).repeat(R.shape[0], 1, 1)
        T[:, :3, :3], T[:, :3, 3] = R, p
        return T

    t_err, r_err, count = _devkit_drift(poses(R, p), poses(R_est, p_est), lengths)
    ours = kitti_drift(R, p, R_est, p_est, lengths_m=lengths)
    assert ours.segments == count > 100
    assert abs(ours.translation_pct - 100.0 * t_err) <= 1e-9 * 100.0 * t_err
    assert abs(ours.rotation_deg_per_m - math.degrees(r_err)) <= 1e-9 * math.degrees(r_err)
