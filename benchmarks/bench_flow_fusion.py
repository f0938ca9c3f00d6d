"""INS vs INS + optical-flow frames on 10 s of the simulated walk (an accuracy experiment).

Exact rendered flow plus Gaussian noise at ``--points`` random static, visible pixels per
frame (10 Hz, 160x120), optionally only pixels nearer than ``--max-depth`` (the true
depth: an oracle selection, for studying the measurement model) and with the parallax
gate ``--min-parallax-sigma``. Prints the final position and attitude errors and the
gyroscope-bias estimate. Usage::

    python benchmarks/bench_flow_fusion.py [--max-depth 8] [--noise 0.3] [--perfect-imu]
"""
from __future__ import annotations

import argparse
import math
import time

import torch

from flowins.data.simulate.render import exact_flow, render
from flowins.data.simulate.scenario import CameraConfig, CameraTrajectory, SimulationConfig, simulate_imu
from flowins.data.simulate.world import build_city
from flowins.data.synthetic import ImuErrors, Walk, WalkConfig
from flowins.filter.ekf import Gate
from flowins.measurements.flow_update import FlowFrame, FlowUpdate
from flowins.flow.points import FlowPoints
from flowins.filter.runner import run_filter
from flowins.geometry import quaternion as quat
from flowins.ins.initialization import augmented_covariance
from flowins.ins.mechanization import ProcessNoise
from flowins.measurements.flow import FlowCamera
from flowins.state import STATE, make_state

F64 = torch.float64


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--max-depth", type=float, default=float("inf"), help="oracle: only points nearer (m)")
    parser.add_argument("--noise", type=float, default=0.3, help="flow noise 1-σ (px)")
    parser.add_argument("--points", type=int, default=100)
    parser.add_argument("--min-parallax-sigma", type=float, default=0.0)
    parser.add_argument("--perfect-imu", action="store_true", help="no IMU errors")
    parser.add_argument("--selection", choices=("random", "parallax", "sigma", "grid"), default="random",
                        help="random: --points random pixels; else --points of a stride-4 grid chosen in the filter")
    parser.add_argument("--moving", action="store_true", help="keep pixels on moving objects")
    parser.add_argument("--gate", choices=("off", "hard"), default="off")
    parser.add_argument("--inflate", type=int, default=1, help="1: parallax noise inflation (default), 0: off")
    parser.add_argument("--floor", type=float, default=0.0, help="flow σ floor added in quadrature (px)")
    parser.add_argument("--iterations", type=int, default=1)
    parser.add_argument("--width", type=int, default=160, help="image width (height 3/4 of it)")
    parser.add_argument("--rate", type=float, default=10.0, help="flow frames per second")
    parser.add_argument("--duration", type=float, default=10.0)
    args = parser.parse_args()

    t0, t1 = 5.0, 5.0 + args.duration
    walk = Walk(WalkConfig(duration_s=t1 + 10.0))
    errors = ImuErrors(0, 0, 0, 0, 0, 0, 0) if args.perfect_imu else SimulationConfig().imu_errors
    t, acc, gyro, truth = simulate_imu(walk, SimulationConfig(duration_s=t1 + 10.0, imu_errors=errors), torch.Generator().manual_seed(0))
    keep = (t >= t0 - 1e-9) & (t <= t1 + 0.01)
    t, acc, gyro = t[keep], acc[keep], gyro[keep]
    cc = CameraConfig(width=args.width, height=args.width * 3 // 4)
    cam, T_ci = cc.intrinsics(), cc.imu_to_camera()
    city = build_city(walk, seed=0)
    camera = FlowCamera.from_calibration(cam, T_ci)
    times = torch.arange(math.ceil(float(t[0]) * args.rate) / args.rate, float(t[-1]), 1 / args.rate, dtype=F64)
    R, P = CameraTrajectory(walk, T_ci).pose(times)
    update = FlowUpdate(
        n_points=None if args.selection == "random" else args.points,
        selection="parallax" if args.selection == "random" else args.selection,
        min_parallax_sigma=args.min_parallax_sigma, parallax_inflation=args.inflate,
        sigma_floor_px=args.floor, gate=Gate(mode=args.gate), iterations=args.iterations,
    )
    gen = torch.Generator().manual_seed(5)
    empty = torch.zeros(0, 2, dtype=F64)
    events, previous = [], None
    for i, ti in enumerate(times.tolist()):
        frame = render(city, cam, R[i], P[i], ti)
        if previous is None:
            flow = uv1 = empty
        else:
            ft = exact_flow(city, cam, previous[0], previous[1], (R[i], P[i], ti), frame)
            usable = ft.valid & (ft.depth < args.max_depth) & (ft.static | args.moving)
            if args.selection == "random":
                ok = usable.nonzero()
                pick = ok[torch.randperm(ok.shape[0], generator=gen)[: args.points]]
            else:
                grid = torch.zeros_like(usable)
                grid[8:-8:8, 8:-8:8] = True
                pick = (usable & grid).nonzero()
            uv1 = torch.stack((pick[:, 1], pick[:, 0]), -1).to(F64)
            flow = ft.flow[pick[:, 0], pick[:, 1]].to(F64) + args.noise * torch.randn(pick.shape[0], 2, generator=gen, dtype=F64)
        sigma = torch.full_like(flow, max(args.noise, 0.1))
        events.append(FlowFrame(ti, FlowPoints(uv1, flow, sigma), camera, update))
        previous = (frame, (R[i], P[i], ti))

    x0 = make_state(p=walk.position(t[:1])[0], v=walk.velocity(t[:1])[0], q=walk.quaternion(t[:1])[0])
    sig = torch.cat((torch.full((3,), 0.01), torch.full((3,), 0.01), torch.full((4,), 1e-3),
                     torch.full((3,), 0.05), torch.full((3,), 0.01), torch.full((3,), 0.02))).to(F64)
    cov0 = augmented_covariance(torch.diag(sig**2), 1e-9)
    print(f"10 s walk, {'perfect' if args.perfect_imu else 'iPad-grade'} IMU, flow noise {args.noise} px, "
          f"{args.points} points/frame, max depth {args.max_depth} m, min parallax {args.min_parallax_sigma} σ")
    for label, ev in (("INS", []), ("INS + flow", events)):
        start = time.perf_counter()
        track = run_filter(t_s=t, acc_mps2=acc, gyro_rps=gyro, mean0=x0, cov0=cov0, noise=ProcessNoise(), events=ev)
        m = track.mean[-1]
        pos_err = float((m[STATE.p] - walk.position(track.t[-1:])[0]).norm())
        att_err = math.degrees(float(quat.angle_between(m[STATE.q], walk.quaternion(track.t[-1:])[0])))
        bw_err = float((m[STATE.b_w] - truth["b_w"][-1]).norm())
        sb = track.cov[-1][STATE.b_w, STATE.b_w].diagonal().sqrt()
        eb = m[STATE.b_w] - truth["b_w"][-1]
        print("  b_w error (mrad/s)", [round(1e3 * v, 3) for v in eb.tolist()], "filter 1-σ", [round(1e3 * v, 3) for v in sb.tolist()])
        sp = track.cov[-1][STATE.p, STATE.p].diagonal().sqrt()
        print("  p error (m)", [round(v, 3) for v in (m[STATE.p] - walk.position(track.t[-1:])[0]).tolist()], "filter 1-σ", [round(v, 3) for v in sp.tolist()])
        fl = [e for e in track.log if e.get("kind") == "flow"]
        if fl:
            print("  per frame: valid", sum(e["valid"] for e in fl) / len(fl), "behind", sum(e["behind"] for e in fl) / len(fl),
                  "degenerate", sum(e["degenerate"] for e in fl) / len(fl), "accepted", sum(e["accepted"] for e in fl) / len(fl))
        used = sum(e.get("valid", 0) for e in track.log if e.get("kind") == "flow")
        print(f"{label:<11} final position error {pos_err:8.3f} m, attitude {att_err:6.2f} deg, "
              f"gyro-bias error {1e3 * bw_err:6.2f} mrad/s, flow points used {used} ({time.perf_counter() - start:.1f} s)")


if __name__ == "__main__":
    main()
