"""The simulated "snowy city block" walk: configuration, generation, caching.

:func:`simulate` writes a sequence in the flowins folder format (see
``docs/sequence_format.md``) plus the exact optical flow and depth of every
consecutive frame pair (``flow/NNNNNN.npz``), and returns it as a
:class:`~flowins.data.sequence.Sequence`. A folder that already holds the same
simulation is read back instead of regenerated: the folder's key
(:meth:`SimulationConfig.key`) covers the configuration, the simulator's source code and
the numeric libraries' versions, and its completion marker lists every file written with
its size and modification time, so a folder whose files were changed afterwards is not
served as the simulation (in the cache it is simulated again; a folder the caller named
is refused unless ``overwrite``).

World frame: local ENU (x east, y north, z up) with its origin on the ground at
the start of the walk; ``config.origin`` is the WGS84 point of that origin, and
the GNSS fixes are written as latitude/longitude/altitude around it. The ground
truth is the IMU (body) pose in this frame: body x forward, y left, z up.
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from flowins.progress import progress as track_progress
from flowins.cache import cache_root, content_key, folder_lock, library_versions, source_digest
from flowins.data.sequence import CameraFrames, PinholeCamera, Sequence
from flowins.data.simulate.gnss import GnssErrors, simulate_fixes
from flowins.data.simulate.tracks import RenderedTracker, TrackConfig
from flowins.data.streams import GnssStream, ImuStream, PoseStream
from flowins.data.synthetic import (
    ImuErrors,
    Vibration,
    Walk,
    WalkConfig,
    corrupt_imu,
    increment_imu,
    sample_times,
    vibrate,
)
from flowins.geometry import quaternion as quat
from flowins.geometry.camera import RigidTransform
from flowins.geometry.geodesy import LocalTangentPlane
from flowins.constants import STANDARD_GRAVITY_MPS2

#: the code that generates a simulation: part of its key
SIMULATOR_CODE = ("flowins.data", "flowins.geometry", "flowins.ins.mechanization", "flowins.constants")
#: added to the seed for the tracks' generator
_TRACKS_SEED = 7_919_000
#: the completion marker: the key and every file written, with its size and modification time
MARKER = ".simulation-complete"

#: Camera axes in the body frame for a device held upright, looking forward:
#: camera x (right) = -body y, camera y (down) = -body z, camera z (forward) = body x.
_BODY_FROM_CAMERA = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)


@dataclass(frozen=True)
class CameraConfig:
    rate_hz: float = 10.0
    width: int = 320
    height: int = 240
    horizontal_fov_deg: float = 62.0
    #: small mounting rotation of the camera relative to the IMU (roll, pitch, yaw), deg
    misalignment_deg: tuple[float, float, float] = (0.8, -1.2, 0.5)
    #: camera centre in the IMU frame, m
    lever_arm_m: tuple[float, float, float] = (0.03, -0.02, 0.01)
    motion_blur: bool = False
    exposure_changes: bool = False

    def intrinsics(self) -> PinholeCamera:
        f = 0.5 * self.width / math.tan(math.radians(0.5 * self.horizontal_fov_deg))
        return PinholeCamera(self.width, self.height, f, f, 0.5 * (self.width - 1), 0.5 * (self.height - 1))

    def imu_to_camera(self) -> RigidTransform:
        """``T_ci``: ``x_cam = R_ci x_imu + t_ci``."""
        roll, pitch, yaw = (torch.tensor(math.radians(a), dtype=torch.float64) for a in self.misalignment_deg)
        R_mis = quat.to_matrix(quat.from_euler(roll, pitch, yaw))
        R_bc = R_mis @ _BODY_FROM_CAMERA
        R_ci = R_bc.T
        t_ci = -R_ci @ torch.tensor(self.lever_arm_m, dtype=torch.float64)
        return RigidTransform(quat.from_matrix(R_ci), t_ci)


@dataclass(frozen=True)
class SimulationConfig:
    duration_s: float = 300.0
    seed: int = 0
    imu_rate_hz: float = 100.0
    imu_jitter: float = 0.1
    imu_errors: ImuErrors = field(default_factory=lambda: ImuErrors(acc_scale_std=0.015))
    #: shaking of the IMU (rotor-like vibration on the ground: ``Vibration(0.5, 0.04, until_s=5.0)``)
    vibration: Vibration = field(default_factory=Vibration)
    camera: CameraConfig = field(default_factory=CameraConfig)
    gnss: GnssErrors = field(default_factory=GnssErrors)
    groundtruth_rate_hz: float = 60.0
    origin: tuple[float, float, float] = (60.1699, 24.9384, 20.0)  # Helsinki centre, ellipsoidal height
    #: write the exact flow of every n-th consecutive frame pair (0: none)
    flow_every: int = 1
    #: ``tracks.csv``: static scene points followed through the frames (``count=0``: none)
    tracks: TrackConfig = field(default_factory=TrackConfig)
    gravity_mps2: float = STANDARD_GRAVITY_MPS2
    #: the city's moving cars and pedestrians (False: none, the rest of the city the same)
    movers: bool = True

    def __post_init__(self) -> None:
        if self.duration_s < 10.0:
            raise ValueError(f"SimulationConfig.duration_s={self.duration_s}; expected >= 10 s (5 s of it stationary)")
        if self.flow_every < 0:
            raise ValueError(f"SimulationConfig.flow_every={self.flow_every}; expected >= 0")

    def as_plain(self) -> dict[str, Any]:
        """The configuration as JSON-ready dicts, lists, numbers and strings."""
        return json.loads(json.dumps(asdict(self), default=str))

    def key(self) -> str:
        """Content key of the simulation: the configuration, the simulator's source code
        (:data:`SIMULATOR_CODE`) and the numeric libraries' versions."""
        return content_key({"config": self.as_plain(),
                            "code": source_digest(*SIMULATOR_CODE), "libraries": library_versions()})


def default_cache_dir(config: SimulationConfig) -> Path:
    """``$FLOWINS_CACHE/simulated/<key>`` (default cache root ``~/.cache/flowins``)."""
    return cache_root() / "simulated" / config.key()


@dataclass(frozen=True)
class CameraTrajectory:
    """Camera poses of the simulation: ``R_wc`` maps camera vectors to world, ``p_wc`` the centre."""

    walk: Walk
    imu_to_camera: RigidTransform

    def pose(self, t_s: Tensor) -> tuple[Tensor, Tensor]:
        R_wb = self.walk.rotation(t_s)
        p_wb = self.walk.position(t_s)
        T_bc = self.imu_to_camera.inverse()  # camera -> body
        R_bc = T_bc.rotation_matrix
        return R_wb @ R_bc, p_wb + (R_wb @ T_bc.translation_m.unsqueeze(-1)).squeeze(-1)


def _manifest(folder: Path) -> dict[str, list[int]]:
    """Every file below ``folder`` but the marker: relative path -> ``[size, mtime_ns]``."""
    files = (f for f in sorted(folder.rglob("*")) if f.is_file() and f.name != MARKER)
    return {f.relative_to(folder).as_posix(): [(st := f.stat()).st_size, st.st_mtime_ns] for f in files}


def _holds(folder: Path, key: str) -> str | None:
    """``None`` when ``folder`` holds the simulation ``key`` exactly as written, else why not."""
    marker = folder / MARKER
    if not marker.is_file():
        return "no completed simulation"
    try:
        written = json.loads(marker.read_text())
        written_key, files = written["key"], written["files"]
    except (ValueError, KeyError, TypeError):
        return f"an unreadable marker {marker}"
    if written_key != key:
        return f"another simulation (key {written_key})"
    now = _manifest(folder)
    changed = sorted(set(files) ^ set(now) | {f for f in set(files) & set(now) if files[f] != now[f]})
    if changed:
        more = f" and {len(changed) - 3} more" if len(changed) > 3 else ""
        return f"this simulation with files changed since it was written ({', '.join(changed[:3])}{more})"
    return None


def open_simulation(out: Path, key: str, *, overwrite: bool, in_cache: bool) -> Sequence | None:
    """The sequence in ``out`` when it holds simulation ``key`` as written; else ``None``,
    with ``out`` created empty (a folder holding something else is cleared when it is in
    the cache or ``overwrite`` is set, else refused)."""
    from flowins.data.folder import read_folder

    why = _holds(out, key) if out.exists() else None
    if out.exists() and why is None:
        return read_folder(out)
    if out.exists() and any(out.iterdir()):
        if not (overwrite or in_cache):
            raise ValueError(
                f"simulate: {out} is not empty and does not hold this simulation (key {key}): it holds {why}; "
                "pass overwrite=True (--overwrite) or choose another folder"
            )
        if in_cache:
            print(f"simulate: the cache folder {out} holds {why}; simulating again")
        import shutil

        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    return None


def seal_simulation(out: Path, key: str) -> Sequence:
    """Write the completion marker of simulation ``key`` in ``out`` and read the folder back."""
    from flowins.data.folder import read_folder

    (out / MARKER).write_text(json.dumps({"key": key, "files": _manifest(out)}))
    return read_folder(out)


def simulate(
    out: str | Path | None = None,
    config: SimulationConfig = SimulationConfig(),
    *,
    overwrite: bool = False,
    progress: bool = True,
) -> Sequence:
    """Generate (or read back from the cache) the simulated walk; see the module docstring.

    Args:
        out: folder to write; default :func:`default_cache_dir`.
        overwrite: replace a folder holding a different simulation (or other files).

    Processes that simulate into one folder at once take turns (:func:`~flowins.cache.folder_lock`).
    """
    in_cache = out is None
    out = Path(out) if out is not None else default_cache_dir(config)
    key = config.key()
    with folder_lock(out):
        held = open_simulation(out, key, overwrite=overwrite, in_cache=in_cache)
        return held if held is not None else _simulate(out, config, key, progress=progress)


def _simulate(out: Path, config: SimulationConfig, key: str, *, progress: bool) -> Sequence:
    """Simulate the walk of ``config`` into the empty folder ``out`` and seal it as ``key``."""
    from flowins.data.folder import write_folder

    gen = torch.Generator().manual_seed(config.seed)
    walk = Walk(WalkConfig(duration_s=config.duration_s))
    t_imu, acc, gyro, imu_truth = simulate_imu(walk, config, gen)
    t_end = float(t_imu[-1])

    # the world and the camera
    from flowins.data.simulate.world import CityConfig, build_city

    city = build_city(walk, seed=config.seed, config=CityConfig(movers=config.movers))
    camera = config.camera.intrinsics()
    imu_to_camera = config.camera.imu_to_camera()
    trajectory = CameraTrajectory(walk, imu_to_camera)

    # GNSS
    t_gnss = torch.arange(1.0 / config.gnss.rate_hz, t_end, 1.0 / config.gnss.rate_hz, dtype=torch.float64)
    true_enu = walk.position(t_gnss)
    enu, h_acc, v_acc, multipath = simulate_fixes(true_enu, city_canyon(city, true_enu), config.gnss, gen)
    lat, lon, alt = LocalTangentPlane(*config.origin).to_geodetic(enu)

    # ground truth, as a visual-inertial reference would report it (poses at 60 Hz)
    t_gt = torch.arange(0.0, t_end, 1.0 / config.groundtruth_rate_hz, dtype=torch.float64)

    # frames and exact flow
    t_frames = torch.arange(0.0, t_end, 1.0 / config.camera.rate_hz, dtype=torch.float64)
    # the tracks draw from their own generator: the IMU, GNSS and images do not depend on them
    tracker = RenderedTracker(camera, config.tracks, torch.Generator().manual_seed(_TRACKS_SEED + config.seed))
    files = _render_frames(city, camera, trajectory, t_frames, t_end, config, out, tracker, progress=progress)

    metadata = _metadata(config, key, imu_truth, multipath)
    sequence = Sequence(
        ImuStream(t_imu, acc, gyro, name="simulated IMU"),
        name=metadata["name"],
        camera=camera,
        imu_to_camera=imu_to_camera,
        frames=CameraFrames(t_frames, files=tuple(files), name="simulated frames"),
        tracks=tracker.tracks() if config.tracks.count else None,
        gnss=GnssStream(t_gnss, lat, lon, alt, h_acc, v_acc, name="simulated GNSS"),
        groundtruth=PoseStream(t_gt, walk.position(t_gt), walk.quaternion(t_gt), name="simulated ground truth"),
        metadata=metadata,
    )
    write_folder(sequence, out, overwrite=True, copy_frames=False)
    _write_truth(out, t_gnss, true_enu, multipath, t_imu, imu_truth)
    return seal_simulation(out, key)


def _render_frames(city: Any, camera: Any, trajectory: CameraTrajectory, t_frames: Tensor, t_end: float,
                   config: SimulationConfig, out: Path, tracker: RenderedTracker, *, progress: bool) -> list[Path]:
    """Render every frame into ``out/frames`` (and, every ``config.flow_every`` frames, the
    exact flow to the next into ``out/flow``), and give each to ``tracker``; the image files, in
    order. ``t_end``: the last IMU time, where a motion-blurred exposure's sub-frame poses are clamped."""
    from flowins.data.simulate.render import exact_flow, render

    frame_dir = out / "frames"
    frame_dir.mkdir(exist_ok=True)
    flow_dir = out / "flow"
    if config.flow_every:
        flow_dir.mkdir(exist_ok=True)
    R_all, p_all = trajectory.pose(t_frames)
    files = []
    previous = None
    import cv2

    for i in track_progress(range(t_frames.shape[0]), description="simulate frames", unit="frame", enabled=progress):
        t = float(t_frames[i])
        pose = (R_all[i], p_all[i], t)
        blur = ()
        if config.camera.motion_blur:  # a 20 ms exposure: the image averages sub-frame poses
            t_sub = torch.tensor([t - 0.01, t - 0.005, t + 0.005, t + 0.01], dtype=torch.float64).clamp(0.0, t_end)
            R_sub, p_sub = trajectory.pose(t_sub)
            blur = tuple((R_sub[j], p_sub[j], float(t_sub[j])) for j in range(4))
        frame = render(city, camera, R_all[i], p_all[i], t, exposure=exposure_gain(config.camera, t), motion_blur=blur)
        if config.tracks.count:
            tracker.add(t, frame.depth, frame.object_id, frame.point, R_all[i], p_all[i])
        image = frame.image.numpy()
        path = frame_dir / f"{i:06d}.png"
        cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        files.append(path)
        if previous is not None and config.flow_every and (i - 1) % config.flow_every == 0:
            prev_frame, prev_pose = previous
            truth = exact_flow(city, camera, prev_frame, prev_pose, pose, frame)
            np.savez_compressed(
                flow_dir / f"{i - 1:06d}.npz",
                flow=truth.flow.numpy().astype(np.float32),
                depth=truth.depth.numpy().astype(np.float32),
                valid=truth.valid.numpy(),
                static=truth.static.numpy(),
                sky=truth.sky.numpy(),
                t0=float(t_frames[i - 1]),
                t1=t,
            )
        previous = (frame, pose)
    return files


def _metadata(config: SimulationConfig, key: str, imu_truth: dict[str, Tensor], multipath: Tensor) -> dict[str, Any]:
    """The simulation's ``metadata.yaml``: its settings, frames, IMU and GNSS truths, name."""
    return {
        "source": "flowins simulator",
        "imu": "simulated_walk",  # the IMU preset (configs/imu) the filter uses on it by default
        "simulation": {"key": key, "config": config.as_plain()},
        "world_frame": "local ENU (x east, y north, z up); origin on the ground at the start of the walk",
        "gnss_origin_lat_lon_alt": list(config.origin),
        "imu_truth": {
            "acc_bias_turn_on_mps2": imu_truth["b_a"][0].tolist(),
            "gyro_bias_turn_on_rps": imu_truth["b_w"][0].tolist(),
            "acc_scale_correction_T_a": imu_truth["T_a"].tolist(),
            "note": "acc = f / T_a + b_a + noise, gyro = w + b_w + noise; bias random walks in truth/imu_errors.csv",
        },
        "gnss_truth": {"multipath_fixes": int(multipath.sum()), "fixes": int(multipath.numel())},
        "flow": (
            "flow/NNNNNN.npz: exact flow (H, W, 2) px from frame NNNNNN to the next, depth (H, W) m of frame "
            "NNNNNN (camera z, inf for sky), valid (non-occluded hit inside frame 2), static (not a moving object), "
            "sky (rotation-only flow of points at infinity)"
            if config.flow_every
            else "not written"
        ),
        "tracks": (f"tracks.csv: static scene points followed while seen ({config.tracks.count} per frame, "
                   f"{config.tracks.noise_px} px noise)" if config.tracks.count else "not written"),
        "name": f"simulated city walk (seed {config.seed})",  # the folder's name is the cache key
    }


def _write_truth(out: Path, t_gnss: Tensor, true_enu: Tensor, multipath: Tensor, t_imu: Tensor,
                 imu_truth: dict[str, Tensor]) -> None:
    """``out/truth``: the fixes' true positions and multipath flags, the IMU's true biases."""
    truth_dir = out / "truth"
    truth_dir.mkdir(exist_ok=True)
    np.savetxt(
        truth_dir / "gnss.csv",
        torch.cat((t_gnss.unsqueeze(-1), true_enu, multipath.unsqueeze(-1).double()), -1).numpy(),
        delimiter=",", header="t,e,n,u,multipath", comments="", fmt="%.17g",
    )
    np.savetxt(
        truth_dir / "imu_errors.csv",
        torch.cat((t_imu.unsqueeze(-1), imu_truth["b_a"], imu_truth["b_w"]), -1).numpy(),
        delimiter=",", header="t,bax,bay,baz,bwx,bwy,bwz", comments="", fmt="%.17g",
    )


def exposure_gain(camera: CameraConfig, t_s: float) -> float:
    """Auto-exposure drift of the camera (1 when ``exposure_changes`` is off)."""
    if not camera.exposure_changes:
        return 1.0
    return 1.0 + 0.15 * math.sin(2 * math.pi * t_s / 23.0) + 0.05 * math.sin(2 * math.pi * t_s / 7.0)


def simulate_imu(
    walk: Walk, config: SimulationConfig, generator: torch.Generator
) -> tuple[Tensor, Tensor, Tensor, dict[str, Tensor]]:
    """``(t_s (N,), acc_mps2 (N, 3), gyro_rps (N, 3), truth)`` of the walk's IMU.

    Sample times are jittered by ``config.imu_jitter`` (relative); each sample is
    the ideal reading of an integrating IMU over the interval it ends
    (:func:`flowins.data.synthetic.increment_imu`: the constant rate and specific
    force that reproduce the true attitude and velocity increments), corrupted by
    ``config.imu_errors`` (:func:`flowins.data.synthetic.corrupt_imu`) and shaken by
    ``config.vibration`` (:func:`flowins.data.synthetic.vibrate`); ``truth``
    holds the true bias trajectories and scale.
    """
    t = sample_times(config.duration_s, config.imu_rate_hz, config.imu_jitter, generator)
    f_true, w_true = increment_imu(walk, t, config.gravity_mps2)
    acc, gyro, truth = corrupt_imu(t, f_true, w_true, config.imu_errors, generator)
    acc, gyro = vibrate(t, acc, gyro, config.vibration, generator)
    return t, acc, gyro, truth


def city_canyon(city: Any, positions_m: Tensor) -> Tensor:
    """How enclosed each position ``(G, 3)`` is, in [0, 1]: the mean building
    elevation angle seen from the receiver over eight azimuths, relative to 60°."""
    return city.canyon(positions_m)
