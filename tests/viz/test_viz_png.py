"""The dependency-free PNG writer: a valid file (signature, CRCs, zlib) with the plot where it should be."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest

from prml2_edge.viz.png import BLUE, RED, Canvas, Series, line_plot, nice_ticks, read_png, write_png


def test_png_round_trip_is_exact(tmp_path, rng):
    img = rng.integers(0, 256, (17, 23, 3), dtype=np.uint8)
    path = write_png(tmp_path / "x.png", img)
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    w, h = struct.unpack(">II", data[16:24])
    assert (w, h) == (23, 17)
    np.testing.assert_array_equal(read_png(path), img)
    bad = bytearray(data)
    bad[30] ^= 0xFF  # inside IHDR/IDAT: the CRC must catch it
    (tmp_path / "bad.png").write_bytes(bytes(bad))
    with pytest.raises((ValueError, zlib.error)):
        read_png(tmp_path / "bad.png")


def test_line_plot_draws_series_in_their_colours_with_equal_aspect(tmp_path):
    t = np.linspace(0, 2 * np.pi, 400)
    path = line_plot(tmp_path / "p.png", [Series(100 * np.cos(t), 100 * np.sin(t), BLUE),
                                          Series(np.array([0.0]), np.array([0.0]), RED, "centre", 4, marker=True)],
                     title="test plot", xlabel="x [m]", ylabel="y [m]", width=600, height=400, equal_aspect=True)
    img = read_png(path)
    assert img.shape == (400, 600, 3)
    blue = np.all(img == BLUE, axis=2)
    ys, xs = np.nonzero(blue)  # unlabelled: no legend entry in blue
    width, height = xs.max() - xs.min(), ys.max() - ys.min()
    assert height > 200 and abs(width - height) <= 0.05 * height  # a circle stays round
    red = np.argwhere(np.all(img == RED, axis=2))
    assert len(red) > 10
    assert (img == 0).all(axis=2).sum() > 500  # axes box and text in black


def test_nan_breaks_lines_and_far_points_are_clipped():
    cv = Canvas(50, 50)
    cv.polyline(np.array([5.0, 45.0, np.nan, 5.0, 1e9]), np.array([5.0, 5.0, np.nan, 45.0, 1e9]), (0, 0, 0))
    assert (cv.img[5, 5:46] == 0).all() and (cv.img[20:40, 5] == 255).all()
    cv.rect(-100, -100, 1000, 1000, (1, 2, 3))  # no IndexError


def test_nice_ticks():
    np.testing.assert_allclose(nice_ticks(-3.2, 48.0), [0, 10, 20, 30, 40])
    assert len(nice_ticks(0.0, 1e-3)) >= 3
