"""How honest is the flow noise? Dense-flow accuracy vs its σ, and one flow update's claimed vs actual spread.

1. SpyNet (N_MC = 10) on simulator frame pairs with exact flow, at full size and at
   ``input_scale`` 0.5: EPE, median Monte Carlo σ, RMS of the error normalised by
   ``sqrt(σ² + floor²)`` (1 = calibrated), and ms per pair.
2. One flow update at a simulated frame (160x120, exact flow + Gaussian noise, random
   points, prior = truth + a draw from the prior covariance), repeated ``--trials``
   times: the position 1-σ the filter claims after the update against the spread of its
   errors, with and without the parallax noise inflation.

    python benchmarks/bench_flow_noise.py [--trials 200] [--noise 0.3] [--floor 0.25]
"""
from __future__ import annotations

import argparse
import time

import torch

from flowins.data.simulate.render import exact_flow, render
from flowins.data.simulate.scenario import CameraConfig, CameraTrajectory
from flowins.data.simulate.world import build_city
from flowins.data.synthetic import Walk, WalkConfig
from flowins.filter.ekf import ekf_update
from flowins.flow.pairs import run_provider
from flowins.flow.points import grid_candidates
from flowins.data.reference_flow import simulator_pair
from flowins.flow.spynet import SpyNetProvider
from flowins.measurements.flow import FlowCamera, epipolar_update, flow_measurements
from flowins.state import STATE, make_state, normalize_quaternions

F64 = torch.float64


def provider_noise(floor: float) -> None:
    provider = SpyNetProvider()
    print("SpyNet, N_MC = 10, simulator pairs (320x240, exact flow, static pixels)")
    print(f"{'pair':>12} {'scale':>5} {'EPE px':>7} {'median σ':>9} {'RMS err/σ_floored':>18} {'ms/pair':>8}")
    for t in (20.0, 40.0):
        pair = simulator_pair(t, t + 0.1)
        a, b = torch.from_numpy(pair.image1)[None], torch.from_numpy(pair.image2)[None]
        truth = torch.from_numpy(pair.flow).permute(2, 0, 1)
        mask = torch.from_numpy(pair.mask)
        for scale in (1.0, 0.5):
            run_provider(provider, a, b, scale)  # warm-up
            start = time.perf_counter()
            result = run_provider(provider, a, b, scale)
            flow, sigma = result.flow, result.sigma
            ms = (time.perf_counter() - start) * 1e3
            err = (flow[0] - truth).norm(dim=0)
            pts = grid_candidates(flow[0].double(), sigma[0].double())
            u, v = pts.uv1_px[:, 0].long(), pts.uv1_px[:, 1].long()
            ok = mask[v, u]
            e = flow[0][:, v, u].T.double() - truth[:, v, u].T.double()
            z = e[ok] / torch.sqrt(pts.sigma_px[ok] ** 2 + floor**2)
            print(f"{t:>5.1f}-{t + 0.1:<5.1f} {scale:>5.1f} {float(err[mask].mean()):>7.3f} "
                  f"{float(sigma[0].norm(dim=0)[mask].median()):>9.3f} {float(z.pow(2).mean().sqrt()):>18.2f} {ms:>8.0f}")


def update_consistency(trials: int, noise: float) -> None:
    walk = Walk(WalkConfig(duration_s=30.0))
    cc = CameraConfig(width=160, height=120)
    cam, T = cc.intrinsics(), cc.imu_to_camera()
    city = build_city(walk, seed=0)
    camera = FlowCamera.from_calibration(cam, T)
    tt = torch.tensor([10.0, 10.1], dtype=F64)
    R, P = CameraTrajectory(walk, T).pose(tt)
    r1, r2 = render(city, cam, R[0], P[0], 10.0), render(city, cam, R[1], P[1], 10.1)
    ft = exact_flow(city, cam, r1, (R[0], P[0], 10.0), (R[1], P[1], 10.1), r2)
    grid = torch.zeros_like(ft.valid)
    grid[4:-4:4, 4:-4:4] = True
    pick = (grid & ft.valid & ft.static).nonzero()
    gen = torch.Generator().manual_seed(3)
    pick = pick[torch.randperm(pick.shape[0], generator=gen)[:100]]
    uv = torch.stack((pick[:, 1], pick[:, 0]), -1).to(F64)
    flow = ft.flow[pick[:, 0], pick[:, 1]].to(F64)
    x = make_state(p=walk.position(tt[1:])[0], v=walk.velocity(tt[1:])[0], q=walk.quaternion(tt[1:])[0]).clone()
    x[STATE.p_prev], x[STATE.q_prev] = walk.position(tt[:1])[0], walk.quaternion(tt[:1])[0]
    sd = torch.zeros(26, dtype=F64)
    sd[STATE.p], sd[STATE.v], sd[STATE.q], sd[STATE.b_w], sd[STATE.b_a] = 0.01, 0.03, 5e-4, 1e-3, 0.02
    sd[STATE.p_prev], sd[STATE.q_prev] = 1e-4, 1e-5
    P0 = torch.diag(sd**2)
    print(f"\nOne flow update, 160x120 frame at t = 10 s, 100 random static points, {noise} px noise, "
          f"prior position 1-σ 1 cm, {trials} trials")
    print(f"{'inflation':>9}  position 1-σ the filter claims (x, y, z) mm   measured spread of its errors (x, y, z) mm")
    for inflate in (False, True):
        g = torch.Generator().manual_seed(7)
        errors, covs = [], []
        for _ in range(trials):
            x0 = normalize_quaternions(x + sd * torch.randn(26, generator=g, dtype=F64))
            noisy = flow + noise * torch.randn(flow.shape, generator=g, dtype=F64)
            m = flow_measurements(x0, noisy, uv, camera)
            upd = epipolar_update(m, torch.full_like(noisy, noise), parallax_inflation=inflate)
            r = ekf_update(x0, P0, innovation=upd.innovation, H=upd.H, noise_cov=upd.noise_cov)
            errors.append(r.mean - x)
            covs.append(r.cov)
        E, C = torch.stack(errors)[:, STATE.p], torch.stack(covs).mean(0)[STATE.p, STATE.p]
        claimed = " ".join(f"{1e3 * v:5.1f}" for v in C.diagonal().sqrt().tolist())
        actual = " ".join(f"{1e3 * v:5.1f}" for v in E.std(0).tolist())
        print(f"{'on' if inflate else 'off':>9}  {claimed:>38}   {actual:>38}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--noise", type=float, default=0.3)
    parser.add_argument("--floor", type=float, default=0.25)
    args = parser.parse_args()
    provider_noise(args.floor)
    update_consistency(args.trials, args.noise)


if __name__ == "__main__":
    main()
