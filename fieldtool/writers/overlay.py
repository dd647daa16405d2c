"""Drawing and encoding of the overlay video ``overlay.mp4`` (OpenCV only: no matplotlib in the run).

What is drawn on a frame (all in the frame's own pixels, BGR uint8):

- :func:`draw_arrows`: velocity vectors coloured by speed (m/s) through a perceptual colour map;
- :func:`draw_section`: the section as a thick line, each subsection coloured by its surface velocity (m/s);
- :func:`draw_legend`: the colour bar with its ticks in m/s;
- :func:`draw_panel`: a text box (site, station, operator, time code, running Q);
- :func:`draw_card`: the closing card (final Q, its 95 % interval, the grade).

The colour maps are matplotlib's ``viridis`` and ``cividis`` sampled at 33 points and interpolated
linearly (within 2.5 and 4.7 of 255 of the originals): :func:`lut`.

:class:`VideoWriter` encodes H.264 (yuv420p, even frame size, ``+faststart`` so a browser plays it while
it loads) through PyAV; where PyAV is missing it falls back to OpenCV's writer (MPEG-4 part 2, which
browsers may not play) and says so in ``warning``.
"""

from __future__ import annotations

import importlib
import unicodedata
from fractions import Fraction
from pathlib import Path
from types import ModuleType

import cv2
import numpy as np

# 33 samples of each map, #rrggbb without the hash, from 0 to 1
_MAPS = {
    "viridis": "440154 470d60 48186a 482374 472d7b 453781 424086 3e4989 3b528b 375b8d 33638d 2f6b8e 2c728e "
    "297a8e 26828e 23898e 21918c 1f988b 1fa088 22a785 28ae80 32b67a 3fbc73 4ec36b 5ec962 70cf57 "
    "84d44b 98d83e addc30 c2df23 d8e219 ece51b fde725",
    "cividis": "00224e 00285b 002e6a 053371 1a386f 273e6e 32436d 3b496c 434e6c 4b546c 535a6d 5a5f6e 61656f "
    "686a71 6f7073 767676 7d7c78 848279 8c8878 938e78 9b9476 a39a74 aba072 b4a76f bcae6c c4b468 "
    "cdbb63 d5c25e dec958 e7d150 f0d846 f9e03a fee838",
}
COLORMAPS = tuple(_MAPS)
NO_VALUE_BGR = (150, 150, 150)  # a subsection without a velocity
GRADE_BGR = {"good": (55, 127, 26), "doubtful": (0, 103, 154), "unusable": (34, 34, 207)}
FONT = cv2.FONT_HERSHEY_SIMPLEX


def lut(name: str = "viridis") -> np.ndarray:
    """(256, 3) uint8 BGR table of the colour map ``name`` (one of :data:`COLORMAPS`)."""
    if name not in _MAPS:
        raise ValueError(f"colour map {name!r} is not one of {', '.join(COLORMAPS)}")
    rgb = np.array([[int(h[i : i + 2], 16) for i in (0, 2, 4)] for h in _MAPS[name].split()], float)
    xa, x = np.linspace(0.0, 1.0, len(rgb)), np.linspace(0.0, 1.0, 256)
    table = np.stack([np.interp(x, xa, rgb[:, k]) for k in range(3)], axis=1)
    return np.round(table[:, ::-1]).astype(np.uint8)  # BGR


def colours(values, vmin: float, vmax: float, table: np.ndarray, levels: int = 256) -> np.ndarray:
    """(N, 3) uint8 BGR colours of ``values`` (m/s) between ``vmin`` and ``vmax`` (clipped); NaN grey.
    ``levels``: the number of distinct colours (fewer draw faster, :func:`draw_arrows`)."""
    v = np.asarray(values, float).ravel()
    span = vmax - vmin if vmax > vmin else 1.0
    q = np.clip(np.round((np.nan_to_num(v, nan=vmin) - vmin) / span * (levels - 1)), 0, levels - 1)
    idx = np.round(q * 255.0 / (levels - 1)).astype(int)
    out = table[idx].copy()
    out[~np.isfinite(v)] = NO_VALUE_BGR
    return out


def nice_ceil(x: float) -> float:
    """The smallest of 1, 1.2, 1.5, 2, 2.5, 3, 4, 5, 6, 8 x 10^k at or above ``x`` (> 0); 1 for x <= 0."""
    if not (np.isfinite(x) and x > 0):
        return 1.0
    e = 10.0 ** np.floor(np.log10(x))
    for m in (1.0, 1.2, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0):
        if m * e >= x * (1 - 1e-9):
            return float(m * e)
    return float(10.0 * e)


def ascii_text(text: str) -> str:
    """``text`` in the characters OpenCV's Hershey fonts draw (m³ -> m3, ± -> +/-, accents dropped)."""
    for a, b in (("³", "3"), ("²", "2"), ("±", "+/-"), ("–", "-"), ("—", "-"), ("·", "|"), ("α", "alpha")):
        text = text.replace(a, b)
    text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode("ascii")
    return "".join(ch if ch.isprintable() else " " for ch in text)


def text_scale(img: np.ndarray) -> float:
    """Font scale that keeps text readable from 360 to 2160 px high frames."""
    return max(0.4, img.shape[0] / 720.0 * 0.6)


def put_text(
    img: np.ndarray, text: str, org: tuple[int, int], scale: float, colour=(255, 255, 255), thickness: int | None = None
) -> None:
    """Text with a dark outline, readable on any background (the outline is the text drawn 1 px off in four
    directions: a thicker stroke would advance the glyphs further and drift from the text)."""
    t = max(1, int(round(scale * 1.8))) if thickness is None else thickness
    s = ascii_text(text)
    for dx, dy in ((-1, -1), (1, -1), (-1, 1), (1, 1)):
        cv2.putText(img, s, (org[0] + dx, org[1] + dy), FONT, scale, (0, 0, 0), t, cv2.LINE_AA)
    cv2.putText(img, s, org, FONT, scale, colour, t, cv2.LINE_AA)


def draw_arrows(img: np.ndarray, start: np.ndarray, end: np.ndarray, bgr: np.ndarray, thickness: int = 2) -> None:
    """Arrows from ``start`` to ``end`` ((N, 2) frame px), each in its colour ``bgr`` ((N, 3) uint8). Drawn one
    polyline call per colour (shaft and head as one open 5-point line), not one call per arrow."""
    h, w = img.shape[:2]
    a, b = np.asarray(start, float).reshape(-1, 2), np.asarray(end, float).reshape(-1, 2)
    c = np.asarray(bgr, np.uint8).reshape(-1, 3)
    keep = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
    keep &= (np.abs(a - (w / 2, h / 2)) < (1.5 * w, 1.5 * h)).all(axis=1)
    keep &= (np.abs(b - (w / 2, h / 2)) < (1.5 * w, 1.5 * h)).all(axis=1)
    a, b, c = a[keep], b[keep], c[keep]
    if not len(a):
        return
    d = b - a
    length = np.hypot(d[:, 0], d[:, 1])
    unit = d / np.maximum(length, 1e-9)[:, None]
    perp = np.c_[-unit[:, 1], unit[:, 0]]
    head = np.minimum(0.4 * length, 4.0 + 2.5 * thickness)[:, None]
    wing1 = b - head * (0.87 * unit + 0.5 * perp)
    wing2 = b - head * (0.87 * unit - 0.5 * perp)
    lines = np.round(np.stack([a, b, wing1, b, wing2], axis=1)).astype(np.int32)  # (N, 5, 2)
    colours_u, which = np.unique(c, axis=0, return_inverse=True)
    which = np.asarray(which).ravel()
    for k, col in enumerate(colours_u):
        cv2.polylines(img, list(lines[which == k]), False, tuple(int(v) for v in col), thickness, cv2.LINE_AA)


def draw_section(
    img: np.ndarray, limits: np.ndarray, v_sub, vmin: float, vmax: float, table: np.ndarray, thickness: int = 7
) -> None:
    """The section through its subsection limits ``limits`` ((n+1, 2) frame px), each subsection filled
    with the colour of its surface velocity ``v_sub`` ((n,) m/s; NaN grey), on a dark outline, with ticks."""
    p = np.asarray(limits, float)
    if len(p) < 2 or not np.all(np.isfinite(p)):
        return
    pts = np.round(p).astype(np.int32)
    cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, (0, 0, 0), thickness + 4, cv2.LINE_AA)
    cols = colours(v_sub, vmin, vmax, table)
    for k in range(len(pts) - 1):
        cv2.line(
            img,
            tuple(int(v) for v in pts[k]),
            tuple(int(v) for v in pts[k + 1]),
            tuple(int(v) for v in cols[k]),
            thickness,
            cv2.LINE_AA,
        )
    for q in pts:
        cv2.circle(img, (int(q[0]), int(q[1])), max(2, thickness // 2), (255, 255, 255), -1, cv2.LINE_AA)


_LEGENDS: dict = {}  # (frame shape, range, table, title) -> (patch, x0, y0): the legend is drawn once


def draw_legend(
    img: np.ndarray, vmin: float, vmax: float, table: np.ndarray, title: str = "surface velocity (m/s)"
) -> None:
    """A vertical colour bar in the top-right corner with round ticks in m/s, on a dark box."""
    key = (img.shape, float(vmin), float(vmax), table.tobytes(), title)
    if key not in _LEGENDS:
        if len(_LEGENDS) > 16:
            _LEGENDS.clear()
        _LEGENDS[key] = _legend_patch(img.shape, vmin, vmax, table, title)
    patch, x0, y0 = _LEGENDS[key]
    img[y0 : y0 + patch.shape[0], x0 : x0 + patch.shape[1]] = patch


def _legend_patch(shape, vmin: float, vmax: float, table: np.ndarray, title: str):
    h, w = shape[:2]
    canvas = np.zeros((h, w, 3), np.uint8)
    s = text_scale(canvas)
    bar_h, bar_w = int(h * 0.35), max(10, int(h * 0.025))
    thick = max(1, int(round(s * 0.8 * 1.8)))  # as put_text draws it
    (tw, th), _ = cv2.getTextSize(ascii_text(title), FONT, s * 0.8, thick)
    (lw, _), _ = cv2.getTextSize(f"{vmax:.2f}", FONT, s * 0.8, thick)
    x1 = w - int(h * 0.03)
    x0 = x1 - bar_w
    y0 = int(h * 0.04) + th + 8
    bx0, by0 = max(0, min(x0 - lw - 16, x1 - tw - 8) - 6), max(0, y0 - th - 14)
    bx1, by1 = min(w, x1 + 8), min(h, y0 + bar_h + 12)
    canvas[by0:by1, bx0:bx1] = (28, 28, 28)
    put_text(canvas, title, (x1 - tw, y0 - 8), s * 0.8)
    ramp = table[::-1][np.linspace(0, 255, bar_h).astype(int)]
    canvas[y0 : y0 + bar_h, x0:x1] = ramp[:, None, :]
    cv2.rectangle(canvas, (x0, y0), (x1 - 1, y0 + bar_h - 1), (255, 255, 255), 1)
    for f in np.linspace(0.0, 1.0, _ticks(vmax - vmin) + 1):
        y = int(round(y0 + (1.0 - f) * (bar_h - 1)))
        label = f"{vmin + f * (vmax - vmin):.2f}"
        cv2.line(canvas, (x0 - 5, y), (x0, y), (255, 255, 255), 1)
        (lw2, lh2), _ = cv2.getTextSize(label, FONT, s * 0.8, thick)
        put_text(canvas, label, (x0 - 8 - lw2, y + lh2 // 2), s * 0.8)
    return canvas[by0:by1, bx0:bx1].copy(), bx0, by0


def _ticks(span: float) -> int:
    """Number of tick intervals (2 to 6) that make round steps of ``span`` (1, 2, 2.5 or 5 x 10^k); 4 else."""
    for n in (4, 5, 3, 6, 2):
        step = span / n
        if step > 0:
            m = step / 10.0 ** np.floor(np.log10(step))
            if any(abs(m - r) < 1e-6 for r in (1.0, 2.0, 2.5, 5.0, 10.0)):
                return n
    return 4


def _shade(img: np.ndarray, x0: int, y0: int, x1: int, y1: int, alpha: float = 0.55) -> None:
    """Darken a box of ``img`` in place (text backgrounds)."""
    h, w = img.shape[:2]
    x0, y0, x1, y1 = max(0, x0), max(0, y0), min(w, x1), min(h, y1)
    if x1 > x0 and y1 > y0:
        img[y0:y1, x0:x1] = (img[y0:y1, x0:x1] * (1.0 - alpha)).astype(np.uint8)


def draw_panel(img: np.ndarray, lines: list[str], corner: str = "tl") -> None:
    """Lines of text in a shaded box, in the top-left (``tl``) or bottom-left (``bl``) corner."""
    lines = [ascii_text(t) for t in lines if t]
    if not lines:
        return
    h, w = img.shape[:2]
    s = text_scale(img)
    sizes = [cv2.getTextSize(t, FONT, s, max(1, int(round(s * 1.8))))[0] for t in lines]
    lh = int(max(sz[1] for sz in sizes) * 1.7) + 2
    bw = max(sz[0] for sz in sizes) + 20
    bh = lh * len(lines) + 10
    x0 = int(h * 0.02)
    y0 = int(h * 0.02) if corner == "tl" else h - int(h * 0.02) - bh
    _shade(img, x0, y0, x0 + bw, y0 + bh)
    for k, t in enumerate(lines):
        put_text(img, t, (x0 + 10, y0 + 5 + lh * (k + 1) - lh // 4), s)


def draw_card(img: np.ndarray, lines: list[tuple[str, tuple[int, int, int], float]], centre: float = 0.72) -> None:
    """The closing card: ``(text, BGR colour, relative size)`` lines centred across the frame at ``centre`` of its
    height (below the middle, where the section usually is), on a shaded box."""
    h, w = img.shape[:2]
    s = text_scale(img)
    sizes = [cv2.getTextSize(ascii_text(t), FONT, s * r, max(1, int(round(s * r * 1.8))))[0] for t, _, r in lines]
    heights = [int(sz[1] * 2.0) for sz in sizes]
    total = sum(heights)
    bw = max(sz[0] for sz in sizes) + int(0.06 * w)
    y = int(min(h * centre - total / 2, h - total - 0.06 * h))
    _shade(img, (w - bw) // 2, y - int(0.02 * h), (w + bw) // 2, y + total + int(0.04 * h), alpha=0.7)
    for (t, c, r), lh, (tw, _) in zip(lines, heights, sizes, strict=False):
        y += lh
        put_text(img, t, ((w - tw) // 2, y), s * r, c)


def even_size(width: int, height: int) -> tuple[int, int]:
    """(width, height) rounded down to even numbers (yuv420p needs both), at least 2."""
    return max(2, int(width) // 2 * 2), max(2, int(height) // 2 * 2)


class VideoWriter:
    """An MP4 file written frame by frame at ``fps`` (s⁻¹), ``width`` x ``height`` px (even).

    ``write(bgr, pts)``: ``pts`` is the frame's position in frame periods (0, 1, 2, ...; a gap is a
    held frame). ``backend`` is "pyav" (H.264) or "opencv" (fallback); ``warning`` says why when the
    fallback was used. x264's ``superfast`` preset at CRF 23: on the demo's particle texture it encodes in
    0.6 of ``veryfast``'s time for a file 1.4 x larger (~1.5 MB for 5 s at 960 x 540).
    """

    def __init__(
        self,
        path: Path | str,
        width: int,
        height: int,
        fps: float,
        *,
        crf: int = 23,
        preset: str = "superfast",
        threads: int = 1,
    ) -> None:
        if width % 2 or height % 2:
            raise ValueError(f"frame size {width}x{height}: H.264 in yuv420p needs even sides")
        self.path, self.width, self.height = Path(path), int(width), int(height)
        self.rate = Fraction(float(fps)).limit_denominator(1001)
        self.frames = 0
        self.warning = ""
        try:
            # imported here, not at the top: `import av` costs 40-75 ms, and every run imports this module
            av: ModuleType | None = importlib.import_module("av")
        except ImportError:
            av = None
        if av is not None:
            self.backend, self.codec = "pyav", "h264"
            self._av = av
            self._c = av.open(str(self.path), "w", format="mp4", options={"movflags": "+faststart"})
            st = self._c.add_stream("libx264", rate=self.rate)
            st.width, st.height, st.pix_fmt = self.width, self.height, "yuv420p"
            st.options = {"preset": preset, "crf": str(int(crf))}
            st.codec_context.thread_count = max(1, int(threads))
            self._s = st
        else:
            self.backend, self.codec = "opencv", "mp4v"
            self.warning = (
                "overlay.mp4 written with OpenCV's MPEG-4 part 2 (mp4v) codec because PyAV is not "
                "installed; browsers may not play it: pip install av"
            )
            self._w: cv2.VideoWriter = cv2.VideoWriter(
                str(self.path), cv2.VideoWriter.fourcc(*"mp4v"), float(self.rate), (self.width, self.height)
            )
            if not self._w.isOpened():
                raise OSError(f"{self.path}: OpenCV cannot write an MP4 file here")
            self._last_pts: int = -1

    def write(self, bgr: np.ndarray, pts: int) -> None:
        """Encode one BGR uint8 frame of this writer's size at position ``pts`` (frame periods)."""
        if bgr.shape[:2] != (self.height, self.width):
            raise ValueError(f"frame {bgr.shape[1]}x{bgr.shape[0]} is not the video's {self.width}x{self.height}")
        if self.backend == "pyav":
            # OpenCV's BT.601 limited-range conversion, as swscale's default, in a fifth of its time
            f = self._av.VideoFrame.from_ndarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_I420), format="yuv420p")
            f.pts, f.time_base = int(pts), 1 / self.rate
            for p in self._s.encode(f):
                self._c.mux(p)
        else:  # constant rate: a gap is filled by repeating the frame
            for _ in range(max(1, int(pts) - self._last_pts)):
                self._w.write(bgr)
            self._last_pts = int(pts)
        self.frames += 1

    def close(self) -> None:
        """Flush the encoder and finish the file."""
        if self.backend == "pyav":
            if self._c is not None:
                for p in self._s.encode():
                    self._c.mux(p)
                self._c.close()
                self._c = None
        else:
            self._w.release()

    def abort(self) -> None:
        """Close without caring for the file (it is removed by the caller)."""
        try:
            if self.backend == "pyav" and self._c is not None:
                self._c.close()
                self._c = None
            elif self.backend == "opencv":
                self._w.release()
        except Exception:  # noqa: BLE001 - the file is being thrown away
            pass
