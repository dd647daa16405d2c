"""PIV correlation engine: frame pairs -> per-pair and time-averaged vector fields with quality.

Thesis 2.2.4 (FFT cross-correlation, multi-pass, sub-pixel, validation), 6.2 and 9.2.8.

How it works
------------
* Every frame is cut into interrogation windows with a strided view (no copy of the frame) and all windows go
  through one batched real FFT (``scipy.fft.rfft2``, float32, ``_WORKERS`` threads). The mean is removed on the
  spectrum (DC = 0) and each window's energy comes from Parseval; the unit-energy factor is kept beside the
  spectrum and applied only where a value is reported (peak value, ensemble sum). A frame's window spectra are
  computed once and serve the pair before it (as frame B) and the pair after it (as frame A).
* Correlation plane of a pair = inverse FFT of ``conj(A) * B`` (a column FFT then a row real FFT, into reused
  buffers); the displacement is the highest peak, refined by a Gaussian 3-point fit (parabolic where a value is
  not positive). Quality per vector: peak-to-second-peak ratio, the second peak being the highest local maximum
  (>= its 8 neighbours) outside a 5 x 5 neighbourhood of the first (found as the highest value there, checked
  against its neighbours; a full local-maximum search only on the planes where that value sits on the first
  peak's shoulder), peak-to-mean ratio and the peak value (a correlation coefficient, 1 = perfect match). The
  planes have zero mean (the windows do), so the peak-to-mean ratio is taken on the plane's mean energy:
  peak / root-mean-square.
* ``search_px`` larger than the first window: the A window is zero-padded inside a B window of the search size, so
  displacements up to (search - window) / 2 are found without wrap-around.
* ``first_guess`` (flow too fast for the first window, measured by ``planning.first_look``): the first pass'
  B window of every node is taken where that node's first guess (rounded to whole pixels) moves it, and the
  peak is the residual (window offset); the search area then stays the window.
* ``passes > 1``: the first pass uses windows ``window_px * 2**(passes-1)``; each later pass deforms the second frame
  with ``cv2.remap`` (Lanczos, 8 x 8; bicubic is 4x faster but biased by up to 0.02 px with 4 px particles) by the
  previous pass' validated field, interpolated bicubically to every pixel (one ``cv2.resize`` by the node
  spacing), correlates the smaller windows and adds the residual to the predictor. The first frame's window
  spectra are not deformed, so they are still computed once per frame.
* Masked nodes (window centre in ``mask``) of the final pass of a multi-pass run are not correlated: their
  windows get no spectrum, inverse FFT or peak search (``_SKIP_MASKED``); they have no vector and add nothing to
  the ensemble. Earlier passes keep every node, because they build the predictor of the unmasked ones.
* ``near`` (the fast path's band around the section): in every pass only the nodes within that pass' distance of
  the section segments are correlated, the same way; the final pass' others are treated as masked (no vector,
  never replaced, ``valid_fraction`` NaN), an earlier pass' others are filled from their neighbours.
* Averaging: ``ensemble`` sums the cross-spectra of all pairs per node, weighted by their signal-to-noise
  (weight = clip(peak ratio - 1, 0, 10)), and takes one peak per node at the end (one inverse FFT for the clip);
  ``mean``/``median`` average the validated per-pair vectors.
* Ensemble sample: the ensemble needs no per-pair vectors, so only a sample of ``ENSEMBLE_PAIRS`` (30) to 59
  evenly spaced pairs gets the final pass' inverse FFT, peaks and validation (all pairs of a clip of fewer than
  60 pairs); they give the per-pair fields of the result (``u_pairs``, ``v_pairs``, ``t_pairs``, ``dt_s``,
  ``pair_index``; ``snr``, ``peak2mean``, ``peak``, ``valid_fraction`` are over these pairs; ``on_pair`` is
  called for them) and the SNR weights. The other pairs' cross-spectra are added with each node's mean weight
  over the sampled pairs so far, with no inverse FFT. ``n_pairs`` counts every pair. The stride is
  pairs // 30 when ``frames`` has a length, else it starts at 1 and doubles (every other kept pair dropped)
  each time 60 pairs are kept, which gives vectors to more pairs on the way. Earlier passes of a multi-pass
  run still correlate every pair (they give that pair's predictor).
* Frames are consumed as a stream: only the previous frame's spectra, the reused work buffers and one
  accumulator are held, plus the per-pair fields the result has to return (2 x 4 bytes per node and pair kept;
  in ensemble mode at most 59 pairs whatever the clip length).

Conventions: image axes, +x right, +y down, origin at the centre of the top-left pixel; u, v in px/s from the
frame timestamps. A node's position is the centre of its final interrogation window.

Modules: ``piv_engine`` (the parameters, pass geometry, window spectra, peaks and the CPU engine), ``piv_gpu``
(the optional CuPy engine), ``piv_openpiv`` (the OpenPIV reference engine) and this one (``analyze``: the stream
of pairs, the ensemble, the averages and their validation).
"""

from __future__ import annotations

import warnings
from collections import deque
from collections.abc import Callable, Iterable, Sized
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np

from fieldtool.errors import Cancelled, InputFileError, ParameterError
from fieldtool.processing import piv_gpu, piv_peaks
from fieldtool.processing import piv_validate as pv
from fieldtool.processing.piv_engine import (
    AVERAGING,
    ENGINES,
    PivParams,
    _chunk_nodes,
    _Engine,
    _find_peaks,
    _guess_at,
    _Level,
    _levels,
    check_params,
    chunked,
    grid,
    near_nodes,
    set_fft_workers,
)

__all__ = [
    "AVERAGING",
    "ENGINES",
    "ENSEMBLE_PAIRS",
    "REVISION",
    "PivParams",
    "PivResult",
    "analyze",
    "check_params",
    "grid",
    "near_nodes",
    "set_fft_workers",
]

#: bumped when the engine gives other vectors for the same inputs (a saved field of another revision is recomputed)
REVISION = 2
#: averaging = ensemble: per-pair vectors are computed and kept for every k-th pair only, so that between
#: ENSEMBLE_PAIRS and 2 * ENSEMBLE_PAIRS - 1 evenly spaced pairs are kept (all pairs of a clip of fewer than
#: 2 * ENSEMBLE_PAIRS). k = pairs // ENSEMBLE_PAIRS when ``frames`` has a length; for a stream of unknown length
#: k starts at 1 and doubles (every other kept pair dropped) each time 2 * ENSEMBLE_PAIRS pairs are kept.
ENSEMBLE_PAIRS = 30


@dataclass
class PivResult:
    """Time-averaged and per-pair vector fields on the node grid (image axes, px/s)."""

    x: np.ndarray  # (ny, nx) node centres, px
    y: np.ndarray
    u: np.ndarray  # (ny, nx) time-averaged velocity, px/s; NaN where invalid
    v: np.ndarray
    valid: np.ndarray  # (ny, nx) bool (measured or replaced from valid neighbours)
    valid_fraction: np.ndarray  # (ny, nx) fraction of pairs in which the node was valid
    u_pairs: np.ndarray  # (n_pairs, ny, nx) px/s, NaN = invalid; ensemble: the sampled pairs (module docstring)
    v_pairs: np.ndarray
    t_pairs: np.ndarray  # (n_pairs,) mid-times, s
    snr: np.ndarray  # (ny, nx) median peak-to-second-peak ratio over the pairs
    params: PivParams
    peak2mean: np.ndarray | None = None  # (ny, nx) median peak-to-mean ratio over the pairs
    peak: np.ndarray | None = None  # (ny, nx) median correlation peak value (correlation coefficient)
    replaced: np.ndarray | None = None  # (ny, nx) bool, average filled in from valid neighbours
    ensemble_snr: np.ndarray | None = None  # (ny, nx) peak ratio of the ensemble plane (averaging = ensemble)
    dt_s: np.ndarray | None = None  # (n_pairs,) time between the frames of each pair, s
    pair_index: np.ndarray | None = None  # (n_pairs,) index of each of these pairs in the clip (0 = frames 0-1)
    n_pairs: int | None = None  # pairs correlated in the clip (ensemble: more than the per-pair fields hold)
    zero_peak_removed: np.ndarray | None = None  # (ny, nx) bool, ensemble plane's zero-displacement block blanked
    first_guess: np.ndarray | None = None  # (ny, nx, 2) px per pair: the first pass' window offset (first_guess=)
    carry: object | None = None  # analyze(select=...): state that a later call continues (``carry=``); not saved


# --------------------------------------------------------------------------------------------- analyze


def _check_frame(i: int, img, shape) -> np.ndarray:
    arr = np.asarray(img)
    if arr.ndim != 2:
        raise InputFileError(
            f"frames: frame {i} has shape {arr.shape}; PIV needs single-channel (gray) frames — convert them first"
        )
    if shape is not None and arr.shape != shape:
        raise InputFileError(
            f"frames: frame {i} is {arr.shape[1]} x {arr.shape[0]} px, the first was "
            f"{shape[1]} x {shape[0]} px; all frames of a clip must have the same size"
        )
    return arr


def _pair_validity(dx, dy, pk_ok, snr, dt, params, node_mask, max_speed):
    """Per-pair validation of displacements (px): peak found, SNR, mask, speed, global std, local median."""
    ok = pk_ok & (np.isnan(snr) | (snr >= params.snr_min)) & ~node_mask  # NaN: engine gives no SNR (windef)
    gu, gv = np.where(ok, dx, np.nan), np.where(ok, dy, np.nan)
    if max_speed is not None:
        ok &= pv.speed_test(gu / dt, gv / dt, max_speed)
    gu, gv = np.where(ok, dx, np.nan), np.where(ok, dy, np.nan)
    ok &= pv.global_std_test(gu, gv, params.std_threshold)
    gu, gv = np.where(ok, dx, np.nan), np.where(ok, dy, np.nan)
    ok &= pv.normalized_median_test(gu, gv, params.median_threshold)
    return ok


def analyze(
    frames: Iterable[tuple[float, np.ndarray]],
    params: PivParams,
    *,
    roi=None,
    mask: np.ndarray | None = None,
    max_speed_px_s: np.ndarray | None = None,
    progress: Callable[[int, int], None] | None = None,
    cancel: Callable[[], bool] | None = None,
    on_pair: Callable | None = None,
    backend: str = "auto",
    select=None,
    carry=None,
    near=None,
    first_guess=None,
) -> PivResult:
    """Run PIV over consecutive frame pairs and average in time.

    Parameters
    ----------
    frames : iterable of (t_s, image), image gray HxW (uint8/float); consumed once, never stored.
        Consecutive frames form pairs; dt = t[i+1] - t[i] from the timestamps (s).
    params : PivParams.
    roi : (x0, y0, x1, y1) full-frame pixels (x1, y1 exclusive) or None for the whole frame.
    mask : bool HxW, True = invalid area; vectors whose window centre falls in it are invalid (never replaced),
        and its pixels are set to the frame mean before correlating.
    max_speed_px_s : (ny, nx) per-node speed limit in px/s (or a scalar), or None.
    progress : progress(done_pairs, total_pairs or 0).
    cancel : cancel() -> True raises fieldtool.errors.Cancelled within one pair.
    on_pair : on_pair(i, t_mid_s, x, y, u_px_s, v_px_s, valid) after each pair with vectors (i = the pair's index
        in the clip; ensemble: the sampled pairs only, see the module docstring).
    backend : "auto" (GPU when CuPy with a CUDA device is importable and passes its self-check, single pass
        only; else CPU), "cpu" or "gpu". See piv_gpu (unverified on real hardware).
    select : pair indices (0 = frames 0-1 of the stream) to correlate, or None for every pair. Frames that belong
        to no selected pair are read but not transformed, and the stream is left after the last selected pair.
        Every selected pair gets per-pair vectors. Used by ``piv_fast.converge`` (pairs added in rounds).
    carry : ``PivResult.carry`` of an earlier call on the same clip, geometry and parameters: its ensemble sums
        and per-pair fields are continued, so the result covers the pairs of all calls.
    near : (segments, reach_px) or None: only the nodes of pass k within ``reach_px[k]`` px of the segments (each
        two image points, px) are correlated (the fast path's band, ``piv_fast.node_reach_px``); the final pass'
        others have no vector, as masked nodes.
    first_guess : (xc, yc, dx, dy) or None: a displacement per pair (px; dx, dy (ny, nx)) on the regular grid of
        node centres xc (nx,), yc (ny,), e.g. ``planning.first_look``'s; the first pass moves each B window by
        it (CPU engine; module docstring). Others ignore it.

    Returns
    -------
    PivResult (px, px/s, image axes).
    """
    total = 0
    if isinstance(frames, Sized):  # a stream that knows its count (run/frames.Sized)
        total = max(len(frames) - max(1, int(params.frame_gap)), 0)
    it = iter(frames)
    try:
        t_prev, first = next(it)
    except StopIteration:
        raise ParameterError(
            "video: no frames in the selected time range; PIV needs at least 2 — check video.start_s / video.end_s"
        ) from None
    first = _check_frame(0, first, None)
    shape = first.shape
    levels, box = _levels(shape, params, roi)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != shape:
            raise ParameterError(
                f"mask: {mask.shape[1]} x {mask.shape[0]} px does not match the {shape[1]} x {shape[0]} px frames"
            )
    if near is not None:
        segs, reach = near
        segs = [np.asarray(sg, float).reshape(2, 2) for sg in segs]
        if len(reach) != len(levels) or not segs:
            raise ValueError("analyze(near=...): one reach per pass and at least one segment")
        near = [near_nodes(lv, segs, r) for lv, r in zip(levels, reach, strict=True)]  # per pass, the nodes correlated
    engine = _make_engine(backend, shape, params, levels, box, mask, near, first_guess)
    if not isinstance(engine, _Engine):  # only the CPU engine moves its windows by it
        first_guess = None
    nodes = _final_nodes(levels[-1], shape, mask, near, max_speed_px_s)

    ens = _Ensemble(engine, nodes.fin, params.snr_min) if params.averaging == "ensemble" else None
    if ens is not None:
        ens.remove_zero = params.remove_zero_peak
    # ensemble: per-pair vectors (inverse FFT + peaks of the final pass) only on every stride-th pair
    subsample = ens is not None and getattr(engine, "spectrum_only", False) and select is None
    stride = max(1, total // ENSEMBLE_PAIRS) if subsample else 1  # clip length unknown (total 0): grown below
    per_pair: dict[str, list] = {k: [] for k in ("u", "v", "t", "dt", "snr", "p2m", "peak", "index")}
    n_done = 0
    if carry is not None:  # continue an earlier call (select=): its ensemble sums and per-pair fields
        ens, per_pair, n_done = carry.ensemble, carry.per_pair, carry.n_pairs
        if ens is not None:
            ens.engine = engine
    wanted = None if select is None else frozenset(int(k) for k in select)
    loop = _PairLoop(engine, params, nodes, ens, wanted, subsample, stride, per_pair, total, shape)
    i = loop.run(it, first, t_prev, cancel, progress, on_pair)
    per_pair = loop.per_pair
    if wanted is not None:
        i = n_done + len(wanted & set(range(i)))
        if not per_pair["u"]:
            raise ParameterError("video: none of the selected pairs is in the clip; PIV needs at least 2 frames")
    return _time_average(per_pair, ens, nodes, params, i, wanted, first_guess)


@dataclass
class _Nodes:
    """The final pass' nodes: grid ``fin``, centres X, Y (px), ``node_mask`` (True: no vector: masked, or
    outside the band of ``near``, which is ``outside``), and the speed limit per node (px/s) or None."""

    fin: _Level
    X: np.ndarray
    Y: np.ndarray
    node_mask: np.ndarray
    outside: np.ndarray | None
    max_speed: np.ndarray | None


def _final_nodes(fin, shape, mask, near, max_speed_px_s) -> _Nodes:
    X, Y = np.meshgrid(fin.xc, fin.yc)
    node_mask = np.zeros((fin.ny, fin.nx), dtype=bool)
    if mask is not None:
        node_mask = mask[np.rint(Y).astype(int).clip(0, shape[0] - 1), np.rint(X).astype(int).clip(0, shape[1] - 1)]
    outside = None if near is None else ~near[-1]
    if outside is not None:
        node_mask = node_mask | outside
    if max_speed_px_s is not None:
        max_speed_px_s = np.broadcast_to(np.asarray(max_speed_px_s, dtype=np.float64), (fin.ny, fin.nx))
    return _Nodes(fin, X, Y, node_mask, outside, max_speed_px_s)


class _PairLoop:
    """The pairs of one :func:`analyze` call: each frame's spectra prepared once, kept for ``frame_gap``
    frames, each pair correlated (or skipped by ``select``), its vectors validated and collected in
    ``per_pair``; the ensemble sums grow on the way."""

    def __init__(
        self,
        engine,
        params: PivParams,
        nodes: _Nodes,
        ens,
        wanted,
        subsample: bool,
        stride: int,
        per_pair: dict,
        total: int,
        shape,
    ):
        self.engine, self.params, self.nodes, self.ens, self.wanted = engine, params, nodes, ens, wanted
        self.subsample, self.stride, self.per_pair, self.total, self.shape = subsample, stride, per_pair, total, shape
        self.gap = max(1, int(params.frame_gap))

    def prep(self, k: int, img):
        """Frame k's spectra; with ``select``: None when no selected pair uses it (it may come undecoded),
        and only what a pair's second frame needs when it is not the first frame of a selected pair."""
        engine, wanted, gap = self.engine, self.wanted, self.gap
        if wanted is None:
            return engine.prepare(img)
        if k not in wanted and k - gap not in wanted:
            return None
        img = _check_frame(k, img, self.shape)
        if type(engine).prepare is not _Engine.prepare:
            return engine.prepare(img)
        return engine.prepare(img, as_a=k in wanted, as_b=k - gap in wanted)

    def run(self, it, first, t_prev, cancel, progress, on_pair) -> int:
        """Read the frames after ``first``; returns the number of pairs passed (correlated or skipped).

        With the CPU engine a frame's spectra are prepared on a thread of their own while the pair before it is
        correlated (one frame ahead: the correlation's chunks and the validation leave a core idle otherwise)."""
        wanted, gap, shape = self.wanted, self.gap, self.shape
        last_wanted = max(wanted) if wanted else -1
        self.history = deque([(self.prep(0, first), float(t_prev))], maxlen=gap)  # the last `gap` frames
        self.i = 0
        t_last = float(t_prev)
        ahead = type(self.engine) is _Engine  # the GPU and OpenPIV engines prepare in the calling thread
        with ThreadPoolExecutor(1, thread_name_prefix="piv-prep") if ahead else nullcontext() as prep_pool:
            pending = None  # (position, t_s, spectra or their future) of the frame read last
            for i_frame, (t, img) in enumerate(it, start=1):
                if wanted is not None and i_frame - gap > last_wanted:  # hook of ``select``: no selected pair left
                    break
                if cancel is not None and cancel():
                    raise Cancelled(f"PIV cancelled by the user after {self.i} pairs")
                if wanted is None:
                    img = _check_frame(i_frame, img, shape)
                t = float(t)
                if not t > t_last:
                    raise InputFileError(
                        f"frames: timestamps must increase; frame {i_frame} is at {t:.6f} s after {t_last:.6f} s"
                    )
                t_last = t
                cur = prep_pool.submit(self.prep, i_frame, img) if prep_pool is not None else self.prep(i_frame, img)
                if pending is not None:
                    self._next(*pending, cancel, progress, on_pair)
                pending = (i_frame, t, cur)
            if pending is not None:
                self._next(*pending, cancel, progress, on_pair)
        i = self.i
        if i == 0:
            if gap > 1:
                raise ParameterError(
                    f"piv.frame_gap: {gap} frames between the images of a pair, but the selected "
                    "time range holds no such pair; lower piv.frame_gap or widen video.start_s / "
                    "video.end_s"
                )
            raise ParameterError(
                "video: only 1 frame in the selected time range; PIV needs at least 2 — widen "
                "video.start_s / video.end_s or lower video.step"
            )
        return i

    def _next(self, i_frame: int, t: float, cur, cancel, progress, on_pair) -> None:
        """Frame ``i_frame`` (its spectra, or their future) joins the history; the pair it ends is correlated."""
        if isinstance(cur, Future):
            cur = cur.result()
        history = self.history
        if len(history) < self.gap:  # the first frames only fill the history
            history.append((cur, t))
            return
        prev, t_prev = history[0]
        if self.wanted is None or self.i in self.wanted:  # else the hook of ``select``: this pair is skipped
            self.pair(self.i, prev, cur, t_prev, t, cancel, on_pair)
        self.i += 1
        if progress is not None:
            progress(self.i, self.total)
        history.append((cur, t))

    def pair(self, i: int, prev, cur, t_prev: float, t: float, cancel, on_pair) -> None:
        """Correlate pair ``i`` (frames at ``t_prev`` and ``t`` s); its vectors (px/s) join ``per_pair``."""
        engine, params, nd, per_pair = self.engine, self.params, self.nodes, self.per_pair
        dt = t - t_prev
        cb = None
        if self.ens is not None:
            cb = self.ens.add_fn(dt, nd.node_mask)
        if self.subsample and i % self.stride:
            engine.correlate(prev, cur, cancel=cancel, ensemble=cb, peaks=False)
            return
        dx, dy, pk = engine.correlate(prev, cur, cancel=cancel, ensemble=cb)
        snr = pk.snr.reshape(dx.shape)
        ok = _pair_validity(dx, dy, pk.ok.reshape(dx.shape), snr, dt, params, nd.node_mask, nd.max_speed)
        u = np.where(ok, dx / dt, np.nan).astype(np.float32)
        v = np.where(ok, dy / dt, np.nan).astype(np.float32)
        tm = 0.5 * (t + t_prev)
        for key, val in (
            ("u", u),
            ("v", v),
            ("t", tm),
            ("dt", dt),
            ("index", i),
            ("snr", np.where(nd.node_mask, np.nan, snr).astype(np.float32)),
            ("p2m", pk.p2m.reshape(dx.shape).astype(np.float32)),
            ("peak", pk.peak.reshape(dx.shape).astype(np.float32)),
        ):
            per_pair[key].append(val)
        if self.subsample and not self.total and len(per_pair["u"]) >= 2 * ENSEMBLE_PAIRS:  # keep every other one
            self.per_pair = {key: val[::2] for key, val in per_pair.items()}
            self.stride *= 2
        if on_pair is not None:
            on_pair(i, tm, nd.X, nd.Y, u, v, ok)


def _time_average(
    per_pair: dict,
    ens,
    nodes: _Nodes,
    params: PivParams,
    n_pairs: int,
    wanted,
    first_guess: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None,
) -> PivResult:
    """The time-averaged field of the pairs (ensemble, mean or median), validated and filled, as a PivResult."""
    fin = nodes.fin
    u_pairs, v_pairs = np.stack(per_pair["u"]), np.stack(per_pair["v"])
    n_valid = np.sum(np.isfinite(u_pairs), axis=0)
    vf = n_valid / float(len(u_pairs))
    if nodes.outside is not None:
        vf = np.where(nodes.outside, np.nan, vf)
    with np.errstate(all="ignore"):
        snr_med = _nanmedian_t(np.stack(per_pair["snr"]))
        p2m_med = _nanmedian_t(np.stack(per_pair["p2m"]))
        peak_med = _nanmedian_t(np.stack(per_pair["peak"]))
    dts = np.asarray(per_pair["dt"])
    ens_snr = None
    if ens is not None:
        u_avg, v_avg, ens_ok, ens_snr = ens.result(keep=wanted is not None)
    else:
        if params.averaging == "mean":
            with np.errstate(all="ignore"):
                u_avg = np.nansum(u_pairs, axis=0, dtype=np.float64) / n_valid
                v_avg = np.nansum(v_pairs, axis=0, dtype=np.float64) / n_valid
        else:
            u_avg, v_avg = _nanmedian_t(u_pairs), _nanmedian_t(v_pairs)
        ens_ok = n_valid > 0
    u_avg, v_avg, valid, replaced = _finish_average(
        u_avg.astype(np.float64),
        v_avg.astype(np.float64),
        ens_ok,
        vf,
        nodes.node_mask,
        nodes.max_speed,
        float(np.median(dts)),
        params,
    )
    return PivResult(
        x=nodes.X,
        y=nodes.Y,
        u=u_avg,
        v=v_avg,
        valid=valid,
        valid_fraction=vf,
        u_pairs=u_pairs,
        v_pairs=v_pairs,
        t_pairs=np.asarray(per_pair["t"]),
        snr=snr_med,
        params=params,
        peak2mean=p2m_med,
        peak=peak_med,
        replaced=replaced,
        ensemble_snr=ens_snr,
        dt_s=dts,
        pair_index=np.asarray(per_pair["index"], dtype=np.int64),
        n_pairs=n_pairs,
        zero_peak_removed=None if ens is None else ens.zero_removed,
        first_guess=None
        if first_guess is None
        else _guess_at(fin, *first_guess, whole=False).reshape(fin.ny, fin.nx, 2),
        carry=_Carry(ens, per_pair, n_pairs) if wanted is not None else None,
    )


@dataclass
class _Carry:
    """What ``analyze(select=...)`` hands to its next call: the ensemble sums, per-pair fields, pairs done."""

    ensemble: object | None
    per_pair: dict
    n_pairs: int


def _nanmedian_t(stack: np.ndarray) -> np.ndarray:
    """Median over axis 0 ignoring NaN; NaN where a node has no value (no warning)."""
    if np.isfinite(stack).all():
        return np.median(stack, axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(stack, axis=0)


def _finish_average(u, v, base_ok, vf, node_mask, max_speed, dt_med, params):
    """Validate the time-averaged field and replace isolated gaps from valid neighbours (masked nodes stay NaN)."""
    ok = base_ok & np.isfinite(u) & np.isfinite(v) & (vf >= params.min_valid_fraction) & ~node_mask
    ok &= pv.speed_test(np.where(ok, u, np.nan), np.where(ok, v, np.nan), max_speed)
    du, dv = np.where(ok, u * dt_med, np.nan), np.where(ok, v * dt_med, np.nan)
    ok &= pv.normalized_median_test(du, dv, params.median_threshold)
    u2, v2, replaced = pv.replace_invalid(
        np.where(ok, u, np.nan), np.where(ok, v, np.nan), keep_invalid=node_mask, min_neighbours=5, max_iter=1
    )
    valid = ok | replaced
    return np.where(valid, u2, np.nan), np.where(valid, v2, np.nan), valid, replaced


class _Ensemble:
    """SNR-weighted sum of the final pass' cross-spectra (or correlation planes) and predictors over all pairs.

    A pair with peaks weighs each node by clip(peak ratio - 1, 0, 10); a pair without (``peaks=None``, ensemble
    mode between the sampled pairs) by the node's mean weight over the pairs with peaks so far.
    """

    def __init__(self, engine, lv: _Level, snr_min: float):
        self.engine = engine
        self.lv = lv
        self.snr_min = snr_min
        self.spec: np.ndarray | None = None  # summed, weighted cross-spectra of the final pass
        self.wsum = np.zeros(lv.ny * lv.nx)
        self.px = np.zeros(lv.ny * lv.nx)
        self.py = np.zeros(lv.ny * lv.nx)
        self.wdt = np.zeros(lv.ny * lv.nx)
        self.wpk = np.zeros(lv.ny * lv.nx)  # sum of the weights of the pairs with peaks
        self.npk = 0
        self.remove_zero = False
        self.zero_removed: np.ndarray | None = None

    def add_fn(self, dt: float, node_mask: np.ndarray):
        def add(cross, pred_x, pred_y, pk, scale=None):
            if pk is not None:
                w = np.clip(np.nan_to_num(pk.snr, nan=1.0) - 1.0, 0.0, 10.0)
                w[node_mask.ravel()] = 0.0
                self.wpk += w
                self.npk += 1
            else:
                w = self.wpk / max(self.npk, 1)
            if scale is not None:
                w = np.where(scale > 0, w, 0.0)  # featureless windows (texture gate) weigh nothing
            wf = w.astype(np.float32)
            if scale is not None:  # planes not normalised yet: unit-energy factors
                wf *= scale
            wf = wf.reshape((-1,) + (1,) * (cross.ndim - 1))
            to_device = getattr(self.engine, "to_device", None)  # GPU engine: weights go to the device
            if to_device is not None:
                cross *= to_device(wf)
                if self.spec is None:
                    self.spec = cross.copy()
                else:
                    self.spec += cross
            else:
                if self.spec is None:
                    self.spec = np.zeros_like(cross)
                spec = self.spec

                def add_rows(lo: int, hi: int) -> None:  # one pass over each chunk of nodes, in cache
                    c = cross[lo:hi]
                    c *= wf[lo:hi]
                    spec[lo:hi] += c

                chunked(len(cross), _chunk_nodes(cross.shape[1]), add_rows)
            self.wsum += w
            self.wdt += w * dt
            if pred_x is not None:
                self.px += w * pred_x.ravel()
                self.py += w * pred_y.ravel()

        return add

    def result(self, keep: bool = False):
        """Time-averaged field; ``keep``: leave the sums usable for more pairs (the inverse FFT works in place)."""
        lv = self.lv
        assert self.spec is not None, "no pair was added"
        spec = self.spec.copy() if keep else self.spec  # the inverse FFT works in place
        if self.remove_zero and type(self.engine) is _Engine and len(self.engine.levels) > 1:
            corr = self.engine.ensemble_planes(spec)
            with np.errstate(all="ignore"):
                self.zero_removed = piv_peaks.blank_zero(corr, lv.margin, self.px / self.wsum, self.py / self.wsum)
            self.zero_removed = self.zero_removed.reshape(lv.ny, lv.nx)
            pk = _find_peaks(corr, lv.margin)
        else:
            pk = self.engine.ensemble_peaks(spec)
        with np.errstate(all="ignore"):
            dt = self.wdt / self.wsum
            dx = pk.dx + self.px / self.wsum
            dy = pk.dy + self.py / self.wsum
            u, v = dx / dt, dy / dt
        ok = (self.wsum > 0) & pk.ok & (np.nan_to_num(pk.snr) >= self.snr_min)
        shp = (lv.ny, lv.nx)
        return u.reshape(shp), v.reshape(shp), ok.reshape(shp), pk.snr.reshape(shp)


def _make_engine(backend, shape, params, levels, box, mask, near=None, guess=None):
    """The engine of ``params.engine`` / ``backend``. ``near`` (per level, the nodes near the section; the others
    are skipped) is only a saving of the CPU engine; the others correlate every node and ``analyze`` drops the far
    ones. ``guess`` (first-pass window offsets) only the CPU engine uses."""
    if params.engine == "openpiv":
        # lazy: openpiv's import (0.3-0.6 s, with its windef) serves only this reference engine
        from fieldtool.processing.piv_openpiv import _OpenPivEngine

        return _OpenPivEngine(shape, params, levels, box, mask)
    if backend not in ("auto", "cpu", "gpu"):
        raise ParameterError(f"piv backend: {backend!r} is not one of auto, cpu, gpu")
    if guess is not None and backend == "gpu":
        raise ParameterError(
            "piv backend: gpu asked for, but the first pass starts from the first look's field, which "
            "only the CPU engine does; set piv.search_px to search a wider area instead"
        )
    if backend in ("auto", "gpu") and guess is None:
        if piv_gpu.usable_for(params) and piv_gpu.available():
            return piv_gpu.GpuEngine(shape, params, levels, box, mask)
        if backend == "gpu":
            raise ParameterError(
                "piv backend: gpu asked for, but it needs CuPy with a CUDA device (checked against "
                "the CPU engine) and piv.passes = 1"
            )
    return _Engine(shape, params, levels, box, mask, near, guess)
