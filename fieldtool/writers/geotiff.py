"""The rectified first frame as a GeoTIFF (``rectified.tif``), written with rasterio, when the GCPs
carry a coordinate reference system (``ortho.crs_epsg``).

Only ``ortho.method = world`` and ``pose`` take GCP coordinates the user surveyed (in that CRS);
``distances`` builds a local frame (P4 at the origin, P1 on +Y) and ``none`` a scale only, so
with those methods a CRS cannot place the image and no GeoTIFF is written (a warning says why).

Georeferencing: the map is north-up, pixel (col, row) centre at X = Xmin + col * r,
Y = Ymax - row * r (r = cell size, m); the GeoTIFF transform is that of the pixel *corners*:
``Affine(r, 0, Xmin - r/2, 0, -r, Ymax + r/2)``. Extent: the image footprint clipped to 3x the GCP
extent; cell size ``ortho.resolution_m`` or automatic (longer side 2000 px). Pixels outside the
frame are 0 and flagged as nodata by an alpha band.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from fieldtool.errors import ParameterError
from fieldtool.project.model import atomic_path

GEOREF_METHODS = ("world", "pose")

# PROJ projection names -> CF grid_mapping_name, and PROJ parameters -> CF attributes
_CF_NAMES = {
    "tmerc": "transverse_mercator",
    "utm": "transverse_mercator",
    "sterea": "stereographic",
    "stere": "stereographic",
    "lcc": "lambert_conformal_conic",
    "merc": "mercator",
    "laea": "lambert_azimuthal_equal_area",
    "aea": "albers_conical_equal_area",
    "omerc": "oblique_mercator",
}


def _rasterio():
    """rasterio, imported on first use: it costs 0.1-0.3 s to import (GDAL) and only a project with a CRS needs it."""
    import rasterio

    return rasterio


def check_crs(epsg: int | None, method: str):
    """The rasterio CRS of ``ortho.crs_epsg`` (None when not set); ParameterError when unusable."""
    if epsg is None:
        return None
    rasterio = _rasterio()
    CRS, CRSError = rasterio.crs.CRS, rasterio.errors.CRSError
    if isinstance(epsg, bool) or not isinstance(epsg, int) or epsg <= 0:
        raise ParameterError(
            f"ortho.crs_epsg: {epsg!r} is not an EPSG code; give a whole number such as 28992 or "
            "32631, or leave the key out"
        )
    try:
        crs = CRS.from_epsg(epsg)
    except CRSError:
        raise ParameterError(
            f"ortho.crs_epsg: EPSG:{epsg} is not a known coordinate reference system; check the "
            "code (e.g. 28992 Amersfoort / RD New, 326zz WGS 84 / UTM zone zz N)"
        ) from None
    if not crs.is_projected or (crs.linear_units or "").lower() not in ("metre", "meter", "m"):
        raise ParameterError(
            f"ortho.crs_epsg: EPSG:{epsg} is not a projected system in metres (the GCP "
            "coordinates and the mapping are metres); use the projected CRS of the survey"
        )
    return crs


def crs_of(project):
    """The CRS the world coordinates of this project are in, or None (not given / a local frame)."""
    o = project.ortho
    if o.crs_epsg is None or o.method not in GEOREF_METHODS:
        return None
    return check_crs(o.crs_epsg, o.method)


def cf_grid_mapping(crs) -> dict:
    """CF grid-mapping attributes of a projected CRS: ``crs_wkt`` and ``spatial_ref`` (read by GDAL and
    xarray), the EPSG code, and the CF projection parameters PROJ gives for the common projections."""
    attrs = {"crs_wkt": crs.to_wkt(), "spatial_ref": crs.to_wkt(), "epsg_code": f"EPSG:{crs.to_epsg()}"}
    d = crs.to_dict()
    name = _CF_NAMES.get(str(d.get("proj", "")))
    if name:
        attrs["grid_mapping_name"] = name
    if d.get("proj") == "utm":
        zone = int(d.get("zone", 0))
        attrs.update(
            longitude_of_central_meridian=zone * 6.0 - 183.0,
            latitude_of_projection_origin=0.0,
            scale_factor_at_central_meridian=0.9996,
            false_easting=500000.0,
            false_northing=10000000.0 if d.get("south") else 0.0,
        )
    else:
        central = (
            "longitude_of_central_meridian"
            if name in ("transverse_mercator", "lambert_conformal_conic", "albers_conical_equal_area")
            else "longitude_of_projection_origin"
        )
        scale = (
            "scale_factor_at_central_meridian" if name == "transverse_mercator" else "scale_factor_at_projection_origin"
        )
        for k, cf in (
            ("lon_0", central),
            ("lat_0", "latitude_of_projection_origin"),
            ("k", scale),
            ("k_0", scale),
            ("x_0", "false_easting"),
            ("y_0", "false_northing"),
        ):
            if k in d:
                attrs[cf] = float(d[k])
        if "lat_1" in d:
            attrs["standard_parallel"] = [float(d[k]) for k in ("lat_1", "lat_2") if k in d]
    for k, cf in (("a", "semi_major_axis"), ("rf", "inverse_flattening")):
        if k in d:
            attrs[cf] = float(d[k])
    return attrs


def rectified_map(result, inputs, resolution_m: float | None = None) -> tuple[np.ndarray, float, float, float]:
    """(RGB map image, cell size r (m), Xmin, Ymax) of the first working frame; pixel centres as in the
    module docstring."""
    img = inputs.first_color
    if inputs.lens is not None:
        img = inputs.lens.undistort(img)
    rgb = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    m = result.mapping
    mapped, A = m.rectified_image(rgb, resolution_m=resolution_m, max_side_px=2000)
    r = 1.0 / A[0, 0]
    return mapped, r, -A[0, 2] * r, A[1, 2] * r


def write_rectified(result, project, inputs, out: Path) -> str | None:
    """Write ``rectified.tif`` into ``out`` when the project gives a CRS; returns its name (or None)."""
    o = project.ortho
    if o.crs_epsg is None:
        return None
    crs = crs_of(project)
    if crs is None:
        result.warnings.append(
            f"ortho.crs_epsg = {o.crs_epsg} is not used: ortho.method = {o.method} builds a local "
            "frame; use method = world with the GCP coordinates in that CRS for a GeoTIFF"
        )
        return None
    rasterio = _rasterio()
    Affine = rasterio.transform.Affine
    img, r, x0, y1 = rectified_map(result, inputs, o.resolution_m)
    alpha = np.where(img.any(axis=2), 255, 0).astype(np.uint8)
    transform = Affine(r, 0.0, x0 - r / 2, 0.0, -r, y1 + r / 2)
    path = Path(out) / "rectified.tif"
    with atomic_path(path) as tmp:
        with rasterio.open(
            tmp,
            "w",
            driver="GTiff",
            width=img.shape[1],
            height=img.shape[0],
            count=4,
            dtype="uint8",
            crs=crs,
            transform=transform,
            compress="deflate",
            photometric="RGB",
            tiled=True,
        ) as dst:
            for b in range(3):
                dst.write(img[..., b], b + 1)
            dst.write(alpha, 4)
            dst.colorinterp = [
                rasterio.enums.ColorInterp.red,
                rasterio.enums.ColorInterp.green,
                rasterio.enums.ColorInterp.blue,
                rasterio.enums.ColorInterp.alpha,
            ]
            dst.update_tags(
                TIFFTAG_SOFTWARE="fieldtool",
                title=f"rectified first frame — {project.name}",
                cell_size_m=f"{r:.6g}",
                ortho_method=o.method,
            )
    return path.name
