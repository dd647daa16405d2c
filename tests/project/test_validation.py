"""The validation layer: every key declared, checked the same way; geometry and path rules."""

import copy
import math
import os

import pytest

from fieldtool.errors import ParameterError
from fieldtool.project import validation as V
from fieldtool.project.model import load_project


@pytest.fixture()
def proj(short_scene):
    return load_project(short_scene.project_path)


def _keys(project, **kw):
    return {p.key for p in V.validate(project, **kw) if p.severity == "error"}


def test_demo_project_is_clean(proj):
    assert V.validate(proj) == []
    V.check(proj)


def test_every_key_is_declared_or_generic():
    specs = V.describe()
    # every saved key is known; undeclared ones (plain booleans) are still checked from their type
    undeclared = sorted(k for k, s in specs.items() if s is None)
    assert set(undeclared) <= {"stabilize.enabled"}, undeclared


@pytest.mark.parametrize(
    "path,value,key",
    [
        ("video.start_s", math.nan, "video.start_s"),
        ("video.end_s", math.inf, "video.end_s"),
        ("section.station_offset_m", math.nan, "section.station_offset_m"),
        ("section.station_offset_m", 1e308, "section.station_offset_m"),
        ("section.n_sub", 10_000_000, "section.n_sub"),
        ("piv.search_px", 2**62, "piv.search_px"),
        ("piv.max_velocity_ms", 0.0, "piv.max_velocity_ms"),
        ("water_level.pixel_uncertainty_px", 1e308, "water_level.pixel_uncertainty_px"),
        ("water_level.dh_m", math.inf, "water_level.dh_m"),
        ("ortho.distances_m", [1e308] * 6, "ortho.distances_m[0]"),
        ("ortho.gcp_px", [[1.0], [2.0, 3.0, 4.0]], "ortho.gcp_px"),
        ("cross_section.points", [[1.0], [2.0, 3.0, 4.0]], "cross_section.points"),
        ("roi.rect_px", [1.0, 2.0], "roi.rect_px"),
        ("stabilize.regions_px", [[1.0, 2.0]], "stabilize.regions_px"),
        ("video.path", "x" * 5000, "video.path"),
        ("name", "a\nb", "name"),
        ("rerun.path", ".", "rerun.path"),
        ("cross_section.depth_m", 1e308, "cross_section.depth_m"),
    ],
)
def test_bad_values_name_their_key(proj, path, value, key):
    table, _, name = path.rpartition(".")
    setattr(getattr(proj, table) if table else proj, name, value)
    assert key in _keys(proj, files=False)
    with pytest.raises(ParameterError, match=key.replace("[", r"\[").replace("]", r"\]")):
        V.check(proj, files=False)


def test_problems_for_prefix(proj):
    proj.piv.overlap_px = 40
    proj.section.n_sub = 0
    assert {p.key for p in V.problems_for(proj, "piv.")} == {"piv.overlap_px"}
    assert {p.key for p in V.problems_for(proj, "section.")} == {"section.n_sub"}


def test_collinear_and_coincident_gcps(proj):
    g = proj.ortho.gcp_px
    q = copy.deepcopy(proj)
    q.ortho.gcp_px[2] = [(g[0][0] + g[1][0]) / 2, (g[0][1] + g[1][1]) / 2 + 0.5]
    assert any("one line" in p.message for p in V.validate(q, files=False))
    q = copy.deepcopy(proj)
    q.ortho.gcp_px[3] = list(g[0])
    assert any("same point" in p.message for p in V.validate(q, files=False))
    q = copy.deepcopy(proj)
    q.ortho.method = "world"
    q.ortho.gcp_world_m = [[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [0.0, 5.0]]
    assert "ortho.gcp_world_m" in _keys(q, files=False)


def test_fifo_directory_and_missing_files(proj, tmp_path):
    fifo = tmp_path / "pipe.mp4"
    os.mkfifo(fifo)
    proj.video.path = str(fifo)
    msg = {p.key: p.message for p in V.validate(proj)}["video.path"]
    assert "pipe" in msg  # and it returned: the FIFO was never opened
    proj.video.path = "river.mp4"
    proj.cross_section.path = str(tmp_path)
    assert "folder" in {p.key: p.message for p in V.validate(proj)}["cross_section.path"]
    proj.cross_section.path = str(tmp_path / "none.csv")
    assert "not found" in {p.key: p.message for p in V.validate(proj)}["cross_section.path"]


def test_filters_nesting_and_background_memory(proj):
    deep: list = []
    for _ in range(5000):
        deep = [deep]
    proj.filters = [{"name": "clahe", "x": deep}]
    assert "filters" in _keys(proj, files=False) or "filters[0]" in _keys(proj, files=False)
    proj.filters = [{"name": "background", "method": "median", "samples": 201}]
    probs = {p.key: p.message for p in V.validate(proj)}
    assert "GiB" in probs["filters[0].samples"]  # 201 x 1280x720 float32, x3 for the median: > 1.5 GB
    proj.filters = [{"name": "background", "method": "median", "samples": 25}]
    assert V.validate(proj) == []


def test_stable_region_on_the_water_is_refused(proj):
    a, b = proj.section.points_px
    mid = [(a[0] + b[0]) / 2, (a[1] + b[1]) / 2]
    proj.stabilize.enabled = True
    proj.stabilize.regions_px = [[mid[0] - 20, mid[1] - 20, mid[0] + 20, mid[1] + 20]]
    assert "stabilize.regions_px[0]" in _keys(proj, files=False)
    proj.stabilize.regions_px = [[0.0, 0.0, 40.0, 40.0]]
    assert "stabilize.regions_px[0]" not in _keys(proj, files=False)


def test_dem_header_bounded_before_reading(proj, tmp_path):
    import struct

    path = tmp_path / "huge.tif"
    # a hand-made TIFF header that claims 100000 x 100000 float32 pixels in one deflated strip of 16 bytes
    tags = [
        (256, 4, 100000),
        (257, 4, 100000),
        (258, 3, 32),
        (259, 3, 8),
        (262, 3, 1),
        (273, 4, 8),
        (277, 3, 1),
        (278, 4, 100000),
        (279, 4, 16),
        (339, 3, 3),
    ]
    ifd = (
        struct.pack("<H", len(tags))
        + b"".join(
            struct.pack("<HHI", t, typ, 1) + (struct.pack("<HH", v, 0) if typ == 3 else struct.pack("<I", v))
            for t, typ, v in tags
        )
        + struct.pack("<I", 0)
    )
    path.write_bytes(b"II*\x00" + struct.pack("<I", 24) + bytes(16) + ifd)
    proj.water_level.method = "dem"
    proj.water_level.dem_path = str(path)
    proj.water_level.dem_x_m = [0.0, 1.0]
    proj.water_level.dem_y_m = [0.0, 1.0]
    proj.water_level.dem_precision_mm = 1.0
    msg = {p.key: p.message for p in V.validate(proj)}["water_level.dem_path"]
    assert "100000x100000" in msg
