"""Image filters before PIV (thesis 7.2, 9.2.7), as an ordered stack from the project file.

The six thesis filters (intensity high-pass, intensity capping, CLAHE, brightness/contrast, gamma,
non-local means) plus temporal background subtraction (PIVlab/RIVeR), which removes what does not
move over the clip, such as static sun glints that pull LSPIV towards zero.

A stack is a list of tables, e.g. ``[{name = "clahe", clip_limit = 2.0}, {name = "gamma"}]``.
A parameter left out takes its default: a generic value, or one computed from the image (the first
frame the stack sees, then kept for the whole clip, so every frame gets the same transform;
:meth:`FilterStack.resolved` tells what was used). Intensities are on the 0-255 scale; each filter
returns float32 clipped to 0-255, as the thesis sets out-of-range pixels to the nearest valid value.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from fieldtool.errors import Cancelled, ParameterError


@dataclass(frozen=True)
class Param:
    """One filter parameter: type, allowed range, default (None = computed from the image)."""

    name: str
    kind: type  # float, int or str
    default: Any
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False  # lo itself not allowed
    odd: bool = False
    choices: tuple[str, ...] = ()
    doc: str = ""

    def check(self, value: Any, key: str) -> Any:
        if self.kind is str:
            if not isinstance(value, str) or value not in self.choices:
                raise ParameterError(f"{key}: {value!r} is not allowed; use one of {', '.join(self.choices)}")
            return value
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ParameterError(f"{key}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ParameterError(f"{key}: {value} is not a finite number")
        if self.kind is int:
            if value != int(value):
                raise ParameterError(f"{key}: expected a whole number, got {value!r}")
            value = int(value)
        else:
            value = float(value)
        too_low = self.lo is not None and (value <= self.lo if self.lo_open else value < self.lo)
        too_high = self.hi is not None and value > self.hi
        if too_low or too_high:
            op = "<" if self.lo_open else "<="
            raise ParameterError(
                f"{key}: {value:g} is out of range; use {self.lo:g} {op} {self.name} <= {self.hi:g}"
                + (f" ({self.doc})" if self.doc else "")
            )
        if self.odd and value % 2 == 0:
            raise ParameterError(f"{key}: {value} must be odd (e.g. {value + 1})")
        return value


def _u8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _clip(img: np.ndarray) -> np.ndarray:
    return np.clip(img, 0.0, 255.0).astype(np.float32, copy=False)


class Filter:
    """Base: holds the user's parameters; missing ones are computed on the first image."""

    name = ""
    params: tuple[Param, ...] = ()

    def __init__(self, values: dict[str, Any], key: str = "filter") -> None:
        known = {p.name: p for p in self.params}
        self.given: dict[str, Any] = {}
        for k, v in values.items():
            if k == "name":
                continue
            if k not in known:
                names = ", ".join(known) or "none"
                raise ParameterError(f"{key}.{k}: unknown parameter for the {self.name} filter (known: {names})")
            self.given[k] = known[k].check(v, f"{key}.{k}")
        self.key = key
        self.values: dict[str, Any] | None = None
        self._validate()

    def _validate(self) -> None:
        """Cross-parameter checks on the given values."""

    def image_defaults(self, img: np.ndarray) -> dict[str, Any]:
        """Defaults computed from ``img`` (float32, 0-255) for the parameters whose default is None."""
        return {}

    def resolve(self, img: np.ndarray) -> dict[str, Any]:
        """Fix every parameter, computing the missing image-based ones from ``img`` once."""
        if self.values is None:
            vals = {p.name: p.default for p in self.params}
            vals.update(self.given)
            missing = [k for k, v in vals.items() if v is None]
            if missing:
                auto = self.image_defaults(img)
                for k in missing:
                    vals[k] = auto[k]
            self.values = vals
        return self.values

    def __call__(self, img: np.ndarray) -> np.ndarray:
        return self.run(img, **self.resolve(img))

    def run(self, img: np.ndarray, **p: Any) -> np.ndarray:
        raise NotImplementedError


class HighPass(Filter):
    """Intensity high-pass (7.2.1): (image - Gaussian low-pass) x factor; factor = 255 / max by default."""

    name = "highpass"
    params = (
        Param("kernel_px", int, 15, 3, 501, odd=True, doc="Gaussian low-pass kernel side, px"),
        Param("factor", float, None, 0.0, 1000.0, lo_open=True, doc="contrast gain after subtraction"),
    )

    def _highpass(self, img: np.ndarray, kernel_px: int) -> np.ndarray:
        return img - cv2.GaussianBlur(img, (kernel_px, kernel_px), 0)

    def image_defaults(self, img):
        hp_max = float(self._highpass(img, self.given.get("kernel_px", 15)).max())
        return {"factor": 255.0 / hp_max if hp_max > 1e-6 else 1.0}

    def run(self, img, kernel_px, factor):
        return _clip(self._highpass(img, kernel_px) * factor)


class Capping(Filter):
    """Intensity capping (7.2.2): pixels above the limit are set to it; limit = median + 2 sd by default."""

    name = "capping"
    params = (Param("limit", float, None, 0.0, 255.0, lo_open=True, doc="grey-level ceiling"),)

    def image_defaults(self, img):
        limit = float(np.median(img) + 2.0 * img.std())
        return {"limit": float(np.clip(limit, 1.0, 255.0))}

    def run(self, img, limit):
        return _clip(np.minimum(img, limit))


class Clahe(Filter):
    """Contrast-limited adaptive histogram equalisation (7.2.3), OpenCV defaults (40, 8 x 8 tiles)."""

    name = "clahe"
    params = (
        Param("clip_limit", float, 40.0, 0.0, 1000.0, lo_open=True, doc="contrast limit"),
        Param("tile_grid", int, 8, 1, 64, doc="tiles per side"),
    )

    def run(self, img, clip_limit, tile_grid):
        clahe = cv2.createCLAHE(clipLimit=clip_limit, tileGridSize=(tile_grid, tile_grid))
        return clahe.apply(_u8(img)).astype(np.float32)


class BrightnessContrast(Filter):
    """g = alpha f + beta (7.2.4); by default the 1st-99th percentiles are stretched to 0-255."""

    name = "brightness_contrast"
    params = (
        Param("alpha", float, None, 0.0, 10.0, lo_open=True, doc="contrast gain"),
        Param("beta", float, None, -255.0, 255.0, doc="brightness offset, grey levels"),
    )

    def image_defaults(self, img):
        lo, hi = (float(v) for v in np.percentile(img, [1, 99]))
        alpha = float(np.clip(255.0 / (hi - lo), 0.1, 10.0)) if hi - lo > 1e-6 else 1.0
        alpha = self.given.get("alpha", alpha)
        beta = float(np.clip(-alpha * lo, -255.0, 255.0))
        return {"alpha": alpha, "beta": beta}

    def run(self, img, alpha, beta):
        return _clip(alpha * img + beta)


class Gamma(Filter):
    """O = (I / 255)^gamma x 255 (7.2.5); by default gamma maps the median grey to mid-grey."""

    name = "gamma"
    params = (Param("gamma", float, None, 0.0, 10.0, lo_open=True, doc="< 1 brightens, > 1 darkens"),)

    def image_defaults(self, img):
        med = float(np.median(img)) / 255.0
        if not 1e-3 < med < 1 - 1e-3:
            return {"gamma": 1.0}
        return {"gamma": float(np.clip(math.log(0.5) / math.log(med), 0.1, 10.0))}

    def run(self, img, gamma):
        return _clip(np.power(np.clip(img, 0, 255) / 255.0, gamma, dtype=np.float32) * 255.0)


class NlMeans(Filter):
    """Non-local means denoising (7.2.6, cv2.fastNlMeansDenoising); strength h from the image noise."""

    name = "nlmeans"
    params = (
        Param("h", float, None, 0.0, 100.0, lo_open=True, doc="filter strength, grey levels"),
        Param("template_px", int, 7, 3, 21, odd=True, doc="patch side, px"),
        Param("search_px", int, 21, 3, 101, odd=True, doc="search window side, px"),
    )

    def _validate(self):
        t, s = self.given.get("template_px", 7), self.given.get("search_px", 21)
        if s < t:
            raise ParameterError(f"{self.key}.search_px: {s} px is smaller than template_px ({t} px); use {t} or more")

    def image_defaults(self, img):
        return {"h": float(np.clip(noise_sigma(img), 1.0, 30.0))}

    def run(self, img, h, template_px, search_px):
        return cv2.fastNlMeansDenoising(_u8(img), None, h, template_px, search_px).astype(np.float32)


class Background(Filter):
    """Temporal background subtraction: image - per-pixel mean (or median) over the clip + offset.

    Needs a pre-pass over the clip (:meth:`FilterStack.prepass`). The mean is streamed; the median
    is taken from at most ``samples`` evenly spaced frames.
    """

    name = "background"
    params = (
        Param("method", str, "mean", choices=("mean", "median")),
        Param("samples", int, 25, 3, 201, doc="frames kept for the median"),
        Param("offset", float, 127.5, 0.0, 255.0, doc="grey level of 'no difference'"),
    )

    def __init__(self, values, key="filter"):
        super().__init__(values, key)
        self.background: np.ndarray | None = None

    def run(self, img, method, samples, offset):
        if self.background is None:
            raise RuntimeError("background filter used before FilterStack.prepass()")
        if img.shape != self.background.shape:
            raise ParameterError(
                f"{self.key}: frame size {img.shape[1]}x{img.shape[0]} differs from the background "
                f"({self.background.shape[1]}x{self.background.shape[0]}); run the pre-pass on the same clip"
            )
        return _clip(img - self.background + offset)


class _MeanAccumulator:
    def __init__(self):
        self.sum: np.ndarray | None = None
        self.n = 0

    def add(self, img):
        self.sum = img.astype(np.float64) if self.sum is None else self.sum + img
        self.n += 1

    def result(self):
        return (self.sum / self.n).astype(np.float32)


class _MedianAccumulator:
    """Evenly spaced sample of at most ``k`` frames: the stride doubles when the buffer is full."""

    def __init__(self, k: int):
        self.k, self.stride, self.seen = k, 1, 0
        self.buf: list = []

    def add(self, img):
        if self.seen % self.stride == 0:
            self.buf.append(img.astype(np.float32))
            if len(self.buf) > self.k:
                self.buf = self.buf[::2]
                self.stride *= 2
        self.seen += 1

    def result(self):
        return np.median(np.stack(self.buf), axis=0).astype(np.float32)


FILTERS: dict[str, type[Filter]] = {
    f.name: f for f in (HighPass, Capping, Clahe, BrightnessContrast, Gamma, NlMeans, Background)
}


def noise_sigma(img: np.ndarray) -> float:
    """Standard deviation of additive white noise (grey levels), Immerkaer's fast estimate (1996)."""
    kernel = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    h, w = img.shape
    if h < 3 or w < 3:
        return 0.0
    conv = cv2.filter2D(img.astype(np.float32), -1, kernel)[1:-1, 1:-1]
    return float(math.sqrt(math.pi / 2) * np.abs(conv).sum() / (6.0 * (w - 2) * (h - 2)))


class FilterStack:
    """An ordered list of filters, applied in turn to every gray frame.

    Build it with :meth:`from_config`; when ``needs_prepass`` is true, feed the clip to
    :meth:`prepass` once before :meth:`apply`.
    """

    def __init__(self, filters: list[Filter], roi: tuple[int, int, int, int] | None = None) -> None:
        self.filters = filters
        self.needs_prepass = any(isinstance(f, Background) for f in filters)
        self._prepassed = False
        self.roi = roi  # (x0, y0, x1, y1) px: filter only there, as the thesis (9.2.7) and PIVlab do

    def _crop(self, x: np.ndarray) -> np.ndarray:
        if self.roi is None:
            return x
        x0, y0, x1, y1 = self.roi
        return x[y0:y1, x0:x1]

    @classmethod
    def from_config(
        cls, items: list[dict], key: str = "filters", roi: tuple[int, int, int, int] | None = None
    ) -> FilterStack:
        """Stack from the project's ``filters`` list; ParameterError names e.g. ``filters[2].gamma``."""
        if items is None:
            items = []
        if not isinstance(items, list):
            raise ParameterError(f"{key}: expected a list of filter tables, got {items!r}")
        filters: list[Filter] = []
        bg_at = None
        for i, item in enumerate(items):
            k = f"{key}[{i}]"
            if not isinstance(item, dict):
                raise ParameterError(f'{k}: expected a table like {{name = "clahe"}}, got {item!r}')
            name = item.get("name")
            if name not in FILTERS:
                raise ParameterError(f"{k}.name: unknown filter {name!r}; use one of {', '.join(FILTERS)}")
            if name == "background":
                if bg_at is not None:
                    raise ParameterError(
                        f"{k}: background subtraction is already in the stack at {key}[{bg_at}]; keep one"
                    )
                bg_at = i
            filters.append(FILTERS[name](item, k))
        return cls(filters, roi)

    def prepass(self, frames: Iterable[np.ndarray], cancel: Callable[[], bool] | None = None) -> None:
        """Compute the background from the clip (streamed; one frame in memory for the mean).

        ``frames`` are the same gray frames :meth:`apply` will get; the filters before the
        background filter are applied to them first.
        """
        idx = next((i for i, f in enumerate(self.filters) if isinstance(f, Background)), None)
        if idx is None:
            self._prepassed = True
            return
        bg = self.filters[idx]
        assert isinstance(bg, Background)  # idx is the first Background
        p = bg.resolve(np.zeros((1, 1), np.float32))
        acc = _MeanAccumulator() if p["method"] == "mean" else _MedianAccumulator(p["samples"])
        shape = None
        for frame in frames:
            if cancel is not None and cancel():
                raise Cancelled("filter pre-pass cancelled")
            x = self._crop(np.asarray(frame, dtype=np.float32))
            if shape is None:
                shape = x.shape
            elif x.shape != shape:
                raise ParameterError(f"{bg.key}: frames of the clip differ in size ({x.shape} vs {shape})")
            for f in self.filters[:idx]:
                x = f(x)
            acc.add(x)
        if shape is None:
            raise ParameterError(f"{bg.key}: background subtraction needs frames, but the clip gave none")
        bg.background = acc.result()
        self._prepassed = True

    def apply(self, gray: np.ndarray) -> np.ndarray:
        """One gray frame (uint8 or float, 0-255) through the stack -> float32 (0-255).

        With a ``roi`` only that rectangle is filtered (its statistics alone set the image-based
        defaults, so banks and sky do not); the rest of the frame is returned unfiltered.
        """
        if self.needs_prepass and not self._prepassed:
            raise RuntimeError("FilterStack.apply() before prepass(): the background needs the clip first")
        full = np.asarray(gray, dtype=np.float32)
        if full.ndim != 2:
            raise ParameterError(f"filters: expected a gray frame (H x W), got shape {full.shape}")
        x = self._crop(full)
        for f in self.filters:
            x = f(x)
        if self.roi is None:
            return x
        out = full.copy()
        x0, y0, x1, y1 = self.roi
        out[y0:y1, x0:x1] = x
        return out

    def resolved(self) -> list[dict[str, Any]]:
        """The stack as applied: every parameter, with the image-based defaults filled in.

        Filters not yet run on a frame show None for their image-based parameters.
        """
        out = []
        for f in self.filters:
            vals = f.values if f.values is not None else {p.name: f.given.get(p.name, p.default) for p in f.params}
            out.append({"name": f.name, **vals})
        return out


def preview(
    items: list[dict],
    gray: np.ndarray,
    frames: Iterable[np.ndarray] | None = None,
    roi: tuple[int, int, int, int] | None = None,
) -> np.ndarray:
    """One frame through the stack ``items`` (filtered inside ``roi`` only, as the pipeline does), as
    uint8 for a PNG.

    ``frames`` (the clip) is needed only when the stack holds background subtraction.
    """
    stack = FilterStack.from_config(items, roi=roi)
    if stack.needs_prepass:
        if frames is None:
            raise ParameterError(
                "filters: the preview of background subtraction needs the clip (it averages all frames)"
            )
        stack.prepass(frames)
    return _u8(stack.apply(gray))
