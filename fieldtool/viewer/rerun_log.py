"""Stream a run to rerun so a supervisor can watch what the tool computes.

:class:`RerunObserver` is a pipeline :class:`~fieldtool.pipeline.Observer`. It logs, on the
``time`` (s, clip time) and ``pair`` / ``frame`` (index) timelines:

=====================================  ==========================================================
entity                                 content
=====================================  ==========================================================
``frames/input``                       decimated working frames (undistorted, stabilised), JPEG
``frames/filtered``                    the same frames after the filter stack
``frames/input/pair_vectors``          ``Arrows2D`` of each pair's valid vectors (image pixels)
``frames/input/mean_field``            ``Arrows2D`` of the time-averaged field
``frames/input/section``               the section of interest and its subsection limits
``map/mean_field``                     ``Arrows2D`` of the rectified field, metres and m/s
``map/section``                        section points labelled with subsection velocities (m/s)
``section/surface_velocity_ms``        ``BarChart`` of the subsection surface velocities
``section/discharge_m3s``              ``BarChart`` of the subsection discharges
``piv/valid_fraction``                 ``Scalars``: fraction of valid vectors in each pair
``discharge/pair_m3s``                 ``Scalars``: discharge of each pair's field
``discharge/running_m3s``              ``Scalars``: median of the pair discharges so far
``discharge/total_m3s``                ``Scalars``: the discharge of the run (last time)
``log``                                ``TextLog``: stages and warnings
=====================================  ==========================================================

Image-space arrows are drawn on the (possibly downscaled) frame: positions are multiplied by
``image_scale`` and a velocity (px/s) is drawn as the displacement over ``arrow_s`` seconds;
both are logged in ``scale`` (a ``TextDocument``).

Three ways to reach a supervisor (``[rerun] mode`` or ``fieldtool run --rerun``): ``save`` to an
``.rrd`` file (the default when enabled), ``connect`` to a viewer the supervisor runs
(``rerun+http://HOST:9876/proxy``), or ``serve`` gRPC and the web viewer from this machine.
rerun's servers listen on ALL network interfaces; serving is never on by default.

Logging never fails a run: any error becomes a warning in the run's result and logging stops.
"""

from __future__ import annotations

import sys
import uuid
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputFileError, ParameterError
from ..pipeline import Observer

MODES = ("off", "save", "connect", "serve")
DEFAULT_URL = "rerun+http://127.0.0.1:9876/proxy"
GRPC_PORT = 9876
WEB_PORT = 9090
SERVE_WARNING = ("rerun serve: the gRPC server (port {grpc}) and the web viewer (port {web}) listen on ALL network "
                 "interfaces of this machine; anyone who can reach it can watch the run. Use it on a trusted network, "
                 "or prefer `--rerun save` and copy the .rrd file.")


def _to_uint8(img: np.ndarray) -> np.ndarray:
    """A frame for display: uint8 kept, other types stretched between their 1st and 99th percentiles."""
    if img.dtype == np.uint8:
        return img
    a = np.asarray(img, np.float32)
    sub = a[::2, ::2]
    fin = sub[np.isfinite(sub)]
    lo, hi = (np.percentile(fin, (1, 99)) if fin.size else (0.0, 1.0))
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

    def __init__(self, mode: str = "save", *, path: str | Path | None = None, url: str | None = None,
                 grpc_port: int = GRPC_PORT, web_port: int = WEB_PORT, max_side_px: int = 640,
                 jpeg_quality: int = 75, recording=None):
        import rerun as rr

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
                self.rec.save(str(self.path))
            except Exception as e:  # noqa: BLE001 - rerun raises its own error types
                raise InputFileError(f"{self.path}: cannot write the rerun recording ({e}); check rerun.path") from e
        elif mode == "connect":
            self.urls["viewer"] = url or DEFAULT_URL
            self.rec.connect_grpc(self.urls["viewer"])
        elif mode == "serve":
            self.urls["grpc"] = self.rec.serve_grpc(grpc_port=grpc_port)
            rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=self.urls["grpc"])
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
        for name, img in (("frames/input", raw), ("frames/filtered", filtered)):
            im = img if img.dtype in (np.uint8, np.float32) else np.asarray(img, np.float32)
            if self.image_scale < 1.0:  # downscale first: the stretch and the encoder see fewer pixels
                im = cv2.resize(im, size, interpolation=cv2.INTER_AREA)
            im = _to_uint8(im)
            if im.ndim == 3:
                im = cv2.cvtColor(im, cv2.COLOR_BGR2RGB)
            self.rec.log(name, rr.Image(im, color_model="L" if im.ndim == 2 else "RGB").compress(
                jpeg_quality=self.jpeg_quality))

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
        self.rec.log("scale", self.rr.TextDocument(
            f"Image-space arrows: positions x {s:.4g} (frame downscale); a velocity in px/s is drawn as its "
            f"displacement over {self.arrow_s:.4g} s. Map arrows: metres, velocity (m/s) x 1 s.",
            media_type="text/markdown"), static=True)

    def _pair(self, i, t_s, x, y, u, v, valid) -> None:
        rr = self.rr
        ok = np.asarray(valid, bool) & np.isfinite(u) & np.isfinite(v)
        if self.arrow_s is None and ok.any():
            self._arrow_scale(x, u[ok], v[ok])
        self._time(t_s, pair=i)
        n_nodes = int(np.size(ok))
        self.rec.log("piv/valid_fraction", rr.Scalars(float(ok.sum()) / n_nodes if n_nodes else 0.0))
        s, a = self.image_scale or 1.0, self.arrow_s or 1.0
        self.rec.log("frames/input/pair_vectors", rr.Arrows2D(
            origins=np.c_[x[ok], y[ok]] * s, vectors=np.c_[u[ok], v[ok]] * (a * s), colors=[255, 140, 0]))
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
            for k, (t, q) in enumerate(zip(t_pairs, res.q_pairs)):
                self._time(t, pair=k)
                self._log_q(q)
        self._time(t_end, pair=max(len(t_pairs) - 1, 0))
        self.rec.log("discharge/total_m3s", rr.Scalars(float(d.discharge_m3s)))
        ok = np.asarray(p.valid, bool) & np.isfinite(p.u) & np.isfinite(p.v)
        if self.arrow_s is None and ok.any():
            self._arrow_scale(p.x, p.u[ok], p.v[ok])
        s, a = self.image_scale or 1.0, self.arrow_s or 1.0
        self.rec.log("frames/input/mean_field", rr.Arrows2D(
            origins=np.c_[p.x[ok], p.y[ok]] * s, vectors=np.c_[p.u[ok], p.v[ok]] * (a * s), colors=[0, 200, 255]))
        XY = res.mapping.image_to_world(np.c_[p.x[ok], p.y[ok]])
        U, V = np.asarray(res.world_u)[ok], np.asarray(res.world_v)[ok]
        self.rec.log("map/mean_field", rr.Arrows2D(origins=XY, vectors=np.c_[U, V], colors=[0, 200, 255]))
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
        labels = [f"{i + 1}: {v:.2f} m/s" + (" (filled)" if f else "")
                  for i, (v, f) in enumerate(zip(vel, d.velocity_filled))]
        self.rec.log("map/section", rr.LineStrips2D([pw], colors=[255, 255, 0]))
        self.rec.log("map/section/subsections", rr.Points2D(mid_w, labels=labels, colors=[255, 255, 0], radii=0.05))
        self.rec.log("section/surface_velocity_ms", rr.BarChart(np.nan_to_num(vel)))
        self.rec.log("section/discharge_m3s", rr.BarChart(np.nan_to_num(np.asarray(d.sub_discharge_m3s, float))))
        self.rec.log("log", rr.TextLog(
            f"discharge {d.discharge_m3s:.4f} m3/s, level {d.water_level_m:.3f} m, "
            f"mean velocity {d.mean_velocity_ms:.3f} m/s, alpha {d.alpha:.2f}", level="INFO"))
        for w in res.warnings:
            self.rec.log("log", rr.TextLog(w, level="WARN"))

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


def check_url(url: str, key: str = "rerun.url") -> str:
    """The viewer URL, checked: ``rerun+http(s)://HOST:PORT/proxy`` or ``rerun://HOST:PORT/proxy``."""
    from urllib.parse import urlparse

    u = urlparse(url)
    if u.scheme not in ("rerun", "rerun+http", "rerun+https") or not u.hostname or u.path != "/proxy":
        raise ParameterError(f"{key}: {url!r} is not a rerun viewer address; write it as "
                             f"rerun+http://HOST:9876/proxy (the address the supervisor's viewer shows)")
    return url


def observer_from_args(project, args, out_dir: str | Path) -> RerunObserver | None:
    """The rerun observer asked for by ``fieldtool run`` flags, or else by the project's ``[rerun]``.

    ``--rerun save|connect|serve`` overrides ``rerun.mode``; ``--rerun-path`` / ``--rerun-url``
    override ``rerun.path`` / ``rerun.url``. Returns None when rerun is off. A relative ``.rrd``
    path is put in ``out_dir``. Serving prints a warning (the servers listen on all interfaces)
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
        rel = flag or cfg.path or "run.rrd"
        if not flag:  # from the project file: confined to the output folder
            from ..validation import out_path_problem

            problem = out_path_problem(rel)
            if problem:
                raise ParameterError(f"rerun.path: {problem}")
        p = Path(rel).expanduser()
        if not p.is_absolute():
            p = (Path.cwd() / p) if flag else Path(out_dir) / p
        if p.exists() and not p.is_file():
            raise ParameterError(f"{'--rerun-path' if flag else 'rerun.path'}: {p} is not a regular file; give the "
                                 ".rrd file to write")
        return RerunObserver("save", path=p)
    if mode == "connect":
        from_flag = getattr(args, "rerun_url", None)
        url = check_url(from_flag or cfg.url or DEFAULT_URL, "--rerun-url" if from_flag else "rerun.url")
        obs = RerunObserver("connect", url=url)
        print(f"rerun: streaming to the viewer at {url}; if it is not reachable the run goes on without it",
              file=sys.stderr)
        return obs
    print("warning: " + SERVE_WARNING.format(grpc=GRPC_PORT, web=WEB_PORT), file=sys.stderr)
    try:
        obs = RerunObserver("serve")
    except Exception as e:  # noqa: BLE001 - e.g. a port already in use: the run goes on without it
        print(f"warning: rerun serve failed ({e}); running without live logging", file=sys.stderr)
        return None
    print(f"rerun: serving gRPC on port {GRPC_PORT} and the web viewer on port {WEB_PORT}. Supervisor: "
          f"`rerun rerun+http://FIELD-MACHINE:{GRPC_PORT}/proxy`, or open {obs.urls['web']} "
          f"(FIELD-MACHINE = this machine's address)", file=sys.stderr)
    return obs
