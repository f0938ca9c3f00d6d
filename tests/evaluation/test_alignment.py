"""Umeyama alignment against known transforms and first-order optimality."""
import math

import pytest
import torch

from flowins.evaluation import (
    apply_alignment,
    apply_alignment_to_quaternions,
    position_rmse,
    umeyama,
)
from flowins.geometry import quaternion

F64 = torch.float64


def random_rotation(gen: torch.Generator, dtype=F64) -> torch.Tensor:
    """A proper rotation from a random rotation vector (angle up to ~π)."""
    rotvec = (torch.rand(3, generator=gen, dtype=F64) * 2 - 1) * 1.8
    return quaternion.to_matrix(quaternion.from_rotation_vector(rotvec)).to(dtype)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_recovers_known_rigid_transform_exactly(seed):
    gen = torch.Generator().manual_seed(seed)
    R = random_rotation(gen)
    t = torch.randn(3, generator=gen, dtype=F64) * 10
    source = torch.randn(25, 3, generator=gen, dtype=F64) * 5
    target = source @ R.T + t
    a = umeyama(source, target)
    assert torch.allclose(a.rotation, R, atol=1e-10, rtol=0)
    assert torch.allclose(a.translation, t, atol=1e-10, rtol=0)
    assert a.scale.item() == 1.0
    assert torch.linalg.det(a.rotation).item() == pytest.approx(1.0, abs=1e-12)
    assert position_rmse(apply_alignment(a, source), target).item() < 1e-10


def test_recovers_known_scale():
    gen = torch.Generator().manual_seed(10)
    R = random_rotation(gen)
    t = torch.tensor([3.0, -2.0, 0.5], dtype=F64)
    c = 2.75
    source = torch.randn(30, 3, generator=gen, dtype=F64)
    target = c * source @ R.T + t
    a = umeyama(source, target, with_scale=True)
    assert a.scale.item() == pytest.approx(c, abs=1e-10)
    assert torch.allclose(a.rotation, R, atol=1e-10, rtol=0)
    assert torch.allclose(a.translation, t, atol=1e-10, rtol=0)
    # Without scale the same data cannot be fitted exactly.
    rigid = umeyama(source, target)
    assert rigid.scale.item() == 1.0
    assert position_rmse(apply_alignment(rigid, source), target).item() > 0.1


def test_planar_points_give_proper_rotation():
    # Planar point sets are where a plain SVD solution can be a reflection.
    gen = torch.Generator().manual_seed(4)
    source = torch.randn(40, 3, generator=gen, dtype=F64)
    source[:, 2] = 0.0
    for seed in range(8):
        g = torch.Generator().manual_seed(100 + seed)
        R = random_rotation(g)
        t = torch.randn(3, generator=g, dtype=F64)
        a = umeyama(source, source @ R.T + t)
        assert torch.linalg.det(a.rotation).item() == pytest.approx(1.0, abs=1e-12)
        assert torch.allclose(a.rotation, R, atol=1e-10, rtol=0)


def test_mirrored_target_still_gives_a_rotation():
    gen = torch.Generator().manual_seed(5)
    source = torch.randn(50, 3, generator=gen, dtype=F64) * torch.tensor([5.0, 3.0, 1.0], dtype=F64)
    mirror = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=F64))
    target = source @ mirror.T
    a = umeyama(source, target)
    assert torch.linalg.det(a.rotation).item() == pytest.approx(1.0, abs=1e-12)
    assert torch.allclose(a.rotation @ a.rotation.T, torch.eye(3, dtype=F64), atol=1e-12)
    # A rotation cannot undo a reflection, so the residual stays clearly positive.
    assert position_rmse(apply_alignment(a, source), target).item() > 0.1


def _residual(R, t, source, target):
    return ((source @ R.T + t - target) ** 2).sum(-1).mean()


def test_is_a_least_squares_minimum_on_noisy_data():
    gen = torch.Generator().manual_seed(6)
    R0 = random_rotation(gen)
    source = torch.randn(60, 3, generator=gen, dtype=F64) * 4
    target = source @ R0.T + torch.tensor([1.0, 2.0, 3.0], dtype=F64) + 0.3 * torch.randn(60, 3, generator=gen, dtype=F64)
    a = umeyama(source, target)
    best = _residual(a.rotation, a.translation, source, target)
    for _ in range(50):
        dR = quaternion.to_matrix(quaternion.from_rotation_vector(1e-3 * torch.randn(3, generator=gen, dtype=F64)))
        dt = 1e-3 * torch.randn(3, generator=gen, dtype=F64)
        assert _residual(dR @ a.rotation, a.translation + dt, source, target) > best


def test_residual_is_invariant_to_a_rigid_motion_of_the_source():
    gen = torch.Generator().manual_seed(7)
    source = torch.randn(40, 3, generator=gen, dtype=F64)
    target = source + 0.1 * torch.randn(40, 3, generator=gen, dtype=F64)
    moved = source @ random_rotation(gen).T + torch.tensor([5.0, -7.0, 2.0], dtype=F64)
    r1 = position_rmse(apply_alignment(umeyama(source, target), source), target)
    r2 = position_rmse(apply_alignment(umeyama(moved, target), moved), target)
    assert r1.item() > 0.05
    assert r2.item() == pytest.approx(r1.item(), abs=1e-12)


def test_float32():
    gen = torch.Generator().manual_seed(8)
    R = random_rotation(gen, torch.float32)
    source = torch.randn(30, 3, generator=gen)
    target = source @ R.T + torch.tensor([1.0, 0.0, -1.0])
    a = umeyama(source, target, with_scale=True)
    assert a.rotation.dtype == torch.float32
    assert torch.allclose(a.rotation, R, atol=1e-5)
    assert a.scale.item() == pytest.approx(1.0, abs=1e-5)


def test_batched_matches_unbatched():
    gen = torch.Generator().manual_seed(9)
    source = torch.randn(3, 2, 10, 3, generator=gen, dtype=F64)
    target = torch.randn(3, 2, 10, 3, generator=gen, dtype=F64)
    a = umeyama(source, target, with_scale=True)
    assert a.rotation.shape == (3, 2, 3, 3) and a.translation.shape == (3, 2, 3) and a.scale.shape == (3, 2)
    aligned = apply_alignment(a, source)
    for i in range(3):
        for j in range(2):
            aij = umeyama(source[i, j], target[i, j], with_scale=True)
            assert torch.allclose(a.rotation[i, j], aij.rotation, atol=1e-12)
            assert torch.allclose(aligned[i, j], apply_alignment(aij, source[i, j]), atol=1e-12)


def test_gradients_match_finite_differences():
    gen = torch.Generator().manual_seed(11)
    source = torch.randn(6, 3, generator=gen, dtype=F64)
    target = (source @ random_rotation(gen).T + 0.2 * torch.randn(6, 3, generator=gen, dtype=F64)).requires_grad_(True)

    def f(tgt):
        a = umeyama(source, tgt, with_scale=True)
        return a.rotation, a.translation, a.scale

    assert torch.autograd.gradcheck(f, (target,))


def test_quaternions_are_rotated_by_the_alignment():
    gen = torch.Generator().manual_seed(12)
    R = random_rotation(gen)
    source = torch.randn(10, 3, generator=gen, dtype=F64)
    a = umeyama(source, source @ R.T)
    q = quaternion.normalize(torch.randn(2, 5, 4, generator=gen, dtype=F64))
    out = apply_alignment_to_quaternions(a, q)
    assert out.shape == (2, 5, 4)
    assert torch.allclose(quaternion.to_matrix(out), R @ quaternion.to_matrix(q), atol=1e-10)


def test_bad_input_messages_name_the_argument():
    src = torch.randn(5, 3, dtype=F64)
    with pytest.raises(ValueError, match="same shape"):
        umeyama(src, torch.randn(6, 3, dtype=F64))
    with pytest.raises(ValueError, match="source.*at least 3"):
        umeyama(src[:2], src[:2])
    with pytest.raises(ValueError, match=r"source must have shape \(\.\.\., N, 3\)"):
        umeyama(torch.randn(5, 2, dtype=F64), torch.randn(5, 2, dtype=F64))
    bad = src.clone()
    bad[3, 1] = math.nan
    with pytest.raises(ValueError, match=r"target contains NaN or inf; first bad row is target\[3\]"):
        umeyama(src, bad)
    inf = src.clone()
    inf[1, 0] = math.inf
    with pytest.raises(ValueError, match=r"source\[1\]"):
        umeyama(inf, src)
    same = torch.tensor([[0.1, 0.2, 0.3]], dtype=F64).expand(5, 3)
    with pytest.raises(ValueError, match="source has no spatial extent"):
        umeyama(same, src)
    with pytest.raises(ValueError, match="target has no spatial extent"):
        umeyama(src, same)
    with pytest.raises(ValueError, match="dtype"):
        umeyama(src, src.float())
