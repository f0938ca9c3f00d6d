"""One data model for every recording flowins reads: :class:`Sequence`.

A sequence holds, with timestamps in seconds on one clock:

* ``imu``: :class:`~flowins.data.streams.ImuStream` (always present);
* ``camera`` (:class:`PinholeCamera`), ``imu_to_camera``
  (:class:`~flowins.geometry.camera.RigidTransform`, ``x_cam = R x_imu + t``) and
  ``frames`` (:class:`CameraFrames`, lazily loaded images from files or a video);
* ``tracks``: optional precomputed sparse tracks (:class:`Tracks`);
* ``gnss``: optional :class:`~flowins.data.streams.GnssStream`;
* ``groundtruth``: optional :class:`~flowins.data.streams.PoseStream` of the IMU
  (body) pose in some world frame (orientation may be missing);
* ``metadata``: free-form facts about the recording (device, simulator settings).

Every part validates itself when built and raises a ``ValueError`` naming the
file (or stream), the row and what was expected. Readers for the formats live
beside this module (``folder``, ``euroc``, ``advio``); they all return a
:class:`Sequence`.
"""
from __future__ import annotations

import math
from collections.abc import Iterator
import dataclasses
from dataclasses import KW_ONLY, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from flowins.data.streams import (
    GnssStream,
    ImuStream,
    PoseStream,
    as_float64,
    _check_finite,
    _set,
)
from flowins.geometry.camera import RigidTransform

SOURCES = ("imu", "frames", "tracks", "gnss", "groundtruth")


#: how far (px) a track point may lie beyond the image's edge pixels (sub-pixel trackers overshoot)
TRACK_MARGIN_PX = 2.0
#: how far (s) a track time may be from a frame time
FRAME_TIME_TOLERANCE_S = 1e-4
#: the fields of view (degrees, along each image axis) a camera's intrinsics may give
MIN_FOV_DEG, MAX_FOV_DEG = 10.0, 179.0


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics of an image of ``width x height`` pixels (OpenCV conventions).

    ``distortion``: radial-tangential ``(k1, k2, p1, p2[, k3])`` of the raw images,
    or ``()`` when they are undistorted (or the lens is ideal).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = ()
    _: KW_ONLY
    name: str = "camera"

    def __post_init__(self) -> None:
        for key in ("width", "height"):
            value = getattr(self, key)
            if int(value) != value or value <= 0:
                raise ValueError(f"{self.name}: {key}={value!r}; expected a positive integer number of pixels")
            object.__setattr__(self, key, int(value))
        for key in ("fx", "fy", "cx", "cy"):
            value = float(getattr(self, key))
            if not math.isfinite(value):
                raise ValueError(f"{self.name}: {key}={value!r}; expected a finite number of pixels")
            object.__setattr__(self, key, value)
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"{self.name}: focal lengths fx={self.fx}, fy={self.fy}; expected > 0 pixels")
        for key, focal, extent, axis in (("fx", self.fx, self.width, "width"), ("fy", self.fy, self.height, "height")):
            fov = math.degrees(2.0 * math.atan(0.5 * extent / focal))
            if not MIN_FOV_DEG <= fov <= MAX_FOV_DEG:
                raise ValueError(
                    f"{self.name}: {key}={focal:g} px over an image {axis} of {extent} px is a {fov:.1f}° field of "
                    f"view; expected {MIN_FOV_DEG:g}° to {MAX_FOV_DEG:g}° (focal length in pixels of this image size?)"
                )
        for key, centre, extent, axis in (("cx", self.cx, self.width, "width"), ("cy", self.cy, self.height, "height")):
            if not -0.5 <= centre <= extent - 0.5:
                raise ValueError(
                    f"{self.name}: principal point {key}={centre:g} px is outside the image ({axis} {extent} px: "
                    f"expected -0.5 to {extent - 0.5:g}); are the intrinsics for this image size?"
                )
        distortion = tuple(float(c) for c in self.distortion)
        if len(distortion) not in (0, 4, 5) or not all(math.isfinite(c) for c in distortion):
            raise ValueError(
                f"{self.name}: distortion={self.distortion!r}; expected () or finite (k1, k2, p1, p2[, k3])"
            )
        object.__setattr__(self, "distortion", distortion)

    @property
    def K(self) -> Tensor:
        """``(3, 3)`` intrinsic matrix, float64."""
        return torch.tensor([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=torch.float64)

    @property
    def size(self) -> tuple[int, int]:
        """``(height, width)``, the shape of an image."""
        return self.height, self.width


@dataclass(frozen=True, eq=False)
class CameraFrames:
    """Frame timestamps and lazily loaded images: a list of files or one video.

    Exactly one of ``files`` (one image per frame) and ``video`` (with ``indices``,
    the 0-based frame number in the video of each timestamp) is given.
    ``read(i)`` returns frame ``i`` as a ``(H, W, 3)`` uint8 RGB tensor (gray images
    are replicated to three channels); ``expected_size`` (``(H, W)``, usually the
    calibration's) is checked on every read.
    """

    t_s: Tensor
    files: tuple[Path, ...] | None = None
    video: Path | None = None
    indices: Tensor | None = None
    _: KW_ONLY
    name: str = "frames"
    expected_size: tuple[int, int] | None = None
    check_files: bool = True

    def __post_init__(self) -> None:
        name = str(self.name)
        t_s = as_float64(self.t_s, stream=name, array="t")
        if t_s.ndim != 1 or t_s.shape[0] == 0:
            raise ValueError(f"{name}: frame timestamps have shape {tuple(t_s.shape)}; expected (N,) with N >= 1")
        _check_finite(t_s, stream=name, array="t")
        steps = t_s[1:] - t_s[:-1]
        bad = torch.nonzero(steps <= 0)
        if bad.numel():
            k = int(bad[0, 0]) + 1
            raise ValueError(
                f"{name}: row {k} (0-based): frame time {float(t_s[k])!r} s is not after the previous "
                f"{float(t_s[k - 1])!r} s; expected strictly increasing frame times"
            )
        if (self.files is None) == (self.video is None):
            raise ValueError(f"{name}: give either files (one per frame) or a video with indices, not both or neither")
        files, video, indices = self.files, self.video, self.indices
        if files is not None:
            files = tuple(Path(f) for f in files)
            if len(files) != t_s.shape[0]:
                raise ValueError(f"{name}: {len(files)} image files for {t_s.shape[0]} timestamps; expected one per frame")
            if self.check_files:
                for k, f in enumerate(files):
                    if not f.is_file():
                        raise ValueError(f"{name}: row {k} (0-based): image file {f} does not exist")
        else:
            video = Path(video)
            if self.check_files and not video.is_file():
                raise ValueError(f"{name}: video file {video} does not exist")
            if indices is None:
                indices = torch.arange(t_s.shape[0])
            indices = torch.as_tensor(indices, dtype=torch.int64)
            if indices.shape != t_s.shape:
                raise ValueError(f"{name}: {indices.shape[0]} video indices for {t_s.shape[0]} timestamps")
            bad = torch.nonzero(indices < 0)
            if bad.numel():
                raise ValueError(f"{name}: row {int(bad[0, 0])} (0-based): negative video frame index")
        _set(self, t_s=t_s, files=files, video=video, indices=indices, name=name)
        object.__setattr__(self, "_capture", None)

    def __len__(self) -> int:
        return self.t_s.shape[0]

    def source(self, i: int) -> str:
        """Where frame ``i`` comes from, for messages."""
        if self.files is not None:
            return str(self.files[i])
        return f"{self.video} frame {int(self.indices[i])}"

    def read(self, i: int) -> Tensor:
        """Frame ``i`` as ``(H, W, 3)`` uint8 RGB."""
        import cv2

        if not 0 <= i < len(self):
            raise IndexError(f"{self.name}: frame {i} out of range [0, {len(self)})")
        if self.files is not None:
            image = cv2.imread(str(self.files[i]), cv2.IMREAD_UNCHANGED)
            if image is None:
                raise ValueError(f"{self.name}: row {i} (0-based): cannot read image {self.files[i]}")
        else:
            image = self._read_video(int(self.indices[i]))
        if image.dtype == np.uint16:  # 16-bit images: keep the top 8 bits
            image = (image >> 8).astype(np.uint8)
        if image.dtype != np.uint8:
            raise ValueError(f"{self.name}: {self.source(i)} has pixel type {image.dtype}; expected 8- or 16-bit")
        if image.ndim == 2:
            image = np.repeat(image[:, :, None], 3, axis=2)
        elif image.shape[2] == 4:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
        else:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
        if self.expected_size is not None and tuple(image.shape[:2]) != tuple(self.expected_size):
            raise ValueError(
                f"{self.name}: {self.source(i)} is {image.shape[1]}x{image.shape[0]} (WxH); the calibration "
                f"expects {self.expected_size[1]}x{self.expected_size[0]}"
            )
        return torch.from_numpy(np.ascontiguousarray(image))

    def read_gray(self, i: int) -> Tensor:
        """Frame ``i`` as ``(H, W)`` float32 luminance in [0, 1] (ITU-R BT.601 weights)."""
        rgb = self.read(i).to(torch.float32) / 255.0
        return rgb @ torch.tensor([0.299, 0.587, 0.114])

    def __iter__(self) -> Iterator[Tensor]:
        for i in range(len(self)):
            yield self.read(i)

    def _read_video(self, index: int) -> np.ndarray:
        import cv2

        cap, position = self._capture or (None, -1)
        if cap is None:
            cap = cv2.VideoCapture(str(self.video))
            if not cap.isOpened():
                raise ValueError(f"{self.name}: cannot open video {self.video}")
            position = 0
        if index != position:  # sequential reads need no seek
            cap.set(cv2.CAP_PROP_POS_FRAMES, index)
        ok, image = cap.read()
        if not ok:
            raise ValueError(f"{self.name}: video {self.video} has no frame {index}")
        object.__setattr__(self, "_capture", (cap, index + 1))
        return image


@dataclass(frozen=True, eq=False)
class Tracks:
    """Precomputed sparse feature tracks: rows ``(t, track_id, u, v)``.

    Rows are grouped by frame time (non-decreasing ``t_s``); within one time a
    track id appears at most once. Pixels follow the OpenCV convention of
    :mod:`flowins.geometry.camera`.
    """

    t_s: Tensor
    track_id: Tensor
    uv_px: Tensor
    _: KW_ONLY
    name: str = "tracks"
    #: ``(H, W)`` of the images: every point must lie on it (within :data:`TRACK_MARGIN_PX`)
    image_size: tuple[int, int] | None = None
    #: the camera's frame times (``frames.csv``): every track time must be one of them
    #: (within :data:`FRAME_TIME_TOLERANCE_S`); ``None``: the tracks' own times are the frame clock
    frame_times_s: Tensor | None = None

    def __post_init__(self) -> None:
        name = str(self.name)
        t_s = as_float64(self.t_s, stream=name, array="t")
        uv = as_float64(self.uv_px, stream=name, array="u,v")
        ids = torch.as_tensor(np.asarray(self.track_id)) if not isinstance(self.track_id, Tensor) else self.track_id
        if t_s.ndim != 1 or t_s.shape[0] == 0:
            raise ValueError(f"{name}: t has shape {tuple(t_s.shape)}; expected (M,) with M >= 1 rows")
        m = t_s.shape[0]
        if uv.shape != (m, 2) or ids.shape != (m,):
            raise ValueError(
                f"{name}: shapes t {tuple(t_s.shape)}, track_id {tuple(ids.shape)}, uv {tuple(uv.shape)}; "
                f"expected (M,), (M,), (M, 2)"
            )
        if ids.is_floating_point():
            frac = torch.nonzero(ids != ids.round())
            if frac.numel():
                raise ValueError(f"{name}: row {int(frac[0, 0])} (0-based): track_id {float(ids[frac[0, 0]])} is not an integer")
        ids = ids.to(torch.int64)
        _check_finite(t_s, stream=name, array="t")
        _check_finite(uv, stream=name, array="u,v")
        neg = torch.nonzero(ids < 0)
        if neg.numel():
            raise ValueError(f"{name}: row {int(neg[0, 0])} (0-based): negative track_id")
        back = torch.nonzero(t_s[1:] < t_s[:-1])
        if back.numel():
            k = int(back[0, 0]) + 1
            raise ValueError(
                f"{name}: row {k} (0-based): time {float(t_s[k])!r} s is before the previous row's "
                f"{float(t_s[k - 1])!r} s; expected rows grouped by non-decreasing frame time"
            )
        frame = torch.unique_consecutive(t_s, return_inverse=True)[1]
        key = frame * (int(ids.max()) + 1) + ids
        order = torch.argsort(key, stable=True)
        same = torch.nonzero(key[order][1:] == key[order][:-1])
        if same.numel():
            k = int(order[int(same[0, 0]) + 1])
            raise ValueError(
                f"{name}: row {k} (0-based): track_id {int(ids[k])} appears twice at time {float(t_s[k])!r} s; "
                "expected one row per track and frame"
            )
        if self.image_size is not None:
            h, w = self.image_size
            m = TRACK_MARGIN_PX
            off = torch.nonzero((uv[:, 0] < -0.5 - m) | (uv[:, 0] > w - 0.5 + m)
                                | (uv[:, 1] < -0.5 - m) | (uv[:, 1] > h - 0.5 + m))
            if off.numel():
                k = int(off[0, 0])
                raise ValueError(
                    f"{name}: row {k} (0-based): point (u, v) = ({float(uv[k, 0]):g}, {float(uv[k, 1]):g}) px is outside "
                    f"the {w}x{h} image (u in [-0.5, {w - 0.5:g}], v in [-0.5, {h - 0.5:g}], ±{m:g} px); "
                    f"{off.shape[0]} rows are; expected pixels of the calibration's image size"
                )
        if self.frame_times_s is not None:
            frames = torch.as_tensor(self.frame_times_s, dtype=torch.float64)
            i = torch.searchsorted(frames, t_s).clamp(1, max(frames.shape[0] - 1, 1))
            nearest = torch.minimum((t_s - frames[i - 1]).abs(), (t_s - frames[i.clamp(max=frames.shape[0] - 1)]).abs())
            off = torch.nonzero(nearest > FRAME_TIME_TOLERANCE_S)
            if off.numel():
                k = int(off[0, 0])
                raise ValueError(
                    f"{name}: row {k} (0-based): time {float(t_s[k])!r} s is {1e3 * float(nearest[k]):.3f} ms from "
                    f"the nearest frame time; {off.shape[0]} rows are off; expected every track time to be a time "
                    f"of frames.csv (within {1e3 * FRAME_TIME_TOLERANCE_S:g} ms)"
                )
        _set(self, t_s=t_s, track_id=ids, uv_px=uv, name=name)

    def __len__(self) -> int:
        return self.t_s.shape[0]

    @property
    def frame_times(self) -> Tensor:
        """Distinct frame times ``(F,)``."""
        return torch.unique_consecutive(self.t_s)

    def at(self, t_s: float) -> tuple[Tensor, Tensor]:
        """``(track_id (n,), uv_px (n, 2))`` of the rows at time ``t_s`` (exact match)."""
        keep = self.t_s == t_s
        return self.track_id[keep], self.uv_px[keep]


@dataclass(frozen=True, eq=False)
class Sequence:
    """A recording: IMU plus any of camera frames, tracks, GNSS and ground truth."""

    imu: ImuStream
    _: KW_ONLY
    name: str = "sequence"
    camera: PinholeCamera | None = None
    imu_to_camera: RigidTransform | None = None
    frames: CameraFrames | None = None
    tracks: Tracks | None = None
    gnss: GnssStream | None = None
    groundtruth: PoseStream | None = None
    metadata: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.imu, ImuStream):
            raise ValueError(f"{self.name}: imu must be an ImuStream, got {type(self.imu).__name__}")
        if (self.frames is not None or self.tracks is not None) and (self.camera is None or self.imu_to_camera is None):
            raise ValueError(
                f"{self.name}: frames or tracks need the camera calibration (intrinsics and imu_to_camera); "
                "none was given"
            )
        if self.frames is not None and self.frames.expected_size is None and self.camera is not None:
            object.__setattr__(self.frames, "expected_size", self.camera.size)
        t0, t1 = float(self.imu.t_s[0]), float(self.imu.t_s[-1])
        for label, times in (("frames", self.frames), ("tracks", self.tracks), ("gnss", self.gnss), ("groundtruth", self.groundtruth)):
            if times is None:
                continue
            lo, hi = float(times.t_s[0]), float(times.t_s[-1])
            if hi < t0 or lo > t1:
                raise ValueError(
                    f"{self.name}: {label} span [{lo:.3f}, {hi:.3f}] s does not overlap the IMU span "
                    f"[{t0:.3f}, {t1:.3f}] s; expected all streams on one clock"
                )

    @property
    def sources(self) -> tuple[str, ...]:
        """The information sources present, in :data:`SOURCES` order."""
        present = {
            "imu": True,
            "frames": self.frames is not None,
            "tracks": self.tracks is not None,
            "gnss": self.gnss is not None,
            "groundtruth": self.groundtruth is not None,
        }
        return tuple(s for s in SOURCES if present[s])

    def describe(self) -> str:
        """A one-paragraph human summary."""
        parts = [f"{self.name}: IMU {len(self.imu)} samples over {self.imu.duration_s:.1f} s ({self.imu.rate_hz:.0f} Hz)"]
        if self.frames is not None:
            rate = (len(self.frames) - 1) / max(float(self.frames.t_s[-1] - self.frames.t_s[0]), 1e-9)
            parts.append(f"{len(self.frames)} frames ({rate:.1f} fps, {self.camera.width}x{self.camera.height})")
        if self.tracks is not None:
            parts.append(f"{len(self.tracks)} track observations in {len(self.tracks.frame_times)} frames")
        if self.gnss is not None:
            parts.append(f"{len(self.gnss)} GNSS fixes")
        if self.groundtruth is not None:
            kind = "poses" if self.groundtruth.quat_wxyz is not None else "positions"
            parts.append(f"{len(self.groundtruth)} ground-truth {kind}")
        return ", ".join(parts)


#: the streams an estimate is made from, each checked against the IMU's time span
INPUT_STREAMS = ("frames", "tracks", "gnss")


def _rows(stream: Any, keep: Tensor) -> Any:
    """``stream`` with only the rows where ``keep`` (an ``(N,)`` bool) holds."""
    index = torch.nonzero(keep)[:, 0]
    if isinstance(stream, CameraFrames):
        files = None if stream.files is None else tuple(stream.files[i] for i in index.tolist())
        indices = None if stream.indices is None else torch.as_tensor(stream.indices)[index]
        return dataclasses.replace(stream, t_s=stream.t_s[index], files=files, indices=indices, check_files=False)
    if isinstance(stream, Tracks):
        return dataclasses.replace(stream, t_s=stream.t_s[index], track_id=torch.as_tensor(stream.track_id)[index],
                                   uv_px=stream.uv_px[index])
    if isinstance(stream, GnssStream):
        return dataclasses.replace(stream, **{k: getattr(stream, k)[index] for k in
                                              ("t_s", "lat_deg", "lon_deg", "alt_m", "h_acc_m", "v_acc_m")})
    raise TypeError(f"no row selection for {type(stream).__name__}")


def within_imu_span(seq: Sequence, *, crop: bool = False) -> tuple[Sequence, list[str]]:
    """``seq`` with every input stream (:data:`INPUT_STREAMS`) inside the IMU's time span.

    A row outside the span is an error naming the stream (its file), the first such row
    and both spans; with ``crop`` every stream is cropped to the span instead and the
    second value lists what was cropped, one line per stream (nothing is dropped
    without a line). Ground truth is a reference, not an input: it is left whole (the
    evaluation pairs it with the estimate by time)."""
    t0, t1 = float(seq.imu.t_s[0]), float(seq.imu.t_s[-1])
    changes: dict[str, Any] = {}
    notes: list[str] = []
    for label in INPUT_STREAMS:
        stream = getattr(seq, label)
        if stream is None:
            continue
        t = torch.as_tensor(stream.t_s, dtype=torch.float64)
        keep = (t >= t0) & (t <= t1)
        if bool(keep.all()):
            continue
        before, after = int((t < t0).sum()), int((t > t1).sum())
        if not crop:
            k = int(torch.nonzero(~keep)[0, 0])
            raise ValueError(
                f"{stream.name}: row {k} (0-based) at t = {float(t[k]):.3f} s is outside the IMU's time span "
                f"[{t0:.3f}, {t1:.3f}] s ({label} span [{float(t[0]):.3f}, {float(t[-1]):.3f}] s; {before} rows "
                f"before, {after} after); check that every stream is on the IMU's clock, or set sequence.crop=true "
                "to crop every stream to the IMU span"
            )
        if not bool(keep.any()):
            raise ValueError(f"{stream.name}: no row inside the IMU's time span [{t0:.3f}, {t1:.3f}] s "
                             f"({label} span [{float(t[0]):.3f}, {float(t[-1]):.3f}] s); nothing is left to crop to")
        changes[label] = _rows(stream, keep)
        notes.append(f"{stream.name}: cropped {before} rows before and {after} after the IMU span "
                     f"[{t0:.3f}, {t1:.3f}] s (sequence.crop=true); {int(keep.sum())} of {len(t)} kept")
    return (dataclasses.replace(seq, **changes) if changes else seq), notes
