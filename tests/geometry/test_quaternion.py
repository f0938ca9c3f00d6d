"""Quaternion algebra against identities, explicit matrices and finite differences (float64)."""
from __future__ import annotations

import math

import pytest
import torch

from flowins.geometry import quaternion as quat

F64 = torch.float64
BATCHES = [(), (1,), (3, 2)]


def random_quaternions(*batch: int, seed: int = 0, unit: bool = True) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(*batch, 4, generator=g, dtype=F64)
    return q / q.norm(dim=-1, keepdim=True) if unit else q


def random_vectors(*batch: int, seed: int = 1, scale: float = 1.0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return scale * torch.randn(*batch, 3, generator=g, dtype=F64)


def skew(a: torch.Tensor) -> torch.Tensor:
    x, y, z = a.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack(
        (torch.stack((o, -z, y), -1), torch.stack((z, o, -x), -1), torch.stack((-y, x, o), -1)), dim=-2
    )


def rodrigues(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """``R = I + sinθ K + (1 - cosθ) K²`` for a unit axis ``(..., 3)``, angle ``(...)``."""
    K = skew(axis)
    s, c = torch.sin(angle)[..., None, None], torch.cos(angle)[..., None, None]
    return torch.eye(3, dtype=axis.dtype) + s * K + (1.0 - c) * (K @ K)


def axis_angle_of(q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Axis and angle of a (normalised here) quaternion, written independently of the library."""
    q = q / q.norm(dim=-1, keepdim=True)
    u = q[..., 1:]
    n = u.norm(dim=-1)
    return u / n.unsqueeze(-1), 2.0 * torch.atan2(n, q[..., 0])


def rx(a):
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=F64)


def ry(a):
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=F64)


def rz(a):
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=F64)


# ------------------------------------------------------------------ algebra


@pytest.mark.parametrize("batch", BATCHES)
def test_product_with_conjugate_is_squared_norm_times_identity(batch):
    q = random_quaternions(*batch, unit=False)
    prod = quat.multiply(q, quat.conjugate(q))
    expected = torch.zeros(*batch, 4, dtype=F64)
    expected[..., 0] = (q * q).sum(-1)
    assert prod.shape == (*batch, 4)
    torch.testing.assert_close(prod, expected, rtol=0, atol=1e-14)
    torch.testing.assert_close(quat.multiply(quat.conjugate(q), q), expected, rtol=0, atol=1e-14)


def test_multiply_is_associative_and_not_commutative():
    a, b, c = (random_quaternions(5, seed=s, unit=False) for s in (1, 2, 3))
    left = quat.multiply(quat.multiply(a, b), c)
    right = quat.multiply(a, quat.multiply(b, c))
    torch.testing.assert_close(left, right, rtol=0, atol=1e-13)
    assert (quat.multiply(a, b) - quat.multiply(b, a)).abs().max() > 1e-3


def test_multiply_matches_unit_quaternion_table():
    """i j = k, j k = i, k i = j, i² = -1 (Hamilton convention)."""
    one, i, j, k = torch.eye(4, dtype=F64)
    torch.testing.assert_close(quat.multiply(i, j), k)
    torch.testing.assert_close(quat.multiply(j, k), i)
    torch.testing.assert_close(quat.multiply(k, i), j)
    torch.testing.assert_close(quat.multiply(i, i), -one)
    torch.testing.assert_close(quat.multiply(j, i), -k)


@pytest.mark.parametrize("batch", BATCHES)
def test_left_and_right_matrices_reproduce_the_product(batch):
    a = random_quaternions(*batch, seed=3, unit=False)
    b = random_quaternions(*batch, seed=4, unit=False)
    ab = quat.multiply(a, b)
    assert quat.left_matrix(a).shape == (*batch, 4, 4)
    torch.testing.assert_close((quat.left_matrix(a) @ b.unsqueeze(-1)).squeeze(-1), ab, rtol=0, atol=1e-14)
    torch.testing.assert_close((quat.right_matrix(b) @ a.unsqueeze(-1)).squeeze(-1), ab, rtol=0, atol=1e-14)


def test_multiply_broadcasts():
    a = random_quaternions(3, 1, seed=5)
    b = random_quaternions(1, 2, seed=6)
    out = quat.multiply(a, b)
    assert out.shape == (3, 2, 4)
    torch.testing.assert_close(out[2, 1], quat.multiply(a[2, 0], b[0, 1]))


def test_wrong_last_dimension_raises():
    with pytest.raises(ValueError, match="last dimension 4"):
        quat.multiply(torch.zeros(3, dtype=F64), torch.zeros(4, dtype=F64))
    with pytest.raises(ValueError, match="last dimension 3"):
        quat.rotate(quat.identity(dtype=F64), torch.zeros(4, dtype=F64))


# ------------------------------------------------------------------ rotation matrices


@pytest.mark.parametrize("batch", BATCHES)
def test_to_matrix_is_a_rotation_equal_to_rodrigues(batch):
    q = random_quaternions(*batch, seed=7, unit=False)  # to_matrix normalises
    R = quat.to_matrix(q)
    assert R.shape == (*batch, 3, 3)
    eye = torch.eye(3, dtype=F64).expand_as(R)
    torch.testing.assert_close(R @ R.transpose(-1, -2), eye, rtol=0, atol=1e-14)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(batch, dtype=F64), rtol=0, atol=1e-14)
    axis, angle = axis_angle_of(q)
    torch.testing.assert_close(R, rodrigues(axis, angle), rtol=0, atol=1e-14)


@pytest.mark.parametrize("batch", BATCHES)
def test_to_matrix_jacobian_is_the_central_difference(batch):
    q = random_quaternions(*batch, seed=3, unit=False)
    J = quat.to_matrix_jacobian(q)
    assert J.shape == (*batch, 4, 3, 3)
    eps = 1e-6
    for k in range(4):
        e = torch.zeros(4, dtype=F64)
        e[k] = eps
        fd = (quat.to_matrix(q + e) - quat.to_matrix(q - e)) / (2 * eps)
        torch.testing.assert_close(J[..., k, :, :], fd, rtol=0, atol=1e-8)
    # normalised inside: no change along q itself
    radial = (J * q[..., :, None, None]).sum(-3)
    torch.testing.assert_close(radial, torch.zeros_like(radial), rtol=0, atol=1e-13)


@pytest.mark.parametrize("batch", BATCHES)
def test_rotate_equals_matrix_times_vector_and_sandwich_product(batch):
    q = random_quaternions(*batch, seed=8)
    v = random_vectors(*batch, seed=9)
    out = quat.rotate(q, v)
    assert out.shape == (*batch, 3)
    torch.testing.assert_close(out, (quat.to_matrix(q) @ v.unsqueeze(-1)).squeeze(-1), rtol=0, atol=1e-14)
    pure = torch.cat((torch.zeros(*batch, 1, dtype=F64), v), -1)
    sandwich = quat.multiply(quat.multiply(q, pure), quat.conjugate(q))
    torch.testing.assert_close(out, sandwich[..., 1:], rtol=0, atol=1e-14)


def test_rotation_of_a_product_composes():
    a, b = random_quaternions(4, seed=10), random_quaternions(4, seed=11)
    torch.testing.assert_close(
        quat.to_matrix(quat.multiply(a, b)), quat.to_matrix(a) @ quat.to_matrix(b), rtol=0, atol=1e-14
    )


@pytest.mark.parametrize("batch", BATCHES)
def test_from_matrix_inverts_to_matrix_up_to_sign(batch):
    q = random_quaternions(*batch, seed=12)
    back = quat.from_matrix(quat.to_matrix(q))
    assert back.shape == (*batch, 4)
    assert (back[..., 0] >= 0).all()
    sign = torch.where(q[..., :1] < 0, -1.0, 1.0).to(F64)
    torch.testing.assert_close(back, sign * q, rtol=0, atol=1e-13)


def test_from_matrix_covers_all_four_shepperd_branches():
    """Rotations where w, x, y and z in turn is the largest component."""
    qs = torch.tensor(
        [[0.9, 0.1, 0.2, 0.3], [0.1, 0.9, -0.2, 0.3], [0.2, -0.1, 0.9, 0.3], [0.1, 0.3, -0.2, 0.9]], dtype=F64
    )
    qs = qs / qs.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(quat.from_matrix(quat.to_matrix(qs)), qs, rtol=0, atol=1e-14)


@pytest.mark.parametrize(
    "axis", [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 0.0], [1.0, -2.0, 3.0]]
)
def test_from_matrix_has_no_nan_at_180_degrees(axis):
    axis = torch.tensor(axis, dtype=F64)
    axis = axis / axis.norm()
    R = rodrigues(axis, torch.tensor(math.pi, dtype=F64)).requires_grad_(True)
    q = quat.from_matrix(R)
    assert torch.isfinite(q).all()
    # the quaternion of a half turn is (0, ±axis)
    assert abs(float(q[0].detach())) < 1e-7
    torch.testing.assert_close(q[1:].detach().abs(), axis.abs(), rtol=0, atol=1e-7)
    torch.testing.assert_close(quat.to_matrix(q).detach(), R.detach(), rtol=0, atol=1e-12)
    (grad,) = torch.autograd.grad(q.sum(), R)
    assert torch.isfinite(grad).all()


# ------------------------------------------------------------------ rotation vectors


@pytest.mark.parametrize("batch", BATCHES)
def test_from_rotation_vector_is_the_axis_angle_quaternion(batch):
    theta = random_vectors(*batch, seed=13)
    q = quat.from_rotation_vector(theta)
    assert q.shape == (*batch, 4)
    angle = theta.norm(dim=-1)
    expected = torch.cat(
        (torch.cos(angle / 2).unsqueeze(-1), (torch.sin(angle / 2) / angle).unsqueeze(-1) * theta), -1
    )
    torch.testing.assert_close(q, expected, rtol=0, atol=1e-15)
    torch.testing.assert_close(quat.to_matrix(q), rodrigues(theta / angle.unsqueeze(-1), angle), rtol=0, atol=1e-14)


@pytest.mark.parametrize("batch", BATCHES)
def test_to_rotation_vector_inverts_from_rotation_vector(batch):
    g = torch.Generator().manual_seed(14)
    axis = torch.randn(*batch, 3, generator=g, dtype=F64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = 1e-3 + (math.pi - 2e-3) * torch.rand(batch, generator=g, dtype=F64)  # in (0, π)
    theta = angle.unsqueeze(-1) * axis
    back = quat.to_rotation_vector(quat.from_rotation_vector(theta))
    assert back.shape == (*batch, 3)
    torch.testing.assert_close(back, theta, rtol=0, atol=1e-12)
    # a negated quaternion is the same rotation
    torch.testing.assert_close(quat.to_rotation_vector(-quat.from_rotation_vector(theta)), theta, rtol=0, atol=1e-12)


@pytest.mark.parametrize("angle", [1e-9, 1e-6, 5e-4, 1e-3, 2e-3, 0.1, 1.0, 3.0, math.pi - 1e-6])
def test_rotation_vector_round_trip_across_the_small_angle_switch(angle):
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=F64)
    theta = angle * axis / axis.norm()
    back = quat.to_rotation_vector(quat.from_rotation_vector(theta))
    torch.testing.assert_close(back, theta, rtol=1e-12, atol=1e-15)


def test_rotations_about_one_axis_compose_additively():
    g = torch.Generator().manual_seed(15)
    a = torch.randn(6, 3, generator=g, dtype=F64)
    t = 2.0 * torch.rand(6, 1, generator=g, dtype=F64) - 1.0
    s = 2.0 * torch.rand(6, 1, generator=g, dtype=F64) - 1.0
    lhs = quat.multiply(quat.from_rotation_vector(a * t), quat.from_rotation_vector(a * s))
    torch.testing.assert_close(lhs, quat.from_rotation_vector(a * (t + s)), rtol=0, atol=1e-14)


def test_angle_between_is_the_relative_rotation_angle():
    q = random_quaternions(5, seed=16)
    axis = random_vectors(5, seed=17)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angles = torch.tensor([0.0, 0.1, 1.0, 2.5, 3.1], dtype=F64)
    p = quat.multiply(q, quat.from_rotation_vector(angles.unsqueeze(-1) * axis))
    torch.testing.assert_close(quat.angle_between(q, p), angles, rtol=0, atol=1e-7)
    torch.testing.assert_close(quat.angle_between(q, -p), angles, rtol=0, atol=1e-7)


# ------------------------------------------------------------------ Euler angles


@pytest.mark.parametrize(
    "rpy_deg", [(5.0, -11.0, 17.0), (10.0, -20.0, 170.0), (-170.0, 80.0, -95.0), (45.0, -89.0, 0.0)]
)
def test_euler_matches_explicit_rz_ry_rx_and_round_trips(rpy_deg):
    roll, pitch, yaw = (math.radians(a) for a in rpy_deg)
    q = quat.from_euler(*(torch.tensor(a, dtype=F64) for a in (roll, pitch, yaw)))
    torch.testing.assert_close(quat.to_matrix(q), rz(yaw) @ ry(pitch) @ rx(roll), rtol=0, atol=1e-14)
    r2, p2, y2 = quat.to_euler(q)
    torch.testing.assert_close(torch.stack((r2, p2, y2)), torch.tensor([roll, pitch, yaw], dtype=F64), rtol=0, atol=1e-9)


@pytest.mark.parametrize("batch", BATCHES)
def test_euler_batched(batch):
    g = torch.Generator().manual_seed(18)
    roll = (2 * torch.rand(batch, generator=g, dtype=F64) - 1) * 3.0
    pitch = (2 * torch.rand(batch, generator=g, dtype=F64) - 1) * 1.5
    yaw = (2 * torch.rand(batch, generator=g, dtype=F64) - 1) * 3.0
    q = quat.from_euler(roll, pitch, yaw)
    assert q.shape == (*batch, 4)
    for got, want in zip(quat.to_euler(q), (roll, pitch, yaw)):
        assert got.shape == batch
        torch.testing.assert_close(got, want, rtol=0, atol=1e-12)


# ------------------------------------------------------------------ cumulative product


@pytest.mark.parametrize("length", [1, 2, 7, 64])
def test_cumulative_product_matches_a_loop(length):
    q = random_quaternions(3, length, seed=length)
    expected = []
    for b in range(3):
        acc = q[b, 0]
        rows = [acc]
        for k in range(1, length):
            acc = quat.multiply(acc, q[b, k])
            rows.append(acc)
        expected.append(torch.stack(rows))
    out = quat.cumulative_product(q)
    assert out.shape == (3, length, 4)
    torch.testing.assert_close(out, torch.stack(expected), rtol=0, atol=1e-13)


def test_cumulative_product_needs_a_sequence_axis():
    with pytest.raises(ValueError):
        quat.cumulative_product(quat.identity(dtype=F64))


# ------------------------------------------------------------------ small angles and gradients

#: ∂𝒬{θ}/∂θ at θ = 0: (cos(|θ|/2), θ/2 + O(θ³))
D_Q_AT_ZERO = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 0.5]], dtype=F64)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("angle", [0.0, 1e-8])
def test_from_rotation_vector_is_finite_at_tiny_angles(dtype, angle):
    theta = torch.tensor([angle, -angle, 0.5 * angle], dtype=dtype)
    q = quat.from_rotation_vector(theta)
    assert q.dtype == dtype
    assert torch.isfinite(q).all()
    expected = torch.cat((torch.ones(1, dtype=dtype), 0.5 * theta))
    torch.testing.assert_close(q, expected, rtol=0, atol=1e-7 if dtype == torch.float32 else 1e-16)
    back = quat.to_rotation_vector(q)
    assert torch.isfinite(back).all()
    torch.testing.assert_close(back, theta, rtol=1e-5, atol=1e-20)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_gradient_of_from_rotation_vector_at_exactly_zero(dtype):
    theta = torch.zeros(3, dtype=dtype, requires_grad=True)
    q = quat.from_rotation_vector(theta)
    rows = [torch.autograd.grad(q[i], theta, retain_graph=True)[0] for i in range(4)]
    jac = torch.stack(rows)
    assert torch.isfinite(jac).all()
    torch.testing.assert_close(jac, D_Q_AT_ZERO.to(dtype), rtol=0, atol=0)


def test_gradient_of_to_rotation_vector_at_identity():
    """θ ≈ 2 u / |q| at q = (1, 0, 0, 0): ∂θ/∂q = [0 | 2 I] (the length direction drops out)."""
    q = quat.identity(dtype=F64).requires_grad_(True)
    theta = quat.to_rotation_vector(q)
    jac = torch.stack([torch.autograd.grad(theta[i], q, retain_graph=True)[0] for i in range(3)])
    assert torch.isfinite(jac).all()
    expected = torch.cat((torch.zeros(3, 1, dtype=F64), 2.0 * torch.eye(3, dtype=F64)), 1)
    torch.testing.assert_close(jac, expected, rtol=0, atol=1e-15)


@pytest.mark.parametrize("angle", [1e-5, 1.0])
def test_gradcheck_from_rotation_vector(angle):
    axis = torch.tensor([[0.3, -0.5, 0.8], [1.0, 0.0, 0.0]], dtype=F64)
    theta = (angle * axis / axis.norm(dim=-1, keepdim=True)).requires_grad_(True)
    assert torch.autograd.gradcheck(quat.from_rotation_vector, (theta,), eps=1e-7, atol=1e-9, rtol=1e-7)


@pytest.mark.parametrize("angle", [1e-5, 1.0, 3.0])
def test_gradcheck_to_rotation_vector(angle):
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=F64)
    q = (1.3 * quat.from_rotation_vector(angle * axis / axis.norm())).requires_grad_(True)
    assert torch.autograd.gradcheck(quat.to_rotation_vector, (q,), eps=1e-7, atol=1e-8, rtol=1e-6)
