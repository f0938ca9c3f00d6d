"""The flow model's triangulation (eigenvectors plus a Newton step; eigh on the CPU, one-sided
Jacobi on a GPU), against an eigh-free adjugate solve and torch.linalg.svd.

Builds ``--points`` two-view DLT systems per frame (random rigs in camera 1's frame,
points 5-20 m away, ``--baseline`` m apart, flow noise ``--noise`` in normalised
coordinates) and prints, in one run, milliseconds per frame for

* eigh: :func:`flowins.geometry.triangulation.solve_dlt` with ``eigen="eigh"``
  (``torch.linalg.eigh`` of ``AᵀA``, then one Newton step): what flowins runs on the CPU;
* Jacobi: ``eigen="jacobi"``, a fixed number of sweeps of plane rotations of ``A``'s columns
  (elementwise operations only: no LAPACK call, no wait on a GPU), then the same step:
  what flowins runs on a GPU;
* without eigh (:func:`solve_without_eigh`): the start from the adjugate of ``AᵀA`` and
  ``--newton`` Newton steps, each with the inverse of a ``4 x 4`` matrix in closed form;
* reference: ``torch.linalg.svd`` of the same equilibrated matrices;

their ratios, and how far each null vector is from the SVD's (largest distance, and largest
distance times the conditioning, which is what rounding bounds; each solve also counts the
points beyond ``1e-12`` by that measure). ``--device cuda`` runs all on the GPU (timings
synchronise it before reading the clock).

    python benchmarks/bench_triangulation.py [--points 256] [--frames 200] [--baseline 0.1] [--noise 1e-3]
                                             [--newton 3] [--device cpu|cuda]
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from flowins.config import check_device
from flowins.geometry import quaternion as quat
from flowins.geometry.triangulation import camera_matrix, dlt_matrix, project_homogeneous, solve_dlt

F64 = torch.float64
_PAIRS = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]


def _cofactor_tables() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Index tables of :func:`adjugate`: the columns ``(i, j)`` of the six ``2 x 2`` minors; for
    each entry of the adjugate its three terms (entry of ``m``, minor, sign) by Laplace expansion
    of the ``3 x 3`` minor along its one row outside the pair of rows (0, 1) or (2, 3)."""
    entry, minor, sign = [], [], []
    for i in range(4):
        for j in range(4):  # adj[i, j] = (-1)^(i+j) det(m without row j and column i)
            rows = [r for r in range(4) if r != j]
            columns = [c for c in range(4) if c != i]
            single = 1 - j if j < 2 else 5 - j  # the row whose partner is deleted
            offset = 6 if j < 2 else 0  # then the minors of rows (2, 3), else of rows (0, 1)
            for t, column in enumerate(columns):
                entry.append(4 * single + column)
                minor.append(offset + _PAIRS.index(tuple(c for c in columns if c != column)))
                sign.append((-1) ** (i + j + rows.index(single) + t))
    pair_columns = [i for i, _ in _PAIRS] + [j for _, j in _PAIRS]
    return torch.tensor(pair_columns), torch.tensor(entry), torch.tensor(minor), torch.tensor(sign, dtype=F64)


_TABLES = _cofactor_tables()


def adjugate(m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(adj(m), det(m))`` of ``(..., 4, 4)`` matrices from their ``2 x 2`` minors (``adj(m) m =
    det(m) I``, also for singular ``m``)."""
    pair_columns, entry, minor, sign = (t.to(m.device) for t in _TABLES)
    g = m.index_select(-1, pair_columns)  # (..., 4, 12): row r at columns i, then at columns j
    minors = (g[..., 0::2, :6] * g[..., 1::2, 6:] - g[..., 0::2, 6:] * g[..., 1::2, :6]).flatten(-2)  # rows (0,1), (2,3)
    terms = (m.flatten(-2).index_select(-1, entry) * minors.index_select(-1, minor) * sign.to(m.dtype))
    terms = terms.view(*m.shape[:-2], 16, 3)
    adj = (terms[..., 0] + terms[..., 1] + terms[..., 2]).view(m.shape)
    det = (m[..., 0, :] * adj[..., :, 0]).sum(-1)
    return adj, det


def solve_without_eigh(A: torch.Tensor, P1: torch.Tensor, newton: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(point, conditioning)`` as :func:`solve_dlt` gives them, without an eigendecomposition:
    the column of ``adj(G)`` (``G = aᵀa``, ``a`` the equilibrated rows) of the largest diagonal
    entry (one inverse iteration from there), then ``newton`` steps ``X ← X - W (aᵀ(a X) - ρ X)``
    with ``ρ = |a X|²`` and ``W = (G - ρ I + X Xᵀ)⁻¹ - X Xᵀ`` by :func:`adjugate`; ``σ₃``, ``σ₁``
    from the characteristic polynomial of ``G`` with the root ``ρ`` divided out (a cubic with real
    roots, by the trigonometric formula)."""
    tiny = torch.finfo(A.dtype).tiny
    rows = A / torch.linalg.vector_norm(A, dim=-1, keepdim=True).clamp_min(tiny**0.5)
    G = rows.transpose(-1, -2) @ rows
    C, _ = adjugate(G)
    best = torch.diagonal(C, dim1=-2, dim2=-1).argmax(-1)
    X = torch.take_along_dim(C, best[..., None, None], -1).squeeze(-1)
    X = X / torch.linalg.vector_norm(X, dim=-1, keepdim=True).clamp_min(tiny)
    eye = torch.eye(4, dtype=A.dtype, device=A.device)
    for _ in range(newton):
        aX = rows @ X.unsqueeze(-1)
        rho = aX.square().sum((-1, -2))
        XX = X.unsqueeze(-1) * X.unsqueeze(-2)
        inverse, det = adjugate(G - rho[..., None, None] * eye + XX)
        det = torch.where(det.abs() > tiny**0.5, det, torch.copysign(torch.full_like(det, tiny**0.5), det))
        W = inverse / det[..., None, None] - XX
        r = (rows.transpose(-1, -2) @ aX).squeeze(-1) - rho.unsqueeze(-1) * X
        X = X - (W @ r.unsqueeze(-1)).squeeze(-1)
        X = X / torch.linalg.vector_norm(X, dim=-1, keepdim=True).clamp_min(tiny)
    z1 = torch.linalg.vecdot(X, P1[..., 2, :])  # the sign that puts the point in front of camera 1
    point = X * torch.copysign(torch.ones_like(z1), z1).unsqueeze(-1)
    rho = (rows @ point.unsqueeze(-1)).square().sum((-1, -2))
    # det(λI - G) = λ⁴ - e₁λ³ + e₂λ² - e₃λ + e₄ = (λ - ρ)(λ³ - b₁λ² + b₂λ - b₃)
    e1 = torch.diagonal(G, dim1=-2, dim2=-1).sum(-1)
    e2 = 0.5 * (e1.square() - G.square().sum((-1, -2)))
    e3 = torch.diagonal(C, dim1=-2, dim2=-1).sum(-1)
    b1 = e1 - rho
    b2 = e2 - rho * b1
    b3 = e3 - rho * b2
    q = ((b1.square() - 3 * b2) / 9).clamp_min(0.0)
    r = (-2 * b1**3 + 9 * b1 * b2 - 27 * b3) / 54
    angle = torch.acos((r / (q * q.sqrt()).clamp_min(tiny)).clamp(-1.0, 1.0)) / 3
    turns = torch.tensor([0.0, 2.0, -2.0], dtype=A.dtype, device=A.device) * (torch.pi / 3)
    roots = b1.unsqueeze(-1) / 3 - 2 * q.sqrt().unsqueeze(-1) * torch.cos(angle.unsqueeze(-1) + turns)
    s31 = roots.aminmax(dim=-1)
    s3, s1 = s31.min.clamp_min(0.0).sqrt(), s31.max.clamp_min(0.0).sqrt()
    return point, (s3 - rho.sqrt()) / s1.clamp_min(tiny)


def frames(n_frames: int, n_points: int, baseline: float, noise: float, seed: int = 0):
    """``(A, P1)`` per frame: DLT matrices ``(n_points, 4, 4)`` and camera 1 ``(3, 4)``."""
    gen = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(n_frames):
        R2 = quat.to_matrix(quat.from_rotation_vector(0.05 * torch.randn(3, generator=gen, dtype=F64)))
        t = baseline * torch.nn.functional.normalize(torch.randn(3, generator=gen, dtype=F64), dim=0)
        P1 = torch.eye(3, 4, dtype=F64)
        P2 = camera_matrix(R2, t)
        X = torch.cat((4 * torch.randn(n_points, 2, generator=gen, dtype=F64),
                       5 + 15 * torch.rand(n_points, 1, generator=gen, dtype=F64)), -1)
        Xh = torch.cat((X, torch.ones(n_points, 1, dtype=F64)), -1)
        x1, _ = project_homogeneous(P1, Xh)
        x2, _ = project_homogeneous(P2, Xh)
        x2 = x2 + noise * torch.randn(n_points, 2, generator=gen, dtype=F64)
        out.append((dlt_matrix(P1, P2, x1, x2), P1))
    return out


def svd_solve(A, P1):
    """The reference: the smallest right singular vector of the row-equilibrated ``A`` by
    ``torch.linalg.svd``, oriented in front of camera 1, and the singular values."""
    rows = A / torch.linalg.vector_norm(A, dim=-1, keepdim=True)
    _, S, Vh = torch.linalg.svd(rows)
    point = Vh[..., -1, :]
    return torch.where((P1[..., 2, :] * point).sum(-1, keepdim=True) < 0, -point, point), S


def timed_ms(fn, data, device: torch.device, repeats: int = 5) -> float:
    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)
    fn(data[0])
    sync()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        for item in data:
            fn(item)
        sync()
        times.append((time.perf_counter() - start) * 1e3 / len(data))
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, default=256)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--baseline", type=float, default=0.1, help="m between the two cameras")
    parser.add_argument("--noise", type=float, default=1e-3, help="flow noise, normalised image units")
    parser.add_argument("--newton", type=int, default=3, help="Newton steps of the eigh-free solve")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    args = parser.parse_args()
    for name in ("points", "frames", "newton"):
        if getattr(args, name) < (0 if name == "newton" else 1):
            parser.error(f"--{name} must be >= {0 if name == 'newton' else 1}, got {getattr(args, name)}")
    try:
        device = check_device(args.device, "--device")
    except ValueError as error:
        parser.error(str(error))
    data = [(A.to(device), P1.to(device)) for A, P1 in frames(args.frames, args.points, args.baseline, args.noise)]
    with torch.inference_mode():
        ours = timed_ms(lambda item: solve_dlt(*item, eigen="eigh"), data, device)
        jacobi = timed_ms(lambda item: solve_dlt(*item, eigen="jacobi"), data, device)
        free = timed_ms(lambda item: solve_without_eigh(*item, args.newton), data, device)
        reference = timed_ms(lambda item: svd_solve(*item), data, device)
        worst = {"flowins": [0.0, 0.0], "jacobi": [0.0, 0.0], "free": [0.0, 0.0]}
        off = {"flowins": 0, "jacobi": 0, "free": 0}
        worst_s = 0.0
        min_cond = float("inf")
        for A, P1 in data:
            solution = solve_dlt(A, P1, eigen="eigh")
            point, S = svd_solve(A, P1)
            free_point, _ = solve_without_eigh(A, P1, args.newton)
            jacobi_point = solve_dlt(A, P1, eigen="jacobi").point
            for name, found in (("flowins", solution.point), ("jacobi", jacobi_point), ("free", free_point)):
                # a non-finite vector counts as infinitely far (max() would pass over a NaN)
                dist = torch.linalg.vector_norm(found - point, dim=-1).nan_to_num(nan=float("inf"))
                scaled = dist * solution.conditioning.clamp_min(0.0)
                worst[name] = [max(worst[name][0], float(dist.max())), max(worst[name][1], float(scaled.max()))]
                off[name] += int((scaled > 1e-12).sum())
            worst_s = max(worst_s, float((solution.singular_values - S).abs().nan_to_num(nan=float("inf")).max()))
            min_cond = min(min_cond, float(solution.conditioning.min()))
    where = (torch.cuda.get_device_name(device) if device.type == "cuda" else
             f"the CPU, {torch.get_num_threads()} threads")
    print(f"{args.frames} frames of {args.points} points, baseline {args.baseline} m, noise {args.noise}, "
          f"float64, on {where}; smallest conditioning {min_cond:.1e}")
    steps = f"{args.newton} Newton step{'' if args.newton == 1 else 's'}"
    print(f"flowins runs {'Jacobi' if device.type == 'cuda' else 'eigh'} on this device")
    print(f"eigh + Newton step:             {ours:.3f} ms per frame")
    print(f"Jacobi + Newton step:           {jacobi:.3f} ms per frame  -> {jacobi / ours:.2f}x eigh's time")
    print(f"without eigh ({steps}): {free:.3f} ms per frame  -> {free / ours:.2f}x eigh's time")
    print(f"torch.linalg.svd:               {reference:.3f} ms per frame  -> {reference / ours:.2f}x eigh's time")
    total = args.frames * args.points
    for name, label in (("flowins", "eigh"), ("jacobi", "Jacobi"), ("free", "without eigh")):
        print(f"{label}: largest distance to the SVD's null vector {worst[name][0]:.1e} (times the conditioning "
              f"{worst[name][1]:.1e}), {off[name]} of {total} points beyond 1e-12")
    print(f"eigh's largest singular-value difference {worst_s:.1e}")

if __name__ == "__main__":
    main()
