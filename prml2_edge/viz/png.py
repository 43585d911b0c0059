"""A small, dependency-free PNG line-plot writer (NumPy + zlib), for ``prml2 demo`` without matplotlib.

:func:`line_plot` draws polylines (and point markers) in data coordinates onto an RGB canvas
with axes, a tick grid with labels, a title and a legend, then :func:`write_png` stores it as an
8-bit RGB PNG (IHDR, one zlib-compressed IDAT, IEND; filter 0 on every row).
"""

from __future__ import annotations

import math
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from prml2_edge.viz.font import GLYPH_H, GLYPH_W, glyph

WHITE = (255, 255, 255)
BLACK = (0, 0, 0)
GREY = (225, 225, 225)
BLUE = (31, 119, 180)
ORANGE = (255, 127, 14)
GREEN = (44, 160, 44)
RED = (214, 39, 40)


@dataclass
class Series:
    """A polyline ``(x, y)`` (N,) in data units, drawn ``width`` pixels wide; ``marker`` draws dots instead."""

    x: np.ndarray
    y: np.ndarray
    color: tuple[int, int, int] = BLUE
    label: str = ""
    width: int = 2
    marker: bool = False


def write_png(path: str | Path, rgb: np.ndarray) -> Path:
    """Write an (H, W, 3) uint8 image as PNG and return the path."""
    img = np.ascontiguousarray(rgb, dtype=np.uint8)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"image must be (H, W, 3) uint8, got {img.shape}")
    h, w, _ = img.shape
    raw = np.zeros((h, 1 + 3 * w), dtype=np.uint8)  # filter byte 0 (None) per scanline
    raw[:, 1:] = img.reshape(h, 3 * w)

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(raw.tobytes(), 6)) + chunk(b"IEND", b"")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(png)
    return path


def read_png(path: str | Path) -> np.ndarray:
    """Read back an 8-bit RGB, non-interlaced PNG with filter 0 rows (what :func:`write_png` writes)."""
    data = Path(path).read_bytes()
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError(f"{path}: not a PNG")
    pos, idat, w, h = 8, b"", 0, 0
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos:pos + 4])
        tag = data[pos + 4:pos + 8]
        body = data[pos + 8:pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length:pos + 12 + length])
        if zlib.crc32(tag + body) & 0xFFFFFFFF != crc:
            raise ValueError(f"{path}: CRC mismatch in chunk {tag!r}")
        if tag == b"IHDR":
            w, h, depth, ctype = struct.unpack(">IIBB", body[:10])
            if (depth, ctype) != (8, 2):
                raise ValueError(f"{path}: only 8-bit RGB is supported")
        elif tag == b"IDAT":
            idat += body
        pos += 12 + length
    raw = np.frombuffer(zlib.decompress(idat), dtype=np.uint8).reshape(h, 1 + 3 * w)
    if np.any(raw[:, 0] != 0):
        raise ValueError(f"{path}: only filter type 0 is supported")
    return raw[:, 1:].reshape(h, w, 3).copy()


def nice_ticks(lo: float, hi: float, target: int = 6) -> np.ndarray:
    """Round tick values (1, 2, 5 x 10^k steps) covering [lo, hi]."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return np.array([lo])
    raw = (hi - lo) / max(target, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1.0, 2.0, 5.0, 10.0) if m * mag >= raw)
    first = math.ceil(lo / step) * step
    ticks = np.arange(first, hi + 0.5 * step, step)
    return ticks[ticks <= hi + 1e-9 * step][: 4 * target]


def _fmt(v: float) -> str:
    if v == 0:
        return "0"
    if abs(v) >= 1000 or abs(v) < 0.01:
        return f"{v:.0e}".replace("e+0", "e").replace("e-0", "e-")
    return f"{v:.2f}".rstrip("0").rstrip(".")


class Canvas:
    """An RGB canvas with pixel-level drawing primitives (clipped to the image)."""

    def __init__(self, width: int, height: int, background: tuple[int, int, int] = WHITE) -> None:
        self.img = np.empty((height, width, 3), dtype=np.uint8)
        self.img[:] = background
        self.w, self.h = width, height

    def points(self, px: np.ndarray, py: np.ndarray, color, radius: int = 0) -> None:
        """Set pixels at (px, py) (float arrays), each as a disc of ``radius``."""
        px = np.rint(np.asarray(px, dtype=np.float64)).astype(np.int64)
        py = np.rint(np.asarray(py, dtype=np.float64)).astype(np.int64)
        offsets = [(dx, dy) for dx in range(-radius, radius + 1) for dy in range(-radius, radius + 1)
                   if dx * dx + dy * dy <= radius * radius + radius]
        for dx, dy in offsets:
            x, y = px + dx, py + dy
            keep = (x >= 0) & (x < self.w) & (y >= 0) & (y < self.h)
            self.img[y[keep], x[keep]] = color

    def polyline(self, px: np.ndarray, py: np.ndarray, color, width: int = 1) -> None:
        """Connected segments through (px, py), sampled every half pixel; NaN points break the line."""
        px = np.asarray(px, dtype=np.float64)
        py = np.asarray(py, dtype=np.float64)
        if px.size == 0:
            return
        if px.size == 1:
            self.points(px, py, color, width // 2)
            return
        x0, x1, y0, y1 = px[:-1], px[1:], py[:-1], py[1:]
        ok = np.isfinite(x0) & np.isfinite(x1) & np.isfinite(y0) & np.isfinite(y1)
        x0, x1, y0, y1 = x0[ok], x1[ok], y0[ok], y1[ok]
        n = np.maximum(np.ceil(2.0 * np.hypot(x1 - x0, y1 - y0)).astype(np.int64), 1)
        n = np.minimum(n, 4 * (self.w + self.h))  # a segment far outside the canvas is not worth more
        seg = np.repeat(np.arange(x0.size), n)
        frac = (np.arange(seg.size) - np.repeat(np.cumsum(n) - n, n)) / np.repeat(n, n)
        px_all = np.concatenate([x0[seg] + frac * (x1 - x0)[seg], x1])  # segment samples, then the end points
        py_all = np.concatenate([y0[seg] + frac * (y1 - y0)[seg], y1])
        self.points(px_all, py_all, color, max(width // 2, 0))

    def rect(self, x0: int, y0: int, x1: int, y1: int, color, fill: bool = False) -> None:
        x0, x1 = sorted((x0, x1))
        y0, y1 = sorted((y0, y1))
        if x1 < 0 or y1 < 0 or x0 >= self.w or y0 >= self.h:
            return
        x0, x1 = max(0, x0), min(self.w - 1, x1)
        y0, y1 = max(0, y0), min(self.h - 1, y1)
        if fill:
            self.img[y0:y1 + 1, x0:x1 + 1] = color
        else:
            self.img[y0, x0:x1 + 1] = color
            self.img[y1, x0:x1 + 1] = color
            self.img[y0:y1 + 1, x0] = color
            self.img[y0:y1 + 1, x1] = color

    def text(self, x: int, y: int, text: str, color=BLACK, scale: int = 2, anchor: str = "left") -> None:
        """Draw ``text`` with its top at ``y``; ``anchor`` left, center or right at ``x``."""
        adv = (GLYPH_W + 1) * scale
        width = len(text) * adv - scale
        if anchor == "center":
            x -= width // 2
        elif anchor == "right":
            x -= width
        for i, ch in enumerate(text):
            bitmap = np.kron(glyph(ch), np.ones((scale, scale), dtype=bool))
            gy, gx = np.nonzero(bitmap)
            self.points(x + i * adv + gx, y + gy, color)

    @staticmethod
    def text_height(scale: int = 2) -> int:
        return GLYPH_H * scale


def line_plot(path: str | Path, series: Sequence[Series], title: str = "", xlabel: str = "", ylabel: str = "",
              width: int = 900, height: int = 700, equal_aspect: bool = False) -> Path:
    """Plot ``series`` in data coordinates and write a PNG; returns the path.

    ``equal_aspect`` keeps one data unit the same length on both axes (trajectories in metres).
    """
    left, right, top, bottom = 90, 20, 50 if title else 20, 60
    cv = Canvas(width, height)
    xs = np.concatenate([np.asarray(s.x, dtype=np.float64).ravel() for s in series]) if series else np.zeros(1)
    ys = np.concatenate([np.asarray(s.y, dtype=np.float64).ravel() for s in series]) if series else np.zeros(1)
    ok = np.isfinite(xs) & np.isfinite(ys)
    xs, ys = (xs[ok], ys[ok]) if ok.any() else (np.zeros(1), np.zeros(1))
    x_lo, x_hi, y_lo, y_hi = float(xs.min()), float(xs.max()), float(ys.min()), float(ys.max())
    pad_x = max(0.05 * (x_hi - x_lo), 1e-6)
    pad_y = max(0.05 * (y_hi - y_lo), 1e-6)
    x_lo, x_hi, y_lo, y_hi = x_lo - pad_x, x_hi + pad_x, y_lo - pad_y, y_hi + pad_y
    plot_w, plot_h = width - left - right, height - top - bottom
    sx, sy = plot_w / (x_hi - x_lo), plot_h / (y_hi - y_lo)
    if equal_aspect:
        s = min(sx, sy)
        cx, cy = 0.5 * (x_lo + x_hi), 0.5 * (y_lo + y_hi)
        x_lo, x_hi = cx - 0.5 * plot_w / s, cx + 0.5 * plot_w / s
        y_lo, y_hi = cy - 0.5 * plot_h / s, cy + 0.5 * plot_h / s
        sx = sy = s

    def to_px(x, y):
        return left + (np.asarray(x, dtype=np.float64) - x_lo) * sx, top + plot_h - (np.asarray(y, dtype=np.float64)
                                                                                       - y_lo) * sy

    for tx in nice_ticks(x_lo, x_hi):
        px, _ = to_px(tx, y_lo)
        cv.rect(int(round(float(px))), top, int(round(float(px))), top + plot_h, GREY)
        label = _fmt(float(tx))
        if float(px) + 6 * len(label) < width:  # a label cut by the image edge is worse than none
            cv.text(int(round(float(px))), top + plot_h + 8, label, anchor="center")
    for ty in nice_ticks(y_lo, y_hi):
        _, py = to_px(x_lo, ty)
        cv.rect(left, int(round(float(py))), left + plot_w, int(round(float(py))), GREY)
        cv.text(left - 8, int(round(float(py))) - Canvas.text_height() // 2, _fmt(float(ty)), anchor="right")
    for s in series:
        px, py = to_px(s.x, s.y)
        if s.marker:
            cv.points(px[np.isfinite(px) & np.isfinite(py)], py[np.isfinite(px) & np.isfinite(py)], s.color, s.width)
        else:
            cv.polyline(px, py, s.color, s.width)
    cv.rect(left, top, left + plot_w, top + plot_h, BLACK)
    if title:
        cv.text(width // 2, 15, title, anchor="center")
    if xlabel:
        cv.text(left + plot_w // 2, height - 24, xlabel, anchor="center")
    if ylabel:
        cv.text(8, top - 16 if top > 30 else 2, ylabel)
    labelled = [s for s in series if s.label]
    if labelled:
        line_h = Canvas.text_height() + 8
        box_w = 40 + max(len(s.label) for s in labelled) * 12
        box_h = line_h * len(labelled) + 6
        # the corner of the plot area that hides the fewest data points
        all_px, all_py = to_px(xs, ys)
        corners = [(left + plot_w - box_w - 10, top + 10), (left + 10, top + 10),
                   (left + plot_w - box_w - 10, top + plot_h - box_h - 10), (left + 10, top + plot_h - box_h - 10)]
        hidden = [int(np.count_nonzero((all_px >= cx) & (all_px <= cx + box_w) & (all_py >= cy) &
                                       (all_py <= cy + box_h))) for cx, cy in corners]
        bx, by = corners[int(np.argmin(hidden))]
        cv.rect(bx, by, bx + box_w, by + line_h * len(labelled) + 6, WHITE, fill=True)
        cv.rect(bx, by, bx + box_w, by + line_h * len(labelled) + 6, BLACK)
        for i, s in enumerate(labelled):
            yy = by + 6 + i * line_h + Canvas.text_height() // 2
            if s.marker:
                cv.points(np.array([bx + 18.0]), np.array([float(yy)]), s.color, max(s.width, 2))
            else:
                cv.polyline(np.array([bx + 6.0, bx + 30.0]), np.array([float(yy)] * 2), s.color, max(s.width, 2))
            cv.text(bx + 36, yy - Canvas.text_height() // 2, s.label)
    return write_png(path, cv.img)
