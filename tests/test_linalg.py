"""Batched linear algebra (flowins.linalg): the slices give the one call's values and gradients; short
dot products are the in-order sums of their entries' products."""
import pytest
import torch

from flowins.linalg import SHORT_DOT, dot, in_slices, jacobi_right_singular


def _spd(*batch: int, n: int = 4) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    a = torch.randn(*batch, n, n, generator=g, dtype=torch.float64)
    return a @ a.transpose(-1, -2) + 0.1 * torch.eye(n, dtype=torch.float64)


def test_eigh_in_slices_of_seven_is_the_one_call_with_its_gradient():
    gram = _spd(5, 6).requires_grad_()
    lam, V = in_slices(torch.linalg.eigh, gram, batch_dims=2, limit=7)
    lam_ref, V_ref = torch.linalg.eigh(gram)
    assert lam.shape == (5, 6, 4) and V.shape == (5, 6, 4, 4)
    torch.testing.assert_close(lam, lam_ref, rtol=0, atol=0)
    torch.testing.assert_close(V, V_ref, rtol=0, atol=0)
    w = torch.randn(5, 6, 4, dtype=torch.float64)
    (grad,) = torch.autograd.grad((lam * w).sum() + V[..., 0].abs().sum(), gram)
    (grad_ref,) = torch.autograd.grad((lam_ref * w).sum() + V_ref[..., 0].abs().sum(), gram)
    torch.testing.assert_close(grad, grad_ref, rtol=1e-12, atol=1e-12)


def test_a_two_input_call_in_slices_pairs_each_slice_with_its_own():
    S = _spd(3, 5, n=2)
    b = torch.randn(3, 5, 2, 1, dtype=torch.float64)
    L = torch.linalg.cholesky(S)

    def solve(L, b):
        return torch.linalg.solve_triangular(L, b, upper=False)

    torch.testing.assert_close(in_slices(solve, L, b, batch_dims=2, limit=4), solve(L, b), rtol=0, atol=0)
    # below the limit, and off CUDA with no limit: the call itself
    torch.testing.assert_close(in_slices(torch.linalg.cholesky, S, batch_dims=2), L, rtol=0, atol=0)


def test_inputs_of_other_batch_shapes_are_refused():
    with pytest.raises(ValueError, match=r"batch shapes \(3, 5\) and \(3, 4\) differ"):
        in_slices(torch.linalg.solve_triangular, _spd(3, 5), torch.zeros(3, 4, 4, 1), batch_dims=2, limit=2)


@pytest.mark.parametrize("n", [1, 2, 3, 4, SHORT_DOT + 3])
def test_dot_is_the_in_order_sum_of_products_broadcast_with_its_gradient(n):
    g = torch.Generator().manual_seed(n)
    a = (torch.randn(5, 1, n, generator=g, dtype=torch.float64) * 1e3).requires_grad_()
    b = torch.randn(4, n, generator=g, dtype=torch.float64).requires_grad_()
    out = dot(a, b)
    assert out.shape == (5, 4)
    # the naive reference: Python floats, added in entry order
    a_list, b_list, out_list = a.detach().tolist(), b.detach().tolist(), out.detach().tolist()
    for i in range(5):
        for j in range(4):
            total = 0.0
            for k in range(n):
                total += a_list[i][0][k] * b_list[j][k]
            assert abs(out_list[i][j] - total) <= (0.0 if n <= SHORT_DOT else 1e-12 * max(1.0, abs(total)))
    w = torch.randn(5, 4, generator=g, dtype=torch.float64)
    grads = torch.autograd.grad((out * w).sum(), (a, b))
    # d/da_k = b_k, d/db_k = a_k, summed over the broadcast
    torch.testing.assert_close(grads[0], (w.unsqueeze(-1) * b).sum(1, keepdim=True), rtol=1e-13, atol=0)
    torch.testing.assert_close(grads[1], (w.unsqueeze(-1) * a).sum(0), rtol=1e-13, atol=1e-12)


@pytest.mark.parametrize("batch", [(), (1,), (3, 2)])
@pytest.mark.parametrize("rows", [4, 12])
def test_jacobi_right_singular_is_the_svd(batch, rows):
    """Against torch.linalg.svd: singular values to rounding, V orthonormal, A V's columns
    orthogonal, and the null vector of a nearly rank-deficient matrix to rounding."""
    gen = torch.Generator().manual_seed(rows)
    A = torch.randn(*batch, rows, 4, generator=gen, dtype=torch.float64)
    A[..., 3] = A[..., 0] - 2.0 * A[..., 1] + 1e-9 * A[..., 3]  # σ₄ / σ₁ ≈ 1e-9
    sigma_sq, V = jacobi_right_singular(A)
    _, S, Vh = torch.linalg.svd(A)
    assert sigma_sq.shape == (*batch, 4) and V.shape == (*batch, 4, 4)
    torch.testing.assert_close(sigma_sq.sqrt(), S.flip(-1), atol=1e-14, rtol=0)
    eye = torch.eye(4, dtype=torch.float64)
    torch.testing.assert_close(V.transpose(-1, -2) @ V, eye.expand_as(V), atol=1e-14, rtol=0)
    B = A @ V
    off = B.transpose(-1, -2) @ B - torch.diag_embed(sigma_sq)
    assert float(off.abs().max()) < 1e-13 * float(sigma_sq.max())
    null, reference = V[..., 0], Vh[..., -1, :]
    distance = torch.minimum((null - reference).norm(dim=-1), (null + reference).norm(dim=-1))
    assert float(distance.max()) < 1e-13


def test_jacobi_right_singular_of_orthogonal_or_equal_columns_is_finite_with_its_gradient():
    """Columns already orthogonal, two of equal norm, and a zero column: every rotation is
    the identity (``t = 0``), values and gradients finite."""
    A = torch.tensor([[2.0, 0.0, 0.0, 0.0], [0.0, 2.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 0.0]],
                     dtype=torch.float64, requires_grad=True)
    sigma_sq, V = jacobi_right_singular(A)
    torch.testing.assert_close(sigma_sq, torch.tensor([0.0, 1.0, 4.0, 4.0], dtype=torch.float64))
    (sigma_sq.sum() + V[..., 0].abs().sum()).backward()
    assert bool(torch.isfinite(A.grad).all())
