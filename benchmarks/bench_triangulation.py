"""The flow model's triangulation: eigh of AᵀA plus a Newton step against torch.linalg.svd.

Builds ``--points`` two-view DLT systems per frame (random rigs in camera 1's frame,
points 5-20 m away, ``--baseline`` m apart, flow noise ``--noise`` in normalised
coordinates) and prints, in one run, milliseconds per frame for

* flowins: :func:`flowins.geometry.triangulation.solve_dlt` (eigh + Newton step);
* reference: ``torch.linalg.svd`` of the same equilibrated matrices;

their ratio, and how far the null vectors and singular values are from the SVD's
(largest distance, and largest distance times the conditioning, which is what
rounding bounds for either method).

    python benchmarks/bench_triangulation.py [--points 256] [--frames 200] [--baseline 0.1] [--noise 1e-3]
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from flowins.geometry import quaternion as quat
from flowins.geometry.triangulation import camera_matrix, dlt_matrix, project_homogeneous, solve_dlt

F64 = torch.float64


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


def timed_ms(fn, data, repeats: int = 5) -> float:
    fn(data[0])
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        for item in data:
            fn(item)
        times.append((time.perf_counter() - start) * 1e3 / len(data))
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, default=256)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--baseline", type=float, default=0.1, help="m between the two cameras")
    parser.add_argument("--noise", type=float, default=1e-3, help="flow noise, normalised image units")
    args = parser.parse_args()
    data = frames(args.frames, args.points, args.baseline, args.noise)
    with torch.inference_mode():
        ours = timed_ms(lambda item: solve_dlt(*item), data)
        reference = timed_ms(lambda item: svd_solve(*item), data)
        worst = worst_scaled = worst_s = 0.0
        min_cond = float("inf")
        for A, P1 in data:
            solution = solve_dlt(A, P1)
            point, S = svd_solve(A, P1)
            dist = torch.linalg.vector_norm(solution.point - point, dim=-1)
            worst = max(worst, float(dist.max()))
            worst_scaled = max(worst_scaled, float((dist * solution.conditioning).max()))
            worst_s = max(worst_s, float((solution.singular_values - S).abs().max()))
            min_cond = min(min_cond, float(solution.conditioning.min()))
    print(f"{args.frames} frames of {args.points} points, baseline {args.baseline} m, noise {args.noise}, "
          f"float64, {torch.get_num_threads()} threads; smallest conditioning {min_cond:.1e}")
    print(f"flowins (eigh + Newton step): {ours:.3f} ms per frame")
    print(f"torch.linalg.svd:             {reference:.3f} ms per frame  -> {reference / ours:.2f}x flowins")
    print(f"largest distance to the SVD's null vector {worst:.1e} (times the conditioning {worst_scaled:.1e}); "
          f"largest singular-value difference {worst_s:.1e}")


if __name__ == "__main__":
    main()
