"""Stream a run to rerun so a supervisor can watch what the tool computes.

:class:`RerunObserver` is a pipeline :class:`~fieldtool.run.observer.Observer`. It logs, on the
``time`` (s, clip time) and ``pair`` / ``frame`` (index) timelines:

=====================================  ==========================================================
entity                                 content
=====================================  ==========================================================
``frames/input``                       decimated working frames (undistorted, stabilised), JPEG
``frames/filtered``                    the same frames after the filter stack
``frames/input/pair_vectors``          ``Arrows2D`` of each pair's valid vectors (image pixels)
``frames/input/mean_field``            ``Arrows2D`` of the time-averaged field
``frames/input/section``               the section of interest and its subsection limits
``map/background``                     the rectified first frame (north up), placed in metres
``map/mean_field``                     ``Arrows2D`` of the rectified field, metres; m/s x ``map_arrow_s``
``map/section``                        the section and its subsection midpoints (velocities: profile)
``section/profile``                    surface velocity along the section, its band (2.5-97.5 % of
                                       the pair fields) and labels (station m, velocity m/s)
``section/surface_velocity_ms``        ``BarChart`` of the subsection surface velocities
``section/discharge_m3s``              ``BarChart`` of the subsection discharges
``piv/valid_fraction``                 ``Scalars``: fraction of valid vectors in each pair
``discharge/pair_m3s``                 "per-pair Q": discharge of each pair's field
``discharge/running_m3s``              "running estimate": median of the pair discharges so far
``discharge/final_m3s``                "final Q": the run's discharge, drawn over the clip span
``discharge/final_ci95_lo_m3s``, _hi   "final Q 95 % lower/upper": its interval (when the run has one)
``log``                                ``TextLog``: stages and warnings (and the overlay video's path)
``overlay/video``                      ``AssetVideo`` of overlay.mp4 (``--overlay``) with its frames on ``time``
=====================================  ==========================================================

Map coordinates: screen x = world X, screen y = -world Y (2D views draw y down; this keeps north up),
velocities likewise (U, -V). The profile: x = station (m), y = -velocity (m/s) x ``PROFILE_SCALE``.

A blueprint (:func:`blueprint`) lays the views out: the current frame with live vectors (large),
the rectified map, the section profile, and the discharge over time with its named series.

Image-space arrows are drawn on the (possibly downscaled) frame: positions are multiplied by
``image_scale`` and a velocity (px/s) is drawn as the displacement over ``arrow_s`` seconds;
both are logged in ``scale`` (a ``TextDocument``).

Three ways to reach a supervisor (``[rerun] mode`` or ``fieldtool run --rerun``): ``save`` to an
``.rrd`` file (the default when enabled), ``connect`` to a viewer the supervisor runs
(``rerun+http://HOST:9876/proxy``), or ``serve`` gRPC and the web viewer from this machine,
with no outside request (:mod:`fieldtool.viewer.rerun_web`). rerun's servers listen on ALL network
interfaces; serving is never on by default.

Logging never fails a run: any error becomes a warning in the run's result and logging stops.
"""

from __future__ import annotations

import sys
import uuid
from pathlib import Path
from urllib.parse import urlparse

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from scipy.spatial import cKDTree

from fieldtool.errors import InputFileError, ParameterError
from fieldtool.processing import discharge as dq
from fieldtool.run.observer import Observer
from fieldtool.viewer.rerun_web import OfflineWebViewer, disable_rerun_analytics

MODES = ("off", "save", "connect", "serve")
OVERLAY_MAX_BYTES = 64 * 2**20  # overlay.mp4 is put into the recording up to this size (else only named in the log)
PROFILE_SCALE = 10.0  # section profile: 1 m/s is drawn as 10 "metres" of station, so both axes read well
SERIES = {
    "pair_m3s": ("per-pair Q (one frame pair's field)", [150, 150, 150]),
    "running_m3s": ("running estimate (median of the pairs so far)", [255, 140, 0]),
    "final_m3s": ("final Q (the run's mean field)", [0, 200, 255]),
    "final_ci95_lo_m3s": ("final Q 95 % lower", [0, 120, 160]),
    "final_ci95_hi_m3s": ("final Q 95 % upper", [0, 120, 160]),
}


def blueprint():
    """The supervisor's layout: frame + live vectors (large) | map, section profile, discharge over time."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial2DView(origin="/frames/input", name="Current frame and live vectors (px)"),
            rrb.Vertical(
                rrb.Spatial2DView(origin="/map", name="Rectified map and mean field (m, north up)"),
                rrb.Spatial2DView(
                    origin="/section/profile",
                    name=f"Section: surface velocity and band (x station m, y m/s x {PROFILE_SCALE:g})",
                ),
                rrb.TimeSeriesView(
                    origin="/discharge", name="Discharge over time (m³/s)", plot_legend=rrb.PlotLegend(visible=True)
                ),
                row_shares=[3, 2, 2],
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(state="collapsed"),
        collapse_panels=True,
    )


DEFAULT_URL = "rerun+http://127.0.0.1:9876/proxy"
GRPC_PORT = 9876
WEB_PORT = 9090
SERVE_WARNING = (
    "rerun serve: the gRPC server (port {grpc}) and the web viewer (port {web}) listen on ALL network "
    "interfaces of this machine; anyone who can reach it can watch the run. Use it on a trusted network, "
    "or prefer `--rerun save` and copy the .rrd file."
)


def _to_uint8(img: np.ndarray) -> np.ndarray:
    """A frame for display: uint8 kept, other types stretched between their 1st and 99th percentiles."""
    if img.dtype == np.uint8:
        return img
    a = np.asarray(img, np.float32)
    sub = a[::2, ::2]
    fin = sub[np.isfinite(sub)]
    lo, hi = np.percentile(fin, (1, 99)) if fin.size else (0.0, 1.0)
    if hi <= lo:
        hi = lo + 1.0
    return np.clip((np.nan_to_num(a, nan=lo) - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)


class RerunObserver(Observer):
    """Pipeline observer that logs to a rerun recording (see the module docstring).

    Parameters
    ----------
    mode : "save" | "connect" | "serve"
    path : .rrd file (mode = save)
    url : viewer address rerun+http://HOST:PORT/proxy (mode = connect)
    grpc_port, web_port : ports of the servers (mode = serve)
    max_side_px : frames are downscaled so that their longer side is at most this (px)
    jpeg_quality : JPEG quality of the logged frames (1-100)
    recording : an existing ``rr.RecordingStream`` to log to (tests); ``mode`` is then ignored
    """

    def __init__(
        self,
        mode: str = "save",
        *,
        path: str | Path | None = None,
        url: str | None = None,
        grpc_port: int = GRPC_PORT,
        web_port: int = WEB_PORT,
        max_side_px: int = 640,
        jpeg_quality: int = 75,
        recording=None,
    ):
        self.rr = rr
        self.mode = mode
        self.max_side_px = max_side_px
        self.jpeg_quality = jpeg_quality
        self.warnings: list[str] = []
        self.failed = False
        self.image_scale: float | None = None
        self.arrow_s: float | None = None
        self.urls: dict[str, str] = {}
        self.path: Path | None = None
        self._q_pairs: list[float] = []
        self._pair_q = None  # live discharge of one field, from the pipeline's geometry()
        self._first: np.ndarray | None = None  # first working frame, for the map's background
        self.web = None
        if recording is not None:
            self.rec = recording
            return
        self.rec = rr.RecordingStream("fieldtool", recording_id=str(uuid.uuid4()))
        if mode == "save":
            if path is None:
                raise ParameterError("rerun.path: give the .rrd file to save to")
            self.path = Path(path)
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                self.rec.save(str(self.path), default_blueprint=blueprint())
            except Exception as e:  # noqa: BLE001 - rerun raises its own error types
                raise InputFileError(f"{self.path}: cannot write the rerun recording ({e}); check rerun.path") from e
        elif mode == "connect":
            self.urls["viewer"] = url or DEFAULT_URL
            self.rec.connect_grpc(self.urls["viewer"], default_blueprint=blueprint())
        elif mode == "serve":
            disable_rerun_analytics()
            self.urls["grpc"] = self.rec.serve_grpc(grpc_port=grpc_port, default_blueprint=blueprint())
            self.web = OfflineWebViewer(self.urls["grpc"], grpc_port, web_port)
            self.urls["local"] = self.web.start()
            self.urls["web"] = f"http://FIELD-MACHINE:{web_port}/?url=rerun%2Bhttp://FIELD-MACHINE:{grpc_port}/proxy"
        else:
            raise ParameterError(f"rerun.mode: {mode!r} is not one of {', '.join(MODES)}")

    # -------------------------------------------------------------------- guard

    def _guard(self, fn, *args) -> None:
        if self.failed:
            return
        try:
            fn(*args)
        except Exception as e:  # noqa: BLE001 - logging must never fail a measurement
            self.failed = True
            self.warnings.append(f"rerun logging stopped ({self.mode}): {type(e).__name__}: {e}")

    def _time(self, t_s: float, **seq: int) -> None:
        self.rec.set_time("time", duration=float(t_s))
        for name, value in seq.items():
            self.rec.set_time(name, sequence=int(value))

    # -------------------------------------------------------------------- Observer

    def stage(self, name: str) -> None:
        self._guard(lambda: self.rec.log("log", self.rr.TextLog(f"stage: {name}", level="INFO")))

    def warning(self, message: str) -> None:
        self._guard(lambda: self.rec.log("log", self.rr.TextLog(message, level="WARN")))

    def frame(self, index, t_s, raw, filtered) -> None:
        self._guard(self._frame, index, t_s, raw, filtered)

    def _frame(self, index, t_s, raw, filtered) -> None:
        rr = self.rr
        h, w = raw.shape[:2]
        if self.image_scale is None:
            self.image_scale = min(1.0, self.max_side_px / max(h, w))
        size = (max(1, round(w * self.image_scale)), max(1, round(h * self.image_scale)))
        self._time(t_s, frame=index)
        if self._first is None:
            self._first = np.array(raw, copy=True)
            self._series_names()
        for name, img in (("frames/input", raw), ("frames/filtered", filtered)):
            im = img if img.dtype in (np.uint8, np.float32) else np.asarray(img, np.float32)
            if self.image_scale < 1.0:  # downscale first: the stretch and the encoder see fewer pixels
                im = cv2.resize(im, size, interpolation=cv2.INTER_AREA)
            im = _to_uint8(im)
            if im.ndim == 3:
                im = cv2.cvtColor(im, cv2.COLOR_BGR2RGB)
            self.rec.log(
                name, rr.Image(im, color_model="L" if im.ndim == 2 else "RGB").compress(jpeg_quality=self.jpeg_quality)
            )

    def _series_names(self) -> None:
        """Name and colour the discharge series once (static), so none can be confused in the plot."""
        rr = self.rr
        for key, (name, colour) in SERIES.items():
            style = (
                rr.SeriesPoints(names=name, colors=[colour], marker_sizes=[3.0])
                if key == "pair_m3s"
                else rr.SeriesLines(names=name, colors=[colour], widths=[1.0 if "ci95" in key else 2.0])
            )
            self.rec.log(f"discharge/{key}", style, static=True)

    def geometry(self, pair_discharge) -> None:
        self._pair_q = pair_discharge

    def pair(self, i, t_s, x, y, u_px_s, v_px_s, valid) -> None:
        self._guard(self._pair, i, t_s, x, y, u_px_s, v_px_s, valid)

    def _log_q(self, q: float) -> None:
        """One pair's discharge and the running median, at the current time."""
        if np.isfinite(q):
            self._q_pairs.append(float(q))
            self.rec.log("discharge/pair_m3s", self.rr.Scalars(float(q)))
        if self._q_pairs:
            self.rec.log("discharge/running_m3s", self.rr.Scalars(float(np.median(self._q_pairs))))

    def _arrow_scale(self, x, u, v) -> None:
        xs = np.unique(np.round(np.asarray(x, float).ravel(), 3))
        spacing = float(np.median(np.diff(xs))) if len(xs) > 1 else 16.0
        sp = np.hypot(u, v)
        sp = sp[np.isfinite(sp)]
        ref = float(np.percentile(sp, 90)) if sp.size else 0.0
        self.arrow_s = 0.9 * spacing / ref if ref > 0 else 1.0
        s = self.image_scale or 1.0
        self.rec.log(
            "scale",
            self.rr.TextDocument(
                f"Image-space arrows: positions x {s:.4g} (frame downscale); a velocity in px/s is drawn as its "
                f"displacement over {self.arrow_s:.4g} s.",
                media_type="text/markdown",
            ),
            static=True,
        )

    def _pair(self, i, t_s, x, y, u, v, valid) -> None:
        rr = self.rr
        ok = np.asarray(valid, bool) & np.isfinite(u) & np.isfinite(v)
        if self.arrow_s is None and ok.any():
            self._arrow_scale(x, u[ok], v[ok])
        self._time(t_s, pair=i)
        n_nodes = int(np.size(ok))
        self.rec.log("piv/valid_fraction", rr.Scalars(float(ok.sum()) / n_nodes if n_nodes else 0.0))
        s, a = self.image_scale or 1.0, self.arrow_s or 1.0
        self.rec.log(
            "frames/input/pair_vectors",
            rr.Arrows2D(origins=np.c_[x[ok], y[ok]] * s, vectors=np.c_[u[ok], v[ok]] * (a * s), colors=[255, 140, 0]),
        )
        if self._pair_q is not None:
            self._log_q(self._pair_q(x, y, np.where(ok, u, np.nan), np.where(ok, v, np.nan)))

    def result(self, result) -> None:
        self._guard(self._result, result)
        self.close()
        result.warnings.extend(w for w in self.warnings if w not in result.warnings)

    def _result(self, res) -> None:
        rr = self.rr
        p, d, geom = res.piv, res.discharge, res.section
        t_pairs = np.asarray(p.t_pairs, float)
        t_end = float(t_pairs[-1]) if len(t_pairs) else 0.0
        # per-pair and running discharge on the clip's timeline: logged live when the pipeline gave the
        # geometry; again here when it was not, or when the section was swapped after the run
        if self._pair_q is None or res.section.swapped:
            self._q_pairs = []
            for k, (t, q) in enumerate(zip(t_pairs, res.q_pairs, strict=False)):
                self._time(t, pair=k)
                self._log_q(q)
        if self._first is None:
            self._series_names()
        # the final Q (and its 95 % interval when the run has one) drawn across the clip's span
        ci = _interval(res)
        t_start = float(t_pairs[0]) if len(t_pairs) else 0.0
        for k, t in ((0, t_start), (max(len(t_pairs) - 1, 0), t_end)):
            self._time(t, pair=k)
            self.rec.log("discharge/final_m3s", rr.Scalars(float(d.discharge_m3s)))
            if ci is not None:
                self.rec.log("discharge/final_ci95_lo_m3s", rr.Scalars(ci[0]))
                self.rec.log("discharge/final_ci95_hi_m3s", rr.Scalars(ci[1]))
        ok = np.asarray(p.valid, bool) & np.isfinite(p.u) & np.isfinite(p.v)
        if self.arrow_s is None and ok.any():
            self._arrow_scale(p.x, p.u[ok], p.v[ok])
        s, a = self.image_scale or 1.0, self.arrow_s or 1.0
        self.rec.log(
            "frames/input/mean_field",
            rr.Arrows2D(
                origins=np.c_[p.x[ok], p.y[ok]] * s, vectors=np.c_[p.u[ok], p.v[ok]] * (a * s), colors=[0, 200, 255]
            ),
        )
        XY = res.mapping.image_to_world(np.c_[p.x[ok], p.y[ok]])
        U, V = np.asarray(res.world_u)[ok], np.asarray(res.world_v)[ok]
        flip = np.array([1.0, -1.0])  # screen y = -world Y: north up
        if self._first is not None:
            self._map_background(res, self._first)
        self.map_arrow_s = _map_arrow_s(XY, U, V)
        self.rec.log(
            "map/mean_field",
            rr.Arrows2D(
                origins=XY * flip, vectors=np.c_[U, V] * flip * self.map_arrow_s, colors=[0, 200, 255], radii=0.02
            ),
        )
        self.rec.log(
            "map/scale",
            rr.TextDocument(
                f"Map: metres, north up (screen y = -Y). A velocity (m/s) is drawn as its displacement over "
                f"{self.map_arrow_s:.3g} s.",
                media_type="text/markdown",
            ),
            static=True,
        )
        # the section: in the image (with subsection limits) and on the map (with velocities)
        edges = np.asarray(geom.station_edges, float)
        frac = (edges - edges[0]) / (edges[-1] - edges[0]) if edges[-1] != edges[0] else np.linspace(0, 1, len(edges))
        pi, pw = np.asarray(geom.p_img, float), np.asarray(geom.p_world, float)
        ticks_w = pw[0] + frac[:, None] * (pw[1] - pw[0])
        ticks_i = res.mapping.world_to_image(ticks_w)
        self.rec.log("frames/input/section", rr.LineStrips2D([pi * s], colors=[255, 255, 0], radii=1.5))
        self.rec.log("frames/input/section/limits", rr.Points2D(ticks_i * s, colors=[255, 255, 0], radii=3.0))
        mid_w = 0.5 * (ticks_w[:-1] + ticks_w[1:])
        vel = np.asarray(d.surface_velocity_ms, float)
        self.rec.log("map/section", rr.LineStrips2D([pw * flip], colors=[255, 255, 0]))
        self.rec.log("map/section/subsections", rr.Points2D(mid_w * flip, colors=[255, 255, 0], radii=0.08))
        self._profile(res)
        self.rec.log("section/surface_velocity_ms", rr.BarChart(np.nan_to_num(vel)))
        self.rec.log("section/discharge_m3s", rr.BarChart(np.nan_to_num(np.asarray(d.sub_discharge_m3s, float))))
        self.rec.log(
            "log",
            rr.TextLog(
                f"discharge {d.discharge_m3s:.4f} m3/s, level {d.water_level_m:.3f} m, "
                f"mean velocity {d.mean_velocity_ms:.3f} m/s, alpha {d.alpha:.2f}",
                level="INFO",
            ),
        )
        qual = _quality_line(res)
        if qual is not None:
            self.rec.log("log", rr.TextLog(qual[0], level=qual[1]))
        for w in res.warnings:
            self.rec.log("log", rr.TextLog(w, level="WARN"))
        self._overlay(res)

    def _overlay(self, res) -> None:
        """overlay.mp4 (``fieldtool run --overlay``): a log line naming it and, when small enough, the video
        itself at ``overlay/video`` on the clip's timeline. Its failure is a warning; the rest was logged."""
        name = (res.files or {}).get("overlay")
        if not name or res.out_dir is None:
            return
        path = Path(res.out_dir) / name
        info = res.summary().get("overlay") or {}
        self.rec.log(
            "log",
            self.rr.TextLog(
                f"overlay video: {path} ({info.get('frames', '?')} frames of the analysed range + "
                f"{info.get('card_frames', 0)} of the closing card, {info.get('codec', '?')}); also at /overlay/video",
                level="INFO",
            ),
        )
        try:
            if info.get("codec") != "h264" or path.stat().st_size > OVERLAY_MAX_BYTES:
                return
            rr = self.rr
            video = rr.AssetVideo(path=path)
            self.rec.log("overlay/video", video, static=True)
            ts = video.read_frame_timestamps_nanos()
            t0 = float(info.get("t_first_s") or 0.0)
            self.rec.send_columns(
                "overlay/video",
                indexes=[rr.TimeColumn("time", duration=t0 + ts * 1e-9)],
                columns=rr.VideoFrameReference.columns_nanos(ts),
            )
        except Exception as e:  # noqa: BLE001 - the video is extra; the run's log is complete without it
            self.warnings.append(f"rerun: overlay.mp4 not added to the recording ({type(e).__name__}: {e})")

    def _map_background(self, res, first: np.ndarray) -> None:
        """The rectified first frame under the map, pixel (c, r) centre at (Xmin + c r, -(Ymax - r r))."""
        rr = self.rr
        img, A = res.mapping.rectified_image(_to_uint8(first), max_side_px=800)
        r = 1.0 / A[0, 0]
        x0, y1 = -A[0, 2] * r, A[1, 2] * r
        im = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        self.rec.log("map/background", rr.Transform3D(translation=[x0 - r / 2, -y1 - r / 2, 0.0], scale=r), static=True)
        self.rec.log(
            "map/background", rr.Image(im, color_model="L" if im.ndim == 2 else "RGB", draw_order=-10.0), static=True
        )

    def _profile(self, res) -> None:
        """Surface velocity along the section with the 2.5-97.5 % band of the pair fields."""
        rr = self.rr
        b = dq.profile_band(res.discharge, res.piv, res.section, res.mapping)
        k = -PROFILE_SCALE  # screen y down: velocity up
        s, v = b["station_m"], b["velocity_ms"]
        band = np.isfinite(b["p025_ms"]) & np.isfinite(b["p975_ms"])
        if band.any():
            lo, hi = np.c_[s[band], k * b["p025_ms"][band]], np.c_[s[band], k * b["p975_ms"][band]]
            self.rec.log(
                "section/profile/band", rr.LineStrips2D([lo, hi], colors=[[120, 170, 230], [120, 170, 230]], radii=0.04)
            )
        fin = np.isfinite(v)
        self.rec.log(
            "section/profile/velocity", rr.LineStrips2D([np.c_[s[fin], k * v[fin]]], colors=[0, 120, 255], radii=0.08)
        )
        every = max(1, int(np.ceil(fin.sum() / 6)))  # at most ~6 labels: more overlap; hover shows the rest
        labels = [
            (f"{st:.1f} m: {vel:.2f} m/s" + (" (filled)" if f else "")) if i % every == 0 else ""
            for i, (st, vel, f) in enumerate(zip(s[fin], v[fin], b["filled"][fin], strict=True))
        ]
        self.rec.log(
            "section/profile/subsections",
            rr.Points2D(np.c_[s[fin], k * v[fin]], labels=labels, colors=[0, 120, 255], radii=0.15),
        )
        self.rec.log(
            "section/profile/zero",
            rr.LineStrips2D([[[s.min() - 0.5, 0.0], [s.max() + 0.5, 0.0]]], colors=[128, 128, 128], radii=0.02),
        )

    def close(self, timeout_s: float = 3.0) -> None:
        """Flush what is buffered (a viewer that cannot be reached becomes a warning); in save mode
        also finish the .rrd file. Servers of ``serve`` keep running until the process ends. Never raises."""
        try:
            self.rec.flush(timeout_sec=timeout_s)
        except Exception as e:  # noqa: BLE001 - rerun raises RuntimeError for a lost connection
            where = self.urls.get("viewer", self.mode)
            self.warnings.append(f"rerun: the live stream ({where}) did not get everything: {e}")
        if self.mode == "save":
            try:
                self.rec.disconnect()
            except Exception as e:  # noqa: BLE001
                self.warnings.append(f"rerun: could not finish {self.path}: {e}")


def _map_arrow_s(XY: np.ndarray, U: np.ndarray, V: np.ndarray) -> float:
    """Seconds of displacement per map arrow so that a fast (90th percentile) arrow spans 0.9 node spacing."""
    if len(XY) < 2:
        return 1.0
    spacing = float(np.median(cKDTree(XY).query(XY, k=2)[0][:, 1]))
    ref = float(np.percentile(np.hypot(U, V), 90))
    return 0.9 * spacing / ref if ref > 0 and spacing > 0 else 1.0


def _interval(res) -> tuple[float, float] | None:
    """Q's 95 % interval from the run's summary (helper `quality`'s keys), or None until it exists."""
    try:
        s = res.summary()
        ci = s.get("discharge_ci95_m3s") or (s.get("uncertainty") or {}).get("ci95_m3s")
        if ci is None:
            return None
        lo, hi = (float(v) for v in ci)
    except (TypeError, ValueError, AttributeError):
        return None
    return (lo, hi) if np.isfinite(lo) and np.isfinite(hi) else None


def _quality_line(res) -> tuple[str, str] | None:
    """("Q = … ± …, grade: reasons", log level) from helper `quality`'s keys, or None until they exist."""
    try:
        q = res.summary().get("quality")
    except (TypeError, ValueError, AttributeError):
        return None
    if not isinstance(q, dict) or not q.get("grade"):
        return None
    ci = _interval(res)
    head = f"discharge {res.discharge.discharge_m3s:.3f} m3/s" + (
        f", 95 % interval {ci[0]:.3f} - {ci[1]:.3f}" if ci is not None else ""
    )
    reasons = "; ".join(str(r.get("message", r.get("code", ""))) for r in q.get("reasons") or [] if isinstance(r, dict))
    level = {"good": "INFO", "doubtful": "WARN"}.get(str(q["grade"]), "ERROR")
    return f"{head}: quality {q['grade']}" + (f" ({reasons})" if reasons else ""), level


def confined_rrd_path(rel: str, out_dir: str | Path, key: str = "rerun.path") -> Path:
    """The ``.rrd`` file named by the project key, inside the output folder, or ParameterError.

    A project file is data that may come from someone else: its ``rerun.path`` is a file name
    relative to the output folder, never absolute, never climbing out with ``..``, never the
    folder itself. (``fieldtool run --rerun-path`` is the operator's own choice and is not confined.)
    """
    text = str(rel).strip()
    p = Path(text)
    fix = "give a file name such as run.rrd; it is written in the output folder"
    if not text or text in (".", "..") or p.name in ("", ".", ".."):
        raise ParameterError(f"{key}: {rel!r} is not a file name; {fix}")
    if p.is_absolute() or text.startswith("~") or ".." in p.parts or any(ord(c) < 32 for c in text):
        raise ParameterError(f"{key}: {rel!r} points outside the output folder; {fix}")
    out = Path(out_dir).resolve()
    target = (out / p).resolve()
    if out != target and out not in target.parents:  # e.g. a symbolic link inside the folder
        raise ParameterError(f"{key}: {rel!r} resolves outside the output folder {out}; {fix}")
    if target.is_dir():
        raise ParameterError(f"{key}: {rel!r} is a folder; {fix}")
    return target


def check_url(url: str, key: str = "rerun.url") -> str:
    """The viewer URL, checked: ``rerun+http(s)://HOST:PORT/proxy`` or ``rerun://HOST:PORT/proxy``."""
    u = urlparse(url)
    if u.scheme not in ("rerun", "rerun+http", "rerun+https") or not u.hostname or u.path != "/proxy":
        raise ParameterError(
            f"{key}: {url!r} is not a rerun viewer address; write it as "
            f"rerun+http://HOST:9876/proxy (the address the supervisor's viewer shows)"
        )
    return url


def observer_from_args(project, args, out_dir: str | Path) -> RerunObserver | None:
    """The rerun observer asked for by ``fieldtool run`` flags, or else by the project's ``[rerun]``.

    ``--rerun save|connect|serve`` overrides ``rerun.mode``; ``--rerun-path`` / ``--rerun-url``
    override ``rerun.path`` / ``rerun.url``. Returns None when rerun is off. ``rerun.path`` is
    confined to ``out_dir`` (:func:`confined_rrd_path`). Serving prints a warning (the servers listen on all interfaces)
    and the addresses to stderr.
    """
    cfg = project.rerun
    mode = getattr(args, "rerun", None) or cfg.mode or "off"
    if mode not in MODES:
        raise ParameterError(f"rerun.mode: {mode!r} is not one of {', '.join(MODES)}")
    if mode == "off":
        return None
    if mode == "save":
        flag = getattr(args, "rerun_path", None)
        if flag:  # typed on the command line by the user: taken as given (relative to the working folder)
            p = Path(flag).expanduser()
            return RerunObserver("save", path=p if p.is_absolute() else Path.cwd() / p)
        return RerunObserver("save", path=confined_rrd_path(cfg.path or "run.rrd", out_dir))
    if mode == "connect":
        from_flag = getattr(args, "rerun_url", None)
        url = check_url(from_flag or cfg.url or DEFAULT_URL, "--rerun-url" if from_flag else "rerun.url")
        obs = RerunObserver("connect", url=url)
        print(
            f"rerun: streaming to the viewer at {url}; if it is not reachable the run goes on without it",
            file=sys.stderr,
        )
        return obs
    print("warning: " + SERVE_WARNING.format(grpc=GRPC_PORT, web=WEB_PORT), file=sys.stderr)
    try:
        obs = RerunObserver("serve")
    except Exception as e:  # noqa: BLE001 - e.g. a port already in use: the run goes on without it
        print(f"warning: rerun serve failed ({e}); running without live logging", file=sys.stderr)
        return None
    print(
        f"rerun: serving gRPC on port {GRPC_PORT} and the web viewer on port {WEB_PORT} (no outside requests, "
        f"rerun analytics off). Supervisor: `rerun rerun+http://FIELD-MACHINE:{GRPC_PORT}/proxy`, or open "
        f"{obs.urls['web']} (FIELD-MACHINE = this machine's address; here: {obs.urls['local']})",
        file=sys.stderr,
    )
    return obs
