"""Run the steps of a Project in order (thesis figure 9.1) and write the results.

The run is a sequence of named stages, each a module of fieldtool/run/ with explicit inputs and a dataclass
out:

1. inputs (run/inputs.py): cross-section, clip, lens model -> :class:`Inputs`
2. level and mapping (run/geometry.py): water level, image -> water-plane mapping
3. section(s) (run/geometry.py): the main section, ROI and masks -> ``Sections``
4. frames (run/frames.py): undistorted, stabilised, filtered working frames, streamed
5. velocimetry (run/velocimetry.py; rounds of pairs in run/piv_rounds.py, cache in run/piv_cache.py, STIV in
   run/stiv_stage.py, the camera check at the GCPs in run/camera.py) -> ``PivSetup``, ``Velocimetry``
6. discharge (run/discharge.py) -> ``Discharge``
7. quality and uncertainty (run/quality.py, run/assess.py) -> ``Verdict``
8. outputs (run/outputs.py; figures drawn meanwhile in plots/prerender.py) -> files, :class:`RunResult`

``run_project`` runs them and owns what is shared: ``progress(stage, done, total)``, ``cancel() -> bool``,
the ``Observer`` (the rerun logger is one), the timings and the exit stack; it never prints. The TUI runs
single stages by calling their modules.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from pathlib import Path

from fieldtool.project import sections
from fieldtool.project.model import Project
from fieldtool.project.validation import check
from fieldtool.run import camera, discharge, geometry, outdir, outputs, overlay_stage, quality, velocimetry
from fieldtool.run.inputs import load_inputs
from fieldtool.run.observer import Guarded, Observer, Progress
from fieldtool.run.result import RunResult
from fieldtool.writers import check as check_outputs


class _Laps:
    """Seconds each stage took, as result.json's ``timings_s``."""

    def __init__(self) -> None:
        self.timings: dict[str, float] = {}
        self.t0 = time.perf_counter()

    def __call__(self, name: str) -> None:
        now = time.perf_counter()
        self.timings[name] = round(now - self.t0, 3)
        self.t0 = now


def run_project(
    project: Project,
    out_dir: Path | str | None = None,
    *,
    progress: Progress | None = None,
    cancel: Callable[[], bool] | None = None,
    observer: Observer | None = None,
) -> RunResult:
    """Run every step of ``project``; write the results to ``out_dir`` when given. The figure process the run
    draws its figures in (``plots.prerender``) ends with the run, whether it succeeds, fails or is cancelled."""
    with contextlib.ExitStack() as ends:
        return _run_project(project, out_dir, progress, cancel, observer, ends)


def _run_project(
    project: Project,
    out_dir: Path | str | None,
    progress: Progress | None,
    cancel: Callable[[], bool] | None,
    observer: Observer | None,
    ends,
) -> RunResult:
    """:func:`run_project`; ``ends`` (a contextlib.ExitStack) takes what must be closed when the run ends."""
    warnings: list[str] = []
    overlay = overlay_stage.start(project, out_dir, ends)  # [overlay] enabled: overlay.mp4 drawn as frames stream
    obs = Guarded(overlay_stage.fan_out(observer, overlay, warnings), warnings)
    lap = _Laps()
    # the output folder's lock, checks and staging folder (run/outdir.py): everything, the PIV cache too, is
    # written there and swapped in as a unit at the end
    stage = ends.enter_context(outdir.claim(out_dir, project)) if out_dir is not None else None
    if out_dir is not None:
        outputs.start_figures()  # the figure process, forked before this run starts any thread
    warnings += [str(w) for w in check(project)]  # every key, before any step
    extra = sections.parse(project)
    obs("stage", "inputs")
    check_outputs(project)  # a wrong ortho.crs_epsg stops the run before any work
    inputs = load_inputs(project)
    if inputs.source.clock_said:  # slow motion or time-lapse (processing/frames.py filming_clock)
        warnings.append(f"video: {inputs.source.clock_said}")
    lap("inputs")

    obs("stage", "water_level")
    level, mapping = geometry.level_and_mapping(project, inputs)
    lap("level_and_ortho")
    # the input figures are drawn while the PIV is set up (its look at the clip leaves a core partly idle)
    prerendered = outputs.start_prerender(project, inputs, level, mapping, out_dir, ends)

    placed = geometry.place_sections(project, inputs, level.level_m, mapping, extra)
    setup = velocimetry.setup(project, inputs, mapping, placed, warnings, obs)
    project = setup.project  # stabilised on the GCPs where the camera moved and the user did not (run/camera.py)
    pairs = discharge.PairDischarge(mapping, inputs.cross_section, level.level_m, project.section.alpha)
    overlay_stage.bind(overlay, inputs, mapping, placed.geom)
    obs("geometry", pairs.on(placed.geom))
    obs("stage", "piv")
    # the pixel-space field is reused when only the mapping, level, section or alpha changed (not while
    # streaming to an observer, who wants to see the frames and pairs)
    cache_dir = Path(out_dir) if out_dir is not None and observer is None else None
    with camera.explained(setup.camera):  # a registration the camera check chose, failing later, says so
        vel = velocimetry.measure_velocity(
            project,
            inputs,
            setup,
            pairs.on(placed.geom),
            cache_dir,
            stage.path if stage is not None else None,
            cancel,
            obs,
            progress,
            warnings,
            overlay,
        )
    rest = camera.Later(setup.camera, inputs)  # did the GCPs that stayed put at first stay put in the clip?
    lap("frames_and_piv")

    obs("stage", "discharge")
    q = discharge.compute_discharge(project, inputs, level.level_m, mapping, placed.geom, setup, vel, pairs, warnings)
    # the field's figure is drawn during STIV's analysis; the discharge's figures too where the discharge is the
    # PIV's, else during the Monte Carlo, after STIV's analysis has said whether it is STIV's or the combined one
    # (velocity_source "auto": combined where the two agree)
    outputs.prerender_field(prerendered, inputs, mapping, vel, q)
    piv_q = project.section.velocity_source == "piv" or setup.stiv_run is None
    if piv_q:
        outputs.prerender_velocity(prerendered, inputs, mapping, vel, q)
    q = discharge.add_stiv(q, project, inputs, level.level_m, setup, vel)
    rest.join(warnings, q.robust)  # robust.camera with the rest of the clip, before the verdict reads it
    lap("discharge")
    if not piv_q:
        outputs.prerender_velocity(prerendered, inputs, mapping, vel, q)
    verdict = quality.judge(project, inputs, level, mapping, vel, q, pairs, extra, warnings)
    lap("uncertainty_and_quality")

    result = outputs.build_result(project, level, mapping, vel, q, verdict, lap.timings, warnings, prerendered, overlay)
    if out_dir is not None:
        outputs.write_outputs(result, project, inputs, Path(out_dir))
    obs("result", result)
    return result
