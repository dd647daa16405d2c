"""The overlay video of a run, ``overlay.mp4``, drawn while the run streams its frames (no second decode).

What it shows: the analysed range of the clip as the run saw it (lens and stabilisation applied; gray, as
the run reads it) or its rectified view (``[overlay] view``), with

- the per-pair vectors of the section band (the measured pair nearest in time, among those measured so
  far), coloured by surface speed (m/s) through a perceptual colour map, and its legend;
- the section, each subsection coloured by that pair's surface velocity (m/s);
- the time code (clip time, s; frame index), the running Q (median of the pair discharges measured up
  to that time, m³/s), and the project's name, site, station and operator;
- a closing card (``[overlay] card_s``): the mean field, the final Q with its 95 % interval and the grade.

How it is fed (hooks in ``run/pipeline.py``):

- :func:`start` makes the :class:`Recorder` (None unless ``[overlay] enabled`` and an output folder);
  :func:`fan_out` lets the run's one observer slot feed both the user's observer (rerun) and the recorder;
- the recorder asks for every working frame (``wants_every_frame``: the run then builds every frame of its
  first pass, which the fast path would otherwise only decode past) and takes them through ``every_frame``
  from the run's frame thread; a later pass over the clip (the fast path's further rounds) is ignored;
- ``pair`` takes each pair's field from the PIV, ``geometry`` the pair-discharge function;
- frames wait in a bounded buffer (at most :data:`BUFFER_BYTES` of downscaled frames) until the pair at their
  time is measured, and a thread of its own draws and encodes them (H.264 through PyAV,
  :class:`fieldtool.writers.overlay.VideoWriter`);
- :func:`finish` (in ``write_outputs``) adds the closing card, closes the file and moves it into the output
  folder; :func:`abort` throws the partial file away when the run fails or is cancelled.

A run that reuses its PIV field (``piv_cache.npz``) streams no frame: :func:`feed_cached` gives the recorder
the cached per-pair fields, and the recorder takes its frames from the one pass the run then makes anyway
(STIV's lines) or, without STIV, from a pass of its own (:func:`ensure_drawn`): the only decode of that run.

Drawing never fails a run: an error becomes a warning in ``result.json`` and no overlay.mp4 is written.
"""

from __future__ import annotations

import collections
import os
import shutil
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np

from fieldtool.processing import discharge as dq
from fieldtool.writers import overlay as draw

FILE = "overlay.mp4"
BUFFER_BYTES = 96 * 2**20  # downscaled gray frames waiting for their pair (bounded: the clip is never held)
MAX_LAG_S = 4.0  # a frame waits at most this long (clip time) for the pair at its time
MIN_ARROW_GAP_PX = 10.0  # nodes closer than this on the video are thinned (a 1080p clip on a 960 px video)
WAIT_SLICE_S = 0.2  # waits are sliced so that a failed or stopped drawing thread never blocks the run


def start(project, out_dir, ends=None) -> Recorder | None:
    """The recorder of ``project``'s overlay, or None (``[overlay] enabled = false``, or no output folder).
    ``ends`` (a contextlib.ExitStack) gets its :meth:`Recorder.abort`, so a failed run leaves no file."""
    if out_dir is None or not project.overlay.enabled:
        return None
    rec = Recorder(project)
    if ends is not None:
        ends.callback(rec.abort)
    return rec


def fan_out(observer, recorder: Recorder | None, warnings: list[str]):
    """One observer calling ``observer`` (the user's, may be None) and ``recorder``; ``observer`` itself when
    there is no recorder (the run behaves exactly as without an overlay)."""
    if recorder is None:
        return observer
    return Fanout([o for o in (observer, recorder) if o is not None], warnings)


class Fanout:
    """Calls each of several observers in turn; one that raises is dropped with a warning, the others go on."""

    def __init__(self, observers: list, warnings: list[str]):
        self.observers, self.warnings = list(observers), warnings

    def wants_every_frame(self) -> bool:
        return any(bool(getattr(o, "wants_every_frame", lambda: False)()) for o in self.observers)

    def __getattr__(self, method: str) -> Callable:
        if method.startswith("_"):
            raise AttributeError(method)

        def call(*args) -> None:
            for o in list(self.observers):
                fn = getattr(o, method, None)
                if fn is None:
                    continue
                try:
                    fn(*args)
                except Exception as e:  # noqa: BLE001 - a logger must not break a measurement
                    self.observers.remove(o)
                    who = "overlay" if isinstance(o, Recorder) else "live logging"
                    self.warnings.append(f"{who} stopped: {type(e).__name__}: {e}")

        return call


def bind(recorder: Recorder | None, inputs, mapping, geom: dq.SectionGeometry) -> None:
    """Give the recorder the clip, the mapping and the section (before the PIV streams)."""
    if recorder is not None:
        recorder.bind(inputs, mapping, geom)


def feed_cached(recorder: Recorder | None, piv_res) -> None:
    """A run that reused its PIV field: hand the recorder the cached per-pair fields (before any frame)."""
    if recorder is None or recorder.frames_seen or recorder.pairs:
        return
    for k in range(len(piv_res.t_pairs)):
        u, v = piv_res.u_pairs[k], piv_res.v_pairs[k]
        recorder.pair(k, float(piv_res.t_pairs[k]), piv_res.x, piv_res.y, u, v, np.isfinite(u) & np.isfinite(v))


def ensure_drawn(recorder: Recorder | None, frames: Callable[[], Iterator]) -> None:
    """Stream the clip for the recorder when the run streamed none (its PIV field and STIV were reused)."""
    if recorder is not None and recorder.wants_every_frame() and not recorder.frames_seen:
        for _ in frames():
            pass


def finish(result, folder: Path) -> None:
    """Closing card, file closed and moved to ``folder / overlay.mp4``, listed in ``result.files``; its
    facts in ``result.overlay.info``. Any failure is a warning of the run (the measurement is kept)."""
    rec = getattr(result, "overlay", None)
    if rec is None:
        return
    t0 = time.perf_counter()
    try:
        rec.finish(result, Path(folder) / FILE)
        result.files["overlay"] = FILE
    except Exception as e:  # noqa: BLE001 - the video is an illustration; the measurement stands without it
        rec.abort()
        result.warnings.append(f"overlay.mp4 not written: {type(e).__name__}: {e}")
    finally:
        result.timings_s["overlay_finish"] = round(time.perf_counter() - t0, 3)
    if rec.info and rec.info.get("warning"):
        result.warnings.append(rec.info["warning"])


class _Pair:
    """One measured pair as the overlay draws it (computed in the drawing thread, once)."""

    __slots__ = ("end", "ok", "q", "speed", "start", "t", "u", "v", "v_sub", "x", "y")

    def __init__(self, t, x, y, u, v, ok):
        self.t, self.x, self.y, self.u, self.v, self.ok = t, x, y, u, v, ok
        self.start = self.end = self.speed = self.v_sub = None
        self.q = np.nan


class Recorder:
    """Draws and encodes the overlay of one run (see the module docstring). Every public method is safe to
    call from the run's threads; drawing happens in a thread of its own."""

    def __init__(self, project) -> None:
        o = project.overlay
        self.view, self.width_px, self.fps_set, self.card_s = o.view, int(o.width_px), o.fps, float(o.card_s)
        self.table = draw.lut(o.colormap)
        self.header = [
            t
            for t in (
                project.name if project.name != "measurement" else "",
                "  ".join(
                    f"{k} {v}"
                    for k, v in (("site", project.site), ("station", project.station), ("operator", project.operator))
                    if v
                ),
            )
            if t
        ]
        self.pairs: list[_Pair] = []
        self.pair_q: Callable | None = None
        self.frames_seen = 0
        self.info: dict | None = None
        self._bound = False
        self._pass_done = False
        self._last_index = -1
        self._t0: float | None = None
        self._last_pts = -1
        self._pts_slack = 0.25
        self._buf: collections.deque = collections.deque()
        self._cond = threading.Condition()
        self._ended = False
        self._piv_done = False
        self._stop = False
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None
        self._writer: draw.VideoWriter | None = None
        self._tmp: Path | None = None
        self._last_base: np.ndarray | None = None
        self._vrange: tuple[float, float] | None = None
        self._arrow_s: float | None = None
        self._stride = 1
        self._drawn = self._card_frames = 0
        self._busy_s = self._wait_s = self._prep_s = self._encode_s = 0.0
        self._pairs_used: set[int] = set()
        self._t_first = self._t_last = None

    # ------------------------------------------------------------------ set-up

    def bind(self, inputs, mapping, geom: dq.SectionGeometry) -> None:
        """Frame size, rate, view transform, section limits; opens nothing yet."""
        self.mapping, self.geom = mapping, geom
        h, w = inputs.shape
        info = getattr(inputs.source, "info", None)
        clip_fps = float(getattr(info, "fps", 0) or 0) / max(1, int(getattr(inputs.source, "step", 1) or 1))
        self.fps = float(self.fps_set) if self.fps_set else (clip_fps if clip_fps > 0 else 25.0)
        # a frame takes the video's period it falls in, with a quarter of the clip's period of slack for the
        # container's timestamp jitter: at the clip's rate every frame is kept, at half of it every second one
        self._pts_slack = 0.25 * self.fps / clip_fps if clip_fps > 0 else 0.25
        out_w = w if self.width_px == 0 else min(self.width_px, w)
        if self.view == "rectified":
            A, size = _rectified_frame(mapping, (h, w), out_w)
            self.size = draw.even_size(*size)
            self._M = A @ mapping.H
            self.to_view = lambda p: _apply(self._M, p)
        else:
            self.size = draw.even_size(out_w, round(h * out_w / w))
            sx, sy = self.size[0] / w, self.size[1] / h
            self._M = np.array([[sx, 0, 0], [0, sy, 0], [0, 0, 1.0]])
            self.to_view = lambda p: np.asarray(p, float).reshape(-1, 2) * (sx, sy)
        edges = np.asarray(geom.station_edges, float)
        frac = (edges - edges[0]) / (edges[-1] - edges[0]) if edges[-1] != edges[0] else np.linspace(0, 1, len(edges))
        pw = np.asarray(geom.p_world, float)
        self._limits_img = mapping.world_to_image(pw[0] + frac[:, None] * (pw[1] - pw[0]))
        per_frame = self.size[0] * self.size[1]
        self._capacity = max(8, min(int(BUFFER_BYTES // per_frame), int(MAX_LAG_S * self.fps * 2) + 8))
        self._lag = max(4, min(self._capacity - 4, int(MAX_LAG_S * self.fps)))
        self._bound = True

    # ------------------------------------------------------------------ observer hooks

    def wants_every_frame(self) -> bool:
        """True until one pass over the clip was seen whole (later passes are not drawn)."""
        return not self._pass_done and not self._stop and self._error is None

    def geometry(self, pair_discharge) -> None:
        self.pair_q = pair_discharge

    def stage(self, name: str) -> None:
        """After the PIV no further pair comes: the frames still waiting are drawn (during the discharge and
        the Monte Carlo)."""
        if name == "discharge":
            with self._cond:
                self._piv_done = True
                self._cond.notify_all()

    def pair(self, i, t_s, x, y, u_px_s, v_px_s, valid) -> None:
        p = _Pair(
            float(t_s),
            np.asarray(x, float),
            np.asarray(y, float),
            np.array(u_px_s, np.float32),
            np.array(v_px_s, np.float32),
            np.array(valid, bool),
        )
        with self._cond:
            self.pairs.append(p)
            self._cond.notify_all()

    def every_frame(self, index: int, t_s: float, image: np.ndarray) -> None:
        """One working frame (gray or BGR, lens and stabilisation applied), from the run's frame thread."""
        if not self._bound or self._pass_done or index <= self._last_index or self._error is not None:
            return
        self._last_index = index
        if self._t0 is None:
            self._t0 = float(t_s)
        pts = int(np.floor((float(t_s) - self._t0) * self.fps + self._pts_slack))
        if pts <= self._last_pts:  # the video's rate is below the clip's: this frame is dropped
            return
        self._last_pts = pts
        t0 = time.perf_counter()
        img = image if image.dtype == np.uint8 else np.clip(np.nan_to_num(image), 0, 255).astype(np.uint8)
        if self.view == "rectified":
            small = cv2.warpPerspective(img, self._M, self.size, flags=cv2.INTER_LINEAR, borderValue=0)
        else:
            small = downscale(img, self.size)
        self._prep_s += time.perf_counter() - t0
        self.frames_seen += 1
        self._ensure_thread()
        assert self._thread is not None  # started by _ensure_thread
        t1 = time.perf_counter()
        with self._cond:
            while len(self._buf) >= self._capacity and self._thread.is_alive() and not self._stop:
                self._cond.wait(WAIT_SLICE_S)
            self._buf.append((index, float(t_s), pts, small))
            self._cond.notify_all()
        self._wait_s += time.perf_counter() - t1

    def frames_done(self) -> None:
        """The run's frame stream reached the end of the clip: the pass is complete."""
        if self.frames_seen:
            self._pass_done = True
            with self._cond:
                self._cond.notify_all()

    # ------------------------------------------------------------------ drawing thread

    def _ensure_thread(self) -> None:
        if self._thread is None:
            fd, name = tempfile.mkstemp(prefix="fieldtool-overlay-", suffix=".mp4")
            os.close(fd)
            self._tmp = Path(name)
            self._writer = draw.VideoWriter(self._tmp, *self.size, self.fps)
            self._thread = threading.Thread(target=self._loop, name="overlay", daemon=True)
            self._thread.start()

    def _ready(self) -> bool:
        """Whether the oldest buffered frame can be drawn: its pair is measured, it waited long enough, or the
        stream ended."""
        if not self._buf:
            return False
        if self._ended or self._piv_done or len(self._buf) >= self._lag:
            return True
        t = self._buf[0][1]
        return any(p.t >= t for p in self.pairs[-4:])

    def _loop(self) -> None:
        try:
            while True:
                with self._cond:
                    while not self._stop and not self._ready() and not (self._ended and not self._buf):
                        self._cond.wait(WAIT_SLICE_S)
                    if self._stop or (self._ended and not self._buf):
                        return
                    item = self._buf.popleft()
                    pairs = list(self.pairs)
                    self._cond.notify_all()
                t0 = time.perf_counter()
                self._draw_frame(item, pairs)
                self._busy_s += time.perf_counter() - t0
        except BaseException as e:  # noqa: BLE001 - reported by finish() as a warning
            self._error = e
            with self._cond:
                self._buf.clear()
                self._cond.notify_all()

    def _prepare(self, p: _Pair) -> None:
        """World speeds, arrows (working px), subsection velocities and discharge of one pair (once)."""
        if p.speed is not None:
            return
        ok = p.ok & np.isfinite(p.u) & np.isfinite(p.v)
        u, v = np.where(ok, p.u.astype(float), np.nan), np.where(ok, p.v.astype(float), np.nan)
        U, V = self.mapping.rectify_velocity(p.x, p.y, u, v)
        if self._arrow_s is None and ok.any():
            xs = np.unique(np.round(p.x.ravel(), 3))
            spacing = float(np.median(np.diff(xs))) if len(xs) > 1 else 16.0
            sp = np.hypot(u[ok], v[ok])
            ref = float(np.percentile(sp, 90)) if sp.size else 0.0
            self._stride = (
                max(1, int(round(MIN_ARROW_GAP_PX / (spacing * self._M[0, 0])))) if self.view == "camera" else 1
            )  # nodes closer than that on the video: every stride-th drawn
            self._arrow_s = 1.2 * spacing * self._stride / ref if ref > 0 else 0.5
            world = np.hypot(U[ok], V[ok])
            self._vrange = (0.0, draw.nice_ceil(float(np.percentile(world, 98))))  # fixed for the video
        a = self._arrow_s or 0.0
        shown = ok & _every(np.shape(ok), self._stride)
        p.start = np.c_[p.x[shown], p.y[shown]]
        p.end = p.start + np.c_[u[shown], v[shown]] * a
        p.speed = np.hypot(U[shown], V[shown])
        with np.errstate(invalid="ignore"):
            p.v_sub = np.abs(dq.subsection_velocity(self.geom, p.x, p.y, U, V))
        if self.pair_q is not None:
            try:
                p.q = abs(float(self.pair_q(p.x, p.y, u, v)))
            except Exception:  # noqa: BLE001 - a pair without a discharge is drawn without one
                p.q = np.nan
        p.u = p.v = p.ok = None  # only what is drawn is kept

    def _base(self, small: np.ndarray) -> np.ndarray:
        return cv2.cvtColor(small, cv2.COLOR_GRAY2BGR) if small.ndim == 2 else small.copy()

    def _draw_field(self, img, start, end, speed, v_sub) -> None:
        if self._vrange is None:
            return
        lo, hi = self._vrange
        th = max(1, int(round(img.shape[0] / 270)))  # 2 px at 540 lines
        if start is not None and len(start):
            draw.draw_arrows(
                img, self.to_view(start), self.to_view(end), draw.colours(speed, lo, hi, self.table, levels=48), th
            )
        draw.draw_section(
            img,
            self.to_view(self._limits_img),
            v_sub,
            lo,
            hi,
            self.table,
            thickness=max(4, int(round(img.shape[0] / 90))),
        )
        draw.draw_legend(img, lo, hi, self.table)

    def _draw_frame(self, item, pairs: list[_Pair]) -> None:
        index, t, pts, small = item
        img = self._base(small)
        self._last_base = small
        near = None
        if pairs:
            k = int(np.argmin([abs(p.t - t) for p in pairs]))
            near = pairs[k]
            self._prepare(near)
            self._pairs_used.add(id(near))
        if near is not None:
            self._draw_field(img, near.start, near.end, near.speed, near.v_sub)
        else:
            self._draw_field(img, None, None, None, np.full(len(self._limits_img) - 1, np.nan))
        so_far = []
        for p in pairs:
            if p.t <= t + 1e-9:
                self._prepare(p)
                if np.isfinite(p.q):
                    so_far.append(p.q)
        q_line = (
            f"running Q {np.median(so_far):.3f} m3/s (median of {len(so_far)} pair{'s' * (len(so_far) > 1)} so far)"
            if so_far
            else "running Q: no pair measured yet"
        )
        draw.draw_panel(img, self.header + [f"t = {t:.2f} s   frame {index}", q_line])
        if near is not None:
            draw.draw_panel(
                img,
                [f"vectors: frame pair at {near.t:.2f} s" + (" (rectified view)" if self.view == "rectified" else "")],
                corner="bl",
            )
        t_enc = time.perf_counter()
        assert self._writer is not None  # made with the drawing thread that calls this
        self._writer.write(img, pts)
        self._encode_s += time.perf_counter() - t_enc
        self._drawn += 1
        self._t_first = t if self._t_first is None else self._t_first
        self._t_last = t

    # ------------------------------------------------------------------ end

    def finish(self, result, path: Path) -> None:
        """Drain the buffer, add the closing card, close and move the file to ``path``."""
        with self._cond:
            self._ended = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join()
        if self._error is not None:
            raise self._error
        if self._writer is None:
            raise RuntimeError("the run streamed no frame to draw")
        t0 = time.perf_counter()
        n_card = int(round(self.card_s * self.fps))
        if n_card and self._last_base is not None:
            card = self._card(result)
            t_enc = time.perf_counter()
            for k in range(n_card):
                self._writer.write(card, self._last_pts + 1 + k)
            self._encode_s += time.perf_counter() - t_enc
            self._card_frames = n_card
        self._writer.close()
        self._busy_s += time.perf_counter() - t0
        shutil.move(str(self._tmp), str(path))
        self._tmp = None
        self.info = {
            "file": FILE,
            "backend": self._writer.backend,
            "codec": self._writer.codec,
            "pix_fmt": "yuv420p" if self._writer.backend == "pyav" else None,
            "width_px": self.size[0],
            "height_px": self.size[1],
            "fps": float(self._writer.rate),
            "view": self.view,
            "frames": self._drawn,
            "card_frames": self._card_frames,
            "t_first_s": self._t_first,
            "t_last_s": self._t_last,
            "pairs_drawn": len(self._pairs_used),
            "pairs_known": len(self.pairs),
            "draw_encode_s": round(self._busy_s, 3),
            "encode_s": round(self._encode_s, 3),
            "frame_prep_s": round(self._prep_s, 3),
            "run_waited_s": round(self._wait_s, 3),
            "warning": self._writer.warning or None,
        }

    def _card(self, result) -> np.ndarray:
        """The closing card: the mean field and the subsections' final velocities under Q, its interval and the
        grade."""
        assert self._last_base is not None  # called once a frame was drawn
        img = (self._base(self._last_base) * 0.5).astype(np.uint8)
        p, d = result.piv, result.discharge
        ok = np.asarray(p.valid, bool) & np.isfinite(p.u) & np.isfinite(p.v)
        if self._arrow_s is not None:
            ok &= _every(np.shape(ok), self._stride)
            start = np.c_[p.x[ok], p.y[ok]]
            end = start + np.c_[p.u[ok], p.v[ok]] * self._arrow_s
            speed = np.hypot(np.asarray(result.world_u)[ok], np.asarray(result.world_v)[ok])
            v_sub = np.abs(np.asarray(d.surface_velocity_ms, float))
            if result.section.swapped:  # the section was turned round after the frames were drawn
                v_sub = v_sub[::-1]
            self._draw_field(img, start, end, speed, v_sub)
        unc = getattr(result, "uncertainty", None)
        ci = getattr(unc, "ci95_m3s", None) if unc is not None else None
        grade = getattr(getattr(result, "quality", None), "grade", None)
        lines = [(f"Q = {d.discharge_m3s:.3f} m3/s", (255, 255, 255), 2.2)]
        if ci is not None and np.all(np.isfinite(ci)):
            lines.append((f"95 % interval {ci[0]:.3f} - {ci[1]:.3f} m3/s", (255, 255, 255), 1.2))
        if grade:
            lines.append((f"grade: {grade.upper()}", draw.GRADE_BGR.get(grade, (255, 255, 255)), 1.5))
        lines.append(
            (
                f"mean velocity {d.mean_velocity_ms:.3f} m/s   level {d.water_level_m:.3f} m   "
                f"area {d.wetted_area_m2:.2f} m2",
                (220, 220, 220),
                0.9,
            )
        )
        draw.draw_card(img, lines)
        draw.draw_panel(img, self.header + ["final result (mean field)"])
        return img

    def abort(self) -> None:
        """Stop the drawing thread and remove the partial file (a failed or cancelled run)."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=10)
        if self._writer is not None and self._tmp is not None:
            self._writer.abort()
        if self._tmp is not None:
            self._tmp.unlink(missing_ok=True)
            self._tmp = None


def _every(shape: tuple, stride: int) -> np.ndarray:
    """Bool mask of every ``stride``-th node in each direction of a (ny, nx) grid (all for a 1-D one)."""
    if stride <= 1 or len(shape) != 2:
        return np.ones(shape, bool)
    r, c = np.indices(shape)
    return (r % stride == 0) & (c % stride == 0)


def downscale(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``img`` at ``size`` (width, height): bilinear down to half size (4x faster than area averaging at 0.75, on
    the run's frame thread), area averaging below."""
    fine = size[0] >= 0.5 * img.shape[1] and size[1] >= 0.5 * img.shape[0]
    return cv2.resize(img, size, interpolation=cv2.INTER_LINEAR if fine else cv2.INTER_AREA)


def _apply(M: np.ndarray, pts) -> np.ndarray:
    p = np.asarray(pts, float).reshape(-1, 2)
    q = np.c_[p, np.ones(len(p))] @ M.T
    return q[:, :2] / q[:, 2:3]


def _rectified_frame(mapping, shape: tuple[int, int], out_w: int) -> tuple[np.ndarray, tuple[int, int]]:
    """The world -> map-pixel affine and the map size (px) of the rectified view, as
    ``OrthoMapping.rectified_image`` lays it out (its longer side ``out_w``)."""
    probe, A = mapping.rectified_image(np.zeros(shape, np.uint8), max_side_px=out_w)
    return A, (probe.shape[1], probe.shape[0])
