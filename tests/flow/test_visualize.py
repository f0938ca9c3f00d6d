"""Middlebury colour wheel, the Fig. 2 panel, and .flo files."""
import math
import struct
import zlib

import cv2
import numpy as np
import pytest
import torch

from flowins.flow.flo import FLO_MAGIC, read_flo, write_flo
from flowins.flow.visualize import flow_panel, flow_panel_figure, flow_to_rgb

# ---------------------------------------------------------------- colour wheel

def naive_wheel() -> list[tuple[float, float, float]]:
    """colorcode.cpp's makecolorwheel, written out loop by loop."""
    wheel = []
    RY, YG, GC, CB, BM, MR = 15, 6, 4, 11, 13, 6
    for i in range(RY):
        wheel.append((255, math.floor(255 * i / RY), 0))
    for i in range(YG):
        wheel.append((255 - math.floor(255 * i / YG), 255, 0))
    for i in range(GC):
        wheel.append((0, 255, math.floor(255 * i / GC)))
    for i in range(CB):
        wheel.append((0, 255 - math.floor(255 * i / CB), 255))
    for i in range(BM):
        wheel.append((math.floor(255 * i / BM), 0, 255))
    for i in range(MR):
        wheel.append((255, 0, 255 - math.floor(255 * i / MR)))
    return wheel


def naive_color(u: float, v: float) -> tuple[int, int, int]:
    """colorcode.cpp's computeColor for one already normalised vector."""
    wheel = naive_wheel()
    n = len(wheel)
    rad = math.sqrt(u * u + v * v)
    a = math.atan2(-v, -u) / math.pi
    fk = (a + 1) / 2 * (n - 1)
    k0 = int(fk)
    k1 = (k0 + 1) % n
    f = fk - k0
    out = []
    for b in range(3):
        col = ((1 - f) * wheel[k0][b] + f * wheel[k1][b]) / 255
        col = 1 - rad * (1 - col) if rad <= 1 else col * 0.75
        out.append(int(255 * col))
    return tuple(out)


def test_wheel_has_55_colours():
    assert len(naive_wheel()) == 55


@pytest.mark.parametrize(
    "u, v, hue",
    [(1.0, 0.0, "red"), (0.0, 1.0, "orange"), (-1.0, 0.0, "cyan-blue"), (0.0, -1.0, "violet"), (0.6, -0.3, None), (-0.2, 0.7, None)],
)
def test_wheel_directions(u, v, hue):
    flow = torch.tensor([u, v], dtype=torch.float32).view(2, 1, 1)
    rgb = flow_to_rgb(flow, max_magnitude=1.0)[0, 0]
    assert tuple(int(c) for c in rgb) == naive_color(u, v)
    r, g, b = (int(c) for c in rgb)
    if hue == "red":  # atan2(-0.0, -1) = -π: wheel index 0, (255, 0, 0); with +0.0 index 54, (255, 0, 43)
        assert r == 255 and g == 0 and b < 50
    elif hue == "orange":  # index 13.5: between RY 13 and 14, (255, 229, 0)
        assert r == 255 and 200 < g < 255 and b == 0
    elif hue == "cyan-blue":  # index 27: CB ramp, (0, 209, 255)
        assert r == 0 and 180 < g < 230 and b == 255
    elif hue == "violet":  # index 40.5: BM ramp, (88, 0, 255)
        assert 60 < r < 120 and g == 0 and b == 255


def test_wheel_normaliser_and_special_values():
    flow = np.zeros((2, 2, 3), np.float32)  # (2, H, W); pixel (0, 0) stays zero
    flow[:, 0, 1] = (2.0, 0.0)  # the largest finite magnitude: saturated red
    flow[:, 0, 2] = (1.0, 0.0)  # half of it: pink
    flow[:, 1, 0] = (np.nan, 0.0)
    rgb = flow_to_rgb(flow)
    assert tuple(rgb[0, 0]) == (255, 255, 255)  # zero flow -> white
    assert tuple(rgb[1, 0]) == (0, 0, 0)  # unknown -> black
    assert tuple(rgb[0, 1]) == (255, 0, 0)
    assert tuple(rgb[0, 2]) == naive_color(0.5, 0.0) == (255, 127, 127)
    flow[:, 1, 1] = (8.0, 0.0)  # beyond an explicit normaliser of 4: darkened to 75 %
    explicit = flow_to_rgb(flow, max_magnitude=4.0)
    assert tuple(explicit[1, 1]) == naive_color(2.0, 0.0) == (191, 0, 0)
    with pytest.raises(ValueError, match="expected \\(2, H, W\\)"):
        flow_to_rgb(np.zeros((4, 4, 2)))


# ---------------------------------------------------------------- Fig. 2 panel

def png_size(path) -> tuple[int, int]:
    """Width and height from the PNG's IHDR chunk, checking the signature and the chunk's CRC."""
    with open(path, "rb") as f:
        data = f.read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    length, kind = struct.unpack(">I4s", data[8:16])
    assert kind == b"IHDR" and length == 13
    assert struct.unpack(">I", data[29:33])[0] == zlib.crc32(data[12:29])
    return struct.unpack(">II", data[16:24])


def test_flow_panel_writes_png(tmp_path):
    h, w = 60, 80
    rng = np.random.default_rng(0)
    image1 = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    image2 = torch.rand(3, h, w)
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    flow_a = torch.from_numpy(np.stack([0.1 * u, -0.05 * v]))
    flow_b = torch.from_numpy(np.stack([-0.1 * v, 0.02 * u]))
    sigma = torch.full((1, 2, h, w), 0.5)
    pa = flow_panel(image1, image2, flow_a, sigma, tmp_path / "a.png", title="pair a")
    pb = flow_panel(image1, image2, flow_b[None], sigma, tmp_path / "b.png", title="pair b")
    # 5 panels of 2.4 in at 100 dpi; height: the images' aspect plus 0.9 in for titles and colour bars + 0.35 for the title
    # (to within a pixel: matplotlib < 3.8 truncates 14.399999 in x 100 dpi to 1439 px, later versions round)
    expected = (5 * 2.4 * 100, (2.4 * h / w + 0.9 + 0.35) * 100)
    assert png_size(pa) == png_size(pb)
    assert all(abs(got - want) < 1 for got, want in zip(png_size(pa), expected)), (png_size(pa), expected)
    a, b = cv2.imread(str(pa)), cv2.imread(str(pb))
    assert a.shape == (*png_size(pa)[::-1], 3)
    assert (a != b).any(axis=-1).mean() > 0.02
    six = flow_panel(image1, image2, flow_a, sigma, tmp_path / "c.png", sigma_mode="components")
    assert abs(png_size(six)[0] - 6 * 2.4 * 100) < 1
    with pytest.raises(ValueError, match="same size"):
        flow_panel(image1[:30], image2, flow_a, sigma, tmp_path / "d.png")


@pytest.mark.parametrize(
    "sigma_mode, expected",
    [
        ("magnitude", {"horizontal flow Δu (px)": "Δu [px]", "vertical flow Δv (px)": "Δv [px]", "uncertainty |σ| (px)": "|σ| [px]"}),
        (
            "components",
            {
                "horizontal flow Δu (px)": "Δu [px]",
                "vertical flow Δv (px)": "Δv [px]",
                "uncertainty σu (px)": "σu [px]",
                "uncertainty σv (px)": "σv [px]",
            },
        ),
    ],
)
def test_flow_panel_colour_bars_are_labelled(sigma_mode, expected):
    h, w = 60, 80
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    flow = np.stack([0.1 * u, -0.05 * v])
    sigma = np.full((2, h, w), 0.5, np.float32)
    image = np.zeros((h, w, 3), np.uint8)
    fig = flow_panel_figure(image, image, flow, sigma, title="pair", sigma_mode=sigma_mode)
    fig.canvas.draw()
    bars = {ax.get_title(): im.colorbar for ax in fig.axes for im in ax.images if im.colorbar is not None}
    assert {title: bar.ax.get_xlabel() for title, bar in bars.items()} == expected
    figure_box = fig.bbox
    renderer = fig.canvas.get_renderer()
    for title, bar in bars.items():
        (image_ax,) = [ax for ax in fig.axes if ax.get_title() == title]
        label_box = bar.ax.xaxis.label.get_window_extent(renderer)
        assert label_box.width > 0 and "px" in bar.ax.get_xlabel()
        # drawn inside the figure, between the colour bar and the image above it
        assert figure_box.x0 <= label_box.x0 and label_box.x1 <= figure_box.x1, (title, label_box, figure_box)
        assert bar.ax.get_window_extent(renderer).y1 <= label_box.y0, title
        assert label_box.y1 <= image_ax.get_window_extent(renderer).y0, title


# ---------------------------------------------------------------- .flo files

def flo_bytes(flow: np.ndarray) -> bytes:
    """A .flo file built by hand: float32 magic, int32 width, height, then (H, W, 2) float32."""
    h, w = flow.shape[:2]
    return np.float32(202021.25).tobytes() + np.int32(w).tobytes() + np.int32(h).tobytes() + flow.astype("<f4").tobytes()


def test_flo_round_trip(tmp_path):
    flow = np.random.default_rng(1).normal(size=(7, 5, 2)).astype(np.float32)
    path = write_flo(tmp_path / "x.flo", flow)
    assert path.read_bytes() == flo_bytes(flow)
    assert path.read_bytes()[:4] == b"PIEH" and FLO_MAGIC == np.float32(202021.25)
    (tmp_path / "y.flo").write_bytes(flo_bytes(flow))
    back = read_flo(tmp_path / "y.flo")
    assert back.dtype == np.float32 and back.shape == (7, 5, 2)
    np.testing.assert_array_equal(back, flow)
    write_flo(tmp_path / "z.flo", torch.from_numpy(flow).double())
    np.testing.assert_array_equal(read_flo(tmp_path / "z.flo"), flow)


def test_flo_errors(tmp_path):
    flow = np.zeros((4, 6, 2), np.float32)
    good = flo_bytes(flow)
    (tmp_path / "magic.flo").write_bytes(np.float32(1.0).tobytes() + good[4:])
    with pytest.raises(ValueError, match="magic.flo.*magic number"):
        read_flo(tmp_path / "magic.flo")
    (tmp_path / "short.flo").write_bytes(good[:-5])
    with pytest.raises(ValueError, match="truncated.*expected 204"):
        read_flo(tmp_path / "short.flo")
    (tmp_path / "header.flo").write_bytes(good[:9])
    with pytest.raises(ValueError, match="12-byte header"):
        read_flo(tmp_path / "header.flo")
    (tmp_path / "size.flo").write_bytes(good[:4] + np.int32(-3).tobytes() + good[8:])
    with pytest.raises(ValueError, match="width=-3"):
        read_flo(tmp_path / "size.flo")
    with pytest.raises(ValueError, match="expected \\(H, W, 2\\)"):
        write_flo(tmp_path / "bad.flo", np.zeros((2, 4, 6), np.float32))
