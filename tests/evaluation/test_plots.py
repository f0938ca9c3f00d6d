"""Trajectory and error figures: a real PNG of the promised size, content, and no plots of NaN;
the figure's artists: legend entries, GNSS colours apart from viridis, accuracy circles that do not fill."""
import math
import struct

import numpy as np
import pytest
import torch
from matplotlib import colormaps
from matplotlib.collections import PatchCollection
from matplotlib.colors import to_rgba_array
from matplotlib.image import imread

from flowins.evaluation import plot_errors, plot_trajectory
from flowins.evaluation.plots import errors_figure, trajectory_figure

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


def test_each_error_series_is_drawn_at_its_own_values_in_its_legend_colour():
    """Two series at 1 m and 3 m: the rendered pixels along each level are that line's colour
    (read back from the legend entry of its name), and nothing of it sits at the other level."""
    t = torch.linspace(0, 10, 50, dtype=F64)
    fig = errors_figure(series={"filter": (t, torch.full_like(t, 3.0)), "smoother": (t, torch.full_like(t, 1.0))},
                        figsize_in=(6.0, 3.0), dpi=100)
    (ax,) = fig.axes
    ax.get_legend().set_visible(False)
    ax.set_ylim(0.0, 4.0)
    colours = {line.get_label(): to_rgba_array(line.get_color())[0, :3] * 255 for line in ax.get_lines()}
    assert set(colours) == {"filter", "smoother"}
    fig.canvas.draw()
    image = np.asarray(fig.canvas.buffer_rgba())[..., :3].astype(np.float64)

    def nearest(level, colour):
        """Per point along the level, the colour distance of the closest pixel within 2 rows
        (a 1 pt line is anti-aliased over about two pixel rows)."""
        xy = ax.transData.transform(np.stack((np.linspace(2.0, 8.0, 25), np.full(25, level)), -1))
        cols, rows = np.floor(xy[:, 0]).astype(int), image.shape[0] - 1 - np.floor(xy[:, 1]).astype(int)
        window = np.stack([image[rows + d, cols] for d in range(-2, 3)], 1)  # (25, 5, 3)
        return np.abs(window - colour).max(-1).min(-1)

    for name, level, other in (("filter", 3.0, 1.0), ("smoother", 1.0, 3.0)):
        assert nearest(level, colours[name]).max() < 30, name
        assert nearest(other, colours[name]).min() > 60, name


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


# ---------------------------------------------------------------- the figure's artists

VIRIDIS_RGB = colormaps["viridis"](np.linspace(0.0, 1.0, 256))[:, :3]


def panels(fig):
    """The trajectory panels (the axes with a title), without the colour-bar axes."""
    return [ax for ax in fig.axes if ax.get_title()]


def gnss_layers(ax):
    """The GNSS fixes (the scatter labelled GNSS...) and the accuracy circles (the PatchCollection) of one panel."""
    fixes = [c for c in ax.collections if c.get_label().startswith("GNSS")]
    circles = [c for c in ax.collections if isinstance(c, PatchCollection)]
    assert len(fixes) == 1 and len(circles) == 1, [type(c).__name__ + ":" + c.get_label() for c in ax.collections]
    return fixes[0], circles[0]


def visible_rgb(*colour_arrays):
    """RGB rows of every colour with a non-zero alpha."""
    rgba = np.concatenate([to_rgba_array(c) for c in colour_arrays])
    return rgba[rgba[:, 3] > 0, :3]


def gnss_inputs(n=30, radius=5.0):
    t = torch.linspace(0, 60, 400, dtype=F64)
    gnss_t = torch.linspace(0, 60, n, dtype=F64)
    return dict(
        ground_truth_m=circle(t),
        tracks={"filter": (t, circle(t) + 2.0), "smoother": (t, circle(t) + 0.5)},
        gnss_m=circle(gnss_t),
        gnss_radius_m=torch.full((n,), radius, dtype=F64),
    )


def test_legend_names_truth_gnss_and_the_track():
    fig = trajectory_figure(**gnss_inputs(), dpi=50)
    assert [ax.get_title() for ax in panels(fig)] == ["filter", "smoother"]
    for ax in panels(fig):
        texts = [t.get_text() for t in ax.get_legend().get_texts()]
        assert ax.get_title() in texts, texts  # the scatter coloured by time
        assert "ground truth" in texts, texts
        assert any(t.startswith("GNSS") for t in texts), texts
    # a track alone still has its legend entry
    t = torch.linspace(0, 10, 50, dtype=F64)
    (ax,) = panels(trajectory_figure(ground_truth_m=None, tracks={"estimate": (t, circle(t))}, dpi=50))
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["estimate"]


def test_gnss_colours_are_far_from_viridis_and_from_the_red_truth():
    fig = trajectory_figure(**gnss_inputs(), dpi=50)
    for ax in panels(fig):
        fixes, circles = gnss_layers(ax)
        for layer in (fixes, circles):
            rgb = visible_rgb(layer.get_facecolor(), layer.get_edgecolor())
            assert len(rgb) > 0
            to_viridis = np.linalg.norm(rgb[:, None, :] - VIRIDIS_RGB[None], axis=-1)  # (colours, 256)
            assert to_viridis.min() > 0.5, (rgb, to_viridis.min())  # tab:blue was 0.07 from viridis, black is 0.42
            assert np.linalg.norm(rgb - np.array([1.0, 0.0, 0.0]), axis=-1).min() > 0.5, rgb
        # the truth line stays red
        (truth,) = [line for line in ax.get_lines() if line.get_label() == "ground truth"]
        assert to_rgba_array(truth.get_color())[0, :3].tolist() == [1.0, 0.0, 0.0]


def rgba_at(fig, ax, points_m):
    """Rendered RGBA (0..255) of the pixels at the data points ``(K, 2)`` (East, North) of ``ax``."""
    fig.canvas.draw()
    image = np.asarray(fig.canvas.buffer_rgba())
    xy = ax.transData.transform(points_m)  # display pixels, origin at the bottom left
    cols = np.floor(xy[:, 0]).astype(int)
    rows = image.shape[0] - 1 - np.floor(xy[:, 1]).astype(int)
    return image[rows, cols].astype(np.float64)


def test_300_overlapping_accuracy_circles_do_not_fill_their_inside():
    """300 fixes within 1 m of the origin, each with a 10 m radius: inside the circles stays white."""
    g = 300
    rng = np.random.default_rng(3)
    gnss = np.zeros((g, 3))
    gnss[:, :2] = rng.uniform(-1.0, 1.0, (g, 2))
    t = torch.linspace(0, 10, 50, dtype=F64)
    track = torch.stack((torch.full_like(t, 40.0), torch.linspace(-10, 10, 50, dtype=F64), torch.zeros_like(t)), -1)
    fig = trajectory_figure(
        ground_truth_m=None,
        tracks={"filter": (t, track)},
        gnss_m=torch.from_numpy(gnss),
        gnss_radius_m=torch.full((g,), 10.0, dtype=F64),
        panel_size_in=(6.0, 4.0),
        dpi=100,
    )
    (ax,) = panels(fig)
    _, circles = gnss_layers(ax)
    assert (to_rgba_array(circles.get_facecolor())[:, 3] == 0).all()  # no fill at all
    ax.get_legend().set_visible(False)  # "best" may put it anywhere; only the circles are under test
    angle = np.linspace(0.0, 2 * np.pi, 72, endpoint=False)
    ring = lambda r: np.stack((r * np.cos(angle), r * np.sin(angle)), -1)  # noqa: E731
    inside = rgba_at(fig, ax, np.concatenate([ring(r) for r in (3.0, 5.0, 7.0)]))
    # the old drawing (300 fills of alpha 0.15) made this a solid blue: 1 - 0.85**300 = 1
    assert inside[:, :3].min() > 0.95 * 255, inside[:, :3].min()
    # the outlines themselves are drawn: the band 9..11 m is tinted (magenta has no green)
    band = rgba_at(fig, ax, np.concatenate([ring(r) for r in np.linspace(9.0, 11.0, 9)]))
    assert band[:, 1].min() < 0.8 * 255, band[:, 1].min()
