"""Stage 8, the outputs: result.json, subsections.csv, mean_field.npz/.npy, the standard files (NetCDF,
GeoTIFF, video metadata) and the figures, staged in a folder beside the output folder and swapped in at
once (run/outdir.py), so a run that fails or is killed leaves the previous results as they were.

The figures are drawn in the figure process (plots/prerender.py) while the run works; :func:`start_figures`
forks it and warms the imports the outputs need, and :func:`write_outputs` copies what it drew, drawing a
figure itself only when the process did not."""

from __future__ import annotations

import importlib
import io
import json
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from fieldtool.errors import FieldToolError
from fieldtool.plots import prerender
from fieldtool.processing.discharge import DischargeResult
from fieldtool.processing.piv import PivResult
from fieldtool.processing.piv_engine import PivParams
from fieldtool.project.model import Project, atomic_write_bytes, project_to_dict
from fieldtool.run import outdir, overlay_stage, stiv_stage
from fieldtool.run.discharge import Discharge
from fieldtool.run.inputs import Inputs
from fieldtool.run.outdir import strict_json
from fieldtool.run.quality import Verdict
from fieldtool.run.result import RunResult
from fieldtool.run.velocimetry import Velocimetry
from fieldtool.writers import write_standard


def start_figures() -> None:
    """Fork the figure process (plots.prerender) before the run starts any thread, and import in a thread
    what the outputs need while the PIV waits for its frames: scipy.spatial (~0.1 s, the NetCDF grid), and
    matplotlib (~0.5 s) where no figure process draws the figures."""
    prerender.start()
    modules = ("scipy.spatial",) if prerender.can_fork() else ("fieldtool.plots.discharge", "scipy.spatial")
    threading.Thread(target=lambda: [importlib.import_module(m) for m in modules], daemon=True).start()


def write_outputs(result: RunResult, project: Project, inputs: Inputs, out: Path) -> None:
    """result.json, subsections.csv, mean_field.npz/.npy and the PNG plots, each written atomically."""
    t0 = time.perf_counter()
    with outdir.claim(out, project) as stage:  # the run's own claim (run_project), or one for this call alone
        _write_outputs(result, inputs, stage.path)
        write_standard(result, project, inputs, stage.path)  # mean_field.nc, rectified.tif (with a CRS), video metadata
        overlay_stage.finish(result, stage.path)  # overlay.mp4: closing card, file closed and moved in
        _write_figures(result, inputs, stage.path)  # last: the figure process draws them meanwhile
        result.timings_s["outputs"] = round(time.perf_counter() - t0, 3)  # all but result.json itself
        _write_result_json(result, stage.path)
        stage.commit()
    result.out_dir = out


def _write_result_json(result: RunResult, out: Path) -> None:
    """result.json, strict JSON: a non-finite number is written as null and named in the warnings."""
    extra: list[str] = []
    summary = strict_json(result.summary(), extra)
    assert isinstance(summary, dict)  # strict_json keeps a dict a dict
    if extra:
        summary["warnings"] = list(summary.get("warnings") or []) + extra
    atomic_write_bytes(
        out / "result.json", json.dumps(summary, indent=2, default=json_default, allow_nan=False).encode()
    )


def _write_outputs(result: RunResult, inputs: Inputs, out: Path) -> None:
    d, p = result.discharge, result.piv
    files = result.files
    lines = [
        "subsection,station_from_m,station_to_m,area_m2,mean_depth_m,surface_velocity_ms,velocity_filled,discharge_m3s,stiv_velocity_ms"
    ]
    stiv_v = stiv_stage.stiv_column(result.stiv, len(d.area_m2))
    for i in range(len(d.area_m2)):
        lines.append(
            f"{i + 1},{d.station_from[i]:.4f},{d.station_to[i]:.4f},{d.area_m2[i]:.5f},{d.mean_depth_m[i]:.4f},"
            f"{d.surface_velocity_ms[i]:.5f},{int(d.velocity_filled[i])},{d.sub_discharge_m3s[i]:.5f},{stiv_v[i]}"
        )
    atomic_write_bytes(out / "subsections.csv", ("\n".join(lines) + "\n").encode())
    files["subsections"] = "subsections.csv"

    XY = result.mapping.image_to_world(np.c_[p.x.ravel(), p.y.ravel()]).reshape(p.x.shape + (2,))
    arrays: dict[str, Any] = dict(
        x_px=p.x,
        y_px=p.y,
        u_px_s=p.u,
        v_px_s=p.v,
        X_m=XY[..., 0],
        Y_m=XY[..., 1],
        U_ms=result.world_u,
        V_ms=result.world_v,
        valid=p.valid,
        valid_fraction=p.valid_fraction,
        H=result.mapping.H,
        water_level_m=np.float64(d.water_level_m),
        discharge_m3s=np.float64(d.discharge_m3s),
    )
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    atomic_write_bytes(out / "mean_field.npz", buf.getvalue())
    buf = io.BytesIO()
    np.save(buf, np.stack([p.x, p.y, XY[..., 0], XY[..., 1], result.world_u, result.world_v], axis=-1))
    atomic_write_bytes(out / "mean_field.npy", buf.getvalue())
    files["mean_field"] = "mean_field.npz"
    files["mean_field_npy"] = "mean_field.npy"
    files["result"] = "result.json"


def _write_figures(result: RunResult, inputs: Inputs, out: Path) -> None:
    """vectors.png, rectified.png, section.png (drawn by the figure process during the Monte Carlo, else here)
    and water_level.png (drawn there during the PIV, else here). matplotlib is imported only to draw here."""
    files = result.files
    pre = result.prerendered
    for key, name, draw in (
        ("vectors_png", "vectors.png", lambda p, f: p.plot_vectors(f, inputs.first_color, result, inputs)),
        ("rectified_png", "rectified.png", lambda p, f: p.plot_rectified(f, inputs.first_color, result, inputs)),
        ("section_png", "section.png", lambda p, f: p.plot_section(f, inputs.cross_section, result)),
    ):
        png = pre.file(name) if pre is not None else None  # drawn by the figure process
        if png:
            atomic_write_bytes(out / name, png)
            files[key] = name
        else:
            files[key] = draw(_plots().discharge, out / name).name
    try:
        png = pre.file("water_level.png") if pre is not None else None
        if png:
            atomic_write_bytes(out / "water_level.png", png)
            files["water_level_png"] = "water_level.png"
        else:
            files["water_level_png"] = (
                _plots().water_level.plot_level(out / "water_level.png", inputs.cross_section, result.level).name
            )
    except FieldToolError as e:
        result.warnings.append(f"water-level plot not written: {e}")


def json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _plots():
    """fieldtool.plots with its discharge and water_level modules, imported only when a figure is drawn in this
    process rather than in the figure process (matplotlib: ~0.5 s)."""
    from fieldtool.plots import discharge, water_level  # lazy: matplotlib, only for a figure drawn here

    return SimpleNamespace(discharge=discharge, water_level=water_level)


def start_prerender(project: Project, inputs: Inputs, level, mapping, out_dir, ends) -> prerender.Prerender | None:
    """Start drawing the figures of the inputs in the figure process (during the PIV) when the run writes
    ``out_dir``; ``ends`` (a contextlib.ExitStack) closes it when the run ends. None without an output folder."""
    if out_dir is None:
        return None
    prerendered = prerender.Prerender(project, inputs, level, mapping, warm=(PivResult, DischargeResult, PivParams))
    ends.callback(prerendered.close)
    return prerendered


def prerender_field(prerendered, inputs: Inputs, mapping, vel: Velocimetry, q: Discharge) -> None:
    """Hand the field's figure (the PIV's velocities, m/s on the water plane) to the figure process as soon as
    they are on the water plane, drawn there during STIV's analysis; nothing when nothing was measured or no folder
    is written."""
    if q.unmeasured is None and prerendered is not None:
        prerendered.field(inputs, vel.piv, q.world_u, q.world_v, q.geom, mapping)


def prerender_velocity(prerendered, inputs: Inputs, mapping, vel: Velocimetry, q: Discharge) -> None:
    """Hand the velocity figures (m/s on the water plane, the section's discharge in m³/s) to the figure
    process, drawn there while the Monte Carlo runs; nothing when nothing was measured or no folder is written."""
    if q.unmeasured is None and prerendered is not None:
        prerendered.results(inputs, q.result, vel.piv, q.world_u, q.world_v, q.geom, mapping, inputs.cross_section)


def build_result(
    project: Project,
    level,
    mapping,
    vel: Velocimetry,
    q: Discharge,
    verdict: Verdict,
    timings_s: dict[str, float],
    warnings: list[str],
    prerendered,
    overlay,
) -> RunResult:
    """The run's :class:`RunResult` from its stages' outputs (discharge m³/s, level m, velocities m/s, stage
    timings s); no output folder set (``out_dir`` None) and no video metadata yet: the writers add them."""
    return RunResult(
        q.result,
        q.q_pairs,
        level,
        mapping,
        vel.piv,
        q.geom,
        q.world_u,
        q.world_v,
        None,
        timings_s=timings_s,
        warnings=warnings,
        stabilization=vel.stabilization or None,
        project=project_to_dict(project),
        piv_reused=vel.reused,
        uncertainty=verdict.uncertainty,
        quality=verdict.quality,
        sections=verdict.sections,
        robust=q.robust,
        stiv=q.stiv,
        piv_fast=vel.fast,
        prerendered=prerendered,
        uncertainty_standard=verdict.standard,
        overlay=overlay,
    )
