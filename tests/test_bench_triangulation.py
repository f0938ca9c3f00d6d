"""``benchmarks/bench_triangulation.py``'s eigh-free solve: the closed-form adjugate against
``det(m) I`` and LAPACK's determinant, and the solve against ``torch.linalg.svd``."""
import importlib.util
from pathlib import Path

import torch

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_triangulation.py"
_SPEC = importlib.util.spec_from_file_location("bench_triangulation", _PATH)
bench = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(bench)

F64 = torch.float64


def test_the_adjugate_times_the_matrix_is_its_determinant():
    m = torch.randn(50, 4, 4, generator=torch.Generator().manual_seed(0), dtype=F64)
    adj, det = bench.adjugate(m)
    assert torch.allclose(det, torch.linalg.det(m), rtol=1e-12, atol=1e-12)
    eye = torch.eye(4, dtype=F64)
    assert torch.allclose(adj @ m, det[:, None, None] * eye, atol=1e-12)
    assert torch.allclose(m @ adj, det[:, None, None] * eye, atol=1e-12)


def test_the_adjugate_of_a_rank_3_matrix_spans_its_null_vector():
    gen = torch.Generator().manual_seed(1)
    u, _, vh = torch.linalg.svd(torch.randn(20, 4, 4, generator=gen, dtype=F64))
    m = u @ torch.diag_embed(torch.tensor([3.0, 2.0, 1.0, 0.0], dtype=F64)) @ vh
    adj, det = bench.adjugate(m)
    null = vh[:, -1, :]
    # adj(m) = (product of the nonzero singular values) ± v uᵀ with v, u the null vectors
    expected = 6.0 * null.unsqueeze(-1) * u[:, :, -1].unsqueeze(-2) * torch.linalg.det(u @ vh)[:, None, None]
    assert torch.allclose(adj, expected, atol=1e-12)
    assert det.abs().max() < 1e-12


def _systems(baseline: float, seed: int = 0):
    (A, P1), = bench.frames(1, 300, baseline, 1e-3, seed=seed)
    rows = A / torch.linalg.vector_norm(A, dim=-1, keepdim=True)
    _, S, Vh = torch.linalg.svd(rows)
    return A, P1, Vh[..., -1, :], S


def test_the_eigh_free_solve_reaches_the_svd_null_vector_on_well_posed_points():
    A, P1, null, S = _systems(baseline=1.0)
    point, conditioning = bench.solve_without_eigh(A, P1, newton=3)
    reference = null * torch.sign((null * point).sum(-1, keepdim=True))
    assert ((point - reference).norm(dim=-1) <= 1e-13 / conditioning).all()
    assert torch.allclose(conditioning, (S[..., 2] - S[..., 3]) / S[..., 0], rtol=1e-9, atol=1e-12)
    assert (torch.linalg.vecdot(point, P1[2]) > 0).all()  # in front of camera 1
    start, _ = bench.solve_without_eigh(A, P1, newton=0)  # the adjugate's column alone is farther
    assert (start - reference).norm(dim=-1).max() > 1e3 * (point - reference).norm(dim=-1).max()
