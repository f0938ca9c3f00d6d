"""Recovery after a run of rejected GNSS fixes: a filter started 500 m off with a small
covariance rejects every fix; with recovery it is reset to the fixes and tracks them."""
from __future__ import annotations

import torch

from flowins.filter.ekf import Gate
from flowins.measurements.gnss import gnss_fixes, GnssRecovery, reset_matrices
from flowins.filter.runner import run_filter
from flowins.ins.initialization import InitialUncertainty, still_prior
from flowins.ins.mechanization import STANDARD_GRAVITY_MPS2 as G
from flowins.ins.mechanization import ProcessNoise
from flowins.state import STATE, make_state

F64 = torch.float64


def run(recovery: GnssRecovery):
    """A still device at the origin, fixes at 1 Hz exactly at the origin, the prior at (500, 0, 0)."""
    n = 1601
    t = torch.arange(n, dtype=F64) / 100
    acc = torch.tensor([0.0, 0.0, G], dtype=F64).expand(n, 3)
    gyro = torch.zeros(n, 3, dtype=F64)
    mean, cov = still_prior(acc[:100], gyro[:100], position_m=torch.tensor([500.0, 0.0, 0.0], dtype=F64),
                            uncertainty=InitialUncertainty(position_m=1.0, yaw_rad=0.01))
    fix_t = torch.arange(1.0, 16.0, 1.0, dtype=F64)  # before the drift covariance reaches 500 m
    fixes = gnss_fixes(fix_t, torch.zeros(len(fix_t), 3, dtype=F64), torch.eye(3, dtype=F64).expand(len(fix_t), 3, 3),
                       gate=Gate(), recovery=recovery)
    return run_filter(t_s=t, acc_mps2=acc, gyro_rps=gyro, mean0=mean, cov0=cov, noise=ProcessNoise(), events=fixes)


def test_without_recovery_every_fix_is_rejected_and_the_filter_stays_off():
    track = run(GnssRecovery(after_rejections=0))
    accepted = [e["accepted"] for e in track.log if e.get("kind") == "gnss"]
    assert accepted and max(accepted) == 0.0
    assert float(track.mean[-1, STATE.p][0]) > 499.0


def test_recovery_resets_after_k_rejections_and_the_later_fixes_are_accepted():
    track = run(GnssRecovery(after_rejections=3))
    resets = [e for e in track.log if e.get("kind") == "gnss_reset"]
    assert len(resets) == 1 and resets[0]["rejected"] == 3 and abs(resets[0]["offset_m"] - 500.0) < 1.0
    assert abs(resets[0]["t_s"] - 3.0) < 1e-9  # the third fix
    later = [e["accepted"] for e in track.log if e.get("kind") == "gnss" and e["t_s"] > 3.0]
    assert later and min(later) == 1.0
    assert float(torch.linalg.vector_norm(track.mean[-1, STATE.p])) < 0.5
    assert float(torch.linalg.eigvalsh(track.node_cov[-1]).min()) > 0


def test_reset_matrices_keep_the_previous_frame_offset_and_set_the_mean_velocity():
    mean = make_state(p=torch.tensor([10.0, 0.0, 0.0], dtype=F64), v=torch.zeros(3, dtype=F64),
                      q=torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=F64), p_prev=torch.tensor([9.0, 1.0, 0.0], dtype=F64))
    R = 4.0 * torch.eye(3, dtype=F64)
    fixes = [(0.0, torch.tensor([0.0, 0.0, 0.0], dtype=F64), R), (2.0, torch.tensor([6.0, 2.0, 0.0], dtype=F64), R)]
    A, b, Q, with_v = reset_matrices(mean, fixes, GnssRecovery())
    out = A @ mean + b
    assert with_v
    torch.testing.assert_close(out[STATE.p], fixes[-1][1])
    torch.testing.assert_close(out[STATE.p_prev] - out[STATE.p], mean[STATE.p_prev] - mean[STATE.p])
    torch.testing.assert_close(out[STATE.v], torch.tensor([3.0, 1.0, 0.0], dtype=F64))
    # velocity variance: (R + R) / dt^2 + (1/2 * 1 m/s^2 * dt)^2 per axis
    torch.testing.assert_close(torch.diagonal(Q[STATE.v, STATE.v]), torch.full((3,), 8.0 / 4.0 + 1.0, dtype=F64))
