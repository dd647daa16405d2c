"""Standard outputs: CF NetCDF of the mean field (xarray) and the rectified frame as GeoTIFF (rasterio)."""

from __future__ import annotations

import json
from datetime import UTC

import cv2
import numpy as np
import pytest
import rasterio
import tomli_w
import xarray as xr

from fieldtool.cli.main import main
from fieldtool.errors import ParameterError
from fieldtool.project.model import load_project, project_to_dict
from fieldtool.run.geometry import build_mapping
from fieldtool.run.inputs import load_inputs
from fieldtool.run.pipeline import run_project

OFFSET = np.array([190000.0, 330000.0])  # GCPs surveyed in Amersfoort / RD New (EPSG:28992)


def _world_project(short_scene):
    """The short scene with its GCPs given as RD New coordinates (method world) and the CRS key."""
    p = load_project(short_scene.project_path)
    p.video.end_s = 0.5
    m = build_mapping(p, load_inputs(p), None)
    p.ortho.method, p.ortho.gcp_world_m, p.ortho.crs_epsg = "world", (m.gcp_world + OFFSET).tolist(), 28992
    return p


@pytest.fixture(scope="module")
def world_run(short_scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("std") / "out"
    p = _world_project(short_scene)
    return p, run_project(p, out), out


def test_netcdf_is_cf_with_units_names_bounds_and_the_project(world_run):
    project, result, out = world_run
    assert result.files["netcdf"] == "mean_field.nc"
    with xr.open_dataset(out / "mean_field.nc", decode_times=False) as ds:
        assert ds.attrs["Conventions"] == "CF-1.8"
        for name, std in (
            ("surface_velocity_x", "sea_water_x_velocity"),
            ("surface_velocity_y", "sea_water_y_velocity"),
            ("surface_speed", "sea_water_speed"),
        ):
            v = ds[name]
            assert v.attrs["standard_name"] == std and v.attrs["units"] == "m s-1" and v.attrs["long_name"]
            assert v.dims == ("time", "y", "x") and v.attrs["grid_mapping"] == "crs"
        assert ds["valid_fraction"].attrs["units"] == "1"
        assert ds.x.attrs["standard_name"] == "projection_x_coordinate" and ds.x.attrs["units"] == "m"
        assert ds.y.attrs["standard_name"] == "projection_y_coordinate" and ds.y.attrs["axis"] == "Y"
        # time and its bounds: the span of the averaged pairs (s)
        assert ds.time.attrs["bounds"] == "time_bnds" and "since" in ds.time.attrs["units"]
        lo, hi = ds.time_bnds.values[0]
        t = np.asarray(result.piv.t_pairs)
        assert lo <= t.min() < t.max() <= hi and lo < float(ds.time.values[0]) < hi
        assert "Amersfoort / RD New" in ds.crs.attrs["crs_wkt"] and ds.crs.attrs["grid_mapping_name"]
        # x, y in the site's coordinates (the RD New GCPs), the project as attributes
        gw = np.asarray(project.ortho.gcp_world_m)
        assert gw[:, 0].min() - 20 < float(ds.x.min()) and float(ds.x.max()) < gw[:, 0].max() + 20
        assert ds.attrs["project_piv_window_px"] == project.piv.window_px
        assert json.loads(ds.attrs["fieldtool_project_json"])["ortho"]["crs_epsg"] == 28992
        assert ds.attrs["discharge_m3s"] == pytest.approx(result.discharge.discharge_m3s)
        # the values: the regular grid read back at the nodes gives the nodes' velocities
        p = result.piv
        ok = p.valid & np.isfinite(result.world_u)
        XY = result.mapping.image_to_world(np.c_[p.x[ok], p.y[ok]])
        got = (
            ds.surface_velocity_x.isel(time=0)
            .sel(x=xr.DataArray(XY[:, 0], dims="n"), y=xr.DataArray(XY[:, 1], dims="n"), method="nearest")
            .values
        )
        fin = np.isfinite(got)
        assert fin.mean() > 0.9  # every node has data in its own cell (the edges of the hull aside)
        err = np.abs(got[fin] - result.world_u[ok][fin])
        assert np.median(err) < 0.03 * np.abs(result.world_u[ok]).max()


def test_geotiff_has_the_crs_and_a_transform_that_puts_pixels_where_the_frame_shows_them(world_run, short_scene):
    project, result, out = world_run
    assert result.files["geotiff"] == "rectified.tif"
    inputs = load_inputs(project)
    gray = cv2.cvtColor(inputs.first_color, cv2.COLOR_BGR2GRAY).astype(np.float32)
    with rasterio.open(out / "rectified.tif") as r:
        assert r.crs.to_epsg() == 28992 and r.count == 4
        rgb = np.dstack([r.read(b) for b in (1, 2, 3)])
        alpha = r.read(4)
        T = r.transform
    tif_gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    rows, cols = np.nonzero(alpha[5:-5, 5:-5])
    pick = np.random.default_rng(0).choice(len(rows), 4000, replace=False)
    rows, cols = rows[pick] + 5, cols[pick] + 5

    def misfit(shift_cells: float) -> float:
        X, Y = (np.asarray(a) for a in rasterio.transform.xy(T, rows, cols + shift_cells, offset="center"))
        img = result.mapping.world_to_image(np.c_[X, Y]).astype(np.float32)
        src = cv2.remap(gray, img[:, 0:1], img[:, 1:2], cv2.INTER_LINEAR)[:, 0]
        return float(np.mean(np.abs(src - tif_gray[rows, cols])))

    assert misfit(0.0) < 3.0  # grey levels: the transform is right to a fraction of a cell
    assert misfit(1.0) > 2 * misfit(0.0)  # and the check sees a one-cell error


def _write(tmp_path, p):
    d = project_to_dict(p)
    path = tmp_path / "project.toml"
    path.write_text(tomli_w.dumps(d))
    return path


def test_crs_errors_stop_the_run_with_exit_2(short_scene, tmp_path, capsys):
    p = _world_project(short_scene)
    p.root = short_scene.project_path.parent
    for bad, words in ((4326, "not a projected system"), (999999, "not a known")):
        d = project_to_dict(p)
        d["ortho"]["crs_epsg"] = bad
        for k in ("video", "cross_section"):
            if d[k].get("path"):
                d[k]["path"] = str(p.resolve(d[k]["path"]))
        path = tmp_path / "project.toml"
        path.write_text(tomli_w.dumps(d))
        assert main(["run", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert "ortho.crs_epsg" in err and words in err and "Traceback" not in err
        assert not (tmp_path / "out").exists()


def test_no_geotiff_for_a_local_frame_and_netcdf_without_crs(short_scene, tmp_path):
    p = load_project(short_scene.project_path)
    p.video.end_s = 0.3
    p.ortho.crs_epsg = 28992  # method distances: a local frame, the CRS cannot place it
    r = run_project(p, tmp_path / "out")
    assert "geotiff" not in r.files and not (tmp_path / "out" / "rectified.tif").exists()
    assert any("ortho.crs_epsg" in w and "local frame" in w for w in r.warnings)
    with xr.open_dataset(tmp_path / "out" / "mean_field.nc") as ds:
        assert "crs" not in ds and "grid_mapping" not in ds.surface_speed.attrs
        assert "local frame" in ds.x.attrs["long_name"] and ds.x.attrs["units"] == "m"
        assert ds.x.attrs["standard_name"] == "projection_x_coordinate"  # CRS unknown: no grid mapping
    with pytest.raises(ParameterError):
        from fieldtool.writers import check

        p.ortho.crs_epsg = 4326
        p.ortho.method = "world"
        check(p)


def _ebml(eid: int, payload: bytes, unknown_size: bool = False) -> bytes:
    """One EBML element (id bytes as written, 8-byte size)."""
    idb = eid.to_bytes((eid.bit_length() + 7) // 8, "big")
    size = b"\x01\xff\xff\xff\xff\xff\xff\xff" if unknown_size else (0x01 << 56 | len(payload)).to_bytes(8, "big")
    return idb + size + payload


def test_recording_time_from_a_matroska_header(tmp_path):
    """MKV/WebM: Segment/Info/DateUTC (ns since 2001-01-01 UTC), read from the headers only."""
    from datetime import datetime

    from fieldtool.records.video_meta import mkv_creation_time, recording_time

    when = datetime(2024, 5, 1, 8, 30, 15, tzinfo=UTC)
    ns = int((when - datetime(2001, 1, 1, tzinfo=UTC)).total_seconds()) * 10**9
    header = _ebml(0x1A45DFA3, _ebml(0x4282, b"matroska"))
    info = _ebml(0x1549A966, _ebml(0x2AD7B1, (1000000).to_bytes(3, "big")) + _ebml(0x4461, ns.to_bytes(8, "big")))
    seek = _ebml(0x114D9B74, b"\x00" * 20)  # an element before Info, skipped
    path = tmp_path / "clip.mkv"
    path.write_bytes(header + _ebml(0x18538067, seek + info + _ebml(0x1F43B675, b"\x00" * 64), unknown_size=True))
    assert mkv_creation_time(path) == when
    assert recording_time(path) == ("2024-05-01T08:30:15Z", "container")
    # no DateUTC: the file time, said so
    path.write_bytes(header + _ebml(0x18538067, _ebml(0x1549A966, b"") + _ebml(0x1F43B675, b"\x00" * 8)))
    assert mkv_creation_time(path) is None and recording_time(path)[1] == "file mtime"
    (tmp_path / "not.mkv").write_bytes(b"RIFF....")
    assert mkv_creation_time(tmp_path / "not.mkv") is None


def test_the_grid_interpolation_is_scipys_linear_nd():
    """writers.netcdf interpolates on Delaunay triangles itself (import time); same values as SciPy's."""
    from scipy.interpolate import LinearNDInterpolator

    from fieldtool.writers.netcdf import _linear_on_triangles

    rng = np.random.default_rng(1)
    XY = rng.uniform(0, 10, (200, 2))
    V = np.c_[np.sin(XY[:, 0]) + XY[:, 1], XY[:, 0] * XY[:, 1]]
    pts = rng.uniform(-1, 11, (500, 2))
    ours = _linear_on_triangles(XY, V, pts)
    ref = LinearNDInterpolator(XY, V)(pts)
    np.testing.assert_array_equal(np.isnan(ours), np.isnan(ref))
    ok = ~np.isnan(ref)
    assert ok.sum() > 300
    np.testing.assert_allclose(ours[ok], ref[ok], rtol=1e-10, atol=1e-10)


def test_no_netcdf_where_no_node_has_a_vector(tmp_path):
    """A measurement with nothing measured (graded unusable) writes no mean_field.nc and says why in one line,
    instead of the gridding's own error (a 60 fps clip of slow flow before processing/decorrelation.py)."""
    from types import SimpleNamespace

    from fieldtool.writers.netcdf import write_mean_field

    nan = np.full(4, np.nan)
    result = SimpleNamespace(piv=SimpleNamespace(valid=np.zeros(4, bool)), world_u=nan, world_v=nan, warnings=[])
    assert write_mean_field(result, None, None, tmp_path) is None
    assert result.warnings == ["mean_field.nc not written: no node has a valid velocity vector"]
    assert not (tmp_path / "mean_field.nc").exists()
