"""What a clip's own frames say about its noise, tracer contrast, texture and glare, and the gates set from them.

Thresholds in grey levels fit one camera and one light; these estimates let every gate be set relative to the
clip instead (issue 23). All from a few dozen frames inside the region PIV reads:

- **noise** (grey levels): per-pixel temporal noise, the robust MAD over time of frame-to-frame differences
  divided by sqrt(2) (moving tracers cross a pixel in a few frames, so the median ignores them); the median
  over the box is reported.
- **contrast** (grey levels): how far the tracers stand above the water, per window of ``win`` px: the 99th
  percentile of the frame minus its pixel's temporal median, smoothed by a 1.5 px Gaussian (tracers are
  blobs of several pixels, sensor noise is white), less 2.33 times that smoothed residual's own noise; the
  median over the windows is reported (a glint column or an empty band does not set it: a window whose bright
  events the flow does not carry, found again in the next frame displaced as the window's others are, is a
  glare window: :func:`carried_share`).
- **cnr**: contrast / noise (dimensionless).
- **texture** (grey levels): the windows' rms of the smoothed residual (median reported).
- **glare_fraction**: share of box pixels that are bright (above their median by more than
  ``GLARE_K`` noise and twice the tracer contrast) in a few of the frames only, in the glare windows (those whose
  bright events the flow does not carry: bright tracers flicker at a pixel too, but move on): specular flicker.
  Where it is set, ``median`` is the glints' background, the median of the frames in which the pixel does not
  shine (:func:`background`): the per-frame mask (processing/lowlight.py) puts it where a glint shines, in the
  glare windows only (``glare_windows``).

:func:`gates` turns them into the standardisation's soft threshold and the PIV texture gate, and a plan name.
Pure numpy: no file, no print.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from math import erfc, exp, pi, sqrt

import cv2
import numpy as np
from scipy import fft as sp_fft

from fieldtool.processing import decorrelation, piv_engine

#: grey levels: the noise never reads below the quantisation's (a codec reproduces static areas exactly)
NOISE_FLOOR = 0.5
#: below this contrast-to-noise ratio the clip is "weak" (dusk, night, haze): the low-light plan
CNR_WEAK = 6.0
#: bright by more than this many noise sd above the pixel's median: a glint candidate
GLARE_K = 8.0
#: weak clips only: above this share of glint candidates, glints are masked frame by frame (in a weak clip the
#: tracers are faint, so what stands that far above the median is specular)
GLARE_ON = 0.005
#: windows where less than this share of the bright events is carried by the flow (found again in the next frame
#: at the window's displacement, beyond what frames half the stack apart give there) are glare windows, left out of
#: the contrast. Tracers are carried (0.5-0.95 measured, below 1 for sub-pixel shifts and noise at the threshold),
#: glints are not, whether they flicker in place or appear at new places (0.05-0.3). A test on how long a pixel
#: stays bright took fast tracers (20 px a frame, one frame on a pixel) for glints, and missed dense glints
GLARE_CARRIED = 0.35
#: px: the farthest a bright event is looked for in the next frame (half a window of the estimates)
CARRY_REACH = 32
#: a window's carried share is judged from at least this many bright events (its sampling error about 0.2): a
#: window with fewer neither sets the glare nor has glints masked
GLARE_MIN_EVENTS = 25
#: percentile of a window's smoothed residual that is its contrast: a window whose bright events are fewer than
#: (100 - this) % of its pixel-frames cannot set it, and is not judged
CONTRAST_PCT = 99.0
#: share of the clip's frames in which a glint candidate may be bright (short-lived)
GLARE_DUTY = 0.3


@dataclass
class ClipStats:
    """Estimates from the frames (grey levels of the frames given, dimensionless ratios)."""

    frames: int
    noise: float  # median per-pixel temporal noise sd (grey levels)
    contrast: float  # median over windows of the tracers' contrast above the noise (grey levels)
    cnr: float  # contrast / noise
    texture: float  # median over windows of the rms of the smoothed residual (grey levels)
    level: float  # median brightness of the box (grey levels)
    glare_fraction: float  # share of box pixels with short-lived specular flicker
    windows: int  # windows that entered the medians
    contrast_spread: tuple[float, float] = field(default=(0.0, 0.0))  # 10th, 90th percentile of window contrast
    median: np.ndarray | None = field(default=None, repr=False)  # per-pixel temporal median of the box (grey levels)
    box: tuple[int, int, int, int] | None = None  # (x0, y0, x1, y1) px the estimates cover
    #: the box's pixels (its shape, bool) in windows whose bright events the flow does not carry: where glints are
    #: masked (processing/lowlight.py); None: no such window
    glare_windows: np.ndarray | None = field(default=None, repr=False)
    #: how many frames the pattern takes to change at a pixel (processing/decorrelation.py), None: unknown
    decorrelation: decorrelation.Decorrelation | None = None

    @property
    def glint_threshold(self) -> float:
        """Grey levels above the pixel's median beyond which a pixel is a glint candidate."""
        return glint_threshold(self.noise, self.contrast)

    def to_dict(self) -> dict:
        d = {k: v for k, v in asdict(self).items() if k not in ("median", "box", "decorrelation", "glare_windows")}
        d["contrast_spread"] = list(self.contrast_spread)
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in d.items()}


def median0(stack: np.ndarray) -> np.ndarray:
    """``np.median(stack, axis=0)`` of finite values, the same numbers, by one sort along the first axis (3x
    faster than numpy's partition for the few frames of a clip check: 20 frames of 549 x 462 px, 90 -> 29 ms)."""
    n = len(stack)
    s = sort0(stack)
    m = n // 2
    return s[m] if n % 2 else np.mean(s[m - 1 : m + 1], axis=0)


def _in_bands(n: int, fn) -> list:
    """``fn(lo, hi)`` over ``range(n)`` in four bands on the engine's threads (``piv_engine.chunked``: in order,
    in the calling thread where the engine has one thread). Not to be called from inside a chunked function."""
    return piv_engine.chunked(n, max(1, -(-n // 4)), fn)


def sort0(stack: np.ndarray) -> np.ndarray:
    """``np.sort(stack, axis=0)``, the same array, sorted in bands of rows on the engine's threads (NumPy's sort
    releases the GIL)."""
    if stack.ndim < 2 or stack.shape[1] < 8:
        return np.sort(stack, axis=0)
    out = np.empty_like(stack)
    rows = stack.shape[1]

    def band(lo: int, hi: int) -> None:
        out[:, lo:hi] = np.sort(stack[:, lo:hi], axis=0)

    _in_bands(rows, band)
    return out


def temporal_noise(stack: np.ndarray) -> np.ndarray:
    """Per-pixel temporal noise sd (grey levels) of ``stack`` (n >= 3, h, w): 1.4826 MAD of the differences
    / sqrt(2)."""
    d = np.diff(stack.astype(np.float32), axis=0)
    med = median0(d)
    return 1.4826 * median0(np.abs(d - med)) / np.sqrt(2.0)


def estimate(frames, box: tuple[int, int, int, int] | None = None, *, win: int = 64, step: int = 1) -> ClipStats:
    """Estimates from ``frames`` (a sequence of 2-D grey arrays, >= 3) inside ``box`` (x0, y0, x1, y1, px; None =
    whole frame). ``step``: take every step-th pixel for the noise (cost)."""
    fr = [np.asarray(f) for f in frames if f is not None]
    if len(fr) < 3:
        raise ValueError("clip_stats.estimate needs at least 3 frames")
    h, w = fr[0].shape[:2]
    x0, y0, x1, y1 = (
        (0, 0, w, h)
        if box is None
        else (max(int(box[0]), 0), max(int(box[1]), 0), min(int(box[2]), w), min(int(box[3]), h))
    )
    st = np.stack([f[y0:y1, x0:x1] for f in fr]).astype(np.float32)
    n = st.shape[0]
    sig = temporal_noise(st[:, ::step, ::step])
    noise = float(max(np.median(sig), NOISE_FLOOR))
    med = median0(st)
    resid = st - med
    sm = np.stack([cv2.GaussianBlur(r, (0, 0), 1.5) for r in resid])
    # the smoothed residual's noise: measured, but never above what the sensor noise alone leaves after the same
    # blur (tracers that move more than their size between frames read as temporal noise of the smoothed
    # residual, and would cancel their own contrast: the fast_1080p scene read 0 grey levels of contrast)
    sig_s = float(max(min(np.median(temporal_noise(sm[:, ::step, ::step])), noise * _blur_gain(1.5)), 1e-4))
    hh, ww = med.shape
    # bright events against the noise alone, per window: a glint column's windows are left out of the contrast
    # (their glints would read as tracers of 100+ grey levels); the flow carries the tracers' events, not the glints'
    flick = resid > GLARE_K * noise
    corners = [
        (r0, c0)
        for r0 in range(0, max(hh - win // 2, 1), win)
        for c0 in range(0, max(ww - win // 2, 1), win)
        if sm[:, r0 : r0 + win, c0 : c0 + win].size
    ]

    def windows(lo: int, hi: int) -> list[tuple[float, float, float | None, bool]]:
        out = []
        for r0, c0 in corners[lo:hi]:
            blk = sm[:, r0 : r0 + win, c0 : c0 + win]
            ev = _window_events(flick, (r0, c0, win))  # the events carried_share weighs
            out.append(
                (
                    max(float(np.percentile(blk, CONTRAST_PCT)) - 2.33 * sig_s, 0.0),
                    float(np.sqrt(np.mean(blk * blk))),
                    carried_share(flick, (r0, c0, win), CARRY_REACH, GLARE_MIN_EVENTS),
                    bool(np.count_nonzero(ev) > _contrast_floor(ev.size)),  # enough to set the contrast
                )
            )
        return out

    # the windows on the engine's threads (their FFTs and sorts release the GIL), in order: the same values
    per = [v for part in _in_bands(len(corners), windows) for v in part]
    cons = [v[0] for v in per]
    texs = [v[1] for v in per]
    shares = [v[2] for v in per]  # every window with GLARE_MIN_EVENTS: where glints are masked
    carried = [v[2] if v[3] else None for v in per]  # the windows whose events can set their contrast
    cons_a = np.asarray(cons) if cons else np.zeros(1)
    clean = np.asarray([c is None or c >= GLARE_CARRIED for c in carried] or [True])
    contrast = float(np.median(cons_a[clean] if clean.any() else cons_a))
    # the glare windows: where the bright events are not carried by the flow. Bright tracers (a bright seeding, or
    # one brighter than twice the windows' typical contrast) flicker at a pixel as glints do, but move on
    glare_win = np.zeros((hh, ww), bool)
    m = win // 4  # and a quarter window around them: a glint at a window's edge spills into its neighbour
    for (r0, c0), c in zip(corners, shares, strict=True):
        if c is not None and c < GLARE_CARRIED:
            glare_win[max(r0 - m, 0) : r0 + win + m, max(c0 - m, 0) : c0 + win + m] = True
    bright = (resid > glint_threshold(noise, contrast)) & glare_win
    share = bright.mean(axis=0)
    glare = float(np.mean((share > 0) & (share <= GLARE_DUTY)))
    if glare > GLARE_ON:  # the glints' background: the median of the frames in which the pixel does not shine
        med = background(st, bright)
    return ClipStats(
        frames=n,
        noise=noise,
        contrast=contrast,
        cnr=contrast / noise,
        texture=float(np.median(texs or [0.0])),
        level=float(np.median(med)),
        glare_fraction=glare,
        windows=len(cons),
        contrast_spread=(float(np.percentile(cons_a, 10)), float(np.percentile(cons_a, 90))),
        median=med,
        box=(x0, y0, x1, y1),
        glare_windows=glare_win if glare_win.any() else None,
        # on the smoothed frames (the smoothed residual and the smoothed median): sensor noise, white in time,
        # weighs less there (a dusk clip's share of persistent variance 0.12 -> 0.5); whole, so that the fit takes
        # out an exposure's or a fade's change of every pixel's gain; every 4th pixel each way (more apart in a box
        # of over 1 Mpx: at most 64k pixels) is plenty for a handful of sums (4 ms at 720p, 8 ms at 4K)
        decorrelation=decorrelation.fit(
            sm[:, :: (k := _every(hh * ww)), ::k] + cv2.GaussianBlur(med, (0, 0), 1.5)[::k, ::k]
        ),
    )


def _every(pixels: int, most: int = 65536) -> int:
    """Stride (>= 4) each way that leaves at most about ``most`` of ``pixels``."""
    return max(4, int(np.ceil(np.sqrt(pixels / most))))


def _contrast_floor(pixel_frames: int) -> float:
    """Fewest bright events that can set a window's contrast: (100 - ``CONTRAST_PCT``) % of its pixel-frames."""
    return (1.0 - CONTRAST_PCT / 100.0) * pixel_frames


def _window_events(events: np.ndarray, window: tuple[int, int, int]) -> np.ndarray:
    """The events of ``window`` (row, col, size px) that :func:`carried_share` follows: those of every other frame
    t < n - 1 (every other pair: half the transforms, and the far frames are the near ones)."""
    r0, c0, win = window
    return events[: len(events) - 1 : 2, r0 : r0 + win, c0 : c0 + win]


def carried_share(
    events: np.ndarray, window: tuple[int, int, int], reach: int, min_events: int | None = None
) -> float | None:
    """Share of a window's bright events that the flow carries: ``events`` (n >= 3, h, w) bool, ``window`` (row,
    col, size) px, ``reach`` px. The events of every other frame t (t < n - 1) inside the window are correlated
    with those of frame t + 1 at every displacement within ``reach`` (summed over t), and with those of frames
    about half the stack away (what stays in place or falls anywhere by chance, measured at each displacement:
    glints that flicker in place or in a band). At the displacement where the next frame beats the far ones
    most, the excess over the far frames' hits, divided by what it could be (the events that land inside the
    frame there, less the far frames' hits): about 1 for tracers the flow carries (a sub-pixel shift and noise
    at the threshold lose some), about 0 for glints. None where the events are fewer than ``min_events``
    (None: (100 - ``CONTRAST_PCT``) % of the window's pixel-frames, below which they do not set its contrast)."""
    n, h, w = events.shape
    r0, c0, win = window
    t = np.arange(0, n - 1, 2)  # the frames of _window_events
    a = _window_events(events, window)
    e = float(np.count_nonzero(a))
    if n < 3 or e <= (_contrast_floor(a.size) if min_events is None else min_events):
        return None
    wh, ww = a.shape[1:]
    s0, s1 = wh + 2 * reach, ww + 2 * reach
    ys, xs = r0 - reach, c0 - reach  # the window grown by ``reach``, zero outside the frame
    y0, x0, y1, x1 = max(ys, 0), max(xs, 0), min(r0 + wh + reach, h), min(c0 + ww + reach, w)
    pad = np.zeros((len(t), s0, s1), np.float32)
    pad[:, :wh, :ww] = a
    fa = np.conj(sp_fft.rfft2(pad, workers=1))
    near_i, far_i = t + 1, (t + 1 + 2 * (n // 4)) % n
    frames = np.unique(np.concatenate([near_i, far_i]))
    grown = np.zeros((len(frames), s0, s1), np.float32)
    grown[:, y0 - ys : y1 - ys, x0 - xs : x1 - xs] = events[frames, y0:y1, x0:x1]
    fb = sp_fft.rfft2(grown, workers=1)
    at = {int(f): k for k, f in enumerate(frames)}
    inside = np.zeros((s0, s1), np.float32)
    inside[y0 - ys : y1 - ys, x0 - xs : x1 - xs] = 1.0

    def hits(spec: np.ndarray) -> np.ndarray:  # hits[dy + reach, dx + reach] = sum over t, p of a_t[p] b_t[p + d]
        return sp_fft.irfft2(spec, s=(s0, s1), workers=1)[: 2 * reach + 1, : 2 * reach + 1]

    near = hits((fa * fb[[at[int(f)] for f in near_i]]).sum(axis=0))
    far = hits((fa * fb[[at[int(f)] for f in far_i]]).sum(axis=0))
    room = hits(fa.sum(axis=0) * sp_fft.rfft2(inside, workers=1))  # events whose displaced place is in the frame
    k = np.unravel_index(int(np.argmax(near - far)), near.shape)
    return float(max(near[k] - far[k], 0.0) / max(room[k] - far[k], 1.0))


def glint_threshold(noise: float, contrast: float) -> float:
    """Grey levels above a pixel's median beyond which it is a glint candidate: ``GLARE_K`` times the temporal
    noise, and twice the tracers' contrast (both grey levels)."""
    return max(GLARE_K * noise, 2.0 * contrast)


def background(stack: np.ndarray, bright: np.ndarray) -> np.ndarray:
    """Per-pixel temporal median of ``stack`` (n, h, w) over the frames in which the pixel is not ``bright``
    (grey levels): where glints shine in a third of the frames, the plain median is lifted by them. A pixel
    bright in every frame keeps its plain median."""
    # the bright values sorted to the end (as +inf): the median of a pixel's k others is the mean of its sorted
    # values (k - 1) // 2 and k // 2, which is np.nanmedian's value, 3x faster than it
    ordered = sort0(np.where(bright, np.float32(np.inf), stack))
    k = (~bright).sum(axis=0)
    lo = np.take_along_axis(ordered, np.maximum((k - 1) // 2, 0)[None], 0)[0]
    hi = np.take_along_axis(ordered, np.minimum(k // 2, len(stack) - 1)[None], 0)[0]
    with np.errstate(invalid="ignore"):  # all-bright pixels: inf - inf, replaced below
        bg = (lo.astype(np.float64) + hi) / 2.0
    return np.where(k > 0, bg, median0(stack)).astype(np.float32)


def _blur_gain(sigma_px: float) -> float:
    """The standard deviation of white noise of sd 1 after ``cv2.GaussianBlur`` of ``sigma_px`` (measured once
    on a seeded 256 x 256 field; about 0.19 at 1.5 px)."""
    if sigma_px not in _BLUR_GAIN:
        z = np.random.default_rng(0).standard_normal((256, 256)).astype(np.float32)
        _BLUR_GAIN[sigma_px] = float(cv2.GaussianBlur(z, (0, 0), sigma_px)[16:-16, 16:-16].std())
    return _BLUR_GAIN[sigma_px]


_BLUR_GAIN: dict[float, float] = {}


def soft_threshold_residual(k: float) -> float:
    """rms (in noise sd) of Gaussian noise left by a soft threshold at ``k`` sd: sqrt(2[(1+k²)Q(k) - k φ(k)])."""
    q = 0.5 * erfc(k / sqrt(2.0))
    phi = exp(-0.5 * k * k) / sqrt(2 * pi)
    return sqrt(max(2.0 * ((1 + k * k) * q - k * phi), 0.0))


@dataclass
class Gates:
    """Gates derived from :class:`ClipStats` (standardised units where the standardisation is on)."""

    plan: str  # "standard" | "low_light"
    shrink: float  # the standardisation's soft threshold (robust sd of the standardised frame)
    min_texture: float  # PIV texture gate (standardised units)
    min_pairs: int | None  # ensemble: at least this many pairs (None = the project's)
    reasons: list[str] = field(default_factory=list)
    denoise_half: int = 0  # > 0: temporal mean over 2 * half + 1 frames (processing/lowlight.py)
    mask_glints: bool = False  # per-frame masking of short-lived specular pixels (processing/lowlight.py)
    variants: list | None = None  # self-check scores of the variants tried (processing/selfcheck.py), if any
    min_valid_fraction: float | None = None  # PIV's share of valid pairs a node needs (None = the project's)
    step: int = 1  # every step-th frame of the clip is used (processing/decorrelation.py); 1: every frame

    def to_dict(self) -> dict:
        return {
            "plan": self.plan,
            "frame_step": self.step,
            "shrink": round(self.shrink, 4),
            "min_texture": round(self.min_texture, 5),
            "min_pairs": self.min_pairs,
            "denoise_frames": 2 * self.denoise_half + 1 if self.denoise_half else 1,
            "mask_glints": self.mask_glints,
            "min_valid_fraction": self.min_valid_fraction,
            "variants": self.variants,
            "reasons": list(self.reasons),
        }


def ambiguous(stats: ClipStats) -> bool:
    """True where either plan may fit: the contrast-to-noise ratio from half :data:`CNR_WEAK` up to it, or up to
    twice it where the clip has glare (the weak-signal plan masks glints and judges a node by its ensemble peak).

    Above :data:`CNR_WEAK` without glare the standard gates were made for the clip, and the self-check's valid
    share would favour the weak-signal plan for its looser gates alone: five drawn scenes with bright tracers
    (contrast 7-11 x the noise) read -6 to -67 % through it, -2.1 to +0.04 % through the standard plan."""
    if stats.cnr >= CNR_WEAK:
        return stats.cnr < 2.0 * CNR_WEAK and stats.glare_fraction > GLARE_ON
    return stats.cnr >= CNR_WEAK / 2.0


def gates(
    stats: ClipStats,
    *,
    shrink_default: float,
    min_texture_default: float,
    min_pairs: int,
    n_frames: int,
    force: str | None = None,
) -> Gates:
    """The soft threshold, texture gate and pair count for a clip.

    Where the tracers stand well above the noise (cnr >= :data:`CNR_WEAK`) the defaults stand: they were set
    for such clips (a threshold at ``shrink_default`` noise sd removes noise, not tracers). Below it, the
    threshold would erase tracers as faint as the noise: it is lowered to half the tracers' contrast in noise
    sd, the texture gate to the rms that pure noise keeps after that threshold (a window with less is
    featureless, one with tracers has more), scaled like the default is to the default threshold's residual,
    and the ensemble uses every pair (noise averages out as 1 / sqrt(pairs)). ``force``: "standard" or
    "low_light" whatever the ratio (the self-check's variants).
    """
    if force == "standard" or (force is None and stats.cnr >= CNR_WEAK):
        return Gates(
            "standard",
            shrink_default,
            min_texture_default,
            None,
            [
                f"tracer contrast {stats.contrast:.1f} grey levels is {stats.cnr:.1f} x the noise "
                f"({stats.noise:.2f}): default gates"
            ],
        )
    glare = stats.glare_fraction > GLARE_ON
    k = max(0.5 * stats.cnr, 0.0)
    # glints masked per frame over faint tracers (cnr below CNR_WEAK): no soft threshold. It is set against the
    # box's robust spread, and where glints shine the masked glints' edges raise the local spread: the threshold
    # would erase the faint tracers between the glints and keep the glints' edges (glare_column: nothing measured
    # inside the column). Where the tracers stand out (a clip sent here by the self-check) the threshold stays:
    # it is what removes texture fixed in the world, such as standing ripples, which pulls towards zero
    faint_glare = glare and stats.cnr < CNR_WEAK
    k = 0.0 if faint_glare else min(k, shrink_default)
    # the default gate is min_texture_default at a residual of soft_threshold_residual(shrink_default) noise
    # sd; keep the gate at the same fraction of the standardised noise, but never above what pure noise
    # keeps at the lower threshold (so tracer windows, which keep more, pass)
    resid = soft_threshold_residual(k)
    std_noise = 0.5  # standardised noise sd where noise dominates: sd / (sd + std_ref), std_ref ~ sd
    mt = min(min_texture_default, 0.5 * resid * std_noise)
    why = (
        [
            f"{100 * stats.glare_fraction:.1f} % of the pixels flicker brighter than {stats.glint_threshold:.0f} grey "
            "levels above their median in a few frames only, where the flow does not carry them: masked per frame "
            "there"
            + (
                ", no soft threshold, and a node is judged by its ensemble peak, not by its share of valid single "
                "pairs (a glint hides part of each window in every frame)"
                if faint_glare
                else ""
            )
        ]
        if glare
        else []
    )
    return Gates(
        "low_light" + ("+glare" if glare else ""),
        k,
        mt,
        max(min_pairs, n_frames - 1),
        why
        + [
            "temporal mean over 3 frames (noise / sqrt(3))",
            f"tracer contrast {stats.contrast:.1f} grey levels is {stats.cnr:.1f} x the noise "
            f"({stats.noise:.2f}; weak below {CNR_WEAK:g}): soft threshold {k:.2f} sd (default {shrink_default:g}), "
            f"texture gate {mt:.4f} (default {min_texture_default:g}), ensemble over every pair",
        ],
        denoise_half=1,
        mask_glints=glare,
        min_valid_fraction=0.0 if faint_glare else None,
    )
