"""Writers of standard formats beside the run's own files (thesis outputs in formats other tools open).

- ``mean_field.nc``: the time-averaged surface velocity as CF-convention NetCDF (:mod:`.netcdf`);
- ``rectified.tif``: the rectified first frame as a GeoTIFF, only when the GCPs carry a CRS
  (``ortho.crs_epsg``, :mod:`.geotiff`);
- the report's figures ``profile.png`` / ``section_profile.csv`` and ``gcp.png``
  (:mod:`fieldtool.plots.report_figures`), and the clip's metadata in ``result.json`` ``video``.

:func:`write_standard` is the one hook ``run.outputs.write_outputs`` calls; :func:`check` is called
before any work so that a wrong CRS stops the run at once (exit 2).
"""

from __future__ import annotations

from pathlib import Path

from fieldtool.errors import FieldToolError
from fieldtool.project.model import atomic_write_bytes
from fieldtool.records.video_meta import video_info
from fieldtool.writers import geotiff, netcdf
from fieldtool.writers.geotiff import check_crs


def _figures():
    """plots.report_figures, imported only when the figure process did not draw a figure: matplotlib costs
    0.3-0.5 s to import, and a run's own process leaves it to the figure process (plots.prerender)."""
    from fieldtool.plots import report_figures

    return report_figures


def check(project) -> None:
    """ParameterError naming ``ortho.crs_epsg`` when it is not a usable projected CRS in metres."""
    check_crs(project.ortho.crs_epsg, project.ortho.method)


def write_standard(result, project, inputs, out: Path) -> None:
    """Write the standard outputs of a run into ``out`` and list them in ``result.files``.

    A writer that fails (a library missing, a disk error) leaves a warning; the run's own files
    are unaffected.
    """
    try:
        result.video = video_info(project, inputs.source)
    except (OSError, ValueError) as e:
        result.warnings.append(f"video metadata not read: {e}")

    pre = getattr(result, "prerendered", None)  # the figure process' files (plots.prerender), or None
    try:  # the report's figures: velocity profile with its band, GCPs with distances and residuals
        csv, png = (pre.file("section_profile.csv"), pre.file("profile.png")) if pre is not None else (None, None)
        if csv and png:
            atomic_write_bytes(out / "section_profile.csv", csv)
            atomic_write_bytes(out / "profile.png", png)
            result.files["section_profile"], result.files["profile_png"] = "section_profile.csv", "profile.png"
        else:  # drawn here (matplotlib imported only then)
            result.files["section_profile"], result.files["profile_png"] = _figures().write_profile(out, result)
        png = pre.file("gcp.png") if pre is not None else None
        if png:
            atomic_write_bytes(out / "gcp.png", png)
            gcp = "gcp.png"
        else:
            gcp = _figures().write_gcp(out, project, result, inputs)
        if gcp is not None:
            result.files["gcp_png"] = gcp
    except (OSError, ValueError) as e:
        result.warnings.append(f"report figures not written: {e}")
    for key, write in (("netcdf", netcdf.write_mean_field), ("geotiff", geotiff.write_rectified)):
        try:
            name = write(result, project, inputs, out)
        except FieldToolError:
            raise
        except (ImportError, OSError, ValueError, RuntimeError) as e:
            result.warnings.append(f"{key} output not written: {type(e).__name__}: {e}")
            continue
        if name is not None:
            result.files[key] = name
