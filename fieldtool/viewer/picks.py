"""Pick modes of the viewer as small state machines (no viser, no files).

Each mode turns clicks (pixel coordinates, OpenCV convention) into the value of one project
field, with numbering for the overlay and undo that reverses the last action:

==========  ==================================  ==================  ========================
mode        project field                       image               value
==========  ==================================  ==================  ========================
gcp         ortho.gcp_px                        frame               P1..P4 [[x, y], ...]
section     section.points_px                   frame               left, right water edge
roi         roi.rect_px                         frame               [x0, y0, x1, y1]
masks       roi.masks_px                        frame               closed polygons
stable      stabilize.regions_px                frame               rectangles [x0, y0, x1, y1]
edges       water_level.edges_px                frame               2 water edges (image method)
edges1      water_level.edges1_px               image1              2 water edges (angle/height)
edges2      water_level.edges2_px               image2              2 water edges (angle/height)
divergence  water_level.divergence_station_m    dem_plot            station (m) of one click
==========  ==================================  ==================  ========================
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from fieldtool.project.sync import ProjectSync
from fieldtool.viewer.mapping import PlotAxes


def _pt(x: float, y: float, exact: bool = False) -> list[float]:
    """A clicked point, rounded to 0.01 px (a click is no finer); ``exact`` keeps every digit
    (a point snapped to a target's centre)."""
    if exact:
        return [float(x), float(y)]
    return [round(float(x), 2), round(float(y), 2)]


def _keep(x: float, y: float) -> list[float]:
    """A point loaded from the project: kept exactly (only a click changes a pick)."""
    return [float(x), float(y)]


class PickState:
    """Common interface: ``click``, ``undo``, ``close``, ``value``, ``load``, ``labels``.

    ``click``/``undo``/``close`` return a short message for the operator. ``value()`` is what the
    project field should hold now, or ``...`` (Ellipsis) when nothing is ready to be saved.
    """

    def click(self, x: float, y: float, exact: bool = False) -> str:
        """Place a point at (x, y) px; ``exact``: keep every digit (a point snapped to a target's centre)."""
        raise NotImplementedError

    def undo(self) -> str:
        raise NotImplementedError

    def close(self) -> str:
        return "nothing to close in this mode"

    def value(self) -> Any:
        raise NotImplementedError

    def load(self, value: Any) -> None:
        raise NotImplementedError

    def labels(self) -> list[tuple[str, list[float]]]:
        """(text, [x, y]) pairs to number the picked points on screen."""
        raise NotImplementedError

    @property
    def complete(self) -> bool:
        raise NotImplementedError


class PointsPick(PickState):
    """A fixed number of named points, in order (e.g. P1..P4)."""

    def __init__(self, names: tuple[str, ...]):
        self.names = tuple(names)
        self.points: list[list[float]] = []

    def click(self, x, y, exact: bool = False):
        if self.complete:
            return f"all {len(self.names)} points are placed; Undo removes {self.names[-1]} so it can be placed again"
        self.points.append(_pt(x, y, exact))
        name = self.names[len(self.points) - 1]
        nxt = f"; next: {self.names[len(self.points)]}" if not self.complete else "; done"
        return f"{name} at ({x:.1f}, {y:.1f}) px{nxt}"

    def undo(self):
        if not self.points:
            return "nothing to undo"
        self.points.pop()
        return f"removed {self.name(len(self.points))}"

    def value(self):
        return [list(p) for p in self.points]

    def load(self, value):
        self.points = [_keep(*p[:2]) for p in (value or []) if len(p) >= 2]  # all kept (pose: 6+ GCPs)

    def name(self, i: int) -> str:
        """Label of point ``i``; points beyond the named ones (loaded from the file) get #n."""
        return self.names[i] if i < len(self.names) else f"#{i + 1}"

    def labels(self):
        return [(self.name(i), p) for i, p in enumerate(self.points)]

    @property
    def next_name(self) -> str | None:
        """Name of the point the next click places; None when complete."""
        return None if self.complete else self.names[len(self.points)]

    @property
    def complete(self):
        return len(self.points) >= len(self.names)


class StationPick(PointsPick):
    """One click on a plot with known axes; the value is the station (m) under the click."""

    def __init__(self, axes: PlotAxes | None, name: str = "D"):
        super().__init__((name,))
        self.axes = axes
        self._loaded: float | None = None

    def click(self, x, y, exact: bool = False):
        if self.axes is None:
            return "no plot axes: show the DEM plot first"
        if not self.axes.contains_px((x, y)):
            return "click inside the plotting area"
        self.points = [_pt(x, y)]
        self._loaded = None
        return f"divergence point at station {self.value():.3f} m"

    def undo(self):
        self._loaded = None
        return super().undo()

    def value(self):
        if not self.points:
            return None
        if self._loaded is not None:
            return self._loaded  # as in the file, to the last digit
        return round(float(self.axes.px_to_data([self.points[0]])[0, 0]), 4)

    def load(self, value):
        self.points = []
        self._loaded = None if value is None else float(value)
        if value is not None and self.axes is not None:
            mid = 0.5 * (self.axes.y_min + self.axes.y_max)
            self.points = [_keep(*self.axes.data_to_px([[value, mid]])[0])]


def _rect(a, b) -> list[float]:
    return [min(a[0], b[0]), min(a[1], b[1]), max(a[0], b[0]), max(a[1], b[1])]


class RectPick(PickState):
    """One rectangle from two opposite corners; a third click starts a new rectangle."""

    def __init__(self):
        self.corners: list[list[float]] = []

    def click(self, x, y, exact: bool = False):
        if len(self.corners) == 2:
            self.corners = []
        self.corners.append(_pt(x, y, exact))
        if len(self.corners) == 1:
            return "first corner placed; click the opposite corner"
        return "rectangle {:.0f}, {:.0f} - {:.0f}, {:.0f} px".format(*self.value())

    def undo(self):
        if not self.corners:
            return "nothing to undo"
        self.corners.pop()
        return "removed the last corner"

    def value(self):
        if len(self.corners) == 1:
            return ...
        return _rect(*self.corners) if self.corners else []

    def load(self, value):
        self.corners = [_keep(value[0], value[1]), _keep(value[2], value[3])] if value and len(value) == 4 else []

    def labels(self):
        return [(f"C{i + 1}", p) for i, p in enumerate(self.corners)]

    @property
    def complete(self):
        return len(self.corners) == 2


class RectListPick(PickState):
    """Any number of rectangles, two clicks each; undo removes the last corner clicked."""

    def __init__(self):
        self.rects: list[list[list[float]]] = []  # each: [corner_a, corner_b]
        self.pending: list[float] | None = None

    def click(self, x, y, exact: bool = False):
        if self.pending is None:
            self.pending = _pt(x, y, exact)
            return f"region {len(self.rects) + 1}: first corner placed; click the opposite corner"
        self.rects.append([self.pending, _pt(x, y, exact)])
        self.pending = None
        return f"region {len(self.rects)} added"

    def undo(self):
        if self.pending is not None:
            self.pending = None
            return "removed the pending corner"
        if not self.rects:
            return "nothing to undo"
        self.pending = self.rects.pop()[0]
        return f"region {len(self.rects) + 1} reopened: click its second corner again"

    def value(self):
        return [_rect(a, b) for a, b in self.rects]

    def load(self, value):
        self.rects = [[_keep(r[0], r[1]), _keep(r[2], r[3])] for r in (value or []) if len(r) == 4]
        self.pending = None

    def labels(self):
        out = [(f"S{i + 1}", _rect(a, b)[:2]) for i, (a, b) in enumerate(self.rects)]
        if self.pending is not None:
            out.append((f"S{len(self.rects) + 1}", self.pending))
        return out

    @property
    def complete(self):
        return self.pending is None and bool(self.rects)


class SectionListPick(PickState):
    """More sections of interest (``sections``): two clicks each, the left then the right water edge. A section
    loaded from the project keeps its other keys (name, cross-section file); a new one is named "section N"."""

    def __init__(self):
        self.items: list[dict] = []
        self.pending: list[float] | None = None

    def click(self, x, y, exact: bool = False):
        if self.pending is None:
            self.pending = _pt(x, y, exact)
            return f"section {len(self.items) + 2}: left water edge placed; click the right one"
        self.items.append({"name": f"section {len(self.items) + 2}", "points_px": [self.pending, _pt(x, y, exact)]})
        self.pending = None
        return f"section {len(self.items) + 1} added"

    def undo(self):
        if self.pending is not None:
            self.pending = None
            return "removed the pending left edge"
        if not self.items:
            return "nothing to undo"
        self.pending = self.items.pop()["points_px"][0]
        return f"section {len(self.items) + 2} reopened: click its right water edge again"

    def value(self):
        return [dict(it) for it in self.items]

    def load(self, value):
        self.items = []
        for it in value or []:
            pts = it.get("points_px") if isinstance(it, dict) else None
            if isinstance(pts, list) and len(pts) == 2 and all(len(p) >= 2 for p in pts):
                self.items.append({**it, "points_px": [_keep(*pts[0][:2]), _keep(*pts[1][:2])]})
        self.pending = None

    def labels(self):
        out = []
        for i, it in enumerate(self.items):
            out += [(f"L{i + 2}", it["points_px"][0]), (f"R{i + 2}", it["points_px"][1])]
        if self.pending is not None:
            out.append((f"L{len(self.items) + 2}", self.pending))
        return out

    @property
    def complete(self):
        return self.pending is None and bool(self.items)


class PolygonListPick(PickState):
    """Mask polygons: click vertices; Close (or a click on the first vertex) closes the polygon.

    Undo removes the last vertex of the open polygon; with no open polygon it reopens the last
    closed one, so every action can be reversed one by one.
    """

    def __init__(self, close_tol_px: float = 8.0):
        self.closed: list[list[list[float]]] = []
        self.open: list[list[float]] = []
        self.close_tol_px = close_tol_px

    def click(self, x, y, exact: bool = False):
        if len(self.open) >= 3 and np.hypot(x - self.open[0][0], y - self.open[0][1]) <= self.close_tol_px:
            return self.close()
        self.open.append(_pt(x, y, exact))
        return f"mask {len(self.closed) + 1}: vertex {len(self.open)}" + (
            "; Close (or click the first vertex) to finish" if len(self.open) >= 3 else ""
        )

    def close(self):
        if len(self.open) < 3:
            return f"a mask needs at least 3 vertices (has {len(self.open)})"
        self.closed.append(self.open)
        self.open = []
        return f"mask {len(self.closed)} closed ({len(self.closed[-1])} vertices)"

    def undo(self):
        if self.open:
            self.open.pop()
            return f"removed vertex {len(self.open) + 1}"
        if self.closed:
            self.open = self.closed.pop()
            return f"mask {len(self.closed) + 1} reopened"
        return "nothing to undo"

    def value(self):
        return [[list(p) for p in poly] for poly in self.closed]

    def load(self, value):
        self.closed = [[_keep(*p[:2]) for p in poly] for poly in (value or []) if len(poly) >= 3]
        self.open = []

    def labels(self):
        out = [(f"M{i + 1}", poly[0]) for i, poly in enumerate(self.closed)]
        out += [(f"{len(self.closed) + 1}.{j + 1}", p) for j, p in enumerate(self.open)]
        return out

    @property
    def complete(self):
        return not self.open and bool(self.closed)


@dataclass(frozen=True)
class ModeSpec:
    """One pick mode: which project field it fills, on which image, and how.

    ``legend`` explains the labels drawn on the image; ``buttons`` are the actions the mode offers
    (``undo``, ``close``, ``clear``); ``step`` places the mode in the viewer's checklist (None: not
    listed) and ``required`` says whether a run needs it. A new mode is one more row of MODES.
    """

    key: str
    label: str
    field: str  # dotted project path, e.g. "ortho.gcp_px"
    image: str  # frame | image1 | image2 | dem_plot
    make: Callable[..., PickState]
    help: str
    legend: str = ""
    buttons: tuple[str, ...] = ("undo", "clear")
    step: int | None = None
    required: bool = False
    snap: bool = False  # clicks snap to a checker target's centre when one is near


MODES: dict[str, ModeSpec] = {
    m.key: m
    for m in (
        ModeSpec(
            "gcp",
            "GCPs P1-P4",
            "ortho.gcp_px",
            "frame",
            lambda axes=None: PointsPick(("P1", "P2", "P3", "P4")),
            "Click the 4 ground control points in the thesis order (fig. 7.13): P1 and P2 on one bank, P3 and "
            "P4 on the other, going round the quadrilateral (L1=|P1P2|, L2=|P2P3|, L3=|P3P4|, L4=|P4P1|). "
            "A click near a checker target snaps to its centre.",
            legend="P1-P4: ground control points, in order round the quadrilateral",
            step=1,
            required=True,
            snap=True,
        ),
        ModeSpec(
            "section",
            "Section end points",
            "section.points_px",
            "frame",
            lambda axes=None: PointsPick(("L", "R")),
            "Click the left then the right water edge of the section (left/right looking downstream).",
            legend="L: left water edge, R: right water edge (looking downstream)",
            step=2,
            required=True,
        ),
        ModeSpec(
            "sections",
            "More sections",
            "sections",
            "frame",
            lambda axes=None: SectionListPick(),
            "Several sections (optional): for each, click its left then its right water edge; each is measured on "
            "the same velocity field (set its own cross-section file in the project, default the main one).",
            legend="L2/R2, L3/R3, ...: left and right water edges of the 2nd, 3rd, ... section",
        ),
        ModeSpec(
            "roi",
            "ROI rectangle",
            "roi.rect_px",
            "frame",
            lambda axes=None: RectPick(),
            "Click two opposite corners of the region where PIV runs.",
            legend="C1, C2: opposite corners of the region where PIV runs",
            step=3,
        ),
        ModeSpec(
            "masks",
            "Mask polygons",
            "roi.masks_px",
            "frame",
            lambda axes=None: PolygonListPick(),
            "Click the vertices of an area to ignore; Close (or click the first vertex) finishes it.",
            legend="M1, M2 ...: closed masks (at their first vertex); 2.3: vertex 3 of mask 2, still open",
            buttons=("undo", "close", "clear"),
            step=4,
        ),
        ModeSpec(
            "stable",
            "Stable regions",
            "stabilize.regions_px",
            "frame",
            lambda axes=None: RectListPick(),
            "Click two opposite corners of each fixed area outside the water (banks, rocks, buildings).",
            legend="S1, S2 ...: fixed regions for stabilisation (at a corner)",
            step=5,
        ),
        ModeSpec(
            "edges",
            "Water edges (image method)",
            "water_level.edges_px",
            "frame",
            lambda axes=None: PointsPick(("E1", "E2")),
            "Click the left then the right water edge on the frame (image method).",
            legend="E1: left water edge, E2: right water edge",
        ),
        ModeSpec(
            "search_line",
            "Water-line search line",
            "water_level.search_line_px",
            "frame",
            lambda axes=None: PointsPick(("S1", "S2")),
            "Water line found in the clip: click a point on one bank, then one on the other bank, across the river.",
            legend="S1, S2: ends of the line searched for the water edges, one on each bank",
        ),
        ModeSpec(
            "edges1",
            "Water edges, image 1",
            "water_level.edges1_px",
            "image1",
            lambda axes=None: PointsPick(("E1", "E2")),
            "Angle-and-height method: click the two water edges on the first (lower) image.",
            legend="E1: left water edge, E2: right water edge (image 1)",
        ),
        ModeSpec(
            "edges2",
            "Water edges, image 2",
            "water_level.edges2_px",
            "image2",
            lambda axes=None: PointsPick(("E1", "E2")),
            "Angle-and-height method: click the same two water edges on the second (higher) image.",
            legend="E1: left water edge, E2: right water edge (image 2)",
        ),
        ModeSpec(
            "divergence",
            "DEM divergence point",
            "water_level.divergence_station_m",
            "dem_plot",
            lambda axes=None: StationPick(axes),
            "Click where the DEM leaves the surveyed bed: the station of the click is the water edge.",
            legend="D: station where the DEM leaves the surveyed bed",
            buttons=("undo",),
        ),
    )
}


def checklist(states: dict[str, PickState]) -> list[tuple[ModeSpec, str, str]]:
    """The picks in order, as (mode, status, detail): status is "done", "next" (the first required
    step not done, else the first optional one not started) or "todo"/"optional".

    ``detail`` says what is placed and what comes next within the mode (e.g. "P1 P2 placed; next P3")."""
    rows: list[list[Any]] = []  # [mode, status, detail]
    for spec in sorted((m for m in MODES.values() if m.step is not None), key=lambda m: m.step or 0):
        st = states.get(spec.key)
        labels = [t for t, _ in st.labels()] if st is not None else []
        done = st is not None and st.complete
        nxt = getattr(st, "next_name", None)
        detail = " ".join(labels) + " placed" if labels else "nothing placed"
        if not done and nxt:
            detail += f"; next {nxt}"
        rows.append([spec, "done" if done else ("todo" if spec.required else "optional"), detail])
    for row in rows:
        if row[1] == "todo":
            row[1] = "next"
            break
    else:
        for row in rows:
            if row[1] == "optional" and row[2] == "nothing placed":
                row[1] = "next"
                break
    return [(r[0], r[1], r[2]) for r in rows]


def next_mode(states: dict[str, PickState]) -> str | None:
    """Key of the checklist's "next" step (None when every step is done)."""
    return next((spec.key for spec, status, _ in checklist(states) if status == "next"), None)


def save_field(project_path, path: str, value: Any) -> Any:
    """Set one dotted field in the project file as it is now (``project.sync``: this one key, comments
    kept, atomic; an invalid or read-only file is refused). Returns the project as saved. The viewer
    itself saves through its ``ProjectSync`` (three-way merge per point)."""
    return ProjectSync(project_path).set_keys({path: value}).project


def get_field(project: Any, path: str) -> Any:
    """Value of a dotted field path (``"ortho.gcp_px"``) of a project."""
    obj = project
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def set_field(project: Any, path: str, value: Any) -> None:
    """Set a dotted field path of a project (the dataclass must have that field)."""
    *head, last = path.split(".")
    obj = project
    for part in head:
        obj = getattr(obj, part)
    if not hasattr(obj, last):
        raise AttributeError(f"the project has no field {path}")
    setattr(obj, last, value)
