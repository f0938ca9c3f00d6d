"""flowins.state: the helpers every covariance goes through."""
import torch

from flowins.state import symmetrize


def test_symmetrize_is_the_mean_with_the_transpose_leaves_its_input_and_carries_the_gradient():
    gen = torch.Generator().manual_seed(0)
    P = torch.randn(3, 2, 5, 5, dtype=torch.float64, generator=gen, requires_grad=True)
    before = P.detach().clone()
    S = symmetrize(P)
    assert torch.equal(S.detach(), (before + before.transpose(-1, -2)) / 2)  # halving is exact
    assert torch.equal(P.detach(), before)
    assert torch.autograd.gradcheck(symmetrize, (P,))
