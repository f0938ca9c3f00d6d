"""The multi-view track update on a drone-like simulated recording, by window size.

A 30 s flight (``--duration``): 3 s on the ground (a still start), a 3 s take-off ramp,
then a figure-eight at 2 m height and about 1.5 m/s with yaw and tilt oscillations. An
industrial IMU (ADIS16448 densities, turn-on biases) at 200 Hz, a 752x480 camera at 20 Hz
looking forward and 30° down, exact tracks of random landmarks around the flight with
0.3 px noise (``flowins.data.simulate.tracks``). Every row runs the filter with the same
data, started still, and prints the RMSE after Procrustes alignment (filter / smoother),
the filter's ratio to the smoother and its time per camera frame, against the paper's
two-view update of the same tracks (``two-view``, consecutive frames, σ the same) measured
in the same process::

    python benchmarks/bench_tracks.py [--windows 1 5 10 20] [--duration 30] [--seed 0] [--min-parallax 0.02]
                                      [--heading-transport on|off]
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import time

import torch
from torch.func import jacfwd

from flowins.data.simulate.tracks import landmark_tracks, scatter_landmarks
from flowins.data.streams import ImuStream
from flowins.data.synthetic import ImuErrors, _smoothstep, _smoothstep_integral, corrupt_imu, increment_imu
from flowins.evaluation.metrics import trajectory_errors
from flowins.flow.pairs import track_pairs
from flowins.geometry import quaternion as quat
from flowins.ins.initialization import InitialUncertainty
from flowins.ins.mechanization import ProcessNoise
from flowins.measurements.flow import FlowCamera, camera_pose
from flowins.measurements.flow_update import FlowUpdate
from flowins.measurements.tracks import TrackUpdate
from flowins.navigation import NavigationConfig, NavigationRun, navigate
from flowins.start import StartSettings
from flowins.state import STATE

F64 = torch.float64


class Flight:
    """Closed-form pose of the flight (see the module doc), batched over times."""

    def __init__(self, still_s: float = 3.0, ramp_s: float = 3.0, radius_m: float = 4.0, height_m: float = 2.0,
                 speed_mps: float = 1.5) -> None:
        self.still_s, self.ramp_s, self.radius_m, self.height_m = still_s, ramp_s, radius_m, height_m
        self.rate = speed_mps / radius_m  # rad/s of the figure-eight's phase

    def _activity(self, t):
        return _smoothstep((t - self.still_s) / self.ramp_s)

    def position(self, t):
        s = self.rate * self.ramp_s * _smoothstep_integral((t - self.still_s) / self.ramp_s)
        x = self.radius_m * torch.sin(s)
        y = self.radius_m * torch.sin(s) * torch.cos(s)
        z = self._activity(t) * (self.height_m + 0.3 * torch.sin(0.7 * s))
        return torch.stack((x, y, z), -1)

    def quaternion(self, t):
        a = self._activity(t)
        roll = 0.08 * a * torch.sin(0.9 * t)
        pitch = 0.06 * a * torch.sin(1.3 * t + 0.4)
        yaw = 0.5 * a * torch.sin(0.25 * (t - self.still_s))
        return quat.from_euler(roll, pitch, yaw)

    def velocity(self, t):
        return torch.vmap(jacfwd(self.position))(t.reshape(-1)).reshape(*t.shape, 3)

    def imu(self, t, gravity_mps2):
        from flowins.data.synthetic import body_readings

        return body_readings(lambda s: quat.to_matrix(self.quaternion(s)), jacfwd(self.position), t, gravity_mps2)


def camera() -> FlowCamera:
    K = torch.tensor([[458.0, 0.0, 367.0], [0.0, 457.0, 248.0], [0.0, 0.0, 1.0]], dtype=F64)
    forward = torch.tensor([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], dtype=F64)  # x_c = -y_b, ...
    tilt = math.radians(30.0)  # about the camera's x axis: the optical axis 30° down
    c, s = math.cos(tilt), math.sin(tilt)
    down = torch.tensor([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]], dtype=F64)
    return FlowCamera(K, down @ forward, torch.tensor([0.05, 0.0, -0.02], dtype=F64))


def recording(duration_s: float, seed: int):
    g = torch.Generator().manual_seed(seed)
    flight = Flight()
    t_imu = torch.arange(0, int(duration_s * 200) + 1, dtype=F64) / 200.0
    f_true, w_true = increment_imu(flight, t_imu)
    errors = ImuErrors(acc_noise=2.0e-3, gyro_noise=1.7e-4, acc_bias_std=0.02, gyro_bias_std=2e-3,
                       acc_bias_walk=3e-3, gyro_bias_walk=1.9e-5, acc_scale_std=0.002)
    acc, gyro, _ = corrupt_imu(t_imu, f_true, w_true, errors, g)
    cam = camera()
    t_cam = torch.arange(0, int(duration_s * 20) + 1, dtype=F64) / 20.0
    R_wc, c_w = camera_pose(flight.quaternion(t_cam), flight.position(t_cam), cam)
    ahead = c_w + 5.0 * R_wc[:, :, 2]
    landmarks = scatter_landmarks(ahead, 500, radius_m=5.0, height_m=(0.0, 5.0), generator=g)
    tracks = landmark_tracks(t_cam, R_wc, c_w, cam.K, (480, 752), landmarks, noise_px=0.3, generator=g)
    return flight, ImuStream(t_imu, acc, gyro, name="simulated ADIS16448"), tracks, cam, len(t_cam)


def score(result, flight) -> tuple[float, float]:
    out = []
    for track in (result.filter, result.smoother):
        t = track.t
        truth = flight.position(t)
        out.append(trajectory_errors(t, track.mean[:, STATE.p], t, truth).rmse_m)
    return out[0], out[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--windows", type=int, nargs="+", default=[1, 5, 10, 20])
    parser.add_argument("--duration", type=float, default=30.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sigma", type=float, default=0.3, help="the tracks' pixel σ the filter uses")
    parser.add_argument("--min-parallax", type=float, default=TrackUpdate.min_parallax_rad,
                        help="filter.tracks.min_parallax_rad (rad; default: the filter's)")
    parser.add_argument("--heading-transport", choices=("on", "off"),
                        default="on" if TrackUpdate.heading_transport else "off",
                        help="filter.tracks.heading_transport (default: the filter's)")
    args = parser.parse_args()
    flight, imu, tracks, cam, frames = recording(args.duration, args.seed)
    per_frame = torch.unique_consecutive(tracks.t_s, return_counts=True)[1].double().mean()
    print(f"flight: {args.duration:.0f} s, {len(imu)} IMU samples (200 Hz), {frames} frames (20 Hz, 752x480), "
          f"{int(torch.unique(tracks.track_id).numel())} tracks, {float(per_frame):.0f} seen per frame, 0.3 px noise")
    base = NavigationConfig(
        noise=ProcessNoise(acc_noise=2.0e-3, gyro_noise=1.7e-4, acc_bias_walk=3e-3, gyro_bias_walk=1.9e-5),
        initial=InitialUncertainty(yaw_rad=0.01, acc_bias_mps2=0.05, gyro_bias_rps=3e-3),
        start=StartSettings(mode="still"))
    rows = []

    def run(label: str, config: NavigationConfig, nav: NavigationRun) -> None:
        navigate(nav, config=config)  # warm-up: caches and first calls
        t0 = time.perf_counter()
        result = navigate(nav, config=config)
        seconds = time.perf_counter() - t0
        f, s = score(result, flight)
        rows.append((label, f, s, 1e3 * seconds / frames))

    pairs = track_pairs(tracks, sigma_px=args.sigma)
    two_view = FlowUpdate(sigma_floor_px=0.0)
    run("two-view", dataclasses.replace(base, flow_update=two_view),
        NavigationRun(imu, flow=pairs, camera=cam))
    for window in args.windows:
        update = TrackUpdate(window=window, sigma_px=args.sigma, min_parallax_rad=args.min_parallax,
                             heading_transport=args.heading_transport == "on")
        run(f"N = {window}", dataclasses.replace(base, tracks=update),
            NavigationRun(imu, tracks=tracks, camera=cam))
    reference = rows[0][3]
    print(f"{'update':10s} {'filter RMSE':>12s} {'smoother RMSE':>14s} {'filter/smoother':>16s} {'ms/frame':>9s} "
          f"{'x two-view':>11s}")
    for label, f, s, ms in rows:
        print(f"{label:10s} {f:10.3f} m {s:12.3f} m {f / s:16.2f} {ms:9.2f} {ms / reference:11.2f}")
    print("RESULT " + " ".join(f"{label.replace(' ', '')}:{f:.3f}/{s:.3f}m,{ms:.1f}ms" for label, f, s, ms in rows))


if __name__ == "__main__":
    main()
