"""The picking viewer: a viser web page where the operator clicks points on the images.

``start_viewer(project_path)`` serves the page on 127.0.0.1 and returns a :class:`ViewerHandle`
(``.url``, ``.port``, ``.set_mode``, ``.show_image``, ``.stop``). Every pick is written to the
project file at once (read, set the field, atomic save, under a lock) and reported to
``on_pick(field, value)`` so the TUI can update, then drawn back as an overlay.

Only the page itself can use the viewer (see :mod:`fieldtool.viewer.guard`): the URL carries a
random key made at each launch, and requests whose Host or Origin is not the viewer's own address
are refused, so another web page open in the same browser can neither read the frames nor move a
pick. The port is fixed per project (``[viewer] port``, remembered after the first launch) so an
SSH tunnel (``ssh_hint(port)``) can be kept.

The page guides the operator: a checklist of the picks in order (done, next), a legend of the
labels, hollow rings that leave the targets visible, only the buttons of the current mode, GCP
clicks snapped to the centre of a checker target (:mod:`fieldtool.viewer.snap`), and a wheel zoom
that keeps the point under the cursor (a small script added to viser's page asks the server to
move the camera about that point).

The page and its scripts come from viser's bundled client (one self-contained HTML file): no
internet access is needed. Binding an address other than the loopback makes the page, and the
power to edit the project, reachable from the network: it is an explicit option and warns.
"""

from __future__ import annotations

import contextlib
import gzip
import io
import threading
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs

import numpy as np
import viser
from websockets.datastructures import Headers
from websockets.http11 import Response

from fieldtool.errors import FieldToolError, ParameterError
from fieldtool.project.model import load_project, project_to_dict
from fieldtool.project.sync import Conflict, ProjectSync, SaveResult, put_mine_back, set_dotted, shown
from fieldtool.viewer import registry
from fieldtool.viewer.guard import AccessGuard, install, page_path, ssh_hint
from fieldtool.viewer.images import FRAME_LIKE, KINDS, Display, lens_of, load_display, load_field
from fieldtool.viewer.mapping import (
    ImagePlane,
    camera_pose,
    fit_plane,
    inside,
    pixel_to_scene,
    ray_to_pixel,
    zoom_about_cursor,
)
from fieldtool.viewer.picks import (
    MODES,
    PickState,
    PolygonListPick,
    StationPick,
    checklist,
    get_field,
    next_mode,
)
from fieldtool.viewer.snap import snap_to_target

LOOPBACK = ("127.0.0.1", "localhost", "::1")
FOV_RAD = np.deg2rad(50.0)
NO_MODE = "view only"
COLORS = {
    "gcp": (255, 200, 0),
    "section": (0, 220, 255),
    "roi": (0, 220, 0),
    "masks": (255, 50, 50),
    "stable": (220, 0, 220),
    "edges": (60, 130, 255),
    "edges1": (60, 130, 255),
    "edges2": (60, 130, 255),
    "divergence": (220, 0, 0),
    "field": (255, 120, 0),
}
OnPick = Callable[[str, Any], None]


class ViewerHandle:
    """A running viewer. Thread-safe; ``stop()`` shuts the web server down."""

    def __init__(self, viewer: _Viewer):
        self._v = viewer
        self.host: str = viewer.host
        self.port: int = viewer.server.get_port()
        self.token: str = viewer.guard.token
        shown = "127.0.0.1" if self.host in ("0.0.0.0", "::") else self.host
        shown = f"[{shown}]" if ":" in shown else shown
        self.url: str = f"http://{shown}:{self.port}/{self.token}/"
        self.warning: str | None = viewer.host_warning
        self.notes: list[str] = []  # what the launch decided about the port, for the CLI/TUI to show
        self.in_process = True  # served by this process (a viewer of another process: registry.RunningViewer)

    @property
    def ssh_hint(self) -> str:
        """The ``ssh -L PORT:127.0.0.1:PORT user@host`` line that forwards this viewer's port."""
        return ssh_hint(self.port)

    @property
    def local_url(self) -> str:
        """The URL to open on the operator's own computer through the SSH tunnel."""
        return f"http://127.0.0.1:{self.port}/{self.token}/"

    @property
    def refused(self) -> list[str]:
        """Why recent requests were refused (host, origin or key), newest last."""
        return list(self._v.guard.refused)

    @property
    def checklist(self) -> list[tuple[str, str, str]]:
        """The picks in order as (mode key, "done" | "next" | "todo" | "optional", detail)."""
        return [(spec.key, status, detail) for spec, status, detail in checklist(self._v.states)]

    def next_mode(self) -> str | None:
        """The mode of the checklist's next step (None when all are done)."""
        return next_mode(self._v.states)

    def zoom(self, ndc_x: float, ndc_y: float, scale: float) -> int:
        """Zoom every open page about the point at normalised device coordinates (x right, y up,
        -1..1) by ``scale`` (< 1 zooms in), as the page's mouse wheel does. Returns the number of
        pages moved."""
        return self._v.zoom(ndc_x, ndc_y, scale)

    def set_mode(self, mode: str | None) -> None:
        """Select a pick mode (a key of ``picks.MODES``, or ``None`` / "" for view only); the image
        the mode needs is shown."""
        self._v.set_mode(mode or None)

    def show_image(self, kind: str) -> None:
        """Show one of ``images.KINDS`` (frame, working, ortho, image1, image2, dem_plot)."""
        self._v.show_image(kind)

    def reload(self) -> None:
        """Re-read the project file (after the TUI changed it) and redraw."""
        self._v.reload()

    def show_field(self, npz_path: str | Path | None = None) -> bool:
        """Overlay the mean velocity field of a run (``mean_field.npz``; default: ``out/`` beside
        the project). Returns False when the file does not exist yet."""
        return self._v.show_field(npz_path)

    def click(self, x: float, y: float) -> str:
        """Apply a pick at display pixel (x, y) exactly as a click in the browser would."""
        return self._v.pick(np.array([x, y], float))

    @property
    def conflicts(self) -> list[Conflict]:
        """The conflicts the page is asking about (the same key or point changed here and in the file)."""
        return list(self._v.conflicts)

    def resolve_conflicts(self, use_mine: bool) -> str:
        """Answer the page's conflict question as its buttons do: put this viewer's values back
        (``use_mine``) or keep the file's. Returns the status shown."""
        return self._v.resolve_conflicts(use_mine)

    @property
    def mode(self) -> str | None:
        return self._v.mode

    @property
    def image(self) -> str:
        return self._v.display.kind

    @property
    def status(self) -> str:
        """The last message shown to the operator."""
        return self._v.status_text

    def stop(self) -> None:
        self._v.stop()

    def __enter__(self) -> ViewerHandle:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def start_viewer(
    project_path: str | Path, host: str = "127.0.0.1", port: int | None = None, on_pick: OnPick | None = None
) -> ViewerHandle:
    """Serve the picking page for the project file ``project_path``.

    Parameters
    ----------
    project_path : path of the project file (TOML); picks are saved into it.
    host : address to bind. Anything but the loopback exposes the page to the network (warns).
    port : TCP port. None: the project's ``viewer.port`` (remembered in the project after the
        first launch; a busy remembered port falls back to the next free one, with a warning);
        0: a free port, not remembered; N: exactly N, remembered (ParameterError when in use).
    on_pick : called as ``on_pick(field, value)`` after each saved pick, from a server thread;
        ``field`` is the dotted project key (``"ortho.gcp_px"``).
    """
    path = Path(project_path).resolve()
    project = load_project(path)
    remembered = int(getattr(getattr(project, "viewer", None), "port", 0) or 0)
    want = remembered if port is None else int(port)
    if want != 0 and not 1024 <= want <= 65535:
        key = "viewer.port" if port is None else "--port"
        raise ParameterError(f"{key} = {want}: give a port from 1024 to 65535 (or 0 for a free one)")
    host_warning = None
    if host not in LOOPBACK:
        host_warning = (
            f"WARNING: the picking viewer listens on {host}: anyone who can reach this machine on the "
            f"port and learns the URL's key can see the frames and change the picks of the project. "
            f"Use the default 127.0.0.1 with SSH port forwarding (ssh -L PORT:127.0.0.1:PORT) unless "
            f"the network is trusted."
        )
        warnings.warn(host_warning, stacklevel=2)
    guard = AccessGuard(host)
    routes = _Routes(guard)
    with contextlib.redirect_stdout(io.StringIO()), install(guard, routes):  # viser prints a banner
        server = viser.ViserServer(host=host, port=want, verbose=False)
    if not guard.hooked:
        server.stop()
        raise FieldToolError(
            "the picking viewer could not install its access check in viser's web server "
            f"(viser {viser.__version__}); it is not started. Please report this."
        )
    got = server.get_port()
    notes = []
    if want != 0 and got != want:
        if port is not None:
            server.stop()
            raise ParameterError(f"--port {want}: the port is in use (another viewer?); stop it or give another port")
        notes.append(f"port {want} (viewer.port) is in use; this viewer uses {got}: tunnel that port this time")
    try:
        viewer = _Viewer(server, path, host, host_warning, on_pick, guard)
        routes.viewer = viewer
        if got != remembered and (port is None and remembered == 0 or port is not None and port != 0):
            ProjectSync(path).set_keys(
                {"viewer.port": got}
            )  # remembered: the next launch (and its tunnel) uses it again
            notes.append(f"port {got} is remembered in viewer.port of {path.name}")
    except BaseException:
        server.stop()
        raise
    handle = ViewerHandle(viewer)
    handle.notes = notes
    if host in LOOPBACK or host in ("0.0.0.0", "::"):
        try:
            registry.register(path, host, handle.port, handle.token, handle.url)  # one viewer per project
        except OSError as e:
            notes.append(f"the viewer's info file was not written ({e.strerror or e}): a second viewer may start")
    return handle


def _under(key: str, field: str) -> bool:
    """Whether a conflict's key (``ortho.gcp_px[1]``) is the project field ``field`` or inside it."""
    return key == field or key.startswith((field + "[", field + "."))


class _Routes:
    """Requests the viewer answers itself: its page (viser's, plus the zoom script) and ``zoom``."""

    def __init__(self, guard: AccessGuard):
        self.guard = guard
        self.viewer: _Viewer | None = None
        self._page: bytes | None = None
        self._page_gz: bytes | None = None

    def page(self) -> tuple[bytes, bytes]:
        if self._page is None:
            html = page_path().read_text(encoding="utf-8")
            if "</body>" not in html:
                raise FieldToolError("viser's page has no </body>: cannot add the zoom script; please report this")
            html = html.replace("</body>", f"<script>{ZOOM_SCRIPT}</script></body>", 1)
            self._page = html.encode("utf-8")
            self._page_gz = gzip.compress(self._page)
        assert self._page_gz is not None
        return self._page, self._page_gz

    def __call__(self, rest: str, request):
        path, _, query = rest.partition("?")
        if path in ("/", "/index.html"):
            raw, gz = self.page()
            use_gz = "gzip" in request.headers.get("Accept-Encoding", "")
            body = gz if use_gz else raw
            return Response(
                200,
                "OK",
                Headers(
                    {
                        "Content-Type": "text/html; charset=utf-8",
                        "Content-Length": str(len(body)),
                        "Content-Encoding": "gzip" if use_gz else "identity",
                    }
                ),
                body,
            )
        if path == "/zoom":
            q = parse_qs(query)
            try:
                x, y, f = (float(q[k][0]) for k in ("x", "y", "f"))
                if not all(np.isfinite([x, y, f])) or f <= 0:
                    raise ValueError
            except (KeyError, ValueError, IndexError):
                return Response(400, "Bad Request", Headers({"Content-Length": "0"}), b"")
            if self.viewer is not None:
                self.viewer.zoom(x, y, f)
            return Response(204, "No Content", Headers({"Content-Length": "0"}), b"")
        return None


# The wheel over the image zooms about the cursor: the page sends the cursor (normalised device
# coordinates) and the zoom factor; the server moves the camera (viser's own wheel zoom goes to the
# view centre). One request in flight at a time; wheel steps arriving meanwhile are summed.
ZOOM_SCRIPT = """
(function () {
  var pending = 0, busy = false, last = null;
  function send() {
    if (busy || pending === 0 || last === null) return;
    var f = Math.min(Math.max(Math.exp(pending * 0.0015), 0.2), 5.0);
    pending = 0; busy = true;
    fetch('zoom?x=' + last.x + '&y=' + last.y + '&f=' + f, {cache: 'no-store'})
      .catch(function () {}).then(function () { busy = false; send(); });
  }
  window.addEventListener('wheel', function (e) {
    var c = e.target;
    if (!(c instanceof HTMLCanvasElement) || c.clientWidth < 200) return;
    e.preventDefault(); e.stopImmediatePropagation();
    var r = c.getBoundingClientRect();
    last = {x: ((e.clientX - r.left) / r.width) * 2 - 1, y: 1 - ((e.clientY - r.top) / r.height) * 2};
    pending += e.deltaY * (e.deltaMode === 1 ? 33 : (e.deltaMode === 2 ? 400 : 1));
    send();
  }, {capture: true, passive: false});
})();
"""


class _Viewer:
    def __init__(
        self, server, path: Path, host: str, host_warning: str | None, on_pick: OnPick | None, guard: AccessGuard
    ):
        self.server, self.path, self.host, self.host_warning, self.on_pick = server, path, host, host_warning, on_pick
        self.guard = guard
        self._lock = threading.RLock()
        self.sync = ProjectSync(path)  # the file as this viewer last read or wrote it (three-way merge)
        self.project = self.sync.load()
        self._stopped = threading.Event()
        self.mode: str | None = None
        self.states: dict[str, PickState] = {}
        self.field: dict | None = None
        self.status_text = ""
        self.conflicts: list[Conflict] = []  # asked about on the page (keep the file's / put mine back)
        self._question: Any = None  # the open question (a viser GuiModalHandle), None when none
        self._overlay: list = []
        self._syncing = False
        self._aspect: dict[int, float] = {}
        self.display = Display("frame", np.full((480, 640, 3), 90, np.uint8))
        self.plane: ImagePlane = fit_plane(640, 480)

        s = server
        s.gui.configure_theme(show_logo=False, show_share_button=False, control_width="medium")
        s.gui.main_panel.dock_right()
        s.scene.set_up_direction("-y")
        s.scene.world_axes.visible = False
        s.gui.add_markdown(f"**fieldtool picks** - `{path.name}`")
        self.gui_image = s.gui.add_dropdown("Image", tuple(KINDS.values()), initial_value=KINDS["frame"])
        self.gui_mode = s.gui.add_dropdown(
            "Pick mode", (NO_MODE,) + tuple(m.label for m in MODES.values()), initial_value=NO_MODE
        )
        self.gui_checklist = s.gui.add_markdown(" ")
        next_btn = s.gui.add_button("Next pick")
        self.gui_help = s.gui.add_markdown("Choose a pick mode, then click on the image.")
        self.gui_legend = s.gui.add_markdown(" ")
        self.buttons = {
            "undo": s.gui.add_button("Undo"),
            "close": s.gui.add_button("Close polygon"),
            "clear": s.gui.add_button("Clear this mode"),
        }
        self.gui_field = s.gui.add_checkbox("Velocity field", True)
        self.gui_status = s.gui.add_markdown(" ")
        s.gui.add_markdown(f"Picks are saved to `{path}` at once. The mouse wheel zooms about the cursor.")

        @self.gui_image.on_update
        def _(_):
            if not self._syncing:
                kind = next(k for k, v in KINDS.items() if v == self.gui_image.value)
                self.show_image(kind)

        @self.gui_mode.on_update
        def _(_):
            if not self._syncing:
                key = next((k for k, m in MODES.items() if m.label == self.gui_mode.value), None)
                self.set_mode(key)

        for action, button in self.buttons.items():
            button.on_click(lambda _, a=action: self._act(a))
        next_btn.on_click(lambda _: self.set_mode(next_mode(self.states)))
        self.gui_field.on_update(lambda _: self.redraw())

        @s.scene.on_click()
        def _(ev):
            self.on_ray(ev.ray_origin, ev.ray_direction)

        @s.on_client_connect
        def _(client):
            self._fit_camera(client)

            @client.camera.on_update
            def _(cam):
                # the page docks its panel after connecting: refit when the canvas shape changes
                if cam.image_height and abs(cam.aspect - self._aspect.get(client.client_id, cam.aspect)) > 0.02:
                    self._fit_camera(client)

        self._load_states()
        self._show_buttons(None)
        self.show_field(None)
        self.show_image("frame")
        self.update_checklist()
        self._watcher = threading.Thread(target=self._watch, name="fieldtool-viewer-watch", daemon=True)
        self._watcher.start()

    # ------------------------------------------------------------------ state

    def _load_states(self) -> None:
        for key, spec in MODES.items():
            if spec.image == "dem_plot":
                continue  # needs the plot's axes: built when the plot is shown
            st = spec.make()
            st.load(get_field(self.project, spec.field))
            self.states[key] = st

    def reload(self) -> None:
        """Take in what another program saved in the project file (merged with this viewer's picks)."""
        with self._lock:
            res = self.sync.poll(self.project)
            if res is None:
                if self.sync.error:
                    self.set_status(f"the project file is not valid now; picks are not saved: {self.sync.error}")
                return
            self._take(res, note=True)

    def _take(self, res: SaveResult, note: bool = False) -> None:
        """Make the viewer show ``res.project``: every pick mode whose field differs is loaded again."""
        old = self.project
        self.project = res.project
        for key, spec in MODES.items():
            st = self.states.get(key)
            if st is None:
                continue
            new = get_field(res.project, spec.field)
            cur = st.value()
            if new != get_field(old, spec.field) or (cur is not ... and new != cur):
                if spec.image == "dem_plot":
                    st = spec.make(axes=getattr(st, "axes", None))
                else:
                    st = spec.make()
                st.load(new)
                self.states[key] = st
        if res.conflicts:
            self.set_status(
                "CONFLICT, the file's value kept: "
                + "; ".join(c.text() for c in res.conflicts[:3])
                + " - the page asks: keep the file's or put yours back"
            )
            self._ask_conflicts(res.conflicts)
        elif note and res.theirs_changed:
            self.set_status(f"updated from {self.path.name}: {', '.join(res.theirs_changed[:4])}")
        self.update_checklist()
        self.redraw()

    def _ask_conflicts(self, conflicts: list[Conflict]) -> None:
        """The file's values were kept (``project.sync``): show both values on every open page and ask, as
        the TUI does: keep the file's, or put this viewer's back. A new conflict while asking joins the question."""
        with self._lock:
            keys = {c.key for c in conflicts}
            pending = [c for c in self.conflicts if c.key not in keys] + list(conflicts)
            self._close_question()
            self.conflicts = pending
            gui = self.server.gui
            lines = [
                f"- `{c.key}`: the file has **{shown(c.theirs)}** (kept); yours was **{shown(c.mine)}**"
                for c in pending[:8]
            ]
            if len(pending) > 8:
                lines.append(f"- ... and {len(pending) - 8} more")
            self._question = modal = gui.add_modal("Changed here and by another program at once")
            with modal:
                gui.add_markdown(
                    "\n".join(lines) + "\n\nThe file's value is kept (the other program saved it first and shows it)."
                )
                keep = gui.add_button("Keep the file's")
                mine = gui.add_button("Put mine back", color="orange")
            keep.on_click(lambda _: self.resolve_conflicts(False))
            mine.on_click(lambda _: self.resolve_conflicts(True))

    def _close_question(self) -> None:
        if self._question is not None and not self._question.closed:
            self._question.close()
        self._question = None

    def resolve_conflicts(self, use_mine: bool) -> str:
        """The operator's answer: keep the file's values, or save this viewer's again (they win now: the
        base has caught up with the file). on_pick is told of each field put back."""
        res = None
        with self._lock:
            conflicts, self.conflicts = self.conflicts, []
            self._close_question()
            if not conflicts:
                return self.status_text
            keys = ", ".join(c.key for c in conflicts[:4])
            if not use_mine:
                msg = f"kept the file's value of {keys}"
            else:
                data = put_mine_back(project_to_dict(self.project), conflicts)
                try:
                    res = self.sync.save(data)
                except (FieldToolError, OSError) as e:
                    msg = f"NOT SAVED: yours cannot be put back ({e}); the file's value of {keys} stays"
                else:
                    self._take(res)
                    msg = self.status_text if res.conflicts else f"put yours back: {keys}"
            self.set_status(msg)
        if res is not None and res.written and self.on_pick is not None:
            fields = [m.field for m in MODES.values() if any(_under(c.key, m.field) for c in conflicts)]
            for f in dict.fromkeys(fields):
                try:
                    self.on_pick(f, get_field(self.project, f))
                except Exception as e:  # noqa: BLE001 - the TUI's callback must not break the viewer
                    self.set_status(f"{msg} (the TUI was not updated: {e})")
        return msg

    def _watch(self) -> None:
        """Look at the project file twice a second; a change made elsewhere is shown within a second."""
        while not self._stopped.wait(0.5):
            try:
                self.reload()
            except Exception as e:  # noqa: BLE001 - a bad moment on disk must not stop the viewer
                self.set_status(f"the project file could not be read again: {e}")

    def set_status(self, text: str) -> None:
        self.status_text = text
        self.gui_status.content = text or " "

    def update_checklist(self) -> None:
        """Redraw the checklist: done, next and the rest, with what is placed in each."""
        marks = {"done": "✓", "next": "➜", "todo": "○", "optional": "○"}
        lines = ["**Checklist**", ""]
        for spec, status, detail in checklist(self.states):
            name = f"**{spec.label}**" if status == "next" else spec.label
            opt = "" if spec.required else " (optional)"
            lines.append(f"- {marks[status]} {name}{opt}: {detail}")
        if next_mode(self.states) is None:
            lines.append("")
            lines.append("All picks are placed.")
        self.gui_checklist.content = "\n".join(lines)

    def _show_buttons(self, key: str | None) -> None:
        wanted = MODES[key].buttons if key else ()
        for action, button in self.buttons.items():
            button.visible = action in wanted

    def set_mode(self, key: str | None) -> None:
        if key is not None and key not in MODES:
            raise ValueError(f"unknown pick mode {key!r}; one of {', '.join(MODES)}")
        with self._lock:
            self.mode = key
            self._sync(self.gui_mode, MODES[key].label if key else NO_MODE)
            self._show_buttons(key)
            if key is None:
                self.gui_help.content = "View only: choose a pick mode (or press Next pick) to click points."
                self.gui_legend.content = " "
                self.redraw()
                return
            spec = MODES[key]
            self.gui_help.content = spec.help
            self.gui_legend.content = f"Legend: {spec.legend}" if spec.legend else " "
            if self.display.pick_image != spec.image:
                self.show_image(spec.image)
                if self.display.pick_image != spec.image:
                    return  # the image could not be shown; the status says why
            else:
                self.redraw()
            if key in self.states:
                self.set_status(f"{spec.label}: {len(self.states[key].labels())} picked")

    def _sync(self, handle, value: str) -> None:
        if handle.value != value:
            self._syncing = True
            try:
                handle.value = value
            finally:
                self._syncing = False

    def show_image(self, kind: str) -> None:
        if kind not in KINDS:
            raise ValueError(f"unknown image {kind!r}; one of {', '.join(KINDS)}")
        with self._lock:
            try:
                disp = load_display(self.project, kind)
            except FieldToolError as e:
                self.set_status(f"cannot show {KINDS[kind].lower()}: {e}")
                self._sync(self.gui_image, KINDS[self.display.kind])
                return
            self.display = disp
            if kind == "dem_plot":
                spec = MODES["divergence"]
                st = spec.make(axes=disp.axes)
                st.load(get_field(self.project, spec.field))
                self.states["divergence"] = st
            self._sync(self.gui_image, KINDS[kind])
            h, w = disp.rgb.shape[:2]
            self.plane = fit_plane(w, h)
            self.server.scene.add_image(
                "/image",
                disp.rgb,
                self.plane.render_width,
                self.plane.render_height,
                format="png" if kind == "dem_plot" else "jpeg",
                jpeg_quality=92,
                cast_shadow=False,
                receive_shadow=False,
            )
            pos, look, up = camera_pose(self.plane, FOV_RAD, 16 / 9)
            cam = self.server.initial_camera
            cam.fov, cam.position, cam.look_at, cam.up = FOV_RAD, pos, look, up
            for client in self.server.get_clients().values():
                self._fit_camera(client)
            if disp.note:
                self.set_status(disp.note)
            self.redraw()

    def _fit_camera(self, client) -> None:
        try:
            cam = client.camera
            aspect = cam.aspect if cam.image_height else 16 / 9
            self._aspect[client.client_id] = aspect
            pos, look, up = camera_pose(self.plane, FOV_RAD, aspect, margin=1.08)
            with client.atomic():
                cam.fov = FOV_RAD
                cam.position = pos
                cam.look_at = look
                cam.up_direction = up
        except Exception as e:  # noqa: BLE001 - a client that went away must not break the viewer
            self.set_status(f"camera not reset for a client: {e}")

    # ------------------------------------------------------------------ picking

    def on_ray(self, origin, direction) -> None:
        px = ray_to_pixel(origin, direction, self.plane)
        if px is None:
            return
        self.pick(px)

    def pick(self, px: np.ndarray) -> str:
        with self._lock:
            if self.mode is None:
                msg = f"clicked ({px[0]:.1f}, {px[1]:.1f}) px; choose a pick mode to record points"
                self.set_status(msg)
                return msg
            spec = MODES[self.mode]
            if not inside(self.plane, px):
                msg = "click on the image"
                self.set_status(msg)
                return msg
            if self.display.pick_image != spec.image:
                msg = f"{spec.label} are picked on the {KINDS[spec.image].lower()}: switch the image"
                self.set_status(msg)
                return msg
            snapped = None
            if spec.snap and self.display.kind in FRAME_LIKE:
                snapped = snap_to_target(self.display.rgb, float(px[0]), float(px[1]))
                if snapped is not None:
                    px = np.array([snapped.x, snapped.y])
            raw = self.display.from_display(px)[0] if self.display.kind in FRAME_LIKE else px
            state = self.states[self.mode]
            before = state.value()
            msg = state.click(float(raw[0]), float(raw[1]), exact=snapped is not None)
            if snapped is not None and state.value() != before:
                msg += (
                    f" - snapped to the target centre ({raw[0]:.2f}, {raw[1]:.2f}) px, "
                    f"{snapped.moved_px:.1f} px from the click (Undo if wrong)"
                )
            elif spec.snap and state.value() != before:  # say so: a click meant for a target stays where it fell
                msg += (
                    " - NOT snapped: no checker target found near the click (a small or far target); placed "
                    "where clicked: zoom in (mouse wheel) to place it on the centre, or Undo"
                )
            msg, saved = self._save_state(spec, state, msg)
        return self._tell_tui(spec, saved, msg)

    def _act(self, action: str) -> str:
        with self._lock:
            if self.mode is None or self.mode not in self.states:
                msg = "choose a pick mode first"
                self.set_status(msg)
                return msg
            spec, state = MODES[self.mode], self.states[self.mode]
            if action == "undo":
                msg = state.undo()
            elif action == "close":
                msg = state.close()
            else:
                fresh = spec.make(axes=getattr(state, "axes", None))
                self.states[self.mode] = state = fresh
                msg = f"{spec.label} cleared"
            msg, saved = self._save_state(spec, state, msg)
        return self._tell_tui(spec, saved, msg)

    def _save_state(self, spec, state: PickState, msg: str) -> tuple[str, bool]:
        """Save the pick mode's value (the caller holds the lock from its change of ``state`` on: a reload of the
        file in between would leave ``state`` with the file's old values of the other points, and the save would
        put them back as this viewer's). Returns (status message, whether the file was written)."""
        value = state.value()
        saved = False
        if value is not ...:
            try:
                mine = set_dotted(project_to_dict(self.project), spec.field, value)
                res = self.sync.save(mine)  # merged per point with what the TUI saved meanwhile
                saved = res.written
                self._take(res)
                if res.conflicts:
                    msg = self.status_text
            except (FieldToolError, OSError) as e:
                msg = f"NOT SAVED: {e}"
        self.set_status(msg)
        self.update_checklist()
        self.redraw()
        return msg, saved

    def _tell_tui(self, spec, saved: bool, msg: str) -> str:
        """Tell the TUI of a saved pick (outside the lock: its callback may call back into the viewer)."""
        if saved and self.on_pick is not None:
            try:
                self.on_pick(spec.field, get_field(self.project, spec.field))
            except Exception as e:  # noqa: BLE001 - the TUI's callback must not break picking
                self.set_status(f"{msg} (the TUI was not updated: {e})")
        return msg

    # ------------------------------------------------------------------ overlays

    def show_field(self, npz_path) -> bool:
        path = Path(npz_path) if npz_path else self.project.root / "out" / "mean_field.npz"
        with self._lock:
            self.field = load_field(path)
            if self.field is not None:
                self.redraw()
            return self.field is not None

    def redraw(self) -> None:
        with self._lock:
            for h in self._overlay:
                try:
                    h.remove()
                except Exception:  # noqa: BLE001 - already gone with a replaced image
                    pass
            self._overlay = []
            kind = self.display.kind
            if kind in FRAME_LIKE:
                for key in ("roi", "stable", "masks", "section", "edges", "gcp"):
                    self._draw_state(key)
                if self.field is not None and self.gui_field.value:
                    self._draw_field()
            elif kind in ("image1", "image2"):
                self._draw_state("edges1" if kind == "image1" else "edges2")
            elif kind == "dem_plot" and "divergence" in self.states:
                self._draw_divergence()

    def _to_scene(self, raw_pts, lift: float = 0.0) -> np.ndarray:
        p = np.asarray(raw_pts, float).reshape(-1, 2)
        if self.display.kind in FRAME_LIKE:
            p = self.display.to_display(p)
        return pixel_to_scene(p, self.plane, lift=lift + self.plane.render_width * 1e-3)

    def _ring_px(self, active: bool) -> float:
        """Radius of the rings around picked points, display pixels."""
        h, w = self.display.rgb.shape[:2]
        return max(5.0, 0.009 * max(w, h)) * (1.3 if active else 1.0)

    def _lines(self, name: str, pts_raw, color, closed: bool = False, width: float = 2.5, gap_px: float = 0.0) -> None:
        """Straight segments between points; ``gap_px`` stops each segment short of its ends (the
        rings), so the lines never cross the targets inside the rings."""
        p = np.asarray(pts_raw, float).reshape(-1, 2)
        if len(p) < 2:
            return
        if closed:
            p = np.vstack([p, p[:1]])
        if gap_px <= 0:
            q = self._to_scene(p)
            seg = np.stack([q[:-1], q[1:]], axis=1)
        else:
            d = self.display.to_display(p) if self.display.kind in FRAME_LIKE else p
            a, b = d[:-1], d[1:]
            n = np.linalg.norm(b - a, axis=1)
            keep = n > 2.2 * gap_px
            if not np.any(keep):
                return
            u = (b - a)[keep] / n[keep, None]
            a, b = a[keep] + gap_px * u, b[keep] - gap_px * u
            lift = self.plane.render_width * 1e-3
            seg = np.stack([pixel_to_scene(a, self.plane, lift=lift), pixel_to_scene(b, self.plane, lift=lift)], axis=1)
        self._overlay.append(
            self.server.scene.add_line_segments(
                f"/overlay/{name}_lines", seg, color, thickness=width, thickness_units="screen"
            )
        )

    def _points(self, name: str, labels: list[tuple[str, list[float]]], color, active: bool) -> None:
        """Hollow rings around the picked points (the target stays visible inside) and their
        labels beside the ring, up and to the right."""
        if not labels:
            return
        raw = np.array([p for _, p in labels], float)
        disp = self.display.to_display(raw) if self.display.kind in FRAME_LIKE else raw
        r = self._ring_px(active)
        th = np.linspace(0, 2 * np.pi, 25)
        circle = np.c_[np.cos(th), np.sin(th)] * r
        rings = disp[:, None, :] + circle[None]  # (N, 25, 2) display px
        lift = self.plane.render_width * 2e-3
        p = pixel_to_scene(rings.reshape(-1, 2), self.plane, lift=lift).reshape(len(disp), len(th), 3)
        seg = np.concatenate([np.stack([q[:-1], q[1:]], axis=1) for q in p])
        self._overlay.append(
            self.server.scene.add_line_segments(
                f"/overlay/{name}_rings", seg, color, thickness=3.0 if active else 2.0, thickness_units="screen"
            )
        )
        at = pixel_to_scene(disp + np.array([0.8 * r, -0.8 * r]), self.plane, lift=lift)
        for i, ((text, _), q) in enumerate(zip(labels, at, strict=True)):
            self._overlay.append(
                self.server.scene.add_label(
                    f"/overlay/{name}_label{i}",
                    text,
                    position=tuple(q),
                    anchor="bottom-left",
                    font_screen_scale=1.3 if active else 1.0,
                )
            )

    def _draw_state(self, key: str) -> None:
        st = self.states.get(key)
        if st is None:
            return
        color, active = COLORS[key], key == self.mode
        width = 3.5 if active else 2.0
        if key == "gcp":
            self._lines(key, st.value(), color, closed=st.complete, width=width, gap_px=self._ring_px(active))
        elif key in ("section", "edges", "edges1", "edges2"):
            self._lines(key, st.value(), color, width=width, gap_px=self._ring_px(active))
        elif key == "roi":
            if st.complete:
                x0, y0, x1, y1 = st.value()
                self._lines(key, self._rect_outline(x0, y0, x1, y1), color, width=width)
        elif key == "stable":
            for i, (x0, y0, x1, y1) in enumerate(st.value()):
                self._lines(f"{key}{i}", self._rect_outline(x0, y0, x1, y1), color, width=width)
        elif key == "masks":
            assert isinstance(st, PolygonListPick)  # MODES["masks"] makes one
            for i, poly in enumerate(st.closed):
                self._lines(f"{key}{i}", poly, color, closed=True, width=width)
            self._lines(f"{key}_open", st.open, color, width=width)
        self._points(key, st.labels(), color, active)

    @staticmethod
    def _rect_outline(x0, y0, x1, y1, n: int = 8) -> np.ndarray:
        """Rectangle corners with points along the edges, so it bends correctly on the undistorted
        frame and on the map."""
        t = np.linspace(0, 1, n, endpoint=False)[:, None]
        a, b, c, d = (np.array(p, float) for p in ((x0, y0), (x1, y0), (x1, y1), (x0, y1)))
        return np.vstack([a + t * (b - a), b + t * (c - b), c + t * (d - c), d + t * (a - d), a[None]])

    def _draw_field(self) -> None:
        f = self.field
        assert f is not None  # drawn only when a field is loaded
        ok = f["valid"]
        if not np.any(ok):
            return
        x, y, u, v = f["x"][ok], f["y"][ok], f["u"][ok], f["v"][ok]
        speed = np.hypot(u, v)
        xs = np.unique(np.round(f["x"].ravel(), 3))
        spacing = float(np.median(np.diff(xs))) if len(xs) > 1 else 16.0
        scale = 0.9 * spacing / max(float(np.percentile(speed, 90)), 1e-9)  # seconds of travel drawn
        start = np.c_[x, y]
        end = start + scale * np.c_[u, v]
        d = end - start
        n = np.hypot(d[:, 0], d[:, 1])[:, None] + 1e-12
        back, side = -d / n * np.minimum(n, 0.35 * spacing), np.c_[-d[:, 1], d[:, 0]] / n * 0.15 * spacing
        head1, head2 = end + back + side, end + back - side
        lens = lens_of(self.project) if self.project.calibration.path else None
        pts = np.vstack([start, end, head1, head2])
        if lens is not None:  # the field is in working (undistorted) pixels
            pts = lens.distort_points(pts)
        k = len(start)
        p = self._to_scene(pts, lift=self.plane.render_width * 5e-4).reshape(4, k, 3)
        seg = np.concatenate([np.stack([p[0], p[1]], 1), np.stack([p[1], p[2]], 1), np.stack([p[1], p[3]], 1)])
        self._overlay.append(
            self.server.scene.add_line_segments(
                "/overlay/field", seg, COLORS["field"], thickness=1.5, thickness_units="screen"
            )
        )

    def _draw_divergence(self) -> None:
        st = self.states["divergence"]
        assert isinstance(st, StationPick)  # MODES["divergence"] makes one
        ax = st.axes
        if ax is None or not st.points:
            return
        col = st.points[0][0]
        color = COLORS["divergence"]
        p = pixel_to_scene([[col, ax.top_px], [col, ax.bottom_px]], self.plane, lift=self.plane.render_width * 1e-3)
        self._overlay.append(
            self.server.scene.add_line_segments(
                "/overlay/divergence", p[None], color, thickness=3.0, thickness_units="screen"
            )
        )
        self._overlay.append(
            self.server.scene.add_label(
                "/overlay/divergence_label", f"D = {st.value():.3f} m", position=tuple(p[0]), anchor="top-left"
            )
        )

    # ------------------------------------------------------------------ zoom

    def zoom(self, ndc_x: float, ndc_y: float, scale: float) -> int:
        moved = 0
        size = max(self.plane.render_width, self.plane.render_height)
        for client in list(self.server.get_clients().values()):
            try:
                cam = client.camera
                aspect = cam.aspect if cam.image_height else 16 / 9
                new = zoom_about_cursor(
                    cam.position,
                    cam.look_at,
                    cam.up_direction,
                    cam.fov,
                    aspect,
                    (ndc_x, ndc_y),
                    scale,
                    self.plane,
                    min_dist=0.02 * size,
                    max_dist=20 * size,
                )
                if new is None:
                    continue
                with client.atomic():
                    cam.position, cam.look_at = new
                moved += 1
            except Exception as e:  # noqa: BLE001 - a client that went away must not break the viewer
                self.set_status(f"zoom not applied for a client: {e}")
        return moved

    def stop(self) -> None:
        self._stopped.set()
        registry.unregister(self.path)
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()
