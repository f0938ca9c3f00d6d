"""flowins.flow.load: the tracks of the multi-view update: the cache file round trip and the
undistortion of their pixels."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from flowins.data.sequence import PinholeCamera, Tracks
from flowins.flow.load import read_tracks, undistort_tracks, write_tracks
from flowins.geometry.camera import distort


def _tracks() -> Tracks:
    g = torch.Generator().manual_seed(0)
    t = torch.tensor([0.0, 0.0, 0.1, 0.1, 0.1, 0.2], dtype=torch.float64)
    ids = torch.tensor([0, 3, 0, 3, 7, 7])
    uv = torch.rand(6, 2, generator=g, dtype=torch.float64) * torch.tensor([640.0, 480.0], dtype=torch.float64)
    return Tracks(t, ids, uv, name="lk tracks")


def test_a_tracks_file_reads_back_what_was_written(tmp_path):
    tracks = _tracks()
    write_tracks(tmp_path / "t.npz", tracks)
    back = read_tracks(tmp_path / "t.npz")
    assert torch.equal(back.t_s, tracks.t_s) and torch.equal(back.track_id, tracks.track_id)
    assert torch.equal(back.uv_px, tracks.uv_px) and back.name == "lk tracks"
    assert not list(tmp_path.glob("*.partial*"))


def test_a_file_of_another_kind_is_refused_naming_it(tmp_path):
    np.savez(tmp_path / "other.npz", t_s=np.zeros(2))
    with pytest.raises(ValueError, match="other.npz: not a flowins tracks file"):
        read_tracks(tmp_path / "other.npz")


def test_undistorted_pixels_distort_back_to_the_recorded_ones():
    camera = PinholeCamera(640, 480, 400.0, 410.0, 320.0, 240.0, (-0.28, 0.07, 1e-4, -2e-4))
    tracks = _tracks()
    ideal = undistort_tracks(tracks, camera)
    f = torch.tensor([400.0, 410.0], dtype=torch.float64)
    c = torch.tensor([320.0, 240.0], dtype=torch.float64)
    again = distort((ideal.uv_px - c) / f, camera.distortion) * f + c
    torch.testing.assert_close(again, tracks.uv_px, atol=1e-4, rtol=0)  # 20 fixed-point steps: 2e-5 px at a corner
    assert float((ideal.uv_px - tracks.uv_px).abs().max()) > 1.0  # the lens does move them
    assert undistort_tracks(tracks, PinholeCamera(640, 480, 400.0, 410.0, 320.0, 240.0)) is tracks
