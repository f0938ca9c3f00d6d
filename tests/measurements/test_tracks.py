"""The multi-view track update (flowins.measurements.tracks) against independent truths."""
from __future__ import annotations

import math

import numpy as np

import pytest
import torch

from flowins.filter.chain import BatchChain
from flowins.filter.ekf import Gate, chi2_quantile
from flowins.geometry import quaternion as quat
from flowins.measurements.flow import FlowCamera
from flowins.measurements.tracks import (
    TrackFrame,
    TrackUpdate,
    TrackViews,
    pose_index,
    project,
    schedule_tracks,
    track_measurements,
)
from flowins.filter.unobservable import unobservable_directions
from flowins.state import normalize_quaternions, pose_slices, state_dim


@pytest.fixture(autouse=True)
def _float64():
    """These tests build their tensors in float64 (the default dtype, restored after each)."""
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(old)


F64 = torch.float64
K = torch.tensor([[460.0, 0.0, 376.0], [0.0, 455.0, 240.0], [0.0, 0.0, 1.0]], dtype=F64)
# a camera looking along the body's x axis (x_c = -y_b, y_c = -z_b, z_c = x_b), 5 cm off the IMU
R_CI = torch.tensor([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], dtype=F64)
T_CI = torch.tensor([0.02, -0.01, 0.05], dtype=F64)
CAMERA = FlowCamera(K, R_CI, T_CI)


def _state(N: int, generator: torch.Generator) -> torch.Tensor:
    """A state with ``N`` clones: poses walking along x, small random rotations."""
    x = torch.zeros(state_dim(N))
    x[16:19] = 1.0  # T_a
    for age, (p, q) in enumerate(pose_slices(x.shape[-1])):
        x[p] = torch.tensor([-0.3 * age, 0.05 * age, 0.0]) + 0.02 * torch.randn(3, generator=generator)
        x[q] = quat.from_rotation_vector(0.05 * torch.randn(3, generator=generator))
    return x


def _points(count: int, generator: torch.Generator) -> torch.Tensor:
    """World points 3-8 m ahead (along x)."""
    ahead = 3.0 + 5.0 * torch.rand(count, 1, generator=generator)
    side = 2.0 * torch.rand(count, 2, generator=generator) - 1.0
    return torch.cat((ahead, 1.5 * side), -1)


def _observe(x: torch.Tensor, X: torch.Tensor, ages: torch.Tensor) -> torch.Tensor:
    """Pixels ``(M, V, 2)`` of points ``X`` ``(M, 3)`` in the poses of ``ages`` ``(M, V)``."""
    index = pose_index(x.shape[-1], x.device)[ages]
    pose = x[index]
    return project(X.unsqueeze(-2), pose[..., :3], pose[..., 3:], K, R_CI, CAMERA.centre_b).pixel


def _psd(D: int, generator: torch.Generator, scale: float = 1e-2) -> torch.Tensor:
    A = torch.randn(D, D, generator=generator)
    return scale * (A @ A.T / D + 0.1 * torch.eye(D))


def test_projection_jacobians_match_autograd():
    g = torch.Generator().manual_seed(1)
    X = _points(4, g)
    p = 0.1 * torch.randn(4, 3, generator=g)
    q = quat.from_rotation_vector(0.1 * torch.randn(4, 3, generator=g)) * 1.3  # not unit: the model normalises

    def pixel(X, p, q):
        return project(X, p, q, K, R_CI, CAMERA.centre_b).pixel

    out = project(X, p, q, K, R_CI, CAMERA.centre_b)
    for i in range(4):
        dX, dp, dq = torch.autograd.functional.jacobian(pixel, (X[i], p[i], q[i]))
        torch.testing.assert_close(out.H_point[i], dX, atol=1e-9, rtol=1e-9)
        torch.testing.assert_close(out.H_pose[i], torch.cat((dp, dq), -1), atol=1e-9, rtol=1e-9)


def test_exact_tracks_triangulate_exactly_and_give_zero_residual():
    g = torch.Generator().manual_seed(2)
    N = 4
    x = _state(N, g)
    X = _points(6, g)
    ages = torch.arange(N + 1).expand(6, N + 1)
    uv = _observe(x, X, ages)
    m = track_measurements(x.unsqueeze(0), uv.unsqueeze(0), ages.unsqueeze(0), torch.ones(1, 6, N + 1, dtype=torch.bool),
                           CAMERA, TrackUpdate(window=N))
    assert bool(m.valid.all())
    torch.testing.assert_close(m.point[0], X, atol=1e-9, rtol=0)
    assert float(m.residual.abs().max()) < 1e-8
    assert m.dof.tolist() == [[2 * (N + 1) - 3] * 6]


def _naive_marginalised(x, P, uv, ages, sigma):
    """The update with the feature in the state (no prior on it: zero information) and then
    marginalised, in information form, with Jacobians by autograd at the triangulated point."""
    D = x.shape[-1]
    m = track_measurements(x.unsqueeze(0), uv[None, None], ages[None, None], torch.ones(1, 1, ages.shape[0], dtype=torch.bool),
                           CAMERA, TrackUpdate(window=(D - 19) // 7, refine_iterations=5))
    X = m.point[0, 0]
    index = pose_index(D, x.device)[ages]

    def h(xx, XX):
        pose = xx[index]
        return project(XX.expand(ages.shape[0], 3), pose[..., :3], pose[..., 3:], K, R_CI, CAMERA.centre_b).pixel.reshape(-1)

    Hx, Hf = torch.autograd.functional.jacobian(h, (x, X))
    r = uv.reshape(-1) - h(x, X)
    Hfull = torch.cat((Hx, Hf), -1)
    info = torch.zeros(D + 3, D + 3)
    info[:D, :D] = torch.linalg.inv(P)
    info = info + Hfull.T @ Hfull / sigma**2
    eta = Hfull.T @ r / sigma**2
    # marginalise the feature: Schur complement of its block
    Ixx, Ixf, Iff = info[:D, :D], info[:D, D:], info[D:, D:]
    info_x = Ixx - Ixf @ torch.linalg.solve(Iff, Ixf.T)
    eta_x = eta[:D] - Ixf @ torch.linalg.solve(Iff, eta[D:])
    P_post = torch.linalg.inv(info_x)
    return x + P_post @ eta_x, P_post


@pytest.mark.parametrize("views", [2, 3, 5])
def test_null_space_update_equals_feature_marginalised(views):
    g = torch.Generator().manual_seed(3 + views)
    N = 4
    x = _state(N, g)
    D = x.shape[-1]
    P = _psd(D, g)
    X = _points(1, g)
    ages = torch.arange(views).unsqueeze(0)
    sigma = 0.7
    uv = _observe(x, X, ages)[0] + sigma * torch.randn(views, 2, generator=g)
    # the filter's event: one row, one track, views padded to N + 1
    update = TrackUpdate(window=N, sigma_px=sigma, gate=Gate(mode="off"), refine_iterations=5,
                         heading_transport=False)
    V = N + 1
    views_in = TrackViews(torch.cat((uv, torch.zeros(V - views, 2))).unsqueeze(0),
                          torch.cat((ages[0], torch.zeros(V - views, dtype=torch.long))).unsqueeze(0),
                          (torch.arange(V) < views).unsqueeze(0), 1)
    chain = BatchChain(1)
    chain.add_nodes([[0.0]], torch.eye(D).expand(1, 1, D, D), x.reshape(1, 1, D), P.reshape(1, 1, D, D))
    from flowins.measurements.tracks import _track_update

    _track_update(chain, [0], [TrackFrame(0.0, views_in, CAMERA, update)])
    mean, cov = chain.mean[0], chain.cov[0]
    ref_mean, ref_cov = _naive_marginalised(x, P, uv, ages[0], sigma)
    torch.testing.assert_close(cov, ref_cov, atol=1e-9, rtol=0)
    torch.testing.assert_close(mean, normalize_quaternions(ref_mean), atol=1e-9, rtol=0)
    entry = chain.logs[0][-1]
    assert entry["kind"] == "tracks" and entry["valid"] == 1 and entry["accepted"] == 1.0


def test_projected_nis_and_likelihood_are_those_of_an_orthonormal_null_space_basis():
    """NIS and log det S of the 2m-3 rows Nᵀ r (N from a complete QR of H_f), computed naively."""
    g = torch.Generator().manual_seed(11)
    N, views = 3, 3
    x = _state(N, g)
    D = x.shape[-1]
    P = _psd(D, g)
    X = _points(1, g)
    ages = torch.arange(views)
    sigma = 0.5
    uv = _observe(x, X, ages.unsqueeze(0))[0] + sigma * torch.randn(views, 2, generator=g)
    mask = torch.zeros(1, 1, N + 1, dtype=torch.bool)
    mask[..., :views] = True
    pad = N + 1 - views
    m = track_measurements(x.unsqueeze(0), torch.cat((uv, torch.zeros(pad, 2)))[None, None],
                           torch.cat((ages, torch.zeros(pad, dtype=torch.long)))[None, None], mask, CAMERA,
                           TrackUpdate(window=N, sigma_px=sigma))
    from flowins.filter.ekf import block_nll

    nis, nll = block_nll(P, m.residual[0], m.H[0], None)  # whitened rows; the whitening's ½ log det apart
    nll = nll + m.noise_logdet[0]
    # naive: the unprojected rows, an orthonormal basis of the left null space of H_f
    index = pose_index(D, x.device)[ages]
    pose = x[index]
    proj = project(m.point[0, 0].expand(views, 3), pose[..., :3], pose[..., 3:], K, R_CI, CAMERA.centre_b)
    Hf = proj.H_point.reshape(-1, 3)
    Hx = torch.zeros(2 * views, D)
    for j in range(views):
        Hx[2 * j:2 * j + 2, index[j]] = proj.H_pose[j]
    r = uv.reshape(-1) - proj.pixel.reshape(-1)
    Q, _ = torch.linalg.qr(Hf, mode="complete")
    Nb = Q[:, 3:]
    S = Nb.T @ Hx @ P @ Hx.T @ Nb + sigma**2 * torch.eye(2 * views - 3)
    v = Nb.T @ r
    ref_nis = v @ torch.linalg.solve(S, v)
    torch.testing.assert_close(nis[0], ref_nis, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(nll[0], 0.5 * (ref_nis + torch.logdet(S)), atol=1e-9, rtol=1e-9)
    assert int(m.dof[0, 0]) == 2 * views - 3
    # the filter's own update adds the same likelihood to a chain that keeps one
    from flowins.measurements.tracks import _track_update

    chain = BatchChain(1, likelihood=True)
    chain.add_nodes([[0.0]], torch.eye(D).expand(1, 1, D, D), x.reshape(1, 1, D), P.reshape(1, 1, D, D))
    views_in = TrackViews(torch.cat((uv, torch.zeros(pad, 2))).unsqueeze(0),
                          torch.cat((ages, torch.zeros(pad, dtype=torch.long))).unsqueeze(0), mask[0], 1)
    update = TrackUpdate(window=N, sigma_px=sigma, gate=Gate(mode="off"), heading_transport=False)
    _track_update(chain, [0], [TrackFrame(0.0, views_in, CAMERA, update)])
    (track,) = chain.finish()
    torch.testing.assert_close(track.nll, 0.5 * (ref_nis + torch.logdet(S)), atol=1e-9, rtol=1e-9)


@pytest.mark.parametrize("heading_transport", [False, True])
def test_padding_and_batching_leave_the_update_unchanged(heading_transport):
    """A track of 3 views updates the same alone (V = 3), padded to V = 6 among other tracks'
    rows' padding, and as one row of a batch of two runs."""
    g = torch.Generator().manual_seed(5)
    N = 5
    x = _state(N, g)
    D = x.shape[-1]
    P = _psd(D, g)
    X = _points(4, g)
    ages = torch.tensor([[0, 1, 2], [1, 2, 3], [0, 1, 2], [2, 3, 4]])
    uv = _observe(x, X, ages) + 0.3 * torch.randn(4, 3, 2, generator=g)
    update = TrackUpdate(window=N, sigma_px=0.5, heading_transport=heading_transport)

    def run(rows_x, rows_views):
        chain = BatchChain(len(rows_x))
        B = len(rows_x)
        chain.add_nodes([[0.0]] * B, torch.eye(D).expand(B, 1, D, D), torch.stack(rows_x).unsqueeze(1),
                        P.expand(B, 1, D, D).clone())
        from flowins.measurements.tracks import _track_update

        _track_update(chain, list(range(B)), [TrackFrame(0.0, v, CAMERA, update) for v in rows_views])
        return chain.mean, chain.cov

    def views(tracks, V):
        pad = V - 3
        return TrackViews(torch.cat((uv[tracks], torch.zeros(len(tracks), pad, 2)), 1),
                          torch.cat((ages[tracks], torch.zeros(len(tracks), pad, dtype=torch.long)), 1),
                          torch.arange(V).expand(len(tracks), V) < 3, len(tracks))

    alone = run([x], [views([0, 1, 2, 3], 3)])
    padded = run([x], [views([0, 1, 2, 3], N + 1)])
    torch.testing.assert_close(padded[0], alone[0], atol=1e-12, rtol=0)
    torch.testing.assert_close(padded[1], alone[1], atol=1e-12, rtol=0)
    other = _state(N, g)
    batched = run([other, x], [views([1, 2], N + 1), views([0, 1, 2, 3], N + 1)])
    torch.testing.assert_close(batched[0][1], alone[0][0], atol=1e-12, rtol=0)
    torch.testing.assert_close(batched[1][1], alone[1][0], atol=1e-12, rtol=0)


def test_gate_tests_each_track_on_its_own_degrees_of_freedom():
    gate = Gate(probability=0.99)
    dof = torch.tensor([1, 3, 7])
    threshold = gate.threshold_for(dof)
    assert threshold.tolist() == pytest.approx([chi2_quantile(0.99, d) for d in (1, 3, 7)])
    nis = threshold - 1e-6
    assert gate.weights(nis, dof).tolist() == [1.0, 1.0, 1.0]
    assert gate.weights(nis + 2e-6, dof).tolist() == [0.0, 0.0, 0.0]
    # a scale (the learnable factor of train.py's tracks_gate_scale) multiplies every dof's threshold
    scaled = Gate(probability=0.99, scale=torch.tensor(1.5, dtype=torch.float64)).threshold_for(dof)
    assert scaled.tolist() == pytest.approx([1.5 * chi2_quantile(0.99, d) for d in (1, 3, 7)])


def test_degenerate_tracks_are_left_out_without_nan():
    g = torch.Generator().manual_seed(7)
    N = 2
    x = _state(N, g)
    # every pose at the same place: no baseline, the point is not fixed
    for p, q in pose_slices(x.shape[-1])[1:]:
        x[p] = x[pose_slices(x.shape[-1])[0][0]]
        x[q] = x[pose_slices(x.shape[-1])[0][1]]
    X = _points(2, g)
    ages = torch.arange(N + 1).expand(2, N + 1)
    uv = _observe(x, X, ages)
    x_batch = x.unsqueeze(0).requires_grad_(True)
    m = track_measurements(x_batch, uv.unsqueeze(0), ages.unsqueeze(0), torch.ones(1, 2, N + 1, dtype=torch.bool),
                           CAMERA, TrackUpdate(window=N))
    assert not bool(m.valid.any())
    assert int(m.n_degenerate[0] + m.n_behind[0] + m.n_low_parallax[0]) == 2  # each counted once, for one reason
    assert bool(torch.isfinite(m.H).all() and torch.isfinite(m.residual).all())
    (m.residual.sum() + m.H.sum()).backward()
    assert bool(torch.isfinite(x_batch.grad).all())


def test_schedule_uses_each_track_once_over_its_views():
    """Hand-made tracks over 6 frames, window 2 (at most 3 views)."""
    rows = [  # (frame, id)
        (0, 1), (0, 2), (0, 3),
        (1, 1), (1, 2),
        (2, 1), (2, 2), (2, 4),
        (3, 1), (3, 4),
        (4, 4), (4, 5),
        (5, 5),
    ]
    t = torch.tensor([float(f) for f, _ in rows])
    ids = torch.tensor([i for _, i in rows])
    uv = torch.tensor([[10.0 * f, float(i)] for f, i in rows])
    out = schedule_tracks(t, ids, uv, torch.arange(6.0), window=2)
    used = {k: sorted((int(v.uv_px[m, 0, 1]), v.ages[m][v.mask[m]].tolist()) for m in range(v.ages.shape[0]))
            for k, v in enumerate(out)}
    # id 3: one view, never used; ids 1, 2: three views at frame 2 (ages 0, 1, 2), then id 1 restarts at
    # frame 3 and ends at frame 4 with one view (unused); id 4: frames 2-4 -> used at 4; id 5: 4-5, the end
    assert used == {0: [], 1: [], 2: [(1, [0, 1, 2]), (2, [0, 1, 2])], 3: [], 4: [(4, [0, 1, 2])], 5: [(5, [0, 1])]}
    assert float(out[2].uv_px[0, 2, 0]) == 0.0 and float(out[2].uv_px[0, 0, 0]) == 20.0  # newest view first


def test_schedule_caps_tracks_per_frame_longest_first():
    rows = [(0, 1), (1, 1), (2, 1), (1, 2), (2, 2), (3, 9)]
    t = torch.tensor([float(f) for f, _ in rows])
    order = torch.argsort(t, stable=True)
    ids = torch.tensor([i for _, i in rows])[order]
    uv = torch.zeros(len(rows), 2)
    out = schedule_tracks(t[order], ids, uv, torch.arange(4.0), window=4, max_tracks=1)
    assert out[3].candidates == 2 and out[3].ages.shape[0] == 1
    assert out[3].mask[0].sum() == 3  # id 1 (3 views) kept over id 2 (2 views)


def test_bad_settings_name_their_key():
    """Built directly the error names the field (``tests/test_config.py``: from a config, the key)."""
    with pytest.raises(ValueError, match=r"TrackUpdate\.window=-1: expected an integer >= 0"):
        TrackUpdate(window=-1)
    with pytest.raises(ValueError, match=r"TrackUpdate\.sigma_px=0\.0: expected a number > 0"):
        TrackUpdate(window=3, sigma_px=0.0)
    with pytest.raises(ValueError, match=r"TrackUpdate\.sigma_px=.*: expected numbers > 0"):
        TrackUpdate(window=3, sigma_px=torch.tensor([0.3, -1.0]))  # a learned σ: its every element
    assert math.isfinite(TrackUpdate(window=3).min_parallax_rad)


def naive_schedule(t_s, track_id, uv_px, frame_times_s, *, window: int,
                    max_tracks: int | None = None) -> list:
    """The frame-by-frame loop the schedule is (the reference: a dict of open segments)."""
    if window < 1:
        raise ValueError(window)
    V = window + 1
    frames = frame_times_s.tolist()
    rows_by_time: dict[float, tuple[np.ndarray, np.ndarray]] = {}
    times, counts = torch.unique_consecutive(t_s, return_counts=True)
    start = 0
    ids_all, uv_all = track_id.numpy(), uv_px.numpy()
    for t, n in zip(times.tolist(), counts.tolist()):
        rows_by_time[t] = (ids_all[start:start + n], uv_all[start:start + n])
        start += n
    active: dict[int, list[tuple[int, np.ndarray]]] = {}
    out = []
    empty_ids, empty_uv = np.zeros(0, np.int64), np.zeros((0, 2))
    for k, t in enumerate(frames):
        ids, uvs = rows_by_time.get(t, (empty_ids, empty_uv))
        seen = set(ids.tolist())
        complete = [active.pop(i) for i in [i for i in active if i not in seen]]
        for i, uv in zip(ids.tolist(), uvs):
            segment = active.setdefault(i, [])
            segment.append((k, uv))
            if len(segment) == V:
                complete.append(active.pop(i))
        if k == len(frames) - 1:
            complete += list(active.values())
        complete = [s for s in complete if len(s) >= 2]
        candidates = len(complete)
        complete.sort(key=len, reverse=True)  # stable: the longest first, then in order
        if max_tracks is not None:
            complete = complete[:max_tracks]
        uv = np.zeros((len(complete), V, 2))
        ages = np.zeros((len(complete), V), np.int64)
        mask = np.zeros((len(complete), V), bool)
        for m, segment in enumerate(complete):
            for j, (frame, pixel) in enumerate(reversed(segment)):
                uv[m, j], ages[m, j], mask[m, j] = pixel, k - frame, True
        out.append(TrackViews(torch.from_numpy(uv), torch.from_numpy(ages), torch.from_numpy(mask), candidates))
    return out



@pytest.mark.parametrize("seed", [0, 1, 2])
def test_schedule_equals_the_frame_by_frame_loop(seed):
    """Random tracks (ids that end, reappear and run past the window; rows at times between the
    frames; frames without rows; ties in length beyond ``max_tracks``): the same views, in the
    same order, as the frame-by-frame loop."""
    gen = np.random.default_rng(seed)
    frames = np.arange(40, dtype=np.float64) * 0.1
    rows = []
    for k, t in enumerate(frames):
        if k in (7, 8):
            continue  # no rows at all
        seen = gen.choice(30, size=int(gen.integers(5, 25)), replace=False)
        rows += [(t, int(i)) for i in seen]
        if k % 5 == 0:
            rows.append((t + 0.05, 99))  # between frames: not used
    t = torch.tensor([r[0] for r in rows], dtype=torch.float64)
    ids = torch.tensor([r[1] for r in rows])
    uv = torch.from_numpy(gen.normal(size=(len(rows), 2)))
    for window, cap in ((3, None), (4, 5), (1, 2)):
        got = schedule_tracks(t, ids, uv, torch.from_numpy(frames), window=window, max_tracks=cap)
        want = naive_schedule(t, ids, uv, torch.from_numpy(frames), window=window, max_tracks=cap)
        assert len(got) == len(want) == len(frames)
        for g, w in zip(got, want):
            assert g.candidates == w.candidates
            for name in ("uv_px", "ages", "mask"):
                assert torch.equal(getattr(g, name), getattr(w, name)), name


def test_a_track_is_blind_to_a_shift_and_a_turn_of_the_whole_track():
    """The projected Jacobian at the estimate times the unobservable directions there is zero:
    a camera cannot tell where the track is or which way it faces."""
    g = torch.Generator().manual_seed(21)
    N = 4
    x = _state(N, g)
    X = _points(6, g)
    ages = torch.stack([torch.arange(5)] * 6)
    uv = _observe(x, X, ages) + 0.3 * torch.randn(6, 5, 2, generator=g)
    m = track_measurements(x.unsqueeze(0), uv.unsqueeze(0), ages.unsqueeze(0), torch.ones(1, 6, 5, dtype=torch.bool),
                           CAMERA, TrackUpdate(window=N))
    assert bool(m.valid.all())
    blind = m.H[0] @ unobservable_directions(x)
    assert float(blind.abs().max()) < 1e-9 * float(m.H.abs().max())


@pytest.mark.parametrize("heading_transport", [True, False])
def test_the_track_update_adds_no_information_along_the_unobservable_directions(heading_transport):
    """``Nᵀ P⁻¹ N`` at the estimate is the same after a track update as before it with the heading
    transport; the plain update changes the estimate and with it the directions, and ends up
    with information there that no camera gave."""
    g = torch.Generator().manual_seed(8)
    N = 4
    x = _state(N, g)
    D = x.shape[-1]
    P = _psd(D, g, scale=1e-3)
    X = _points(8, g)
    ages = torch.stack([torch.arange(5)] * 8)
    uv = _observe(x, X, ages) + 2.0 * torch.randn(8, 5, 2, generator=g)  # the update moves the estimate
    update = TrackUpdate(window=N, sigma_px=0.5, gate=Gate(mode="off"), heading_transport=heading_transport)
    chain = BatchChain(1)
    chain.add_nodes([[0.0]], torch.eye(D).expand(1, 1, D, D), x.reshape(1, 1, D), P.reshape(1, 1, D, D))
    from flowins.measurements.tracks import _track_update

    views = TrackViews(uv, ages, torch.ones(8, 5, dtype=torch.bool), 8)
    _track_update(chain, [0], [TrackFrame(0.0, views, CAMERA, update)])
    mean, cov = chain.mean[0], chain.cov[0]
    assert float(torch.linalg.vector_norm(mean[:3] - x[:3])) > 1e-3

    def information(c, at):
        Nd = unobservable_directions(at)
        return Nd.T @ torch.linalg.solve(c, Nd)

    change = (information(cov, mean) - information(P, x)).abs().max() / information(P, x).abs().max()
    if heading_transport:
        assert float(change) < 1e-8
    else:
        assert float(change) > 1e-4
