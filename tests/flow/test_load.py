"""flowins.flow.load: the flow cache follows the recording's contents: changed frames, images or calibration
are recomputed, unchanged contents are read back, and what is read back equals what an
empty cache computes."""
from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from flowins.data.load import load_recording
from flowins.flow.load import load_flow

CONFIGS = str(Path(__file__).resolve().parents[2] / "configs")


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A 10 s simulated walk, 160 x 120 at 5 Hz (49 frame pairs)."""
    from flowins.data.simulate import CameraConfig, SimulationConfig, simulate

    folder = tmp_path_factory.mktemp("walk")
    simulate(folder, SimulationConfig(duration_s=10.0, seed=1, flow_every=0,
                                      camera=CameraConfig(rate_hz=5.0, width=160, height=120)), progress=False)
    return folder


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, copy_function=shutil.copy2)  # copy2 keeps modification times
    return dst


def _dense_flow(folder: Path, cache: Path, caplog, flow: tuple[str, ...] = ("flow=dis",)) -> tuple:
    """``(pairs, read from the cache?)`` of ``evaluate.py``'s dense flow (DIS by default) on ``folder``."""
    with initialize_config_dir(config_dir=CONFIGS, version_base=None):
        cfg = compose("evaluate", overrides=[f"sequence.path={folder}", f"cache_dir={cache}", "output_dir=unused", *flow,
                                             "flow_pairs.input_scale=1.0", "progress=false"])
    cfg = OmegaConf.to_container(cfg, resolve=True)
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="flowins"):
        pairs = load_flow("dense", load_recording(cfg["sequence"], quick=False), cfg, progress=False)
    return pairs, "read from the cache" in caplog.text


def _same(a, b) -> bool:
    if not (torch.equal(a.t1_s, b.t1_s) and torch.equal(a.t2_s, b.t2_s) and len(a.points) == len(b.points)):
        return False
    return all(torch.equal(x, y) for p, q in zip(a.points, b.points) for x, y in zip(p, q) if x is not None)


def _reverse_frames(folder: Path) -> None:
    lines = (folder / "frames.csv").read_text().splitlines()
    rows = [line.split(",") for line in lines[1:] if line]
    files = [f for _, f in rows][::-1]
    (folder / "frames.csv").write_text("\n".join([lines[0], *(f"{t},{f}" for (t, _), f in zip(rows, files))]) + "\n")


def _touch_up_one_image(folder: Path) -> None:
    """Brighten a patch of frame 10, same size, same modification time."""
    path = folder / "frames" / "000010.png"
    stat = path.stat()
    image = cv2.imread(str(path))
    image[40:80, 60:100] = np.clip(image[40:80, 60:100].astype(int) + 60, 0, 255).astype(np.uint8)
    cv2.imwrite(str(path), image)
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))


def _change_calibration(folder: Path) -> None:
    path = folder / "calibration.yaml"
    calibration = yaml.safe_load(path.read_text())
    calibration["camera"]["fx"] *= 1.01
    path.write_text(yaml.safe_dump(calibration))


@pytest.mark.parametrize("change, flow_changes", [(_reverse_frames, True), (_touch_up_one_image, True),
                                                  (_change_calibration, False)],
                         ids=["frames reordered", "one image changed", "calibration changed"])
def test_a_changed_recording_is_recomputed(recording, tmp_path, caplog, change, flow_changes):
    cache = tmp_path / "cache"
    original, cached = _dense_flow(_copy(recording, tmp_path / "rec"), cache, caplog)
    assert not cached
    change(tmp_path / "rec")
    changed, cached = _dense_flow(tmp_path / "rec", cache, caplog)
    assert not cached
    assert len(list((cache / "flow").glob("dense-*.npz"))) == 2
    fresh, _ = _dense_flow(tmp_path / "rec", tmp_path / "empty-cache", caplog)
    assert _same(changed, fresh)  # what the filter gets is what an empty cache computes
    assert _same(changed, original) != flow_changes


def test_unchanged_contents_are_read_back_wherever_they_lie(recording, tmp_path, caplog):
    cache = tmp_path / "cache"
    first, cached = _dense_flow(_copy(recording, tmp_path / "rec"), cache, caplog)
    assert not cached
    again, cached = _dense_flow(tmp_path / "rec", cache, caplog)
    assert cached and _same(first, again)
    moved, cached = _dense_flow(_copy(tmp_path / "rec", tmp_path / "renamed copy"), cache, caplog)
    assert cached and _same(first, moved)
    assert len(list((cache / "flow").glob("dense-*.npz"))) == 1


def test_changed_tracks_leave_the_dense_flow_in_the_cache(recording, tmp_path, caplog):
    """The dense flow is computed from the frames alone: a recording whose ``tracks.csv`` is
    edited (a pixel moved) or removed reads it back, and it equals an empty cache's."""
    cache = tmp_path / "cache"
    rec = _copy(recording, tmp_path / "rec")
    first, cached = _dense_flow(rec, cache, caplog)
    assert not cached
    lines = (rec / "tracks.csv").read_text().splitlines()
    t, i, u, v = lines[5].split(",")
    lines[5] = ",".join((t, i, str(float(u) + 0.5), v))
    (rec / "tracks.csv").write_text("\n".join(lines) + "\n")
    edited, cached = _dense_flow(rec, cache, caplog)
    assert cached and _same(first, edited)
    (rec / "tracks.csv").unlink()
    without, cached = _dense_flow(rec, cache, caplog)
    assert cached and _same(first, without)
    assert _same(first, _dense_flow(rec, tmp_path / "empty-cache", caplog)[0])


def test_a_corrupted_image_is_an_error_even_with_a_warm_cache(recording, tmp_path, caplog):
    cache = tmp_path / "cache"
    _dense_flow(_copy(recording, tmp_path / "rec"), cache, caplog)
    path = tmp_path / "rec" / "frames" / "000020.png"
    data = bytearray(path.read_bytes())
    data[len(data) // 2 :] = bytes(len(data) - len(data) // 2)  # the second half zeroed
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"000020\.png"):
        _dense_flow(tmp_path / "rec", cache, caplog)


@pytest.mark.slow
def test_closed_form_dropout_shares_one_cache_across_rates(recording, tmp_path, caplog):
    """SpyNet in closed form keeps σ's moments: a second rate reads the first rate's cache, and its
    σ is what the network computes at that rate from scratch (another cache)."""
    def spynet(p):
        return ("flow=spynet", "flow.mc_mode=moments", f"flow.p={p}")

    first, cached = _dense_flow(recording, tmp_path / "shared", caplog, spynet(0.2))
    assert not cached
    again, cached = _dense_flow(recording, tmp_path / "shared", caplog, spynet(0.4))
    assert cached
    fresh, cached = _dense_flow(recording, tmp_path / "own", caplog, spynet(0.4))
    assert not cached
    assert len(again.points) == len(fresh.points) > 0
    for a, b, c in zip(again.points, fresh.points, first.points):
        torch.testing.assert_close(a.sigma_px, b.sigma_px, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(a.flow_px, b.flow_px, rtol=0, atol=0)
    assert any(not torch.allclose(a.sigma_px, c.sigma_px) for a, c in zip(again.points, first.points))
