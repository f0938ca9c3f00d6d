"""Flow over a recording: candidates, pairs, the cache file, tracks and undistortion."""
import numpy as np
import pytest
import torch

from flowins.data.sequence import PinholeCamera, Tracks
from flowins.flow.base import FlowResult
from flowins.flow.pairs import FlowPairs, dense_pairs, pair_indices, sparse_pairs, track_pairs
from flowins.flow.points import FlowPoints, grid_candidates
from flowins.geometry.camera import distort

F64 = torch.float64


class ListFrames:
    """Frames in memory with the CameraFrames interface the pairs need."""

    def __init__(self, images, t_s):
        self.images, self.t_s = images, torch.as_tensor(t_s, dtype=F64)

    def __len__(self):
        return len(self.images)

    def read(self, i):
        return self.images[i]


class AffineFlow:
    """A provider whose flow is a known affine field of the pixel (in input pixels), σ = 0.1 + u / 1000."""

    def __init__(self):
        self.calls = []

    def __call__(self, a, b):
        if a.dtype == torch.uint8:
            B, H, W = a.shape[:3]
        else:
            B, _, H, W = a.shape
        self.calls.append((B, H, W))
        v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
        flow = torch.stack((0.5 + 0.01 * u, -0.25 + 0.02 * v)).expand(B, 2, H, W)
        return FlowResult(flow.clone(), (0.1 + u / 1000).expand(B, 2, H, W).clone())


def test_grid_candidates_sample_the_field_at_their_pixels():
    H, W = 48, 64
    field = torch.randn(2, H, W, dtype=F64)
    sigma = torch.rand(2, H, W, dtype=F64) + 0.1
    pts = grid_candidates(field, sigma, stride_px=8, border_px=5)
    u, v = pts.uv1_px[:, 0].long(), pts.uv1_px[:, 1].long()
    assert (u >= 5).all() and (u <= W - 6).all() and (v >= 5).all() and (v <= H - 6).all()
    assert torch.equal(pts.flow_px, field[:, v, u].T) and torch.equal(pts.sigma_px, sigma[:, v, u].T)
    assert pts.flow_px.is_contiguous() and pts.sigma_px.is_contiguous()  # rows in memory order, as the update reads them
    assert len(torch.unique(u)) == 7 and len(torch.unique(v)) == 5  # every 8 px in the usable 54 x 38
    assert set(torch.diff(torch.unique(u)).tolist()) == {8}


def test_grid_candidates_refuse_non_finite_flow_and_name_the_pixel():
    field = torch.zeros(2, 32, 32, dtype=F64)
    field[1, 11, 19] = float("nan")  # the grid is 3, 11, 19, 27 on both axes
    with pytest.raises(ValueError, match=r"\(u, v\) = \(19, 11\)"):
        grid_candidates(field, torch.ones_like(field), stride_px=8, border_px=0)
    with pytest.raises(ValueError, match="border_px"):
        grid_candidates(field, torch.ones_like(field), border_px=16)


def test_pair_indices_chain_and_refuse_too_few_frames():
    assert pair_indices(7, 2) == [(0, 2), (2, 4), (4, 6)]
    assert pair_indices(3, 1) == [(0, 1), (1, 2)]
    with pytest.raises(ValueError, match="no pair"):
        pair_indices(2, 2)


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_dense_pairs_keep_the_field_in_recording_pixels(scale):
    H, W = 40, 64
    images = [torch.randint(0, 255, (H, W, 3), dtype=torch.uint8) for _ in range(6)]
    provider = AffineFlow()
    pairs = dense_pairs(ListFrames(images, torch.arange(6) * 0.1), provider, step=1, stride_px=8, border_px=4,
                        batch_size=4, input_scale=scale, progress=False)
    assert len(pairs) == 5 and [c[0] for c in provider.calls] == [4, 1]
    assert provider.calls[0][1:] == (round(H * scale), round(W * scale))
    torch.testing.assert_close(pairs.t1_s, torch.arange(5, dtype=F64) * 0.1)
    torch.testing.assert_close(pairs.t2_s, torch.arange(1, 6, dtype=F64) * 0.1)
    pts = pairs.points[2]
    # the affine field evaluated in input pixels, mapped back: Δu = (0.5 + 0.01 u s) / s at full-size pixel u
    u, v = pts.uv1_px[:, 0], pts.uv1_px[:, 1]
    if scale == 1.0:
        expect = torch.stack((0.5 + 0.01 * u, -0.25 + 0.02 * v), -1)
        torch.testing.assert_close(pts.flow_px, expect)
    else:  # area-resize + bilinear back: interior points are within a small interpolation error
        us, vs = (u + 0.5) * scale - 0.5, (v + 0.5) * scale - 0.5
        expect = torch.stack((0.5 + 0.01 * us, -0.25 + 0.02 * vs), -1) / scale
        torch.testing.assert_close(pts.flow_px, expect, atol=0.02, rtol=0)
        assert (pts.sigma_px > 0.1 / scale * 0.99).all()


@pytest.mark.parametrize("column_major", [False, True])
@pytest.mark.parametrize("fields", [3, 5])  # with and without the dropout moments
def test_flow_pairs_round_trip_through_the_cache_file(tmp_path, fields, column_major):
    gen = torch.Generator().manual_seed(0)
    counts = [5, 7, 6] if column_major else [5, 0, 7]
    pts = [FlowPoints(*(torch.rand(n, 2, generator=gen, dtype=F64) * 100 for _ in range(fields))) for n in counts]
    if column_major:  # points laid out (2, M) in memory (a field's samples, transposed): a file in that order
        pts = [FlowPoints(*(None if x is None else x.T.contiguous().T for x in p)) for p in pts]
    pairs = FlowPairs(torch.tensor([0.0, 0.1, 0.2], dtype=F64), torch.tensor([0.1, 0.2, 0.3], dtype=F64), pts, "dense", "test")
    pairs.save(tmp_path / "p.npz")
    with np.load(tmp_path / "p.npz") as z:
        assert z["flow_px"].flags.f_contiguous == column_major
    back = FlowPairs.load(tmp_path / "p.npz")  # read back in row order either way
    assert back.kind == "dense" and back.description == "test" and [len(p) for p in back.points] == counts
    for a, b in zip(pairs.points, back.points):
        assert sum(x is not None for x in b) == fields
        for x, y in zip(a, b):
            if x is not None:
                torch.testing.assert_close(y, x.float().double())  # stored as float32
                assert y.is_contiguous()
    with pytest.raises(ValueError, match="not after its start"):
        FlowPairs(torch.tensor([0.2], dtype=F64), torch.tensor([0.1], dtype=F64), pts[:1], "dense")


def test_track_pairs_match_ids_between_consecutive_times():
    # ids 1, 2, 3 at t=0; 2, 3, 4 at t=1; 3 at t=2 (rows in any id order)
    t = torch.tensor([0, 0, 0, 1, 1, 1, 2], dtype=F64)
    ids = torch.tensor([3, 1, 2, 4, 2, 3, 3])
    uv = torch.tensor([[30, 3], [10, 1], [20, 2], [41, 4], [22, 2], [33, 3], [36, 3]], dtype=F64)
    pairs = track_pairs(Tracks(t, ids, uv), sigma_px=0.4)
    p0, p1 = pairs.points
    order = torch.argsort(p0.uv1_px[:, 0])
    torch.testing.assert_close(p0.uv1_px[order], torch.tensor([[20, 2], [30, 3]], dtype=F64))
    torch.testing.assert_close(p0.flow_px[order], torch.tensor([[2, 0], [3, 0]], dtype=F64))
    torch.testing.assert_close(p1.flow_px, torch.tensor([[3, 0]], dtype=F64))
    assert (p0.sigma_px == 0.4).all() and pairs.kind == "sparse"


def test_undistorted_pairs_invert_the_lens_model():
    cam = PinholeCamera(320, 240, 250.0, 252.0, 160.0, 120.0, distortion=(-0.2, 0.05, 1e-3, -5e-4))
    gen = torch.Generator().manual_seed(1)
    ideal1 = torch.rand(50, 2, generator=gen, dtype=F64) * torch.tensor([300.0, 220.0]) + 10
    ideal2 = ideal1 + torch.randn(50, 2, generator=gen, dtype=F64) * 3
    f, c = torch.tensor([250.0, 252.0], dtype=F64), torch.tensor([160.0, 120.0], dtype=F64)

    def raw(uv):
        return distort((uv - c) / f, cam.distortion) * f + c

    pts = FlowPoints(raw(ideal1), raw(ideal2) - raw(ideal1), torch.full((50, 2), 0.3, dtype=F64))
    out = FlowPairs(torch.zeros(1, dtype=F64), torch.ones(1, dtype=F64), [pts], "sparse").undistorted(cam)
    torch.testing.assert_close(out.points[0].uv1_px, ideal1, atol=1e-6, rtol=0)
    torch.testing.assert_close(out.points[0].flow_px, ideal2 - ideal1, atol=1e-6, rtol=0)


def test_sparse_pairs_reuse_each_frame_and_keep_the_tracker_output():
    images = [np.full((30, 40, 3), i, np.uint8) for i in range(4)]
    seen = []

    def tracker(a, b):
        seen.append((int(a[0, 0, 0]), int(b[0, 0, 0])))
        from flowins.flow.base import SparseFlowResult

        k = torch.tensor([[float(seen[-1][0]), 1.0]])
        return SparseFlowResult(k, k + 1, torch.full_like(k, 0.2))

    pairs = sparse_pairs(ListFrames(images, [0.0, 0.1, 0.2, 0.3]), tracker, step=1, progress=False)
    assert seen == [(0, 1), (1, 2), (2, 3)] and pairs.points[2].uv1_px.tolist() == [[2.0, 1.0]]
