"""What a recording's camera side holds, as one content key: the key under which flow
computed over the recording is cached (:func:`flowins.cache.content_key`).

The key follows the contents, not the names: the frame times and each frame's image
(the SHA-256 of its file's bytes, or of the video file and the frame indices) and the
calibration (intrinsics, distortion, the image size, the IMU-to-camera transform).
Reorder the frames, touch up one image or change the calibration, and the key changes;
copy or rename the recording and it stays the same. A recording's own ``tracks.csv`` is
not part of it: nothing cached is computed from those tracks (they are used as they are),
so adding or editing them leaves the flow computed from the frames in the cache.
Hashing reads every image file once: on the 300 s simulated walk a small fraction of
decoding the frames once (``benchmarks/bench_cache_key.py``, ``docs/caching.md``).
"""
from __future__ import annotations

from typing import Any

from flowins.cache import array_digest, content_key, file_digest
from flowins.data.sequence import CameraFrames, Sequence


def camera_content_key(seq: Sequence) -> str:
    """Content key of ``seq``'s frames and calibration (see the module docstring).

    Raises:
        ValueError: an image (or the video) cannot be read; the message names the
            frames file, the row and the image.
    """
    camera = seq.camera
    transform = seq.imu_to_camera
    return content_key({
        "frames": None if seq.frames is None else _frames_content(seq.frames),
        "camera": None if camera is None else {
            "size": [camera.width, camera.height], "focal": [camera.fx, camera.fy], "centre": [camera.cx, camera.cy],
            "distortion": list(camera.distortion),
        },
        "imu_to_camera": None if transform is None else [array_digest(transform.rotation_wxyz),
                                                         array_digest(transform.translation_m)],
        "tracks": None,  # not keyed (see the module docstring); the entry keeps the keys of recordings without tracks
    })


def _frames_content(frames: CameraFrames) -> dict[str, Any]:
    content: dict[str, Any] = {"t_s": array_digest(frames.t_s), "expected_size": frames.expected_size}
    if frames.files is not None:
        content["images"] = [_digest(frames, file, f"row {i} (0-based): image") for i, file in enumerate(frames.files)]
    else:
        content["video"] = _digest(frames, frames.video, "video")
        content["indices"] = array_digest(frames.indices)
    return content


def _digest(frames: CameraFrames, file, what: str) -> str:
    try:
        return file_digest(file)
    except OSError as exc:
        raise ValueError(f"{frames.name}: {what} {file} cannot be read ({exc.strerror or exc})") from None
