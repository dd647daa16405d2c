"""Terminal plots: a braille line plot (cross-section) and a half-block gray image (filter preview).

Braille cells hold 2 x 4 dots, so an 60 x 8 cell plot has 120 x 32 dots; a half-block cell holds
two pixels one above the other (foreground and background colour).
"""

from __future__ import annotations

import cv2
import numpy as np
from rich.style import Style
from rich.text import Text
from textual.widget import Widget

# dot bit of column c (0, 1), row r (0..3) in a braille cell (U+2800 + bits)
_BRAILLE = ((0x01, 0x08), (0x02, 0x10), (0x04, 0x20), (0x40, 0x80))


def braille_lines(
    series: list[tuple[np.ndarray, np.ndarray]],
    width: int,
    height: int,
    x_range: tuple[float, float],
    y_range: tuple[float, float],
) -> list[list[list[int]]]:
    """Rasterise polylines into braille cells: a ``height`` x ``width`` grid of dot bit masks per series.

    Returns one grid (list of rows of ints) per series, so each can be coloured.
    """
    W, H = 2 * width, 4 * height
    x0, x1 = x_range
    y0, y1 = y_range
    sx = (W - 1) / (x1 - x0) if x1 > x0 else 0.0
    sy = (H - 1) / (y1 - y0) if y1 > y0 else 0.0
    grids = []
    for xs, ys in series:
        grid = [[0] * width for _ in range(height)]
        px = (np.asarray(xs, float) - x0) * sx
        py = (y1 - np.asarray(ys, float)) * sy  # y up
        for k in range(len(px) - 1):
            n = int(max(abs(px[k + 1] - px[k]), abs(py[k + 1] - py[k]))) + 1
            for t in np.linspace(0.0, 1.0, n + 1):
                X = int(round(px[k] + t * (px[k + 1] - px[k])))
                Y = int(round(py[k] + t * (py[k + 1] - py[k])))
                if 0 <= X < W and 0 <= Y < H:
                    grid[Y // 4][X // 2] |= _BRAILLE[Y % 4][X % 2]
        grids.append(grid)
    return grids


class SectionPlot(Widget):
    """Bed profile (station, elevation) with the water level and its wetted part."""

    DEFAULT_CSS = "SectionPlot { height: 8; }"

    def __init__(self, *, id: str | None = None) -> None:
        super().__init__(id=id)
        self.station: np.ndarray | None = None
        self.elevation: np.ndarray | None = None
        self.level: float | None = None
        self.message = ""

    def set_data(self, station=None, elevation=None, level: float | None = None, message: str = "") -> None:
        self.station = None if station is None else np.asarray(station, float)
        self.elevation = None if elevation is None else np.asarray(elevation, float)
        self.level = level
        self.message = message
        self.refresh()

    def render(self) -> Text:
        w, h = self.size.width, self.size.height
        if self.station is None or w < 20 or h < 3:
            return Text(self.message or "no cross-section yet", style="dim")
        s, z = self.station, self.elevation
        assert z is not None  # set_data is given a station and an elevation together
        lab_w = 8
        pw, ph = w - lab_w, h - 1
        zmin, zmax = float(z.min()), float(z.max())
        if self.level is not None:
            zmax = max(zmax, self.level)
        pad = 0.05 * (zmax - zmin or 1.0)
        yr = (zmin - pad, zmax + pad)
        xr = (float(s.min()), float(s.max()))
        series: list[tuple[np.ndarray, np.ndarray]] = [(s, z)]
        if self.level is not None:
            series.append((np.array(xr), np.array([self.level, self.level])))
        grids = braille_lines(series, pw, ph, xr, yr)
        styles = ["yellow", "bold cyan"]
        out = Text()
        for r in range(ph):
            label = f"{yr[1]:7.2f} " if r == 0 else (f"{yr[0]:7.2f} " if r == ph - 1 else " " * lab_w)
            out.append(label, style="dim")
            for c in range(pw):
                bits = [g[r][c] for g in grids]
                k = next((i for i in range(len(bits) - 1, -1, -1) if bits[i]), None)
                if k is None:
                    out.append(" ")
                else:
                    out.append(chr(0x2800 + (bits[0] | (bits[1] if len(bits) > 1 else 0))), style=styles[k])
            out.append("\n")
        foot = f"{xr[0]:.2f} m"
        right = f"{xr[1]:.2f} m"
        lvl = f"  level {self.level:.3f} m" if self.level is not None else ""
        out.append(" " * lab_w + foot + lvl + " " * max(1, pw - len(foot) - len(right) - len(lvl)) + right, style="dim")
        return out


def fit_cells(h: int, w: int, cols: int, rows: int) -> tuple[int, int]:
    """Cells (cols, rows) of an ``h`` x ``w`` px image fitted into ``cols`` x ``rows`` half-block
    cells with its aspect kept (a cell is one pixel wide and two high, about square on screen)."""
    if h <= 0 or w <= 0:
        return 0, 0
    scale = min(cols / w, 2 * rows / h)
    return max(1, min(cols, int(round(w * scale)))), max(1, min(rows, int(round(h * scale / 2))))


class GrayImage(Widget):
    """A gray image drawn with half blocks (two pixels per cell), fitted to the widget with its
    aspect kept, and a caption on the last line."""

    DEFAULT_CSS = "GrayImage { height: 8; }"

    def __init__(self, *, id: str | None = None) -> None:
        super().__init__(id=id)
        self.image: np.ndarray | None = None
        self.caption = ""

    def set_image(self, img: np.ndarray | None, caption: str = "") -> None:
        self.image = None if img is None else np.asarray(img, float)
        self.caption = caption
        self.refresh()

    def render(self) -> Text:
        w, h = self.size.width, self.size.height
        if self.image is None or w < 2 or h < 2:
            return Text(self.caption or "no image", style="dim")

        ih, iw = self.image.shape[:2]
        cols, rows = fit_cells(ih, iw, w, h - 1)
        small = cv2.resize(self.image.astype(np.float32), (cols, 2 * rows), interpolation=cv2.INTER_AREA)
        g = np.clip(small, 0, 255).astype(int)
        out = Text()
        for r in range(0, 2 * rows, 2):
            for c in range(cols):
                top, bot = g[r, c], g[r + 1, c]
                out.append("▀", style=Style(color=f"rgb({top},{top},{top})", bgcolor=f"rgb({bot},{bot},{bot})"))
            out.append("\n")
        out.append(self.caption[:w], style="dim")
        return out


_ARROWS = "→↘↓↙←↖↑↗"  # image axes: x right, y down; index = direction in 45 degree steps from +x


class VectorGrid(Widget):
    """Mean velocity field as one arrow per cell (image axes), brighter = faster; · = no valid vector. With a
    water mask, the grid is cropped to the water's rows and columns and nodes off the water stay blank (no
    arrow on a bank)."""

    DEFAULT_CSS = "VectorGrid { height: 7; }"

    def __init__(self, *, id: str | None = None) -> None:
        super().__init__(id=id)
        self.field: tuple[np.ndarray, np.ndarray] | None = None
        self.water: np.ndarray | None = None

    def set_field(self, u: np.ndarray | None, v: np.ndarray | None, water: np.ndarray | None = None) -> None:
        if u is None:
            self.field, self.water = None, None
        else:
            u, v = np.asarray(u, float), np.asarray(v, float)
            w = None if water is None else np.asarray(water, bool)
            if w is not None and w.shape == u.shape and w.any():
                rows, cols = np.nonzero(w.any(axis=1))[0], np.nonzero(w.any(axis=0))[0]
                sl = np.s_[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
                u, v, w = u[sl], v[sl], w[sl]
            elif w is not None and w.shape != u.shape:
                w = None
            self.field, self.water = (u, v), w
        self.refresh()

    def render(self) -> Text:
        if self.field is None:
            return Text("")
        u, v = self.field
        w, h = self.size.width, self.size.height
        ny, nx = u.shape
        rows = min(h, ny)
        cols = min(w, nx)
        ri = np.linspace(0, ny - 1, rows).round().astype(int)
        ci = np.linspace(0, nx - 1, cols).round().astype(int)
        su, sv = u[np.ix_(ri, ci)], v[np.ix_(ri, ci)]
        wet = None if self.water is None else self.water[np.ix_(ri, ci)]
        speed = np.hypot(su, sv)
        shown = np.isfinite(speed) & (wet if wet is not None else True)
        top = np.nanmax(speed[shown]) if shown.any() else 1.0
        out = Text()
        for r in range(rows):
            for c in range(cols):
                s = speed[r, c]
                if wet is not None and not wet[r, c]:
                    out.append(" ")  # not on the water: no arrow
                    continue
                if not np.isfinite(s):
                    out.append("·", style="dim red")
                    continue
                k = int(np.round(np.arctan2(sv[r, c], su[r, c]) / (np.pi / 4))) % 8
                g = int(90 + 165 * min(s / top, 1.0)) if top > 0 else 255
                out.append(_ARROWS[k], style=f"rgb({g},{g},255)")
            out.append("\n")
        return out
