"""Planar Procrustes (flowins.geometry.procrustes) against a known rotation and translation."""
from __future__ import annotations

import math

import pytest
import torch

from flowins.geometry.procrustes import planar_rotation, rotation_2d

F64 = torch.float64


@pytest.mark.parametrize("batch", [(), (1,), (3, 2)])
def test_a_known_rotation_and_shift_are_recovered_exactly(batch):
    gen = torch.Generator().manual_seed(0)
    theta = torch.rand(batch, generator=gen, dtype=F64) * 6.0 - 3.0
    source = torch.randn(*batch, 7, 2, generator=gen, dtype=F64)
    shift = torch.randn(*batch, 2, generator=gen, dtype=F64)
    target = (rotation_2d(theta).unsqueeze(-3) @ source.unsqueeze(-1)).squeeze(-1) + shift.unsqueeze(-2)
    fit = planar_rotation(source, target)
    torch.testing.assert_close(fit.theta_rad, theta, atol=1e-12, rtol=0)
    torch.testing.assert_close(fit.centre_source, source.mean(-2))
    torch.testing.assert_close(fit.centre_target, target.mean(-2))
    assert fit.weight_sum.shape == batch and bool((fit.weight_sum == 7).all())


def test_weights_leave_out_a_zero_weight_outlier_and_unit_weights_match_none():
    gen = torch.Generator().manual_seed(1)
    source = torch.randn(9, 2, generator=gen, dtype=F64)
    target = (rotation_2d(torch.tensor(0.7, dtype=F64)) @ source.unsqueeze(-1)).squeeze(-1)
    target[4] = torch.tensor([50.0, -80.0], dtype=F64)  # an outlier
    w = torch.ones(9, dtype=F64)
    w[4] = 0.0
    assert math.isclose(float(planar_rotation(source, target, w).theta_rad), 0.7, abs_tol=1e-12)
    assert not math.isclose(float(planar_rotation(source, target).theta_rad), 0.7, abs_tol=1e-3)
    ones = planar_rotation(source, target, torch.ones(9, dtype=F64))
    plain = planar_rotation(source, target)
    torch.testing.assert_close(ones.theta_rad, plain.theta_rad)
    torch.testing.assert_close(ones.spread, plain.spread)


def test_the_spread_is_the_weighted_sum_of_squared_centred_distances():
    source = torch.tensor([[0.0, 0.0], [2.0, 0.0], [0.0, 4.0]], dtype=F64)
    w = torch.tensor([1.0, 2.0, 1.0], dtype=F64)
    centre = (w.unsqueeze(-1) * source).sum(0) / w.sum()
    expected = float((w * ((source - centre) ** 2).sum(-1)).sum())
    assert math.isclose(float(planar_rotation(source, source, w).spread), expected, rel_tol=1e-14)


def test_wahba_recovers_a_rotation_and_a_prior_fills_only_what_the_data_leave():
    from flowins.geometry import quaternion as quat
    from flowins.geometry.procrustes import wahba_rotation

    gen = torch.Generator().manual_seed(3)
    R = quat.to_matrix(quat.from_rotation_vector(torch.tensor([0.4, -1.9, 0.7], dtype=F64)))
    source = torch.randn(12, 3, generator=gen, dtype=F64)
    torch.testing.assert_close(wahba_rotation(source, source @ R.T), R, atol=1e-12, rtol=0)
    # a reflection is never returned: mirrored targets still give a rotation
    mirrored = wahba_rotation(source, -(source @ R.T))
    assert abs(float(torch.linalg.det(mirrored)) - 1.0) < 1e-12
    # vectors along one axis a fix R a only; a prior that agrees with them is returned as it is
    a = torch.tensor([0.0, 0.6, 0.8], dtype=F64)
    along = torch.linspace(-1.0, 1.0, 9, dtype=F64).unsqueeze(-1) * a
    twist = quat.to_matrix(quat.from_rotation_vector(0.9 * (R @ a)))
    prior = twist @ R
    torch.testing.assert_close(wahba_rotation(along, along @ R.T, prior=prior, prior_weight=1e-3), prior,
                               atol=1e-9, rtol=0)
