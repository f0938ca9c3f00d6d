"""Point selection: the spread top-k against a naive reference, the parallax score against geometry."""
import math

import pytest
import torch

from flowins.flow.points import FlowPoints
from flowins.geometry import quaternion as quat
from flowins.measurements.selection import rotation_parallax_px, select_points, spread_top_k
from flowins.state import STATE, make_state

F64 = torch.float64


def naive_spread_top_k(score, uv, k, cell):
    """Round robin over cells: every cell's best, then every cell's second best, ... (ties by score)."""
    cells = {}
    for i in sorted(range(len(score)), key=lambda i: -float(score[i])):
        key = (math.floor(float(uv[i, 0]) / cell), math.floor(float(uv[i, 1]) / cell))
        cells.setdefault(key, []).append(i)
    picked, rank = [], 0
    while len(picked) < min(k, len(score)):
        layer = [members[rank] for members in cells.values() if rank < len(members)]
        picked += sorted(layer, key=lambda i: -float(score[i]))
        rank += 1
    return picked[:k]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_spread_top_k_matches_a_naive_round_robin(seed):
    gen = torch.Generator().manual_seed(seed)
    uv = torch.rand(300, 2, generator=gen, dtype=F64) * torch.tensor([320.0, 240.0])
    uv[:120] = uv[:120] * 0.2  # a crowded corner
    score = torch.rand(300, generator=gen, dtype=F64)
    for k in (1, 17, 64, 299):
        got = spread_top_k(score, uv, k, cell_px=64.0).tolist()
        assert got == naive_spread_top_k(score, uv, k, 64.0)
    assert sorted(spread_top_k(score, uv, 1000, cell_px=64.0).tolist()) == list(range(300))


def test_spreading_takes_every_cell_before_a_second_point_of_any():
    uv = torch.tensor([[1.0, 1], [2, 2], [3, 3], [100, 100], [200, 1]], dtype=F64)
    score = torch.tensor([9.0, 8, 7, 1, 0.5], dtype=F64)
    assert spread_top_k(score, uv, 3, cell_px=50.0).tolist() == [0, 3, 4]


def _state_with_rotation(angle_rad):
    x = make_state(p=torch.zeros(3, dtype=F64), v=torch.zeros(3, dtype=F64), q=quat.from_rotation_vector(torch.tensor([0.0, 0.0, angle_rad], dtype=F64)))
    x = x.clone()
    x[STATE.q_prev] = torch.tensor([1.0, 0, 0, 0], dtype=F64)
    return x


def test_rotation_parallax_is_zero_for_the_flow_of_a_pure_rotation_and_the_ray_angle_otherwise():
    K = torch.tensor([[200.0, 0, 160], [0, 200, 120], [0, 0, 1]], dtype=F64)
    R_ci = torch.eye(3, dtype=F64)
    angle = 0.05
    x = _state_with_rotation(angle)
    gen = torch.Generator().manual_seed(0)
    uv1 = torch.rand(40, 2, generator=gen, dtype=F64) * torch.tensor([320.0, 240.0])
    # camera 2 = camera 1 rotated by R (camera axes = body axes here): a ray d1 appears at R^T d1
    R = quat.to_matrix(x[STATE.q])
    d1 = torch.cat(((uv1 - K[:2, 2]) / 200.0, torch.ones(40, 1, dtype=F64)), -1)
    d2 = d1 @ R  # R^T d1, row-wise
    uv2 = d2[:, :2] / d2[:, 2:] * 200.0 + K[:2, 2]
    pts = FlowPoints(uv1, uv2 - uv1, torch.full_like(uv1, 0.3))
    assert rotation_parallax_px(x, pts, K, R_ci).abs().max() < 1e-9
    # the same flow seen with no rotation in the state: the full ray angle
    expect = 200.0 * torch.atan2(torch.linalg.cross(d1, d2).norm(dim=-1), (d1 * d2).sum(-1))
    torch.testing.assert_close(rotation_parallax_px(_state_with_rotation(0.0), pts, K, R_ci), expect)


def test_select_points_by_parallax_prefers_large_parallax_over_sigma_and_checks_arguments():
    K = torch.tensor([[200.0, 0, 160], [0, 200, 120], [0, 0, 1]], dtype=F64)
    x = _state_with_rotation(0.0)
    uv1 = torch.tensor([[100.0, 100], [110, 100], [120, 100], [130, 100]], dtype=F64)
    flow = torch.tensor([[1.0, 0], [4, 0], [2, 0], [3, 0]], dtype=F64)
    sigma = torch.tensor([[0.5, 0.5], [0.5, 0.5], [0.1, 0.1], [0.5, 0.5]], dtype=F64)
    pts = FlowPoints(uv1, flow, sigma)
    # parallax / σ: 2, 8, 20, 6 (about)
    assert select_points(x, pts, K, torch.eye(3, dtype=F64), n_points=2, cell_px=1000.0).tolist() == [2, 1]
    assert select_points(x, pts, K, torch.eye(3, dtype=F64), n_points=1, method="sigma", cell_px=1000.0).tolist() == [2]
    with pytest.raises(ValueError, match="selection method"):
        select_points(x, pts, K, torch.eye(3, dtype=F64), n_points=2, method="best")
    with pytest.raises(ValueError, match="n_points"):
        select_points(x, pts, K, torch.eye(3, dtype=F64), n_points=0)


def _selection_rows(counts, seed):
    """Per row: a state (a random turn between the frames), its own camera, and candidates."""
    gen = torch.Generator().manual_seed(seed)
    rows = []
    for n in counts:
        x = make_state(p=torch.zeros(3, dtype=F64), v=torch.zeros(3, dtype=F64),
                       q=quat.from_rotation_vector(0.05 * torch.randn(3, generator=gen, dtype=F64)))
        x = x.clone()
        x[STATE.q_prev] = quat.from_rotation_vector(0.05 * torch.randn(3, generator=gen, dtype=F64))
        f = 180.0 + 60.0 * torch.rand(1, generator=gen, dtype=F64)
        K = torch.tensor([[float(f), 0, 160], [0, float(f), 120], [0, 0, 1]], dtype=F64)
        R_ci = quat.to_matrix(quat.from_rotation_vector(0.3 * torch.randn(3, generator=gen, dtype=F64)))
        uv1 = torch.rand(n, 2, generator=gen, dtype=F64) * torch.tensor([320.0, 240.0], dtype=F64)
        uv1[: n // 3] *= 0.2  # a crowded corner
        flow = 3.0 * torch.randn(n, 2, generator=gen, dtype=F64)
        sigma = 0.2 + torch.rand(n, 2, generator=gen, dtype=F64)
        rows.append((x, K, R_ci, FlowPoints(uv1, flow, sigma)))
    return rows


@pytest.mark.parametrize("method", ["parallax", "sigma", "grid"])
@pytest.mark.parametrize("shape", [(1,), (3,), (3, 2)])
@pytest.mark.parametrize("fill", ["tempting", "nan"])
def test_a_batch_with_padding_picks_in_each_row_what_the_row_alone_picks(method, shape, fill):
    """Rows of 30-90 candidates padded to 90 with candidates that would win every ranking
    (in the crowded corner, large flow, tiny σ) or with NaN: the real picks of each row are
    the row's own picks, in order, and the padding comes after them."""
    counts = [90, 30, 64, 45, 90, 71][: math.prod(shape)]
    rows = _selection_rows(counts, seed=len(counts))
    M = max(counts)
    mask = torch.arange(M) < torch.tensor(counts).unsqueeze(-1)
    tensors = []
    for k in range(3):
        t = torch.stack([torch.cat((r[3][k], torch.zeros(M - len(r[3][k]), 2, dtype=F64))) for r in rows])
        t[~mask] = {"tempting": (5.0, 50.0, 1e-3)[k], "nan": float("nan")}[fill]
        tensors.append(t.reshape(*shape, M, 2))
    points = FlowPoints(*tensors)
    x, K, R_ci = (torch.stack([r[i] for r in rows]).reshape(*shape, *rows[0][i].shape) for i in range(3))
    mask = mask.reshape(*shape, M)
    for n_points in (20, 50):
        picked = select_points(x, points, K, R_ci, n_points=n_points, method=method, cell_px=64.0, mask=mask)
        assert picked.shape == (*shape, n_points)
        real = torch.take_along_dim(mask, picked, -1).reshape(-1, n_points)
        picked = picked.reshape(-1, n_points)
        for b, (x_b, K_b, R_b, points_b) in enumerate(rows):
            alone = select_points(x_b, points_b, K_b, R_b, n_points=n_points, method=method, cell_px=64.0)
            n = len(alone)
            assert n == min(n_points, counts[b])
            assert bool(real[b, :n].all()) and not bool(real[b, n:].any())  # real first, then padding
            assert picked[b, :n].tolist() == alone.tolist()


def test_spread_top_k_with_a_mask_is_the_round_robin_of_the_real_points():
    gen = torch.Generator().manual_seed(9)
    uv = torch.rand(2, 200, 2, generator=gen, dtype=F64) * torch.tensor([320.0, 240.0], dtype=F64)
    score = torch.rand(2, 200, generator=gen, dtype=F64)
    mask = torch.rand(2, 200, generator=gen) < 0.6  # padding anywhere, not only at the end
    score[~mask] = 10.0  # the best scores, were they real
    got = spread_top_k(score, uv, 150, cell_px=64.0, mask=mask)
    for b in range(2):
        real = torch.nonzero(mask[b]).squeeze(-1)
        want = [int(real[i]) for i in naive_spread_top_k(score[b, real], uv[b, real], 150, 64.0)]
        assert got[b, : len(want)].tolist() == want
        assert not bool(mask[b, got[b, len(want):]].any())
