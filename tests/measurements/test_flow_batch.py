"""Batches of sequences: the flow measurements and their epipolar update take leading batch
dimensions and a mask of the real points; every row equals the row computed alone, padding
(whatever it holds) is inert, and nothing degenerate or padded puts NaN into a gradient."""
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from flowins.flow.points import FlowPoints
from flowins.geometry import quaternion as quat
from flowins.measurements.flow import FlowCamera, epipolar_update, flow_measurements
from flowins.measurements.selection import select_points
from flowins.state import make_state

F64 = torch.float64
FIELDS = ("residual", "H_x", "H_r", "parallax_px")
COUNTS = ("n_degenerate", "n_behind", "n_low_parallax")


def sequence(gen, n, *, baseline=0.3, still=False, ahead=False):
    """One sequence's frame pair: a camera of its own (intrinsics, mounting), the state, and ``n``
    flow points of a cloud 3-15 m in front of camera 1, projected by hand, with 0.3 px noise.
    ``still``: the second pose is the first (every point degenerate); ``ahead``: camera 2 is 6 m
    ahead along camera 1's axis, in front of the nearer points (behind camera 2)."""
    f = 200.0 + 100.0 * torch.rand(2, generator=gen, dtype=F64)
    c = torch.tensor([160.0, 120.0], dtype=F64) + 10.0 * torch.randn(2, generator=gen, dtype=F64)
    K = torch.tensor([[f[0], 0.0, c[0]], [0.0, f[1], c[1]], [0.0, 0.0, 1.0]], dtype=F64)
    forward = torch.tensor([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], dtype=F64)  # camera z = body x
    R_ci = quat.to_matrix(quat.from_rotation_vector(0.05 * torch.randn(3, generator=gen, dtype=F64))) @ forward
    t_ci = 0.1 * torch.randn(3, generator=gen, dtype=F64)
    q_prev = quat.from_rotation_vector(0.3 * torch.randn(3, generator=gen, dtype=F64))
    q = quat.multiply(q_prev, quat.from_rotation_vector(0.03 * torch.randn(3, generator=gen, dtype=F64)))
    p_prev = torch.randn(3, generator=gen, dtype=F64)
    p = p_prev + baseline * torch.nn.functional.normalize(torch.randn(3, generator=gen, dtype=F64), dim=0)
    if still:
        q, p = q_prev, p_prev
    x = make_state(p=p, v=torch.zeros(3, dtype=F64), q=q, p_prev=p_prev, q_prev=q_prev)

    def camera(q_, p_):
        R_wb = quat.to_matrix(q_)
        R_wc = R_wb @ R_ci.T
        return R_wc, p_ - R_wc @ t_ci

    def project(X, R_wc, c_w):
        y = (X - c_w) @ R_wc @ K.T
        return y[:, :2] / y[:, 2:]

    R1, c1 = camera(q_prev, p_prev)
    if ahead:
        q = q_prev
        p = p_prev + 6.0 * R1[:, 2]
        x = make_state(p=p, v=torch.zeros(3, dtype=F64), q=q, p_prev=p_prev, q_prev=q_prev)
    R2, c2 = camera(q, p)
    depth = 3.0 + 12.0 * torch.rand(n, generator=gen, dtype=F64)
    lateral = (torch.rand(n, 2, generator=gen, dtype=F64) - 0.5) * depth[:, None]
    X = c1 + depth[:, None] * R1[:, 2] + lateral[:, :1] * R1[:, 0] + lateral[:, 1:] * R1[:, 1]
    uv1 = project(X, R1, c1)
    flow = project(X, R2, c2) - uv1 + 0.3 * torch.randn(n, 2, generator=gen, dtype=F64)
    sigma = 0.3 + 0.5 * torch.rand(n, 2, generator=gen, dtype=F64)
    return x, FlowCamera(K, R_ci, t_ci), FlowPoints(uv1, flow, sigma)


def make_rows(counts, *, seed=0, still_row=None, ahead_row=None):
    gen = torch.Generator().manual_seed(seed)
    return [sequence(gen, n, still=(i == still_row), ahead=(i == ahead_row)) for i, n in enumerate(counts)]


def padded(rows, shape, fill):
    """The rows stacked to ``shape + (M, ...)``, a camera per row, and the mask; the padding holds
    ``fill``: "zeros", "degenerate" (the row's first pixel again with zero flow: a point that would
    be used, or count as degenerate or behind, were it real) or "nan"."""
    M = max(len(points) for _, _, points in rows)
    mask = torch.zeros(len(rows), M, dtype=torch.bool)
    tensors = {k: torch.zeros(len(rows), M, 2, dtype=F64) for k in ("uv1", "flow", "sigma")}
    for b, (_, _, points) in enumerate(rows):
        n = len(points)
        mask[b, :n] = True
        for k, t in zip(("uv1", "flow", "sigma"), points):
            tensors[k][b, :n] = t
        if fill == "degenerate":
            tensors["uv1"][b, n:] = points.uv1_px[0]
        elif fill == "nan":
            for k in tensors:
                tensors[k][b, n:] = float("nan")
    x = torch.stack([r[0] for r in rows])
    camera = FlowCamera(*(torch.stack([getattr(r[1], k) for r in rows]) for k in ("K", "R_ci", "t_ci")))
    shape = tuple(shape)

    def view(t: torch.Tensor) -> torch.Tensor:
        return t.reshape(*shape, *t.shape[1:])

    camera = FlowCamera(view(camera.K), view(camera.R_ci), view(camera.t_ci))
    return view(x), camera, FlowPoints(*(view(tensors[k]) for k in ("uv1", "flow", "sigma"))), view(mask)


def min_parallax(points, mask=None):
    """A threshold per point (``(..., M)``, 0 on the padding): 10 σ, so that some points fall below it."""
    threshold = 10.0 * torch.linalg.vector_norm(points.sigma_px, dim=-1) / 2**0.5
    return threshold if mask is None else torch.where(mask, threshold, 0.0)


def assert_rows_equal(batched, singles, mask, flows, *, rtol):
    """Row b of ``batched`` (real points first) against ``singles[b]``, to ``rtol`` of each field's
    scale (for h, a difference of pixel positions, the flow's), the padding all zero."""
    flat_mask = mask.reshape(-1, mask.shape[-1])
    for b, (single, flow) in enumerate(zip(singles, flows)):
        real = flat_mask[b]
        n = int(real.sum())
        for field in FIELDS + ("valid",):
            got = getattr(batched, field).reshape(-1, *getattr(batched, field).shape[mask.ndim - 1:])[b]
            want = getattr(single, field)
            if field == "valid":
                assert torch.equal(got[real], want) and not bool(got[~real].any()), (b, field)
                continue
            scale = max(1.0, float(want.abs().max()), float(flow.abs().max()) if field == "residual" else 0.0)
            torch.testing.assert_close(got[:n], want, rtol=0, atol=rtol * scale)
            assert not bool(got[n:].any()), (b, field)
        for field in COUNTS:
            assert int(getattr(batched, field).reshape(-1)[b]) == int(getattr(single, field)), (b, field)


@pytest.mark.parametrize("shape", [(1,), (3,), (3, 2)])
@pytest.mark.parametrize("fill", ["zeros", "degenerate", "nan"])
def test_each_row_of_a_batch_equals_the_row_alone(shape, fill):
    counts = [40, 23, 31, 40, 12, 36][: int(torch.tensor(shape).prod())]
    rows = make_rows(counts, still_row=1 if len(counts) > 1 else None, ahead_row=2 if len(counts) > 2 else None)
    x, camera, points, mask = padded(rows, shape, fill)
    with torch.no_grad():
        batched = flow_measurements(x, points.flow_px, points.uv1_px, camera, mask=mask,
                                    min_parallax_px=min_parallax(points, mask))
        singles = [flow_measurements(x_, p.flow_px, p.uv1_px, cam, min_parallax_px=min_parallax(p))
                   for x_, cam, p in rows]
    assert batched.residual.shape == (*shape, 40, 2) and batched.H_x.shape == (*shape, 40, 2, 26)
    assert batched.n_behind.shape == shape and batched.n_behind.dtype == torch.int64
    assert all(single.n_behind.shape == () for single in singles)
    for t in (batched.residual, batched.H_x, batched.H_r, batched.parallax_px):
        assert torch.isfinite(t).all()
    assert_rows_equal(batched, singles, mask, [p.flow_px for _, _, p in rows], rtol=1e-12)
    # every kind of point is there: valid, low parallax, degenerate (the still row), behind (the row ahead)
    total = {k: sum(int(getattr(s, k)) for s in singles) for k in COUNTS}
    assert sum(int(s.valid.sum()) for s in singles) > 0 and total["n_low_parallax"] > 0
    if len(counts) > 2:
        assert int(singles[1].n_degenerate) == counts[1] and int(singles[2].n_behind) > 0


def test_a_shared_camera_and_no_mask_need_no_padding():
    rows = make_rows([30, 30, 30], seed=3)
    shared = rows[0][1]
    x = torch.stack([r[0] for r in rows])
    flow = torch.stack([r[2].flow_px for r in rows])
    uv1 = torch.stack([r[2].uv1_px for r in rows])
    with torch.no_grad():
        batched = flow_measurements(x, flow, uv1, shared)
        singles = [flow_measurements(x[b], flow[b], uv1[b], shared) for b in range(3)]
    assert_rows_equal(batched, singles, torch.ones(3, 30, dtype=torch.bool), flow, rtol=1e-12)


@pytest.mark.parametrize("jacobians", ["analytic", "autodiff"])
def test_tracked_and_reference_paths_batch_the_same_way(jacobians):
    """With a gradient to carry (and for the torch.func reference) the valid points are gathered over
    the batch; the rows still equal the rows alone, and the fast path to rounding."""
    rows = make_rows([12, 7, 10], seed=5, still_row=1)
    x, camera, points, mask = padded(rows, (3,), "degenerate")
    x = x.clone().requires_grad_(True)
    batched = flow_measurements(x, points.flow_px, points.uv1_px, camera, mask=mask, jacobians=jacobians,
                                min_parallax_px=min_parallax(points, mask))
    singles = [flow_measurements(x_.clone().requires_grad_(True), p.flow_px, p.uv1_px, cam, jacobians=jacobians,
                                 min_parallax_px=min_parallax(p)) for x_, cam, p in rows]
    detach = type(batched)(*(t.detach() for t in batched))
    assert_rows_equal(detach, [type(s)(*(t.detach() for t in s)) for s in singles], mask,
                      [p.flow_px for _, _, p in rows], rtol=1e-12)
    with torch.no_grad():
        fast = flow_measurements(x, points.flow_px, points.uv1_px, camera, mask=mask,
                                 min_parallax_px=min_parallax(points, mask))
    assert torch.equal(fast.valid, batched.valid)
    for field in FIELDS:
        scale = max(1.0, float(getattr(fast, field).abs().max()))
        torch.testing.assert_close(getattr(batched, field).detach(), getattr(fast, field), rtol=0, atol=1e-9 * scale)


def test_the_epipolar_update_keeps_every_point_and_the_invalid_ones_add_nothing():
    rows = make_rows([25, 14, 20], seed=7, still_row=1)
    x, camera, points, mask = padded(rows, (3,), "zeros")
    with torch.no_grad():
        m = flow_measurements(x, points.flow_px, points.uv1_px, camera, mask=mask,
                              min_parallax_px=min_parallax(points, mask))
        upd = epipolar_update(m, points.sigma_px, parallax_inflation=True)
    assert upd.innovation.shape == (3, 25, 1) and upd.H.shape == (3, 25, 1, 26) and upd.noise_cov.shape == (3, 25, 1, 1)
    assert torch.equal(upd.valid, m.valid)
    invalid = ~m.valid
    assert bool(invalid.any()) and bool(m.valid.any())
    assert float(upd.innovation[invalid].abs().max()) == 0.0 and float(upd.H[invalid].abs().max()) == 0.0
    assert bool((upd.noise_cov[invalid] == 1.0).all())
    for t in upd[:4]:
        assert torch.isfinite(t).all()
    for b, (x_, cam, p) in enumerate(rows):
        with torch.no_grad():
            single = epipolar_update(flow_measurements(x_, p.flow_px, p.uv1_px, cam, min_parallax_px=min_parallax(p)),
                                     p.sigma_px, parallax_inflation=True)
        n = len(p)
        for field in ("innovation", "H", "noise_cov", "direction"):
            want = getattr(single, field)
            scale = max(1.0, float(want.abs().max()))
            torch.testing.assert_close(getattr(upd, field)[b, :n], want, rtol=0, atol=1e-12 * scale)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("jacobians", ["analytic", "autodiff"])
def test_degenerate_points_and_padding_put_no_nan_into_gradients(dtype, jacobians):
    """A still row (every point degenerate), padding of zeros, a learned noise scale: the gradient
    of an update's statistics with respect to the states and the scale is finite."""
    rows = make_rows([15, 9, 12], seed=11, still_row=1)
    x, camera, points, mask = padded(rows, (3,), "zeros")
    camera = FlowCamera(camera.K.to(dtype), camera.R_ci.to(dtype), camera.t_ci.to(dtype))
    x = x.to(dtype).requires_grad_(True)
    log_scale = torch.zeros((), dtype=dtype, requires_grad=True)
    sigma = points.sigma_px.to(dtype) * log_scale.exp()
    m = flow_measurements(x, points.flow_px.to(dtype), points.uv1_px.to(dtype), camera, mask=mask,
                          min_parallax_px=min_parallax(points, mask).to(dtype), jacobians=jacobians)
    assert bool(m.valid.any()) and not bool(m.valid[1].any())
    upd = epipolar_update(m, sigma, parallax_inflation=True)
    loss = (upd.innovation.square() / upd.noise_cov.squeeze(-1)).sum() + upd.H.square().sum() + m.parallax_px.sum()
    grad_x, grad_scale = torch.autograd.grad(loss, (x, log_scale))
    assert torch.isfinite(grad_x).all() and torch.isfinite(grad_scale).all()
    assert float(grad_x.abs().sum()) > 0.0 and float(grad_scale.abs()) > 0.0
    assert float(grad_x[1].abs().max()) == 0.0  # the still row has no valid point


@pytest.mark.parametrize("fill", ["zeros", "nan"])
def test_the_tracked_closed_form_in_place_has_the_gradient_of_the_per_point_reference(fill):
    """With a gradient to carry, the closed form linearises every point in place (a point that is
    not valid on its row's first valid point, a row without one on a stand-in): the gradient of an
    update's statistics with respect to the states and a noise scale equals that of the reference
    (``torch.func.jacrev`` per valid point, gathered), with a still row, a row moving ahead past the
    nearer points and padding of zeros or NaN; as one graph with its backward (a gather of the valid
    points, whose count is data, would break it)."""
    rows = make_rows([14, 9, 12], seed=13, still_row=1, ahead_row=2)
    x0, camera, points, mask = padded(rows, (3,), fill)
    threshold = min_parallax(points, mask)
    sigma = torch.where(mask.unsqueeze(-1), points.sigma_px, 0.5)  # the padding's pixels hold the fill

    def loss(x, log_scale, jacobians):
        m = flow_measurements(x, points.flow_px, points.uv1_px, camera, mask=mask, min_parallax_px=threshold,
                              jacobians=jacobians)
        upd = epipolar_update(m, sigma * log_scale.exp(), parallax_inflation=True)
        return ((upd.innovation.square() / upd.noise_cov.squeeze(-1)).sum() + upd.H.square().sum()
                + m.parallax_px.sum(), m.valid)

    grads = {}
    for jacobians in ("analytic", "autodiff"):
        x, log_scale = x0.clone().requires_grad_(True), torch.tensor(0.2, dtype=F64, requires_grad=True)
        value, valid = loss(x, log_scale, jacobians)
        grads[jacobians] = (value, *torch.autograd.grad(value, (x, log_scale)))
    assert bool(valid[0].any()) and not bool(valid[1].any()) and not bool(valid[2].all()) and bool(valid[2].any())
    for a, b in zip(grads["analytic"], grads["autodiff"]):
        assert torch.isfinite(a).all()
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-8 * max(1.0, float(b.abs().max())))
    assert float(grads["analytic"][1][1].abs().max()) == 0.0  # the still row has no valid point
    if fill != "nan":
        return  # one graph: traced once (a minute or two here)
    torch._dynamo.reset()

    def value_and_gradient(x, log_scale):
        value = loss(x, log_scale, "analytic")[0]
        return value, *torch.autograd.grad(value, (x, log_scale))

    x, log_scale = x0.clone().requires_grad_(True), torch.tensor(0.2, dtype=F64, requires_grad=True)
    compiled = torch.compile(lambda x, s: loss(x, s, "analytic")[0], fullgraph=True, backend="aot_eager")(x, log_scale)
    got = (compiled, *torch.autograd.grad(compiled, (x, log_scale)))
    for a, b in zip(got, value_and_gradient(x0.clone().requires_grad_(True), torch.tensor(0.2, dtype=F64,
                                                                                         requires_grad=True))):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12 * max(1.0, float(b.abs().max())))


class CountOperations(TorchDispatchMode):
    """Dispatcher operations that are not views (what the per-operation overhead multiplies)."""

    def __init__(self):
        super().__init__()
        self.count = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if not func.is_view and func.__name__ not in ("lift_fresh.default", "detach.default"):
            self.count += 1
        return func(*args, **(kwargs or {}))


def frame_operations(x, camera, points, mask):
    with CountOperations() as counter, torch.inference_mode():
        keep = select_points(x, points, camera.K, camera.R_ci, n_points=64, cell_px=80.0, mask=mask)
        take = lambda t: torch.take_along_dim(t, keep.unsqueeze(-1), -2)  # noqa: E731
        mask = torch.take_along_dim(mask, keep, -1)
        uv1, flow, sigma = take(points.uv1_px), take(points.flow_px), take(points.sigma_px)
        m = flow_measurements(x, flow, uv1, camera, mask=mask, min_parallax_px=0.5)
        epipolar_update(m, sigma, parallax_inflation=True)
    return counter.count


def test_the_number_of_operations_per_frame_does_not_grow_with_the_batch():
    """Selection, linearisation and the epipolar update of a frame: a bounded number of PyTorch
    operations, the same for one sequence and for several."""
    rows = make_rows([120, 90, 100, 110, 80], seed=13)
    one, many = padded(rows[:1], (1,), "zeros"), padded(rows, (5,), "zeros")
    frame_operations(*one)  # the constants and the cameras' terms are formed once
    frame_operations(*many)
    one, many = frame_operations(*one), frame_operations(*many)
    assert one == many
    assert one <= 160, one


def test_float32_follows_float64():
    rows = make_rows([40, 23, 31], seed=2, still_row=1)
    x, camera, points, mask = padded(rows, (3,), "zeros")
    single = FlowCamera(camera.K.float(), camera.R_ci.float(), camera.t_ci.float())
    with torch.no_grad():
        ref = flow_measurements(x, points.flow_px, points.uv1_px, camera, mask=mask,
                                min_parallax_px=min_parallax(points, mask))
        low = flow_measurements(x.float(), points.flow_px.float(), points.uv1_px.float(), single, mask=mask,
                                min_parallax_px=min_parallax(points, mask).float())
    assert low.H_x.dtype == torch.float32
    both = ref.valid & low.valid
    assert int(both.sum()) >= 0.9 * int(ref.valid.sum()) > 0
    for field in FIELDS:
        want = getattr(ref, field)[both]
        scale = float(want.abs().max())
        torch.testing.assert_close(getattr(low, field)[both].double(), want, rtol=0, atol=1e-4 * scale)
