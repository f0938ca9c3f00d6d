"""The simulator's city and renderer against independent truths: projection, warping, closed-form flow."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from flowins.data.sequence import PinholeCamera
from flowins.data.simulate.render import exact_flow, render
from flowins.data.simulate.world import build_city, loop_point
from flowins.data.synthetic import Walk
from flowins.geometry.camera import pixel_grid, project, unproject

# camera axes in the body frame (columns): camera x = -body y, camera y = -body z, camera z = body x
R_BODY_CAM = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
CAMERA = PinholeCamera(320, 240, 250.0, 250.0, 160.0, 120.0)


@pytest.fixture(scope="module")
def walk() -> Walk:
    return Walk()


@pytest.fixture(scope="module")
def city(walk):
    return build_city(walk, seed=0)


def walk_pose(walk: Walk, t: float):
    tt = torch.tensor(t, dtype=torch.float64)
    return walk.rotation(tt) @ R_BODY_CAM, walk.position(tt), t


def look_at(eye, target) -> torch.Tensor:
    """``R_wc`` of a camera at ``eye`` whose optical axis passes through ``target`` (x axis horizontal)."""
    eye, target = torch.as_tensor(eye, dtype=torch.float64), torch.as_tensor(target, dtype=torch.float64)
    z = (target - eye) / (target - eye).norm()
    x = torch.linalg.cross(z, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    return torch.stack((x, y, z), 1)


def static_prediction(camera, frame, pose1, pose2) -> torch.Tensor:
    """Flow of frame 1's pixels if the scene were static, from depth and camera motion only."""
    R1, p1, _ = pose1
    R2, p2, _ = pose2
    uv = pixel_grid(camera.height, camera.width)
    ray = unproject(uv, camera.fx, camera.fy, camera.cx, camera.cy)
    world = p1 + (ray * frame.depth.double().unsqueeze(-1)) @ R1.T
    return project((world - p2) @ R2, camera.fx, camera.fy, camera.cx, camera.cy) - uv


def warp_back(image2: torch.Tensor, flow: torch.Tensor) -> np.ndarray:
    """Frame 2 sampled at ``pixel + flow`` (bilinear): frame 1 as seen through the flow."""
    h, w = flow.shape[:2]
    flow = torch.nan_to_num(flow, nan=-1e4)
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    mx, my = u + flow[..., 0].numpy(), v + flow[..., 1].numpy()
    return cv2.remap(image2.numpy(), mx, my, cv2.INTER_LINEAR).astype(np.float32)


def test_render_shapes_and_ids(city, walk):
    frame = render(city, CAMERA, *walk_pose(walk, 30.0))
    assert frame.image.shape == (240, 320, 3) and frame.image.dtype == torch.uint8
    assert frame.depth.dtype == torch.float32 and frame.object_id.dtype == torch.int32
    assert frame.point.dtype == torch.float64 and frame.point.shape == (240, 320, 3)
    sky = frame.object_id == -1
    assert sky.any() and (frame.object_id == 0).any()
    assert torch.isinf(frame.depth[sky]).all() and torch.isfinite(frame.depth[~sky]).all()
    assert torch.isnan(frame.point[sky]).all()
    assert frame.image.float().std() > 20  # textured, not blank
    # every static hit point reprojects into its own pixel centre
    R, p, _ = walk_pose(walk, 30.0)
    static = frame.object_id == 0
    uv = project((frame.point[static] - p) @ R, CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy)
    assert (uv - pixel_grid(240, 320)[static]).abs().max() < 1e-3
    assert torch.allclose(((frame.point[static] - p) @ R)[:, 2], frame.depth[static].double(), rtol=1e-5)


@pytest.mark.parametrize("facade", [3, 40, 120])
def test_facade_point_projects_onto_its_pixel(city, facade):
    """A point on a facade quad, computed from the city's geometry, is where the renderer puts it."""
    a, b, n = city.facade_a[facade], city.facade_b[facade], city.facade_normal[facade]
    target = torch.cat((0.5 * (a + b), torch.tensor([4.0], dtype=torch.float64)))
    eye = torch.cat((0.5 * (a + b) + 9.0 * n + 1.5 * (b - a) / (b - a).norm(), torch.tensor([1.6], dtype=torch.float64)))
    R_wc = look_at(eye, target)
    frame = render(city, CAMERA, R_wc, eye, 0.0)
    cam = (target - eye) @ R_wc
    u, v = project(cam, CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy).tolist()
    assert (u, v) == pytest.approx((160.0, 120.0), abs=1e-9)  # look_at aims the optical axis at it
    assert int(frame.object_id[120, 160]) == 0
    assert torch.allclose(frame.point[120, 160], target, atol=1e-3)
    assert float(frame.depth[120, 160]) == pytest.approx(float(cam[2]), abs=1e-3)


def test_walk_pose_projection_of_facade_points(city, walk):
    """Facade points seen along the walk: rendered point at the projected pixel within a few cm."""
    R, p, t = walk_pose(walk, 40.0)
    frame = render(city, CAMERA, R, p, t)
    checked = 0
    for f in range(city.n_facades):
        a, b = city.facade_a[f], city.facade_b[f]
        for z in (2.0, 5.0, 8.0):
            x = torch.cat((0.5 * (a + b), torch.tensor([z], dtype=torch.float64)))
            cam = (x - p) @ R
            if cam[2] < 1.0:
                continue
            uv = project(cam, CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy)
            u, v = round(float(uv[0])), round(float(uv[1]))
            if not (0 <= u < 320 and 0 <= v < 240) or int(frame.object_id[v, u]) != 0:
                continue
            if abs(float(frame.depth[v, u]) - float(cam[2])) > 0.05 * float(cam[2]):
                continue  # occluded by something nearer
            # the nearest pixel centre is within half a pixel diagonal: its footprint on the facade
            ray = x - p
            cos_incidence = abs(float((ray[:2] @ city.facade_normal[f]) / ray.norm()))
            if cos_incidence < 0.3:
                continue
            tolerance = 0.75 * float(ray.norm()) / CAMERA.fx / cos_incidence + 0.01
            assert float((frame.point[v, u] - x).norm()) < tolerance
            checked += 1
    assert checked >= 3


def test_flow_warps_frame2_onto_frame1(city, walk):
    pose1, pose2 = walk_pose(walk, 30.0), walk_pose(walk, 30.1)
    f1, f2 = render(city, CAMERA, *pose1), render(city, CAMERA, *pose2)
    truth = exact_flow(city, CAMERA, f1, pose1, pose2, f2)
    mask = (truth.valid & truth.static).numpy()
    assert mask.mean() > 0.5
    i1 = f1.image.numpy().astype(np.float32)
    err_flow = np.abs(warp_back(f2.image, truth.flow) - i1)[mask].mean()
    err_zero = np.abs(f2.image.numpy().astype(np.float32) - i1)[mask].mean()
    assert err_zero > 3.0  # the frames differ
    assert err_flow < err_zero / 3


def test_forward_translation_is_radial(city, walk):
    """Pure translation T along the optical axis: static flow is radial, (u - c) T / (Z - T)."""
    R, p, _ = walk_pose(walk, 60.0)
    T = 0.4
    p2 = p + T * R[:, 2]
    f1, f2 = render(city, CAMERA, R, p, 60.0), render(city, CAMERA, R, p2, 60.0)
    truth = exact_flow(city, CAMERA, f1, (R, p, 60.0), (R, p2, 60.0), f2)
    mask = truth.valid & truth.static
    assert mask.float().mean() > 0.5
    uv = pixel_grid(240, 320)
    r = uv - torch.tensor([CAMERA.cx, CAMERA.cy], dtype=torch.float64)
    Z = truth.depth.double()
    expected = r * (T / (Z - T)).unsqueeze(-1)
    flow = truth.flow.double()
    assert torch.allclose(flow[mask], expected[mask], atol=2e-3, rtol=1e-4)
    cross = flow[..., 0] * r[..., 1] - flow[..., 1] * r[..., 0]
    assert (cross[mask].abs() <= 1e-3 * (1 + r.norm(dim=-1)[mask])).all()
    assert ((flow * r).sum(-1)[mask] >= 0).all()  # away from the principal point
    # first-order magnitude f T r / Z (r in normalised units) for far points
    far = mask & (Z > 20)
    approx = r.norm(dim=-1) * T / Z
    assert torch.allclose(flow.norm(dim=-1)[far], approx[far], rtol=0.03, atol=1e-3)
    assert truth.sky.any() and flow[truth.sky].abs().max() < 1e-4  # points at infinity do not move


def _car_in_view(city, t: float):
    """A camera 5 m up on the walk's path beside moving car 1, looking at it, and the car's id."""
    k = 0  # mover 1 is a car
    assert int(city.box_kind[-city.n_movers + k]) == 0
    xy, _ = city.mover_pose(t)
    s = city.mover_s0[k] + city.mover_rate[k] * t
    path_xy, tangent = loop_point(city.walk, s, 0.0, city.outward_sign)
    target = torch.cat((xy[k], torch.tensor([0.8], dtype=torch.float64)))
    eye = torch.cat((path_xy - 1.5 * tangent, torch.tensor([5.0], dtype=torch.float64)))
    return look_at(eye, target), eye, k + 1


def test_moving_car_flow_differs_from_static_prediction(city):
    t = 12.0
    R1, p1, oid = _car_in_view(city, t)
    pose1 = (R1, p1, t)
    pose2 = (R1, p1 + torch.tensor([0.05, 0.03, 0.0], dtype=torch.float64), t + 0.1)
    f1, f2 = render(city, CAMERA, *pose1), render(city, CAMERA, *pose2)
    car = f1.object_id == oid
    assert car.sum() > 500
    # its points lie in its body frame's box
    half = city.box_half[-city.n_movers + oid - 1]
    local = f1.point[car]
    assert (local[:, 0].abs() <= half[0] + 1e-4).all() and (local[:, 1].abs() <= half[1] + 1e-4).all()
    assert (local[:, 2] >= -1e-4).all() and (local[:, 2] <= 2 * half[2] + 1e-4).all()
    truth = exact_flow(city, CAMERA, f1, pose1, pose2, f2)
    predicted = static_prediction(CAMERA, f1, pose1, pose2).float()
    static = truth.valid & truth.static
    assert torch.allclose(truth.flow[static], predicted[static], atol=1e-3)  # consistent for the static scene
    difference = (truth.flow - predicted).norm(dim=-1)[car & truth.valid]
    assert difference.numel() > 300 and difference.median() > 1.0
    # and the images agree: warping with the exact flow beats warping with the static prediction on the car
    mask = (car & truth.valid).numpy()
    i1 = f1.image.numpy().astype(np.float32)
    err_exact = np.abs(warp_back(f2.image, truth.flow) - i1)[mask].mean()
    err_static = np.abs(warp_back(f2.image, predicted) - i1)[mask].mean()
    assert err_exact < err_static / 2


def test_determinism(walk, city):
    pose = walk_pose(walk, 25.0)
    again = build_city(walk, seed=0)
    other = build_city(walk, seed=1)
    a = render(city, CAMERA, *pose)
    b = render(again, CAMERA, *pose)
    c = render(other, CAMERA, *pose)
    assert torch.equal(a.image, b.image) and torch.equal(a.depth, b.depth)
    assert not torch.equal(a.image, c.image)
    assert city.facade_a.shape != other.facade_a.shape or not torch.equal(city.facade_height, other.facade_height)


def test_canyon_is_a_fraction(city, walk):
    t = torch.tensor([10.0, 60.0, 120.0], dtype=torch.float64)
    canyon = city.canyon(walk.position(t))
    assert canyon.shape == (3,) and ((canyon > 0) & (canyon <= 1)).all()


@pytest.mark.parametrize("t", [18.0, 95.0])
def test_culling_and_tiling_change_nothing(city, walk, t):
    """The culled, tiled, occlusion-pruned cast equals a naive one (one tile, no range limit)."""
    pose = walk_pose(walk, t)
    fast = render(city, CAMERA, *pose)
    naive = render(city, CAMERA, *pose, tile=320, max_range_m=1e9)
    assert torch.equal(fast.object_id, naive.object_id)
    assert torch.equal(fast.depth, naive.depth)
    assert torch.equal(fast.image, naive.image)


def test_exposure_and_motion_blur(city, walk):
    pose = walk_pose(walk, 50.0)
    plain = render(city, CAMERA, *pose)
    dark = render(city, CAMERA, *pose, exposure=0.5)
    assert (dark.image.float() - 0.5 * plain.image.float()).abs().max() <= 1.0
    same = render(city, CAMERA, *pose, motion_blur=[pose, pose])
    assert (same.image.int() - plain.image.int()).abs().max() <= 1
    blurred = render(city, CAMERA, *pose, motion_blur=[walk_pose(walk, 50.02), walk_pose(walk, 50.04)])
    assert torch.equal(blurred.depth, plain.depth)  # geometry is the main pose's
    assert (blurred.image.int() - plain.image.int()).abs().float().mean() > 0.5


def test_value_noise_is_a_bilinear_sample_that_wraps_at_every_coordinate():
    """``sample_noise`` against a float64 bilinear sampler with modular indices, at points inside
    its texels and at coordinates a hair below 0 or a multiple of its size, which wrap to that size
    itself in float32 (a mover's face at z = -1e-9 m, which once indexed past the table)."""
    from flowins.data.simulate.world import sample_noise

    gen = torch.Generator().manual_seed(4)
    n = 16
    noise = torch.rand(n, n, generator=gen)
    u = torch.cat((torch.rand(200, generator=gen) * 5 * n - 2 * n,
                   torch.tensor([-1e-9, -1e-7, n - 1e-6, 2 * n - 1e-6, 0.0, float(n), 3.25])))
    v = torch.cat((torch.rand(200, generator=gen) * 5 * n - 2 * n,
                   torch.tensor([-1e-9, n - 1e-6, -1e-7, 0.5, -1e-9, -1e-9, -1e-9])))
    got = sample_noise(noise, u, v)
    u64, v64, table = u.double(), v.double(), noise.double()
    i, j = torch.floor(u64), torch.floor(v64)
    fu, fv = u64 - i, v64 - j
    i, j = i.long() % n, j.long() % n

    def at(a, b):
        return table[b % n, a % n]

    want = ((1 - fv) * ((1 - fu) * at(i, j) + fu * at(i + 1, j))
            + fv * ((1 - fu) * at(i, j + 1) + fu * at(i + 1, j + 1)))
    torch.testing.assert_close(got.double(), want, rtol=0, atol=1e-4)
