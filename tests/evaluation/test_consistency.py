"""Heading consistency against closed forms and sampling: a known turn is its error, whatever the
tilt and the quaternion's sign and norm; the linearised σ is the spread of sampled headings; an
alignment's turn is no error; a consistent filter's normalised errors have unit RMS."""
import math

import pytest
import torch

from flowins.evaluation.alignment import Alignment
from flowins.evaluation.consistency import heading_consistency, heading_error, track_heading_consistency
from flowins.geometry import quaternion as quat

F64 = torch.float64


def z_turn(angle: float | torch.Tensor) -> torch.Tensor:
    return quat.from_rotation_vector(torch.tensor([0.0, 0.0, 1.0], dtype=F64) * torch.as_tensor(angle, dtype=F64)
                                     .unsqueeze(-1))


def random_attitudes(n: int, generator: torch.Generator) -> torch.Tensor:
    """Attitudes of any heading, tilted by up to about 0.3 rad."""
    yaw = (torch.rand(n, dtype=F64, generator=generator) * 2 - 1) * math.pi
    roll, pitch = ((torch.rand(2, n, dtype=F64, generator=generator) * 2 - 1) * 0.3).unbind(0)
    return quat.from_euler(roll, pitch, yaw)


def test_a_turn_about_the_world_vertical_is_its_heading_error_whatever_the_tilt_sign_and_norm():
    g = torch.Generator().manual_seed(0)
    q_ref = random_attitudes(64, g)
    angle = (torch.rand(64, dtype=F64, generator=g) * 2 - 1) * 3.0
    q_est = quat.multiply(z_turn(angle), q_ref)  # turned about the world z
    assert torch.allclose(heading_error(q_est, q_ref), angle, atol=1e-12)
    # q and -q are one rotation, and the filter's quaternions are not exactly of unit norm
    scaled = -1.7 * q_est
    assert torch.allclose(heading_error(scaled, q_ref), angle, atol=1e-12)
    # a turn about the body z of a tilted attitude is not a pure heading change: it differs
    body = quat.multiply(q_ref, z_turn(angle))
    assert (heading_error(body, q_ref) - angle).abs().max() > 1e-3


def test_the_linearised_sigma_is_the_spread_of_sampled_headings():
    g = torch.Generator().manual_seed(1)
    q = random_attitudes(3, g)
    A = torch.randn(3, 4, 4, dtype=F64, generator=g) * 2e-3  # full rank: also along q (no heading change)
    cov = A @ A.transpose(-1, -2)
    result = heading_consistency(q, cov, q)
    assert torch.allclose(result.error_rad, torch.zeros(3, dtype=F64), atol=1e-12)
    samples = q + (A @ torch.randn(3, 4, 40000, dtype=F64, generator=g)).transpose(-1, -2).transpose(0, 1)
    spread = heading_error(samples, q.expand(40000, 3, 4)).std(0)
    # 40000 samples: the standard deviation's own error is about 0.35 %; the linearisation's far less
    assert torch.allclose(result.sigma_rad, spread, rtol=0.02)
    assert float(result.sigma_rad.min()) > 1e-4


def test_an_alignments_turn_is_no_error_and_the_errors_left_are():
    g = torch.Generator().manual_seed(2)
    q_ref = random_attitudes(50, g)
    wander = 0.05 * torch.sin(torch.linspace(0, 6, 50, dtype=F64))
    offset = 0.8
    q_est = quat.multiply(z_turn(offset + wander), q_ref)
    turn_back = quat.to_matrix(z_turn(-offset))
    aligned = heading_consistency(q_est, torch.eye(4, dtype=F64).expand(50, 4, 4) * 1e-6, q_ref,
                                  alignment=Alignment(turn_back, torch.zeros(3, dtype=F64), torch.tensor(1.0, dtype=F64)))
    assert torch.allclose(aligned.error_rad, wander, atol=1e-12)


def test_a_filter_whose_errors_are_drawn_from_its_covariance_scores_about_one():
    g = torch.Generator().manual_seed(3)
    n = 4000
    q_ref = random_attitudes(n, g)
    sigma = 0.01 * (1 + torch.rand(n, dtype=F64, generator=g))
    psi = sigma * torch.randn(n, dtype=F64, generator=g)
    q_est = quat.multiply(z_turn(psi), q_ref)
    # the filter's covariance of a heading σ about its estimate (about the world z: dq = ½ [0, e_z] ⊗ q δψ)
    direction = 0.5 * quat.multiply(torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=F64).expand(n, 4), q_est)
    cov = sigma[:, None, None] ** 2 * direction[:, :, None] * direction[:, None, :] + 1e-14 * torch.eye(4, dtype=F64)
    consistent = heading_consistency(q_est, cov, q_ref)
    assert torch.allclose(consistent.sigma_rad, sigma, rtol=1e-6)
    assert abs(consistent.rms_normalised() - 1.0) < 0.05
    assert consistent.share_beyond(3.0) < 0.01
    overconfident = heading_consistency(quat.multiply(z_turn(9 * psi), q_est), cov, q_ref)  # 10 ψ off
    assert abs(overconfident.rms_normalised() - 10.0) < 0.5
    assert overconfident.share_beyond(3.0) > 0.7


def test_a_track_is_compared_with_the_reference_slerped_to_its_times():
    t_ref = torch.linspace(0.0, 10.0, 101, dtype=F64)
    q_ref = z_turn(0.1 * t_ref)  # turning at 0.1 rad/s
    t_est = torch.tensor([-1.0, 0.52, 3.333, 9.99, 12.0], dtype=F64)  # two outside the reference
    q_est = z_turn(0.1 * t_est + 0.02)
    result = track_heading_consistency(t_est, q_est, torch.eye(4, dtype=F64).expand(5, 4, 4) * 1e-4, t_ref, q_ref)
    assert torch.equal(result.t_s, t_est[1:4])
    assert torch.allclose(result.error_rad, torch.full((3,), 0.02, dtype=F64), atol=1e-12)


def test_shapes_are_checked():
    q = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64)
    with pytest.raises(ValueError, match="cov_q must be"):
        heading_consistency(q, torch.eye(4, dtype=F64), q)
    with pytest.raises(ValueError, match="q_est and q_ref"):
        heading_consistency(q[0], torch.eye(4, dtype=F64), q[0])
