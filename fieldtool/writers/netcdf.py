"""The mean surface velocity field as CF-convention NetCDF (``mean_field.nc``), written with netCDF4 (xarray
reads it back; it is not imported to write, since it and pandas take about half a second to import).

PIV nodes lie on a regular grid in the *image*; on the water plane (an oblique view) they do not.
Tools that read NetCDF (QGIS through GDAL, Panoply, xarray) expect a regular grid, so the valid
node velocities are interpolated linearly (scipy ``LinearNDInterpolator``) onto a regular grid in the site's
coordinates: cell size = the median distance from a valid node to its nearest valid neighbour
(at most 1000 cells a side); a cell is empty (NaN) outside the nodes' convex hull or when its nearest
valid node is farther than that node's distance to its own nearest neighbour (and than one cell).
The native node values stay in ``mean_field.npz``.

Variables (CF 1.8): ``x``, ``y`` (m, the world frame of the GCPs: projected coordinates when
``ortho.crs_epsg`` is given, else the site's local frame), ``time`` with ``time_bnds`` (the clip
span that was averaged), ``surface_velocity_x`` / ``surface_velocity_y`` (standard names
``sea_water_x_velocity`` / ``sea_water_y_velocity``, m s-1), ``surface_speed`` (``sea_water_speed``)
and ``valid_fraction`` (1). The project and the run's key results are global attributes.
"""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path

import netCDF4
import numpy as np

from fieldtool import __version__
from fieldtool.project.model import atomic_path
from fieldtool.writers.geotiff import cf_grid_mapping, crs_of

MAX_CELLS = 300  # per side: the PIV grid has far fewer nodes; a finer grid only costs time


def _spatial():
    """scipy.spatial, lazy: 0.05-0.1 s off the run's start (run.outputs imports it in a thread during the PIV)."""
    import scipy.spatial

    return scipy.spatial


def regular_grid(XY: np.ndarray, values: list[np.ndarray], max_cells: int = MAX_CELLS):
    """Interpolate scattered node values (metres) onto a regular grid.

    Parameters
    ----------
    XY : (N, 2) node positions (m)
    values : arrays of N values each

    Returns
    -------
    x (nx,), y (ny,) cell centres (m, ascending), cell size (m), list of (ny, nx) arrays (NaN = no data)
    """
    tree = _spatial().cKDTree(XY)
    d, _ = tree.query(XY, k=2)
    dx = float(np.median(d[:, 1])) if len(XY) > 1 else 1.0
    lo, hi = XY.min(axis=0), XY.max(axis=0)
    dx = max(dx, float(np.max(hi - lo)) / max_cells, 1e-6)
    dx = float(f"{dx:.3g}")
    x0, y0 = np.floor(lo / dx) * dx
    nx = int(np.ceil((hi[0] - x0) / dx)) + 1
    ny = int(np.ceil((hi[1] - y0) / dx)) + 1
    x = x0 + dx * np.arange(nx)
    y = y0 + dx * np.arange(ny)
    Xg, Yg = np.meshgrid(x, y)
    # empty where the nearest node is farther than that node's own spacing (oblique views: far nodes are sparse)
    dist, idx = tree.query(np.c_[Xg.ravel(), Yg.ravel()])
    far = (dist > np.maximum(d[idx, 1] if len(XY) > 1 else dx, dx)).reshape(Xg.shape)
    if len(XY) >= 3:  # one triangulation for every variable
        g = _linear_on_triangles(XY, np.stack(values, axis=-1), np.c_[Xg.ravel(), Yg.ravel()]).reshape(
            Xg.shape + (len(values),)
        )
    else:
        g = np.full(Xg.shape + (len(values),), np.nan)
    g[far] = np.nan
    return x, y, dx, [g[..., k].astype(np.float32) for k in range(len(values))]


def _linear_on_triangles(XY: np.ndarray, V: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Piecewise-linear interpolation on the Delaunay triangles of ``XY`` (N, 2) of values ``V`` (N, k) at ``pts``
    (M, 2); NaN outside the hull. What ``scipy.interpolate.LinearNDInterpolator`` computes (tests/test_outputs_std.py
    compares them), without importing scipy.interpolate, which imports scipy.optimize (0.3-0.5 s of a run)."""
    tri = _spatial().Delaunay(XY)
    s = tri.find_simplex(pts)
    inside = np.maximum(s, 0)  # any triangle for the points outside: their values are set to NaN below
    T = tri.transform[inside]
    b = np.einsum("nij,nj->ni", T[:, :2], pts - T[:, 2])
    w = np.c_[b, 1.0 - b.sum(axis=1)]
    out = np.einsum("ni,nik->nk", w, V[tri.simplices[inside]])
    out[s < 0] = np.nan
    return out


def _flat_attrs(inputs: dict) -> dict:
    """Scalar project keys as ``project_<table>_<key>`` attributes (lists and tables go in the JSON one)."""
    attrs: dict[str, int | float | str] = {}
    for k, v in inputs.items():
        items = v.items() if isinstance(v, dict) else [(None, v)]
        for k2, v2 in items:
            name = f"project_{k}" + (f"_{k2}" if k2 else "")
            if isinstance(v2, bool):
                attrs[name] = int(v2)
            elif isinstance(v2, (int, float, str)) and not (isinstance(v2, float) and not np.isfinite(v2)):
                attrs[name] = v2
    return attrs


def _valid_nodes(result) -> np.ndarray:
    """The PIV nodes with a valid vector and a finite world velocity (bool, the nodes' shape)."""
    return np.asarray(result.piv.valid, bool) & np.isfinite(result.world_u) & np.isfinite(result.world_v)


def _grid_field(result) -> tuple:
    """The valid PIV node velocities (m s-1) and valid fractions (1) on a regular grid in the world frame:
    ``(x, y, dx, u, v, valid_fraction, speed)``, x and y the cell centres (m), dx the cell size (m)."""
    p = result.piv
    ok = _valid_nodes(result)
    XY = result.mapping.image_to_world(np.c_[p.x[ok], p.y[ok]])
    U, V = np.asarray(result.world_u)[ok], np.asarray(result.world_v)[ok]
    vf = np.asarray(p.valid_fraction, float)[ok]
    x, y, dx, (gu, gv, gf) = regular_grid(XY, [U, V, vf])
    speed = np.hypot(gu, gv)

    return x, y, dx, gu, gv, gf, speed


def _time_span(p, video: dict) -> tuple[float, float, str, str, str | None]:
    """The clip span that was averaged: ``(t0, t1, units, comment, recorded)``, t0 and t1 in seconds from
    the recording start when the container gives its date (``recorded``, ISO UTC), else from the clip's."""
    t = np.asarray(p.t_pairs, float)
    dt = np.asarray(p.dt_s, float) if p.dt_s is not None and len(p.dt_s) else np.zeros_like(t)
    t0 = float(t[0] - dt[0] / 2) if len(t) else 0.0
    t1 = float(t[-1] + dt[-1] / 2) if len(t) else 0.0
    # a date only from the container: a file's modification time says when it was copied, not recorded
    recorded = video.get("recorded_utc") if video.get("recorded_source") == "container" else None
    if recorded:
        t_units = f"seconds since {recorded.replace('T', ' ').replace('Z', '')}"
        t_comment = "seconds from the recording start (container creation time); clip time as in the run"
    else:
        t_units = "seconds since 1970-01-01 00:00:00"
        t_comment = "recording date unknown: the values are seconds from the start of the clip, not a date"
    return t0, t1, t_units, t_comment, recorded


def _cf_variables(x, y, gu, gv, gf, speed, t0: float, t1: float, t_units: str, t_comment: str, frame: str, crs):
    """The CF variables ``{name: (dims, array, attrs, encoding)}``: coordinates x, y (m) in ``frame``, time
    (s, ``t_units``) with its bounds, the gridded velocity components and speed (m s-1), valid fraction (1)."""
    common = {"grid_mapping": "crs"} if crs is not None else {}
    field = {"zlib": True, "complevel": 4, "fill_value": np.float32(np.nan)}
    plain = {"fill_value": False}
    tyx = ("time", "y", "x")
    variables = {
        # projection coordinates also in a local frame: there is no grid mapping then (CRS unknown)
        "time": (
            ("time",),
            np.array([(t0 + t1) / 2]),
            {
                "standard_name": "time",
                "long_name": "time of the mean field",
                "axis": "T",
                "bounds": "time_bnds",
                "units": t_units,
                "calendar": "standard",
                "comment": t_comment,
            },
            plain,
        ),
        "x": (
            ("x",),
            x,
            {"standard_name": "projection_x_coordinate", "long_name": f"x in {frame}", "units": "m", "axis": "X"},
            plain,
        ),
        "y": (
            ("y",),
            y,
            {"standard_name": "projection_y_coordinate", "long_name": f"y in {frame}", "units": "m", "axis": "Y"},
            plain,
        ),
        "surface_velocity_x": (
            tyx,
            gu[None],
            {
                "standard_name": "sea_water_x_velocity",
                "long_name": "surface velocity, x component (LSPIV)",
                "units": "m s-1",
                "cell_methods": "time: mean",
                **common,
            },
            field,
        ),
        "surface_velocity_y": (
            tyx,
            gv[None],
            {
                "standard_name": "sea_water_y_velocity",
                "long_name": "surface velocity, y component (LSPIV)",
                "units": "m s-1",
                "cell_methods": "time: mean",
                **common,
            },
            field,
        ),
        "surface_speed": (
            tyx,
            speed[None].astype(np.float32),
            {
                "standard_name": "sea_water_speed",
                "long_name": "surface speed (LSPIV)",
                "units": "m s-1",
                "cell_methods": "time: mean",
                **common,
            },
            field,
        ),
        "valid_fraction": (
            tyx,
            gf[None],
            {"long_name": "fraction of frame pairs in which the PIV vector was valid", "units": "1", **common},
            field,
        ),
        "time_bnds": (("time", "nv"), np.array([[t0, t1]]), {}, plain),
    }
    return variables


def _global_attrs(result, project, frame: str, dx: float, video: dict) -> dict:
    """The global attributes: provenance, the grid cell ``dx`` (m), the discharge (m3 s-1), the water level (m)
    and the project, flattened and as JSON."""
    d = result.discharge
    now = datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    attrs = {
        "Conventions": "CF-1.8",
        "title": f"LSPIV mean surface velocity — {project.name}",
        "source": f"fieldtool {__version__}: large-scale particle image velocimetry of a river surface video",
        "history": f"{now} written by fieldtool {__version__} (fieldtool run)",
        "references": "thesis: LSPIV discharge measurement (fieldtool/shared/seed)",
        "comment": (
            f"Node velocities interpolated linearly onto a regular {dx:g} m grid in {frame}; cells farther "
            "from a valid node than the local node spacing are empty. Native PIV nodes: mean_field.npz."
        ),
        "site": project.site,
        "video_file": video.get("file", ""),
        "discharge_m3s": float(d.discharge_m3s),
        "water_level_m": float(d.water_level_m),
        "grid_cell_m": dx,
        "fieldtool_project_json": json.dumps(result.project, sort_keys=True, default=str),
        **_flat_attrs(result.project),
    }
    return attrs


def build_dataset(result, project) -> dict:
    """The CF dataset of a run's mean field (see the module docstring), as plain values:
    ``{"dims": {name: size}, "vars": {name: (dims, array, attrs, encoding)}, "attrs": {...}}``."""
    x, y, dx, gu, gv, gf, speed = _grid_field(result)
    video = getattr(result, "video", None) or {}
    t0, t1, t_units, t_comment, recorded = _time_span(result.piv, video)
    crs = crs_of(project)
    frame = (
        f"EPSG:{project.ortho.crs_epsg}"
        if crs is not None
        else f"the site's local frame of the GCPs (ortho.method = {project.ortho.method})"
    )
    variables = _cf_variables(x, y, gu, gv, gf, speed, t0, t1, t_units, t_comment, frame, crs)
    if crs is not None:
        variables["crs"] = ((), np.int32(0), cf_grid_mapping(crs), {})
    attrs = _global_attrs(result, project, frame, dx, video)
    if recorded:
        attrs["time_coverage_start"] = recorded
    return {"dims": {"time": 1, "y": len(y), "x": len(x), "nv": 2}, "vars": variables, "attrs": attrs}


def write_mean_field(result, project, inputs, out: Path) -> str | None:
    """Write ``mean_field.nc`` into ``out`` (through a temporary file and a rename); returns its name, or None
    (and says so in the warnings) where no node has a valid vector: there is no field to grid."""
    if not _valid_nodes(result).any():
        result.warnings.append("mean_field.nc not written: no node has a valid velocity vector")
        return None
    ds = build_dataset(result, project)
    path = Path(out) / "mean_field.nc"
    with atomic_path(path) as tmp:
        with netCDF4.Dataset(tmp, "w", format="NETCDF4") as nc:
            for name, size in ds["dims"].items():
                nc.createDimension(name, size)
            for name, (dims, values, attrs, enc) in ds["vars"].items():
                values = np.asarray(values)
                var = nc.createVariable(name, values.dtype, dims, **enc)
                var.setncatts(attrs)
                var[...] = values
            nc.setncatts(ds["attrs"])
    return path.name
