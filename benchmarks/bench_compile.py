"""A filter step under ``torch.compile``, against eager, on this machine.

``--step flow`` (the default): :func:`flowins.measurements.flow_update.flow_iteration`
(triangulation, residual and closed-form Jacobians of ``--points`` flow points, their
epipolar reduction and the gated scalar update of the 26-dim state), on ``--batch``
synthetic frames (a camera moving 0.12 m between frames and turning by about 0.6°, points
5-25 m ahead, 0.5 px flow noise, the last 10 points padding). ``--step frame``: the frame's
whole update, :func:`flowins.measurements.flow_update.flow_frame_step` (the parallax
selection of 3/4 of the points, two iterations, the recovery's count). ``--step propagation``:
:func:`flowins.filter.propagation.propagate_batched` over ``--imu-steps`` IMU samples
(100 Hz, one node at the end: the propagation between two flow frames at 10 Hz). For each
batch size it prints the eager time per call and the compiled one (``--backend``, default
``inductor``: it needs a C++ compiler), each the median over ``--repeats`` rounds that call both
once, interleaved (this machine's speed drifts), their ratio, the compile time (the first call; a
second process finds inductor's code in its cache) and the largest difference of the outputs::

    python benchmarks/bench_compile.py [--step flow|frame|propagation] [--batch 1 8] [--points 256]
                                       [--imu-steps 10] [--backend inductor] [--repeats 50] [--cpp-wrapper]
                                       [--eigen eigh|jacobi] [--max-fusion-size N]

``--cpp-wrapper``: inductor writes the code that calls its kernels in C++ too (its Python
wrapper runs about 2,200 statements per call of the frame step: allocations, kernel calls,
frees), at the cost of a longer compile.

``--eigen jacobi`` triangulates the flow points by Jacobi rotations
(:func:`flowins.linalg.jacobi_right_singular`, what a GPU runs) instead of ``eigh``, eager and
compiled alike.

``--max-fusion-size N``: the most nodes inductor fuses into one kernel
(``torch._inductor.config.max_fusion_size``, 64 by default): a longer chain of elementwise
operations, as the Jacobi rotations are, is otherwise cut into several kernels that write their
intermediates out.

``--backend eager`` checks only that the step is one graph (``fullgraph=True``: any graph
break is an error), which needs no compiler.
"""
from __future__ import annotations

import argparse
import time

import torch

from flowins.constants import STANDARD_GRAVITY_MPS2
from flowins.filter.propagation import NodePlan, plan_nodes, propagate_batched
from flowins.flow.points import FlowPoints
from flowins.geometry import quaternion as quat
from flowins.measurements.flow import FlowCamera, camera_pose
from flowins.ins.mechanization import ProcessNoise
from flowins.measurements.flow_update import FlowUpdate, flow_frame_step, flow_iteration
from flowins.state import STATE_DIM, make_state

F64 = torch.float64


def frame(batch: int, points: int, seed: int = 0):
    """``(x, cov, points, camera, mask, min_parallax_px)`` of ``batch`` synthetic frames."""
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[266.0, 0.0, 159.5], [0.0, 266.0, 119.5], [0.0, 0.0, 1.0]], dtype=F64)
    camera = FlowCamera(K, torch.tensor([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], dtype=F64),
                        torch.zeros(3, dtype=F64))
    p = torch.randn(batch, 3, generator=g, dtype=F64)
    q = quat.from_rotation_vector(0.1 * torch.randn(batch, 3, generator=g, dtype=F64))
    p_prev = p - torch.tensor([0.12, 0.0, 0.0], dtype=F64)
    q_prev = quat.multiply(q, quat.from_rotation_vector(0.01 * torch.randn(batch, 3, generator=g, dtype=F64)))
    x = make_state(p=p, v=torch.randn(batch, 3, generator=g, dtype=F64), q=q, p_prev=p_prev, q_prev=q_prev)
    R1, c1 = camera_pose(q_prev, p_prev, camera)
    R2, c2 = camera_pose(q, p, camera)
    rays = torch.cat((2 * torch.rand(batch, points, 2, generator=g, dtype=F64) - 1,
                      torch.ones(batch, points, 1, dtype=F64)), -1)
    X = (R1.unsqueeze(1) @ (rays * (5 + 20 * torch.rand(batch, points, 1, generator=g, dtype=F64))).unsqueeze(-1))
    X = X.squeeze(-1) + c1.unsqueeze(1)

    def pixels(R, c):
        Xc = (R.transpose(-1, -2).unsqueeze(1) @ (X - c.unsqueeze(1)).unsqueeze(-1)).squeeze(-1)
        return Xc[..., :2] / Xc[..., 2:] * 266.0 + K[:2, 2]

    uv1 = pixels(R1, c1)
    uv2 = pixels(R2, c2) + 0.5 * torch.randn(batch, points, 2, generator=g, dtype=F64)
    sigma = torch.full((batch, points, 2), 0.5, dtype=F64)
    mask = torch.ones(batch, points, dtype=torch.bool)
    mask[:, -10:] = False
    cov = 0.01 * torch.eye(STATE_DIM, dtype=F64).expand(batch, STATE_DIM, STATE_DIM).clone()
    return x, cov, FlowPoints(uv1, uv2 - uv1, sigma), camera, mask, sigma.norm(dim=-1) / 2**0.5


def step(x, cov, points, camera, mask, min_parallax_px, update=FlowUpdate()):
    """The flow iteration's outputs as plain tensors."""
    it = flow_iteration(x, x, cov, points, camera, mask, min_parallax_px, update=update)
    m = it.measurements
    counts = torch.stack((m.valid.sum(-1), m.n_degenerate, m.n_behind, m.n_low_parallax), -1)
    return it.result.mean, it.result.cov, it.result.weight.sum(-1), counts, it.result.failed


def whole_frame(points: int):
    """A function of a frame's tensors giving :func:`flow_frame_step`'s outputs as plain tensors
    (3/4 of the ``points`` kept, two iterations)."""
    update = FlowUpdate(n_points=3 * points // 4, iterations=2)  # built outside the graph

    def run(x, cov, points, camera, mask, min_parallax_px, gated):
        out = flow_frame_step(x, cov, points, camera, mask, update=update, select=True, gated=gated)
        return out.mean, out.cov, out.values["accepted"], out.values["valid"], out.gated

    return run


def imu_run(batch: int, steps: int, seed: int = 0):
    """``(x0, P0, acc, gyro, dt, variances, group, node_step)``: ``batch`` states moving at 1 m/s
    and ``steps`` noisy 100 Hz IMU samples each, one node after the last."""
    g = torch.Generator().manual_seed(seed)
    q = quat.from_rotation_vector(0.1 * torch.randn(batch, 3, generator=g, dtype=F64))
    x0 = make_state(p=torch.randn(batch, 3, generator=g, dtype=F64), v=torch.ones(batch, 3, dtype=F64), q=q)
    P0 = 0.01 * torch.eye(STATE_DIM, dtype=F64).expand(batch, STATE_DIM, STATE_DIM).clone()
    acc = torch.randn(batch, steps, 3, generator=g, dtype=F64) + torch.tensor([0.0, 0.0, 9.81], dtype=F64)
    gyro = 0.1 * torch.randn(batch, steps, 3, generator=g, dtype=F64)
    dt = torch.full((batch, steps), 0.01, dtype=F64)
    plan = plan_nodes([[steps - 1]] * batch, steps)
    return x0, P0, acc, gyro, dt, ProcessNoise().variances(dt), plan.group, plan.node_step


def propagation(x0, P0, acc, gyro, dt, variances, group, node_step):
    """The propagation's node means, covariances and transitions."""
    real = [[True] * node_step.shape[-1]] * node_step.shape[0]
    return tuple(propagate_batched(x0, P0, acc, gyro, dt, NodePlan(group, node_step, real), variances=variances,
                                   gravity_mps2=STANDARD_GRAVITY_MPS2))


def main() -> None:
    from timing import interleaved_ms  # beside this script (the tests import its frames without it)

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--step", choices=("flow", "frame", "propagation"), default="flow")
    parser.add_argument("--batch", type=int, nargs="+", default=[1, 8])
    parser.add_argument("--points", type=int, default=256)
    parser.add_argument("--imu-steps", type=int, default=10)
    parser.add_argument("--backend", default="inductor")
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--cpp-wrapper", action="store_true",
                        help="inductor's C++ wrapper (torch._inductor.config.cpp_wrapper) instead of its Python one")
    parser.add_argument("--eigen", choices=("eigh", "jacobi"), default="eigh",
                        help="how the flow points are triangulated (flowins.geometry.triangulation.solve_dlt)")
    parser.add_argument("--max-fusion-size", type=int, default=None,
                        help="inductor's largest fusion (torch._inductor.config.max_fusion_size; its default 64)")
    args = parser.parse_args()
    if args.eigen != "eigh":  # before anything is traced: the flow model looks solve_dlt up at each call
        import functools

        import flowins.measurements.flow as flow_model
        from flowins.geometry.triangulation import solve_dlt

        flow_model.solve_dlt = functools.partial(solve_dlt, eigen=args.eigen)
    from torch._inductor import config as inductor

    if args.cpp_wrapper:
        inductor.cpp_wrapper = True
    if args.max_fusion_size is not None:
        inductor.max_fusion_size = args.max_fusion_size
    if args.step == "flow":
        what, fn, make = f"flow_iteration, {args.points} points a frame", step, lambda b: frame(b, args.points)
    elif args.step == "frame":
        what, fn, make = (f"flow_frame_step, {args.points} points a frame", whole_frame(args.points),
                          lambda b: (*frame(b, args.points), torch.zeros(b, dtype=torch.long)))
    else:
        what, fn, make = (f"propagate_batched, {args.imu_steps} IMU steps to one node", propagation,
                          lambda b: imu_run(b, args.imu_steps))
    print(f"{what}, float64, {torch.get_num_threads()} threads, backend {args.backend}"
          + (", C++ wrapper" if args.cpp_wrapper else "")
          + (f", fusions up to {args.max_fusion_size} nodes" if args.max_fusion_size is not None else "")
          + (f", triangulation by {args.eigen}" if args.step != "propagation" else ""))
    for batch in args.batch:
        inputs = make(batch)
        with torch.inference_mode():
            torch._dynamo.reset()
            compiled = torch.compile(fn, fullgraph=True, backend=args.backend, dynamic=False)
            t0 = time.perf_counter()
            got = compiled(*inputs)
            compile_s = time.perf_counter() - t0
            want = fn(*inputs)
            diff = max(float((a.double() - b.double()).abs().max()) for a, b in zip(got[:4], want[:4]))
            eager_ms, compiled_ms = interleaved_ms([lambda: fn(*inputs), lambda: compiled(*inputs)], args.repeats)
            times = {"eager": eager_ms, "compiled": compiled_ms}
        print(f"  batch {batch}: eager {times['eager']:.3f} ms, compiled {times['compiled']:.3f} ms "
              f"({times['eager'] / times['compiled']:.2f}x), compile {compile_s:.1f} s, largest difference {diff:.1e}")


if __name__ == "__main__":
    main()
