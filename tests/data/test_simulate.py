"""The simulator's sensor models against the closed-form truth."""
import math
from dataclasses import replace

import pytest
import torch

from flowins.data.simulate.gnss import GnssErrors, simulate_fixes
from flowins.data.simulate.scenario import SimulationConfig, simulate_imu
from flowins.data.synthetic import ImuErrors, Walk, WalkConfig
from flowins.filter.propagation import propagate_mean
from flowins.ins.mechanization import STANDARD_GRAVITY_MPS2
from flowins.geometry import quaternion as quat
from flowins.state import make_state, split

F64 = torch.float64


def test_noise_free_simulated_imu_integrates_to_a_centimetre_after_60_s():
    """The full walk (bounce and hand shake included), jittered 100 Hz samples,
    integrated by the flowins mechanization from the true initial state."""
    config = SimulationConfig(duration_s=65.0, imu_errors=ImuErrors(0, 0, 0, 0, 0, 0, 0))
    walk = Walk(WalkConfig(duration_s=65.0))
    t, acc, gyro, truth = simulate_imu(walk, config, torch.Generator().manual_seed(0))
    assert torch.equal(truth["T_a"], torch.ones(3, dtype=F64)) and float(truth["b_a"].abs().max()) == 0.0
    x0 = make_state(p=walk.position(t[0]), v=walk.velocity(t[:1])[0], q=walk.quaternion(t[0]))
    xs = propagate_mean(x0, acc[1:], gyro[1:], torch.diff(t), STANDARD_GRAVITY_MPS2, "midpoint")
    err = (split(xs).p - walk.position(t[1:])).norm(dim=-1)
    assert float(t[-1]) > 64.0
    assert float(err.max()) < 0.01, f"max position error {float(err.max()):.3g} m"
    # and the walk really moves and shakes: the test is not trivially easy
    assert float((walk.position(t[-1:]) - walk.position(t[:1])).norm()) > 40.0
    assert float(gyro[1000:, 0].abs().max()) > 0.1  # roll rate of the hand shake, rad/s


def test_simulated_imu_errors_follow_the_configured_model():
    errors = ImuErrors(acc_noise=0.0, gyro_noise=0.0, acc_bias_walk=0.0, gyro_bias_walk=0.0)
    config = SimulationConfig(duration_s=20.0, imu_errors=errors)
    walk = Walk(WalkConfig(duration_s=20.0))
    clean = simulate_imu(walk, replace(config, imu_errors=ImuErrors(0, 0, 0, 0, 0, 0, 0)), torch.Generator().manual_seed(1))
    t, acc, gyro, truth = simulate_imu(walk, config, torch.Generator().manual_seed(1))
    assert torch.equal(t, clean[0])
    # acc = f / T_a + b_a with a constant turn-on bias and scale, gyro = w + b_w
    torch.testing.assert_close(acc, clean[1] / truth["T_a"] + truth["b_a"], rtol=0, atol=1e-12)
    torch.testing.assert_close(gyro, clean[2] + truth["b_w"], rtol=0, atol=1e-12)
    assert 0.001 < float((truth["T_a"] - 1).abs().max()) < 0.06  # scale errors of ±1-2 % (1.5 % std)
    steps = torch.diff(t)
    assert float(steps.min()) < 0.0095 and float(steps.max()) > 0.0105  # jittered, non-equidistant


def test_gnss_errors_are_consistent_with_the_reported_accuracy():
    G = 20000
    gen = torch.Generator().manual_seed(0)
    truth = torch.zeros(G, 3, dtype=F64)
    canyon = 0.5 + 0.5 * torch.sin(torch.arange(G, dtype=F64) / 300.0)
    errors = GnssErrors(multipath_probability=0.05)
    measured, h_acc, v_acc, multipath = simulate_fixes(truth, canyon, errors, gen)
    assert float(h_acc.min()) >= errors.min_acc_m and float(h_acc.max()) <= errors.max_acc_m
    assert float(h_acc.max() - h_acc.min()) > 10.0  # varies with the canyon
    torch.testing.assert_close(v_acc, errors.vertical_ratio * h_acc)
    clean = ~multipath
    z = measured[clean] / torch.stack((h_acc, h_acc, v_acc), -1)[clean]
    assert z.std(dim=0).sub(1.0).abs().max() < 0.1  # errors as large as the radius says
    # correlated between consecutive fixes (Gauss-Markov, 10 s at 1 Hz: ρ = e^-0.1)
    zc = measured[:, 0] / h_acc
    pair = clean[:-1] & clean[1:]
    rho = float(torch.corrcoef(torch.stack((zc[:-1][pair], zc[1:][pair])))[0, 1])
    assert abs(rho - math.exp(-0.1)) < 0.05
    rate = float(multipath.double().mean())
    expected = float((errors.multipath_probability * (1 + 2 * canyon) / 3).mean())
    assert abs(rate - expected) < 0.2 * expected
    outlier_z = (measured[multipath, :2] / h_acc[multipath].unsqueeze(-1)).norm(dim=-1)
    assert float(outlier_z.median()) > 2.0  # displaced by 20-60 m, more than the radius says


# --------------------------------------------------------------------------- the written sequence


@pytest.fixture(scope="module")
def small_simulation(tmp_path_factory):
    from flowins.data.simulate.scenario import CameraConfig, simulate

    from flowins.data.simulate.tracks import TrackConfig

    config = SimulationConfig(duration_s=10.0, seed=3, camera=CameraConfig(rate_hz=5.0, width=160, height=120),
                              tracks=TrackConfig(count=120, noise_px=0.0))
    out = tmp_path_factory.mktemp("sim")
    return config, out, simulate(out, config, progress=False)


def test_simulated_sequence_has_every_source(small_simulation):
    config, out, seq = small_simulation
    assert seq.sources == ("imu", "frames", "tracks", "gnss", "groundtruth")
    assert len(seq.frames) == 50 and seq.camera.size == (120, 160)
    assert tuple(seq.frames.read(0).shape) == (120, 160, 3)
    assert seq.metadata["simulation"]["key"] == config.key()
    assert len(list((out / "flow").glob("*.npz"))) == 49


def test_projecting_a_world_point_through_the_written_files_gives_the_rendered_pixel(small_simulation):
    """Renderer at the true pose -> a pixel's world point; the *written* ground-truth
    pose and calibration project it back onto that pixel."""
    from flowins.data.simulate.render import render
    from flowins.data.simulate.scenario import CameraTrajectory
    from flowins.data.simulate.world import build_city
    from flowins.data.synthetic import Walk, WalkConfig
    from flowins.geometry.camera import project

    config, out, seq = small_simulation
    walk = Walk(WalkConfig(duration_s=config.duration_s))
    city = build_city(walk, seed=config.seed)
    trajectory = CameraTrajectory(walk, config.camera.imu_to_camera())
    i = 40  # t = 8 s, walking
    t = float(seq.frames.t_s[i])
    R_wc, p_wc = trajectory.pose(torch.tensor([t], dtype=F64))
    frame = render(city, seq.camera, R_wc[0], p_wc[0], t)
    static = (frame.object_id == 0).nonzero()
    pixels = static[torch.linspace(0, static.shape[0] - 1, 25).long()]  # (row, col)
    X_w = frame.point[pixels[:, 0], pixels[:, 1]]  # (25, 3) world points
    # the written ground truth at the frame time (60 Hz poses; frame times are on that grid)
    gt = seq.groundtruth
    k = int(torch.argmin((gt.t_s - t).abs()))
    assert abs(float(gt.t_s[k]) - t) < 1e-9
    R_wb = quat.to_matrix(gt.quat_wxyz[k])
    X_b = (R_wb.T @ (X_w - gt.pos_m[k]).T).T
    X_c = seq.imu_to_camera.apply(X_b)
    cam = seq.camera
    uv = project(X_c, cam.fx, cam.fy, cam.cx, cam.cy)
    expected = torch.stack((pixels[:, 1], pixels[:, 0]), -1).to(F64)
    assert float((uv - expected).abs().max()) < 1e-3
    torch.testing.assert_close(X_c[:, 2].float(), frame.depth[pixels[:, 0], pixels[:, 1]], rtol=1e-5, atol=1e-4)


def _camera_from_world(seq, t: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(R_cw, t_cw)`` of the written ground truth and calibration at frame time ``t``: ``x_c = R_cw x_w + t_cw``."""
    gt = seq.groundtruth
    k = int(torch.argmin((gt.t_s - t).abs()))
    assert abs(float(gt.t_s[k]) - t) < 1e-9
    R_bw = quat.to_matrix(gt.quat_wxyz[k]).T
    R_ci, t_ci = seq.imu_to_camera.rotation_matrix, seq.imu_to_camera.translation_m
    return R_ci @ R_bw, t_ci - R_ci @ R_bw @ gt.pos_m[k]


def test_written_tracks_are_static_points_seen_from_the_written_poses(small_simulation):
    """Each track of ``tracks.csv`` (no pixel noise here) is one world point: triangulated by
    DLT from all its views with the written poses and calibration, it reprojects onto every one
    of them to 1e-3 px."""
    _, _, seq = small_simulation
    tr, cam = seq.tracks, seq.camera
    K = torch.tensor([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]], dtype=F64)
    poses = {float(t): _camera_from_world(seq, float(t)) for t in seq.frames.t_s}
    ids, counts = tr.track_id.unique(return_counts=True)
    long = ids[counts >= 3]
    assert long.numel() > 100
    worst = 0.0
    for i in long[torch.linspace(0, long.numel() - 1, 60).long()].tolist():
        rows = (tr.track_id == i).nonzero().squeeze(-1)
        P = [K @ torch.cat((R, t.unsqueeze(-1)), -1) for R, t in (poses[float(tr.t_s[r])] for r in rows)]
        A = torch.cat([torch.stack((uv[0] * Pj[2] - Pj[0], uv[1] * Pj[2] - Pj[1]))
                       for uv, Pj in zip(tr.uv_px[rows], P)])
        X = torch.linalg.svd(A).Vh[-1]
        for uv, Pj in zip(tr.uv_px[rows], P):
            x = Pj @ X
            worst = max(worst, float((x[:2] / x[2] - uv).abs().max()))
    assert worst < 1e-3


def test_a_written_track_ends_where_its_point_is_hidden_or_out_of_view(small_simulation):
    """Rendered again from the walk and seen through the written poses, each observation shows its
    track's point, and every track that ends before the last frame ends
    where the next frame does not show its point: beyond the range, outside the image, or hidden,
    the depth rendered around its pixel not its own (behind a nearer surface or at its edge)."""
    from flowins.data.simulate.render import render
    from flowins.data.simulate.scenario import CameraTrajectory
    from flowins.data.simulate.world import build_city
    from flowins.data.synthetic import Walk, WalkConfig

    config, _, seq = small_simulation
    walk = Walk(WalkConfig(duration_s=config.duration_s))
    city = build_city(walk, seed=config.seed)
    trajectory = CameraTrajectory(walk, config.camera.imu_to_camera())
    tr, cam, t_frames = seq.tracks, seq.camera, seq.frames.t_s
    R_all, p_all = trajectory.pose(t_frames)
    frame_of = torch.searchsorted(t_frames, tr.t_s - 1e-9)
    renders: dict = {}

    def shot(f: int):
        if f not in renders:
            renders[f] = render(city, cam, R_all[f], p_all[f], float(t_frames[f]))
        return renders[f]

    def point_of(row: int) -> torch.Tensor:
        """The track's world point: the scene at its first (whole) pixel."""
        first = int((tr.track_id == tr.track_id[row]).nonzero()[0])
        u0, v0 = tr.uv_px[first].long().tolist()
        return shot(int(frame_of[first])).point[v0, u0]

    def seen(X: torch.Tensor, f: int, slack_px: float) -> tuple[bool, bool]:
        """Whether ``X`` is inside frame ``f``'s image and range, and shown there: the inverse depth
        interpolated between the four pixels around it (exact on a plane) is its own within 1 %.
        ``slack_px``: how far past the 1 px border still counts as inside (the written poses hold
        the pixels to 1e-3 px)."""
        R, t = _camera_from_world(seq, float(t_frames[f]))
        X_c = R @ X + t
        u, v = cam.fx * X_c[0] / X_c[2] + cam.cx, cam.fy * X_c[1] / X_c[2] + cam.cy
        lo = 1 - slack_px
        inside = bool(0 < X_c[2] <= config.tracks.max_depth_m) and lo <= u <= cam.width - 1 - lo and lo <= v <= cam.height - 1 - lo
        if not inside:
            return False, False
        i, j = min(int(v), cam.height - 2), min(int(u), cam.width - 2)
        a, b = float(v) - i, float(u) - j
        inv = 1.0 / shot(f).depth[i:i + 2, j:j + 2].double()
        inv = (1 - a) * ((1 - b) * inv[0, 0] + b * inv[0, 1]) + a * ((1 - b) * inv[1, 0] + b * inv[1, 1])
        return True, bool((inv - 1.0 / X_c[2]).abs() <= 0.01 / X_c[2])

    ended_hidden = ended_outside = 0
    for f in range(25, 48):  # walking
        later = set(tr.track_id[frame_of == f + 1].tolist())
        for row in (frame_of == f).nonzero().squeeze(-1).tolist():
            X = point_of(row)
            assert seen(X, f, 1e-3) == (True, True)
            if int(tr.track_id[row]) in later:
                continue
            inside, shown = seen(X, f + 1, -1e-3)
            if not inside:
                ended_outside += 1
            else:  # hidden: behind a nearer surface, or at its edge
                assert not shown
                ended_hidden += 1
    assert ended_outside + ended_hidden > 10


def test_fresh_track_pixels_take_one_static_pixel_per_free_cell():
    from flowins.data.simulate.tracks import fresh_pixels

    static = torch.zeros(40, 64, dtype=torch.bool)
    static[:, 16:] = True  # the left quarter is not static (sky, a mover)
    taken = torch.tensor([[20.0, 3.0], [45.5, 30.2]])  # cells (2, 0) and (5, 3) hold tracked points
    uv = fresh_pixels(static, taken, need=1000, cell_px=8, generator=torch.Generator().manual_seed(0))
    cells = (uv[:, 1] // 8) * 8 + uv[:, 0] // 8
    assert bool(static[uv[:, 1], uv[:, 0]].all())
    assert cells.unique().numel() == cells.numel() == 6 * 5 - 2  # every free static cell once
    assert not bool(((cells == 2) | (cells == 3 * 8 + 5)).any())
    few = fresh_pixels(static, taken, need=5, cell_px=8, generator=torch.Generator().manual_seed(1))
    assert few.shape == (5, 2)


def test_written_flow_warps_the_written_frames(small_simulation):
    import cv2
    import numpy as np

    config, out, seq = small_simulation
    i = 30
    truth = np.load(out / "flow" / f"{i:06d}.npz")
    img1 = seq.frames.read_gray(i).numpy()
    img2 = seq.frames.read_gray(i + 1).numpy()
    H, W = img1.shape
    grid_u, grid_v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    flow = np.nan_to_num(truth["flow"])
    warped = cv2.remap(img2, grid_u + flow[..., 0], grid_v + flow[..., 1], cv2.INTER_LINEAR)
    mask = truth["valid"] & truth["static"]
    assert mask.mean() > 0.5
    err_flow = np.abs(warped - img1)[mask].mean()
    err_zero = np.abs(img2 - img1)[mask].mean()
    assert err_flow < err_zero / 3, (err_flow, err_zero)
    assert float(truth["t1"] - truth["t0"]) == pytest.approx(1.0 / config.camera.rate_hz)


def test_a_second_simulation_reads_the_cache(small_simulation):
    from flowins.data.simulate.scenario import simulate

    config, out, seq = small_simulation
    png = out / "frames" / "000000.png"
    before = png.stat().st_mtime_ns
    again = simulate(out, config, progress=False)
    assert png.stat().st_mtime_ns == before  # nothing re-rendered
    assert torch.equal(again.imu.acc_mps2, seq.imu.acc_mps2)
    # a different configuration in the same folder is refused, not silently mixed
    with pytest.raises(ValueError, match="does not hold this simulation"):
        simulate(out, replace(config, seed=4), progress=False)


def _tiny(seed: int = 2):
    from flowins.data.simulate.scenario import CameraConfig

    return SimulationConfig(duration_s=10.0, seed=seed, flow_every=0, camera=CameraConfig(rate_hz=2.0, width=80, height=60))


def test_a_cached_simulation_whose_files_changed_is_simulated_again(tmp_path, monkeypatch, capsys):
    from flowins.data.simulate.scenario import default_cache_dir, simulate

    monkeypatch.setenv("FLOWINS_CACHE", str(tmp_path / "cache"))
    config = _tiny()
    first = simulate(config=config, progress=False)
    imu = default_cache_dir(config) / "imu.csv"
    original = imu.read_text()
    lines = original.splitlines()
    lines[5] = ",".join(["0.5" if i else value for i, value in enumerate(lines[5].split(","))])
    imu.write_text("\n".join(lines) + "\n")
    capsys.readouterr()
    again = simulate(config=config, progress=False)
    assert "files changed since it was written (imu.csv); simulating again" in capsys.readouterr().out
    assert imu.read_text() == original  # the simulation as generated, not the edited file
    assert torch.equal(again.imu.acc_mps2, first.imu.acc_mps2)
    # unchanged: read back, not regenerated
    before = imu.stat().st_mtime_ns
    simulate(config=config, progress=False)
    assert imu.stat().st_mtime_ns == before and "simulating again" not in capsys.readouterr().out


def test_a_named_folder_whose_files_changed_is_refused(tmp_path):
    from flowins.data.simulate.scenario import simulate

    out = tmp_path / "walk"
    simulate(out, _tiny(), progress=False)
    (out / "frames" / "000001.png").write_bytes(b"not an image")
    with pytest.raises(ValueError, match=r"files changed since it was written \(frames/000001\.png\); pass overwrite"):
        simulate(out, _tiny(), progress=False)
    simulate(out, _tiny(), progress=False, overwrite=True)
    assert (out / "frames" / "000001.png").read_bytes()[:4] == b"\x89PNG"


def test_the_simulation_key_follows_the_simulator_code(tmp_path, monkeypatch):
    import sys

    from flowins.data.simulate import scenario

    package = tmp_path / "simulator_part"
    package.mkdir()
    (package / "__init__.py").write_text("SPEED = 1.0\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(scenario, "SIMULATOR_CODE", (*scenario.SIMULATOR_CODE, "simulator_part"))
    before = _tiny().key()
    assert _tiny().key() == before and _tiny(seed=3).key() != before
    (package / "__init__.py").write_text("SPEED = 1.5\n")
    assert _tiny().key() != before
    sys.modules.pop("simulator_part", None)


def test_simulation_is_deterministic_in_the_seed():
    walk = Walk(WalkConfig(duration_s=12.0))
    config = SimulationConfig(duration_s=12.0)
    a = simulate_imu(walk, config, torch.Generator().manual_seed(5))
    b = simulate_imu(walk, config, torch.Generator().manual_seed(5))
    c = simulate_imu(walk, config, torch.Generator().manual_seed(6))
    assert torch.equal(a[1], b[1]) and torch.equal(a[2], b[2])
    assert not torch.equal(a[1], c[1])


def test_a_city_without_movers_is_the_city_with_them_less_its_movers():
    """``CityConfig(movers=False)`` draws the movers and leaves them out: the facades, the parked
    cars and the ground are those of the city with movers, to the bit, and no box moves."""
    import dataclasses

    from flowins.data.simulate.world import CityConfig, build_city
    from flowins.data.synthetic import Walk, WalkConfig

    walk = Walk(WalkConfig(duration_s=30.0))
    full, still = build_city(walk, seed=3), build_city(walk, seed=3, config=CityConfig(movers=False))
    assert full.n_movers == CityConfig().n_moving_cars + CityConfig().n_pedestrians and still.n_movers == 0
    static = full.box_object_id == 0
    assert int(static.sum()) == still.box_object_id.numel() > 0 and bool((still.box_object_id == 0).all())
    for f in dataclasses.fields(full):
        a, b = getattr(full, f.name), getattr(still, f.name)
        if not isinstance(a, torch.Tensor):
            continue
        if f.name.startswith("mover_"):
            assert b.numel() == 0, f.name
        elif f.name.startswith("box_"):
            assert torch.equal(a[static], b), f.name
        else:
            assert torch.equal(a, b), f.name
