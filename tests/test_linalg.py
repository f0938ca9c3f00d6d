"""Batched linear algebra in slices (flowins.linalg): the slices give the one call's values and gradients."""
import pytest
import torch

from flowins.linalg import in_slices


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
