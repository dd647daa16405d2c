"""Water level (thesis chapter 5): every method against a synthetic scene with known truth.

The scene builders (``dem_scene``, ``nadir_scene``, ``oblique_scene``) are also used by
``benchmarks/water_level_accuracy.py`` to tabulate errors beside the propagated uncertainties.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

from fieldtool.errors import GeometryError, ParameterError
from fieldtool.plots.water_level import plot_level
from fieldtool.processing.cross_section import CrossSection, from_shape
from fieldtool.processing.ortho import from_world_points
from fieldtool.processing.water_level import (
    LevelResult,
    compute_level,
    fov_axis,
    level_from_width,
    level_uncertainty_from_width,
    width_at_level,
)
from fieldtool.project.model import WaterLevelCfg

# ---------------------------------------------------------------------------------------------
# scenes with known truth

# an asymmetric surveyed section (station m, elevation m); at 1.90 m the water runs from 2.000 to 6.8333 m
SECTION = CrossSection(np.array([0.0, 1.5, 3.0, 4.5, 6.0, 7.5, 9.0]), np.array([3.0, 2.2, 1.3, 1.0, 1.4, 2.3, 3.1]))
LEVEL = 1.90
EDGES = (1.5 + 1.5 * (2.2 - LEVEL) / 0.9, 6.0 + 1.5 * (LEVEL - 1.4) / 0.9)


def dem_scene(tmp: Path, bank: str = "left", seed: int = 0) -> tuple[WaterLevelCfg, CrossSection, float]:
    """A bank DEM as SfM gives it: the surveyed bank + 3 mm noise, a hedge-like bump on the bank, and
    over the water the water surface with 15 mm noise (photogrammetry is poor on water)."""
    rng = np.random.default_rng(seed)
    st = np.array([0.0, 0.5, 1.5, 2.5, 3.5, 6.0, 8.0, 10.0])
    el = np.array([2.0, 1.9, 1.6, 1.1, 0.6, 0.5, 1.5, 2.2])
    level = 1.35  # left edge at station 2.0
    if bank == "right":
        st, el = 10.0 - st[::-1], el[::-1]
    cs = CrossSection(st, el)
    pix = 0.01
    x0, x1 = (0.0, 3.0) if bank == "left" else (7.0, 10.0)
    cols, rows = int(round((x1 - x0) / pix)), 80
    xs = x0 + (np.arange(cols) + 0.5) * pix
    bed = np.interp(xs, st, el)
    wet = bed < level
    dem = np.where(wet, level, bed)[None, :] + np.where(wet, 0.015, 0.003) * rng.standard_normal((rows, cols))
    hedge_x = 0.9 if bank == "left" else 9.1  # 1.1 m from the water edge, on the bank
    bump = 0.25 * np.exp(-0.5 * ((xs - hedge_x) / 0.08) ** 2)
    dem += bump[None, :] * rng.uniform(0.7, 1.3, (rows, 1))
    path = tmp / f"dem_{bank}.tif"
    tifffile.imwrite(path, dem.astype(np.float32))
    cfg = WaterLevelCfg(
        method="dem", dem_path=path.name, dem_x_m=[x0, x1], dem_y_m=[0.0, 0.8], dem_precision_mm=10.0, dem_compare_m=2.5
    )
    return cfg, cs, level


def _texture(shape: tuple[int, int], edges_x: tuple[float, float], x0: float, res: float, rng) -> np.ndarray:
    """Top view raster (BGR): textured banks, a blue river band between the two edge X (m)."""
    h, w = shape
    noise = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), 3) * 60
    X = x0 + np.arange(w) * res
    water = (X >= edges_x[0]) & (X <= edges_x[1])
    img = np.empty((h, w, 3), np.float32)
    img[..., 0] = np.where(water, 190, 60)[None, :] + noise * np.where(water, 0.2, 1.0)[None, :]
    img[..., 1] = np.where(water, 120, 115)[None, :] + noise * np.where(water, 0.2, 1.0)[None, :]
    img[..., 2] = np.where(water, 40, 150)[None, :] + noise * np.where(water, 0.2, 1.0)[None, :]
    return np.clip(img, 0, 255).astype(np.uint8)


def _plane_homography(K, R, C, z_w):
    """World plane Z = z_w (X, Y metres) -> image pixels."""
    t = -R @ C
    return K @ np.column_stack([R[:, 0], R[:, 1], R[:, 2] * z_w + t])


def _render(K, R, C, z_w, size, edges_x, rng, extent=(-8.0, 17.0, -10.0, 14.0), res=0.015):
    x0, x1, y0, y1 = extent
    shape = (int((y1 - y0) / res), int((x1 - x0) / res))
    tex = _texture(shape, edges_x, x0, res, rng)
    A = np.array([[res, 0, x0], [0, -res, y1], [0, 0, 1]])  # raster px -> world X, Y
    return cv2.warpPerspective(tex, _plane_homography(K, R, C, z_w) @ A, size, flags=cv2.INTER_LINEAR)


def _project(K, R, C, pts_world):
    p = (K @ (R @ (np.asarray(pts_world, float) - C).T)).T
    return p[:, :2] / p[:, 2:3]


def nadir_scene(
    tmp: Path,
    yaw_deg: float = 15.0,
    seed: int = 1,
    noise_px: float = 0.5,
    shift_m: float = 0.7,
    h_low: float = 7.0,
    dh: float = 4.0,
):
    """Two nadir images (1280x960, FOV_x 70 deg, pinhole) of the SECTION river at LEVEL from heights
    h_low and h_low + dh, the camera ``shift_m`` off the river centre across and 0.4 m along it,
    turned by ``yaw_deg`` so that the section runs at that angle in the image. Edges picked = the
    projected true edges + N(0, noise_px)."""
    rng = np.random.default_rng(seed)
    w, h = 1280, 960
    f = (w / 2) / np.tan(np.radians(70) / 2)
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
    fov = (70.0, float(np.degrees(2 * np.arctan(h / 2 / f))), float(np.degrees(2 * np.arctan(np.hypot(w, h) / 2 / f))))
    ps = np.radians(yaw_deg)
    R = np.array([[np.cos(ps), np.sin(ps), 0], [np.sin(ps), -np.cos(ps), 0], [0, 0, -1.0]])
    centre = 0.5 * (EDGES[0] + EDGES[1])
    names, edges = [], []
    for k, hh in enumerate((h_low, h_low + dh)):
        C = np.array([centre + shift_m, 0.4, LEVEL + hh])
        img = _render(K, R, C, LEVEL, (w, h), EDGES, rng)
        name = f"nadir_{k + 1}.jpg"
        cv2.imwrite(str(tmp / name), img, [cv2.IMWRITE_JPEG_QUALITY, 92])
        names.append(name)
        px = _project(K, R, C, [[EDGES[0], 0.0, LEVEL], [EDGES[1], 0.0, LEVEL]])
        edges.append((px + rng.normal(0, noise_px, px.shape)).tolist())
    cfg = WaterLevelCfg(
        method="angle_height",
        image1=names[0],
        image2=names[1],
        dh_m=dh,
        edges1_px=edges[0],
        edges2_px=edges[1],
        pixel_uncertainty_px=noise_px,
        dh_uncertainty_m=0.02,
        fov_uncertainty_deg=0.1,
    )
    return cfg, fov, EDGES[1] - EDGES[0]


def oblique_scene(tmp: Path, seed: int = 2, noise_px: float = 0.5, raw_offset_px=(0.0, 0.0)):
    """An oblique 1280x720 view of the SECTION river from a camera 5 m above the water,
    12 m downstream of the section; six GCPs on the water plane; the section at Y = 3 m. The "raw
    frame" pixels are the working pixels + ``raw_offset_px`` (a stand-in for lens distortion)."""
    rng = np.random.default_rng(seed)
    w, h = 1280, 720
    K = np.array([[1000.0, 0, (w - 1) / 2], [0, 1000.0, (h - 1) / 2], [0, 0, 1]])
    C = np.array([4.4, -9.0, LEVEL + 5.0])
    target = np.array([4.4, 4.0, LEVEL])
    zc = (target - C) / np.linalg.norm(target - C)
    xc = np.cross(zc, [0, 0, 1.0])
    xc /= np.linalg.norm(xc)
    yc = np.cross(zc, xc)
    R = np.vstack([xc, yc, zc])
    img = _render(K, R, C, LEVEL, (w, h), EDGES, rng)
    gcp_world = np.array([[0.5, 0.0], [8.5, 0.0], [8.5, 7.0], [0.5, 7.0], [0.8, 3.5], [8.2, 3.5]])
    gcp_px = _project(K, R, C, np.c_[gcp_world, np.full(len(gcp_world), LEVEL)]) + rng.normal(0, 0.3, (6, 2))
    mapping = from_world_points(gcp_px, gcp_world, (h, w))
    px = _project(K, R, C, [[EDGES[0], 3.0, LEVEL], [EDGES[1], 3.0, LEVEL]]) + rng.normal(0, noise_px, (2, 2))
    cfg = WaterLevelCfg(
        method="image", edges_px=(px + np.asarray(raw_offset_px)).tolist(), pixel_uncertainty_px=noise_px
    )
    return cfg, mapping, img, px


# ---------------------------------------------------------------------------------------------
# width -> level and its failure cases


def test_level_from_width_known_section():
    # V with a flat bed: bottom 2 m wide at 1.0 m, sides 2 m across per metre up
    cs = CrossSection(np.array([0.0, 4, 6, 10]), np.array([3.0, 1, 1, 3]))
    assert level_from_width(cs, 5.0) == pytest.approx(1.75)
    assert level_from_width(cs, 10.0) == pytest.approx(3.0)
    assert level_uncertainty_from_width(cs, 1.75, 0.04) == pytest.approx(0.01)  # d width / d level = 4
    assert level_from_width(SECTION, EDGES[1] - EDGES[0]) == pytest.approx(LEVEL)
    assert width_at_level(SECTION, LEVEL) == pytest.approx(EDGES[1] - EDGES[0])


def test_too_wide_raises_clear_error():
    with pytest.raises(GeometryError, match=r"wider than the banks.*only 8\.812 m wide"):
        level_from_width(SECTION, 12.0)


def test_rectangular_section_raises_many_levels():
    cs = from_shape("rectangular", top_width_m=5.0, depth_m=1.5, bank_elevation_m=10.0)
    with pytest.raises(GeometryError, match=r"every level from 8\.500 m to 10\.000 m gives this width.*rectangular"):
        level_from_width(cs, 5.0)
    with pytest.raises(GeometryError, match="vertical walls"):
        level_from_width(cs, 4.8)


def test_narrower_than_flat_bed_raises():
    cs = from_shape("trapezoidal", top_width_m=10, bottom_width_m=4, depth_m=2)
    with pytest.raises(GeometryError, match=r"narrower than the narrowest water surface.*4\.000 m"):
        level_from_width(cs, 3.0)


def test_several_solutions_are_listed():
    # two channels separated by a bar: 2 m is the left channel at 1.5 m and the right channel at 1.862 m
    cs = CrossSection(np.array([0.0, 2, 3, 4, 6, 7, 8, 10]), np.array([3.0, 1, 1, 2, 2.2, 1.5, 1.5, 3]))
    with pytest.raises(GeometryError, match=r"matches 2 levels: 1\.500 m .*; 1\.862 m .*one channel only") as e:
        level_from_width(cs, 2.0)
    assert "value_m" in str(e.value)
    # the whole water surface with the bar submerged is unique
    assert level_from_width(cs, 8.0) == pytest.approx(2.0 + 2.0 / 14.0)


# ---------------------------------------------------------------------------------------------
# methods


def test_typed_value_checked_and_default_uncertainty(tmp_path):
    r = compute_level(WaterLevelCfg(method="value", value_m=LEVEL), SECTION, root=tmp_path)
    assert (r.level_m, r.uncertainty_m, r.method) == (LEVEL, 0.01, "value")
    assert r.width_m == pytest.approx(EDGES[1] - EDGES[0])
    assert "default" in r.details["uncertainty_source"]
    with pytest.raises(GeometryError, match="not a depth"):
        compute_level(WaterLevelCfg(method="value", value_m=0.5), SECTION, root=tmp_path)
    with pytest.raises(ParameterError, match="water_level.value_m"):
        compute_level(WaterLevelCfg(method="value"), SECTION, root=tmp_path)


def test_width_method(tmp_path):
    r = compute_level(
        WaterLevelCfg(method="width", width_m=EDGES[1] - EDGES[0], width_uncertainty_m=0.1), SECTION, root=tmp_path
    )
    assert r.level_m == pytest.approx(LEVEL)
    assert r.uncertainty_m == pytest.approx(0.1 / (2 * 1.5 / 0.9))  # each edge moves 1.5/0.9 m per m of level


@pytest.mark.parametrize("bank", ["left", "right"])
def test_dem_method_finds_divergence(tmp_path, bank):
    cfg, cs, level = dem_scene(tmp_path, bank)
    r = compute_level(cfg, cs, root=tmp_path)
    assert r.details["bank"] == bank
    assert abs(r.level_m - level) < 0.02
    edge = 2.0 if bank == "left" else 8.0
    assert abs(r.details["divergence_station_m"] - edge) < 0.05
    assert 0 < r.uncertainty_m < 0.05
    png = plot_level(tmp_path / "dem.png", cs, r)
    assert png.stat().st_size > 10_000


def test_dem_override_and_bad_precision(tmp_path):
    cfg, cs, _ = dem_scene(tmp_path)
    cfg.divergence_station_m = 1.5
    r = compute_level(cfg, cs, root=tmp_path)
    assert r.level_m == pytest.approx(1.6)  # the bed elevation at station 1.5
    assert r.details["overridden"] and r.details["auto_divergence_station_m"] != 1.5
    cfg.dem_precision_mm = 5.0
    with pytest.raises(ParameterError, match="dem_precision_mm = 5 mm/pixel does not match"):
        compute_level(cfg, cs, root=tmp_path)


def test_fov_axis_thresholds():
    assert [fov_axis(a) for a in (0, 29, -20, 170, 31, 59, 61, 90, -100)] == [
        "x",
        "x",
        "x",
        "x",
        "diag",
        "diag",
        "y",
        "y",
        "y",
    ]


@pytest.mark.parametrize("yaw", [15.0, 45.0, 75.0])
def test_angle_height_on_rendered_nadir_pair(tmp_path, yaw):
    cfg, fov, width = nadir_scene(tmp_path, yaw_deg=yaw)
    # the picked edges sit on the rendered water/bank boundary
    img = cv2.imread(str(tmp_path / cfg.image1))
    e = np.asarray(cfg.edges1_px)
    d = (e[1] - e[0]) / np.linalg.norm(e[1] - e[0])
    for p, s in ((e[0], 1), (e[1], -1)):
        inside = img[tuple(np.round(p + s * 6 * d)[::-1].astype(int))].astype(int)
        outside = img[tuple(np.round(p - s * 6 * d)[::-1].astype(int))].astype(int)
        assert inside[0] > inside[2] and outside[2] > outside[0]
    r = compute_level(cfg, SECTION, root=tmp_path, fov_deg=fov)
    axis = {15.0: "x", 45.0: "diag", 75.0: "y"}[yaw]
    assert r.details["fov_axis"] == [axis, axis]
    assert r.details["solution"] == "off-centre"
    assert abs(r.details["measured_width_m"] / width - 1) < 0.01
    assert abs(r.level_m - LEVEL) < 0.03
    assert abs(r.details["H_m"] - 7.0) < 0.1
    assert abs(r.details["measured_width_m"] - width) < 2 * r.details["width_sigma_m"]


def test_angle_height_offcentre_removes_centred_bias(tmp_path):
    # exact picks, camera 1.5 m off the river centre: the centred closed form (eqs. 5.1-5.2) is
    # biased by more than 1 %, the off-centre solution (figure 5.6) is exact
    cfg, fov, width = nadir_scene(tmp_path, shift_m=1.5, noise_px=0.0)
    r = compute_level(cfg, SECTION, root=tmp_path, fov_deg=fov)
    assert r.details["measured_width_m"] == pytest.approx(width, rel=1e-6)
    assert r.details["H_m"] == pytest.approx(7.0, rel=1e-6)
    assert abs(r.details["centred_width_m"] / width - 1) > 0.01


def test_angle_height_falls_back_to_centred(tmp_path, monkeypatch):
    import fieldtool.processing.water_level as wl

    def fail(*args, **kwargs):
        raise GeometryError("no convergence")

    cfg, fov, width = nadir_scene(tmp_path, shift_m=0.0)
    monkeypatch.setattr(wl, "offcentre_solution", fail)
    r = compute_level(cfg, SECTION, root=tmp_path, fov_deg=fov)
    assert r.details["solution"] == "centred"
    assert r.details["measured_width_m"] == r.details["centred_width_m"]
    assert abs(r.details["measured_width_m"] / width - 1) < 0.01


def test_angle_height_centred_matches_thesis_formula(tmp_path):
    cfg, fov, width = nadir_scene(tmp_path, shift_m=0.0, noise_px=0.0)
    r = compute_level(cfg, SECTION, root=tmp_path, fov_deg=fov)
    assert r.details["measured_width_m"] == pytest.approx(width, rel=1e-6)
    assert r.details["centred_width_m"] == pytest.approx(width, rel=1e-6)
    # for a centred camera L = 2 H tan(alpha / 2): the thesis' two-variable propagation with the
    # correlated term equals the full propagation of dh, FOV and pixel errors
    assert r.details["thesis_width_sigma_m"] == pytest.approx(r.details["width_sigma_m"], rel=0.02)
    assert r.details["width_sigma_m"] > 0


def test_angle_height_fov_from_project_and_errors(tmp_path):
    cfg, fov, width = nadir_scene(tmp_path)
    with pytest.raises(ParameterError, match="field of view"):
        compute_level(cfg, SECTION, root=tmp_path)
    cfg.fov_deg = [fov[0]]  # x alone, square pixels
    r = compute_level(cfg, SECTION, root=tmp_path)
    assert abs(r.details["measured_width_m"] / width - 1) < 0.01 and r.details["fov_source"] == "water_level.fov_deg"
    cfg.edges2_px = cfg.edges2_px[::-1]  # picked right edge first on one image: same answer
    assert compute_level(cfg, SECTION, root=tmp_path).level_m == pytest.approx(r.level_m, abs=1e-9)
    cfg.image1, cfg.image2 = cfg.image2, cfg.image1
    cfg.edges1_px, cfg.edges2_px = cfg.edges2_px, cfg.edges1_px
    with pytest.raises(GeometryError, match="narrower in the higher image"):
        compute_level(cfg, SECTION, root=tmp_path)


def test_image_method_on_rendered_oblique_scene(tmp_path):
    offset = np.array([4.0, -3.0])
    cfg, mapping, img, px = oblique_scene(tmp_path, raw_offset_px=offset)
    e = px
    d = (e[1] - e[0]) / np.linalg.norm(e[1] - e[0])
    for p, s in ((e[0], 1), (e[1], -1)):
        inside = img[tuple(np.round(p + s * 5 * d)[::-1].astype(int))].astype(int)
        outside = img[tuple(np.round(p - s * 5 * d)[::-1].astype(int))].astype(int)
        assert inside[0] > inside[2] and outside[2] > outside[0]
    r = compute_level(cfg, SECTION, root=tmp_path, mapping=mapping, points_transform=lambda p: p - offset)
    assert abs(r.level_m - LEVEL) < 0.03
    assert abs(r.width_m - (EDGES[1] - EDGES[0])) < 0.05
    assert 0 < r.uncertainty_m < 0.05
    with pytest.raises(ParameterError, match="orthorectification"):
        compute_level(cfg, SECTION, root=tmp_path)


def test_plot_every_method(tmp_path):
    for method in ("value", "width", "angle_height", "image"):
        r = LevelResult(LEVEL, EDGES[1] - EDGES[0], 0.02, method, {"water_edges_m": list(EDGES)})
        assert plot_level(tmp_path / f"{method}.png", SECTION, r).stat().st_size > 5_000


def test_unknown_method(tmp_path):
    with pytest.raises(ParameterError, match="not one of value, width, dem, angle_height, image"):
        compute_level(WaterLevelCfg(method="guess"), SECTION, root=tmp_path)


def test_angle_height_undistorts_edges_with_a_calibration(tmp_path):
    """Thesis 5.2.1's pinhole formulas need undistorted pixels: with a barrel lens, the raw picks give a
    width error of several per cent; undistorted with the calibration it vanishes."""
    import cv2

    from fieldtool.processing.calibration import LensModel
    from fieldtool.processing.cross_section import from_shape
    from fieldtool.processing.water_level import compute_level
    from fieldtool.project.model import WaterLevelCfg

    W_img, H_img = 1920, 1080
    K = np.array([[1000.0, 0, (W_img - 1) / 2], [0, 1000.0, (H_img - 1) / 2], [0, 0, 1]])
    dist = np.array([-0.30, 0.05, 0, 0, 0])
    lens = LensModel(K, dist, (W_img, H_img))
    cs = from_shape("trapezoidal", top_width_m=16, bottom_width_m=6, depth_m=2, bank_elevation_m=12.0)
    level = 11.0
    left, right = cs.water_edges(level)
    width = right - left
    H, dh = 18.0, 8.0
    for k, h in enumerate((H, H + dh), 1):
        obj = np.array([[-width / 2 + 0.7, 0.4, h], [width / 2 + 0.7, 0.4, h]])  # 0.7 m off-centre
        px, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), K, dist)
        cv2.imwrite(str(tmp_path / f"img{k}.png"), np.zeros((H_img, W_img), np.uint8))
        if k == 1:
            e1 = px.reshape(2, 2)
        else:
            e2 = px.reshape(2, 2)
    cfg = WaterLevelCfg(
        method="angle_height",
        image1="img1.png",
        image2="img2.png",
        dh_m=dh,
        edges1_px=e1.tolist(),
        edges2_px=e2.tolist(),
    )
    fov = lens.fov_deg()
    raw = compute_level(cfg, cs, root=tmp_path, fov_deg=fov)
    und = compute_level(cfg, cs, root=tmp_path, fov_deg=fov, image_undistort=lens.undistort_points_in)
    err_raw = raw.width_m / width - 1
    err_und = und.width_m / width - 1
    assert abs(err_raw) > 0.02, err_raw  # the thesis' flaw: raw distorted picks
    assert abs(err_und) < 0.002, err_und
    assert abs(und.level_m - level) < 0.01
    assert und.details["edges_undistorted"] and not raw.details["edges_undistorted"]
    # a drone photo at another resolution of the same sensor is scaled, not refused
    half = lens.undistort_points_in(e1 / 2, (H_img // 2, W_img // 2))
    np.testing.assert_allclose(half * 2, lens.undistort_points(e1), atol=1e-6)


def test_dem_from_any_gdal_raster(tmp_path):
    """The DEM is read with GDAL (rasterio): GeoTIFF with a no-data value, an ESRI ASCII grid; a header
    that claims an absurd size is refused before reading."""
    import rasterio
    from affine import Affine

    from fieldtool.errors import InputFileError
    from fieldtool.processing.water_level import read_dem

    z = np.arange(12, dtype=np.float32).reshape(3, 4) + 10
    z[1, 2] = -9999
    tif = tmp_path / "dem.tif"
    with rasterio.open(
        tif,
        "w",
        driver="GTiff",
        width=4,
        height=3,
        count=1,
        dtype="float32",
        nodata=-9999,
        transform=Affine(1, 0, 0, 0, -1, 3),
    ) as ds:
        ds.write(z, 1)
    a = read_dem(tif)
    assert np.isnan(a[1, 2]) and a[0, 0] == 10 and a.shape == (3, 4)
    asc = tmp_path / "dem.asc"
    asc.write_text(
        "ncols 4\nnrows 3\nxllcorner 0\nyllcorner 0\ncellsize 1\nNODATA_value -1\n"
        "10 11 12 13\n14 15 -1 17\n18 19 20 21\n"
    )
    b = read_dem(asc)
    assert np.isnan(b[1, 2]) and b[2, 3] == 21
    huge = tmp_path / "huge.asc"
    huge.write_text("ncols 100000\nnrows 100000\nxllcorner 0\nyllcorner 0\ncellsize 1\n1 2 3\n")
    with pytest.raises(InputFileError, match="100000x100000"):
        read_dem(huge)
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"II*\x00garbage")
    with pytest.raises(InputFileError, match="cannot read"):
        read_dem(bad)
