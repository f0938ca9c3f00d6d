"""Trajectory and error figures: a real PNG of the promised size, content, and no plots of NaN."""
import math
import struct

import numpy as np
import pytest
import torch
from matplotlib import colormaps
from matplotlib.image import imread

from flowins.evaluation import plot_errors, plot_trajectory

F64 = torch.float64
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def png_size(path):
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])  # width, height


def circle(t):
    return torch.stack((50 * torch.cos(0.1 * t), 50 * torch.sin(0.1 * t), torch.zeros_like(t)), -1)


def has_colour(image, rgb, tol=0.02):
    return bool((np.abs(image[..., :3] - np.asarray(rgb)).max(axis=-1) < tol).any())


def test_trajectory_png_size_and_content(tmp_path):
    t = torch.linspace(0, 60, 400, dtype=F64)
    gnss_t = t[::40]
    path = plot_trajectory(
        tmp_path / "out" / "traj.png",
        ground_truth_m=circle(t),
        tracks={"filter": (t, circle(t) + 2.0), "smoother": (t, circle(t) + 0.5)},
        gnss_m=circle(gnss_t),
        gnss_radius_m=torch.full((gnss_t.shape[0],), 5.0, dtype=F64),
        title="test",
        panel_size_in=(4.0, 3.0),
        dpi=100,
    )
    assert path.exists()
    assert png_size(path) == (800, 300)
    image = imread(path)
    assert image.shape[:2] == (300, 800)
    assert has_colour(image, (1.0, 0.0, 0.0))  # ground truth line
    viridis = colormaps["viridis"]
    assert has_colour(image, viridis(0.0)[:3], tol=0.03)  # start of the track
    assert has_colour(image, viridis(1.0)[:3], tol=0.03)  # end of the track


def test_trajectory_without_optional_layers(tmp_path):
    t = torch.linspace(0, 10, 50, dtype=F64)
    path = plot_trajectory(tmp_path / "one.png", ground_truth_m=None, tracks={"filter": (t, circle(t))}, dpi=50)
    assert png_size(path) == (250, 225)  # default panel (5.0, 4.5) in


def test_errors_png(tmp_path):
    t = torch.linspace(0, 10, 50, dtype=F64)
    path = plot_errors(
        tmp_path / "err.png",
        series={"filter": (t, t.sqrt()), "smoother": (t, 0.5 * t.sqrt())},
        figsize_in=(6.0, 2.0),
        dpi=100,
    )
    assert png_size(path) == (600, 200)


def test_nan_track_is_refused(tmp_path):
    t = torch.linspace(0, 10, 50, dtype=F64)
    pos = circle(t)
    pos[7, 0] = math.nan
    with pytest.raises(ValueError, match=r"tracks\['smoother'\] pos_m contains NaN or inf; first bad row is 7"):
        plot_trajectory(tmp_path / "nan.png", ground_truth_m=circle(t), tracks={"filter": (t, circle(t)), "smoother": (t, pos)})
    assert not (tmp_path / "nan.png").exists()
    errors = t.clone()
    errors[3] = math.inf
    with pytest.raises(ValueError, match=r"series\['a'\] errors_m .* row is 3"):
        plot_errors(tmp_path / "nan_err.png", series={"a": (t, errors)})


def test_shape_and_argument_errors(tmp_path):
    t = torch.linspace(0, 10, 50, dtype=F64)
    with pytest.raises(ValueError, match="tracks is empty"):
        plot_trajectory(tmp_path / "x.png", ground_truth_m=None, tracks={})
    with pytest.raises(ValueError, match="t_s has 50 samples but pos_m has 49 rows"):
        plot_trajectory(tmp_path / "x.png", ground_truth_m=None, tracks={"f": (t, circle(t)[:49])})
    with pytest.raises(ValueError, match="gnss_radius_m given without gnss_m"):
        plot_trajectory(
            tmp_path / "x.png", ground_truth_m=None, tracks={"f": (t, circle(t))}, gnss_radius_m=torch.ones(3, dtype=F64)
        )
