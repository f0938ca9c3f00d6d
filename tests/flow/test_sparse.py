"""Shi-Tomasi + LK sparse flow: accuracy on exact ground truth, direction, ids across frames."""
import cv2
import numpy as np
import pytest
import torch

from flowins.data.sequence import Tracks
from flowins.data.reference_flow import middlebury_pair, simulator_pair
from flowins.flow.sparse import ShiTomasiLK, track_sequence


def texture(u: np.ndarray, v: np.ndarray, seed: int = 0) -> np.ndarray:
    """A band-limited random texture in [0, 1] evaluated exactly at (sub)pixel positions
    (a sum of 40 plane waves, periods 7-40 px): shifted frames need no interpolation."""
    rng = np.random.default_rng(seed)
    freq = rng.uniform(2 * np.pi / 40, 2 * np.pi / 7, 40)
    angle = rng.uniform(0, 2 * np.pi, 40)
    phase = rng.uniform(0, 2 * np.pi, 40)
    g = sum(np.sin(f * (np.cos(a) * u + np.sin(a) * v) + p) for f, a, p in zip(freq, angle, phase))
    return np.clip(0.5 + g / 27.0, 0.0, 1.0)  # std of g is sqrt(20): ±3 std spans [0, 1]


def as_rgb(g: np.ndarray) -> np.ndarray:
    return np.repeat(np.clip(np.rint(g * 255), 0, 255).astype(np.uint8)[..., None], 3, -1)


def frames_translating(n: int, du: float, dv: float, h: int = 120, w: int = 160, seed: int = 0) -> list[np.ndarray]:
    """Frames ``k = 0..n-1`` (uint8 RGB) with ``frame_k(u, v) = base(u - k du, v - k dv)``."""
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    return [as_rgb(texture(u - k * du, v - k * dv, seed)) for k in range(n)]


def truth_at(pair, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth flow (bilinear) and validity (the nearest pixel's mask) at ``points`` ``(N, 2)``."""
    p = points.astype(np.float32).reshape(-1, 1, 2)
    flow = cv2.remap(pair.flow, p[..., 0], p[..., 1], cv2.INTER_LINEAR).reshape(-1, 2)
    iu = np.rint(points).astype(int)
    return flow, pair.mask[iu[:, 1], iu[:, 0]]


def epe_on_points(pair) -> tuple[float, int]:
    result = ShiTomasiLK()(pair.image1, pair.image2)
    truth, valid = truth_at(pair, result.points.numpy())
    err = np.linalg.norm(result.flow.numpy() - truth, axis=-1)[valid]
    return float(err.mean()), int(valid.sum())


def test_lk_epe_middlebury():
    epe, n = epe_on_points(middlebury_pair())
    # measured 0.88 px on 55 points with known flow (90 kept; corners crowd the masked depth edges)
    assert epe < 1.1, epe
    assert n >= 40, n


def test_lk_epe_simulator():
    epe, n = epe_on_points(simulator_pair())
    # measured 0.17 px on 217 valid & static points (225 kept)
    assert epe < 0.21, epe
    assert n >= 160, n


def test_direction_synthetic_translation_and_result_layout():
    du, dv = 2.3, -1.6
    a, b = frames_translating(2, du, dv)
    lk = ShiTomasiLK()
    result = lk(a, b)  # image1(u, v) = image2(u + du, v + dv)
    n = result.points.shape[0]
    assert n > 50
    assert result.points.shape == result.flow.shape == result.sigma.shape == (n, 2)
    torch.testing.assert_close(result.track_id, torch.arange(n))
    err = (result.flow - torch.tensor([du, dv])).norm(dim=1)
    assert err.median() < 0.03 and err.quantile(0.95) < 0.1, err  # measured median 0.008 px, 95 % 0.028, max 0.17 (108 points)
    assert (result.sigma >= lk.sigma0_px).all() and (result.sigma[:, 0] == result.sigma[:, 1]).all()
    p = result.points
    assert ((p >= lk.border_px) & (p <= torch.tensor([160, 120]) - 1 - lk.border_px)).all()


def test_fb_threshold_rejects_unrelated_images():
    a = frames_translating(1, 0, 0)[0]
    other = frames_translating(1, 0, 0, seed=7)[0]
    kept_same = ShiTomasiLK()(a, a).points.shape[0]
    kept_other = ShiTomasiLK()(a, other).points.shape[0]
    assert kept_other < 0.3 * kept_same, (kept_other, kept_same)


def test_track_sequence_keeps_ids():
    du, dv = 1.3, 0.7
    frames = frames_translating(4, du, dv)
    times = [10.0, 10.1, 10.2, 10.3]
    out = track_sequence(frames, ShiTomasiLK(), t_s=times)
    tracks = out.tracks
    assert isinstance(tracks, Tracks) and len(out.pairs) == 3
    torch.testing.assert_close(tracks.frame_times, torch.tensor(times, dtype=torch.float64))
    ids0, uv0 = tracks.at(10.0)
    torch.testing.assert_close(ids0, out.pairs[0].track_id)
    for k, t in enumerate(times[1:], start=1):
        ids, uv = tracks.at(t)
        common, i0, ik = np.intersect1d(ids0.numpy(), ids.numpy(), return_indices=True)
        assert len(common) > 0.9 * len(ids0)  # a pure translation loses (almost) nothing
        drift = uv[ik] - uv0[i0] - torch.tensor([k * du, k * dv], dtype=torch.float64)
        dist = drift.norm(dim=1)  # the same physical point: drift measured median <= 0.010 px, 90 % <= 0.018, max 0.24 (k = 3); 108 of 108 kept
        assert dist.median() < 0.03 and dist.quantile(0.9) < 0.1, (k, dist)
    # the pairs' ids follow the tracks: pair 1's points in frame 1 carry the ids of frame 1's rows
    ids1, uv1 = tracks.at(10.1)
    lookup = dict(zip(ids1.tolist(), uv1.tolist()))
    for i, p in zip(out.pairs[1].track_id.tolist(), out.pairs[1].points.tolist()):
        assert np.allclose(lookup[i], p, atol=1e-4)


def test_track_sequence_without_seeds_matches_within_radius():
    class NoSeeds(ShiTomasiLK):
        supports_seeds = False

    frames = frames_translating(3, 1.0, 0.0)  # integer shift: re-detected corners land on the tracked ends
    out = track_sequence(frames, NoSeeds())
    ids0 = set(out.tracks.at(0.0)[0].tolist())
    ids2 = set(out.tracks.at(2.0)[0].tolist())
    assert len(ids0 & ids2) > 0.5 * len(ids0)


def test_track_sequence_errors():
    with pytest.raises(ValueError, match="at least 2"):
        track_sequence(frames_translating(1, 0, 0), ShiTomasiLK())
    with pytest.raises(ValueError, match="one per frame"):
        track_sequence(frames_translating(2, 0, 0), ShiTomasiLK(), t_s=[0.0])
