"""Two-view DLT triangulation against known geometry and finite differences."""
import functools

import pytest
import torch

from flowins.geometry import quaternion as quat
from flowins.geometry.triangulation import (
    camera_matrix,
    project_homogeneous,
    triangulate,
)

F64 = torch.float64


def random_rig(gen, batch=(), baseline=1.0):
    """Two cameras looking roughly along +z at points 5-20 m away."""
    q1 = quat.from_rotation_vector(0.1 * torch.randn(*batch, 3, generator=gen, dtype=F64))
    q2 = quat.from_rotation_vector(0.1 * torch.randn(*batch, 3, generator=gen, dtype=F64))
    p1 = torch.randn(*batch, 3, generator=gen, dtype=F64)
    p2 = p1 + baseline * torch.randn(*batch, 3, generator=gen, dtype=F64) / 3**0.5
    X = p1 + torch.cat((4 * torch.randn(*batch, 2, generator=gen, dtype=F64), 5 + 15 * torch.rand(*batch, 1, generator=gen, dtype=F64)), -1)
    return quat.to_matrix(q1), p1, quat.to_matrix(q2), p2, X


@pytest.mark.parametrize("batch", [(), (1,), (3, 2)])
def test_noise_free_point_is_recovered_exactly(batch):
    gen = torch.Generator().manual_seed(0)
    R1, p1, R2, p2, X = random_rig(gen, batch)
    P1, P2 = camera_matrix(R1, p1), camera_matrix(R2, p2)
    Xh = torch.cat((X, torch.ones(*batch, 1, dtype=F64)), -1)
    x1, z1 = project_homogeneous(P1, Xh)
    x2, _ = project_homogeneous(P2, Xh)
    tri = triangulate(P1, P2, x1, x2)
    assert tri.point.shape == (*batch, 4)
    recovered = tri.point[..., :3] / tri.point[..., 3:]
    torch.testing.assert_close(recovered, X, rtol=0, atol=1e-9)
    assert (tri.point[..., 3] > 0).all()  # oriented in front of camera 1
    assert (tri.conditioning > 1e-3).all()


def test_pure_rotation_gives_a_point_at_infinity_and_flags_degeneracy():
    gen = torch.Generator().manual_seed(1)
    R1, p1, R2, _, X = random_rig(gen, (5,))
    P1, P2 = camera_matrix(R1, p1), camera_matrix(R2, p1)  # same centre
    Xh = torch.cat((X, torch.ones(5, 1, dtype=F64)), -1)
    x1, _ = project_homogeneous(P1, Xh)
    x2, _ = project_homogeneous(P2, Xh)
    tri = triangulate(P1, P2, x1, x2)
    assert torch.isfinite(tri.point).all()
    assert (tri.conditioning < 1e-6).all()
    # whatever point in the 2-D null space was chosen, it reprojects onto both pixels
    for P, x in ((P1, x1), (P2, x2)):
        y, _ = project_homogeneous(P, tri.point)
        torch.testing.assert_close(y, x, rtol=0, atol=1e-8)


def test_triangulation_gradient_matches_finite_differences():
    gen = torch.Generator().manual_seed(2)
    R1, p1, R2, p2, X = random_rig(gen)
    P1, P2 = camera_matrix(R1, p1), camera_matrix(R2, p2)
    Xh = torch.cat((X, torch.ones(1, dtype=F64)))
    x1, _ = project_homogeneous(P1, Xh)
    x2, _ = project_homogeneous(P2, Xh)
    x2 = x2 + 1e-3 * torch.randn(2, generator=gen, dtype=F64)  # inconsistent: a least-squares point

    def euclidean(p2_, x2_):
        tri = triangulate(P1, camera_matrix(R2, p2_), x1, x2_)
        return tri.point[:3] / tri.point[3]

    assert torch.autograd.gradcheck(euclidean, (p2.clone().requires_grad_(), x2.clone().requires_grad_()))


@pytest.mark.parametrize("eigen", ["eigh", "jacobi"])
@pytest.mark.parametrize("baseline", [1.0, 1e-3])
def test_eigenvectors_with_newton_step_equal_the_svd_null_vector(baseline, eigen):
    """solve_dlt (eigh of AᵀA, or one-sided Jacobi of A; one Newton step) against
    torch.linalg.svd of the same equilibrated matrix, on noisy points down to a small
    baseline (ill-conditioned)."""
    from flowins.geometry.triangulation import dlt_matrix, solve_dlt

    gen = torch.Generator().manual_seed(4)
    R1, p1, R2, p2, X = random_rig(gen, (500,), baseline=baseline)
    P1, P2 = camera_matrix(R1, p1 - p1), camera_matrix(R2, p2 - p1)
    Xh = torch.cat((X - p1, torch.ones(500, 1, dtype=F64)), -1)
    x1, _ = project_homogeneous(P1, Xh)
    x2, _ = project_homogeneous(P2, Xh)
    x2 = x2 + 3e-4 * torch.randn(500, 2, generator=gen, dtype=F64)
    solution = solve_dlt(dlt_matrix(P1, P2, x1, x2), P1, eigen=eigen)
    _, S, Vh = torch.linalg.svd(solution.rows)
    reference = Vh[..., -1, :] * torch.sign((Vh[..., -1, :] * solution.point).sum(-1, keepdim=True))
    if baseline < 1:
        assert float(solution.conditioning.min()) < 1e-4  # ill-conditioned points among them
    # either method's rounding error is ~ eps / conditioning; eigh of AᵀA alone is ~ eps / conditioning²
    bound = 2e-14 / solution.conditioning
    assert ((solution.point - reference).norm(dim=-1) <= bound).all()
    assert ((solution.singular_values - S).abs().max(-1).values <= bound).all()


@pytest.mark.parametrize("eigen", ["eigh", "jacobi"])
def test_solve_dlt_is_one_graph(eigen):
    """No graph break (no ``.item()``, no data-dependent branch): ``torch.compile(fullgraph=True)``
    with a backend that needs no compiler, equal to eager; the GPU's Jacobi equals eigh."""
    from flowins.geometry.triangulation import dlt_matrix, solve_dlt

    gen = torch.Generator().manual_seed(5)
    R1, p1, R2, p2, X = random_rig(gen, (64,), baseline=0.1)
    P1, P2 = camera_matrix(R1, p1 - p1), camera_matrix(R2, p2 - p1)
    Xh = torch.cat((X - p1, torch.ones(64, 1, dtype=F64)), -1)
    A = dlt_matrix(P1, P2, project_homogeneous(P1, Xh)[0], project_homogeneous(P2, Xh)[0])
    torch._dynamo.reset()
    compiled = torch.compile(functools.partial(solve_dlt, eigen=eigen), fullgraph=True, backend="eager")
    for got, want in zip(compiled(A, P1), solve_dlt(A, P1, eigen=eigen)):
        torch.testing.assert_close(got, want, atol=0, rtol=0)
    jacobi, eigh = solve_dlt(A, P1, eigen="jacobi"), solve_dlt(A, P1, eigen="eigh")
    torch.testing.assert_close(jacobi.point, eigh.point, atol=1e-12, rtol=0)
    torch.testing.assert_close(jacobi.conditioning, eigh.conditioning, atol=1e-12, rtol=0)
