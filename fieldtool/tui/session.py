"""The measurement being edited: the Project, its file, and what was computed from it.

Every change is written to the project file at once (atomically, merged with other editors by
``project.sync``). Results are the files of the last run in ``out/`` beside the project file;
``result.json`` carries the inputs that made it, so a result whose inputs have changed since is known to
be stale, even after the project is closed and opened again.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fieldtool.errors import FieldToolError, InputFileError
from fieldtool.processing.filters import FilterStack
from fieldtool.project.model import Project, project_to_dict
from fieldtool.project.sync import ProjectSync, SaveResult, adopt
from fieldtool.run.inputs import load_inputs
from fieldtool.tui.checks import CoreChecks, is_missing
from fieldtool.tui.fields import field_errors
from fieldtool.tui.jobs import PREVIEW_DIR, cached_piv
from fieldtool.tui.steps import PIV_TABLES, STEP_IDS, STEPS, calibration_mode, fields_for, step_problems

IGNORED_KEYS = ("name", "step", "rerun", "site", "station", "operator", "viewer", "overlay")  # no effect on Q


@dataclass
class LastResult:
    """What the last run wrote: result.json's summary and subsections.csv's rows."""

    summary: dict
    subsections: list[dict] = field(default_factory=list)


class Session:
    """One project file open in the TUI."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path).resolve()
        self.sync = ProjectSync(self.path)  # the file as this session last read or wrote it (three-way merge)
        if self.path.exists():
            self.project = self.sync.load()
        else:
            self.project = Project(name=self.path.parent.name or "measurement", root=self.path.parent)
            self.save()
        if self.project.step not in STEP_IDS:
            self.project.step = STEP_IDS[0]
        self.ui: dict[str, Any] = {"calibration_mode": calibration_mode(self.project)}
        self._inputs_key: str | None = None
        self._inputs = None
        self.piv_preview: dict | None = None  # PIV-only run: {"inputs": tables, "stats": {...}}
        self.calibration_run: dict | None = None  # {"inputs": calibration table, "rms_px":, "fov_deg":}
        self.core = CoreChecks()
        self.mark_reasons: dict[str, str] = {}  # step -> first message, for the sidebar's ✗ and ·
        self._cache_looked: str | None = None  # PIV tables the PIV cache was last looked up for

    # -- file --------------------------------------------------------------------------------
    def save(self) -> SaveResult:
        """Merge this session's values into the file as it is on disk now (``ProjectSync.save``: per key
        and per point against what this session last read, so a value another program saved meanwhile
        is kept and never put back) and take the merged values in. Raises ``ProjectRefused`` (file
        invalid or read-only: nothing written) or OSError; the entries stay in ``self.project``."""
        res = self.sync.save(self.project)
        adopt(self.project, res.project)
        return res

    def poll(self) -> SaveResult | None:
        """The file's change by another program since the last read or write, merged into this
        session's values (None when unchanged or invalid: ``self.sync.error`` says why)."""
        res = self.sync.poll(self.project)
        if res is not None:
            adopt(self.project, res.project)
        return res

    @property
    def out_dir(self) -> Path:
        return self.project.root / "out"

    # -- inputs (cross-section, clip, lens), cached on their tables ------------------------------
    def inputs(self):
        """run.inputs.Inputs for the current project; loaded again only when their tables change."""
        d = project_to_dict(self.project)
        key = json.dumps([d.get(t) for t in ("video", "cross_section", "calibration")], sort_keys=True)
        if key != self._inputs_key:
            self._inputs = None
            self._inputs = load_inputs(self.project)
            self._inputs_key = key
        return self._inputs

    # -- results and staleness ----------------------------------------------------------------
    def last_result(self) -> LastResult | None:
        """The last run's result files, or None when there are none (or they cannot be read)."""
        rj = self.out_dir / "result.json"
        if not rj.is_file():
            return None
        try:
            summary = json.loads(rj.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        rows: list[dict] = []
        sc = self.out_dir / "subsections.csv"
        if sc.is_file():
            with sc.open(newline="", encoding="utf-8") as fh:
                rows = list(csv.DictReader(fh))
        return LastResult(summary, rows)

    def changed_tables(self, inputs: dict | None) -> set[str]:
        """Tables whose values differ from ``inputs`` (a project dict saved with a result)."""
        if inputs is None:
            return set()
        now = project_to_dict(self.project)
        keys = (set(now) | set(inputs)) - set(IGNORED_KEYS)
        return {k for k in keys if now.get(k) != inputs.get(k)}

    def result_state(self) -> tuple[str, set[str]]:
        """("none" | "current" | "stale", changed tables) of the last run's results."""
        res = self.last_result()
        if res is None:
            return "none", set()
        changed = self.changed_tables(res.summary.get("inputs"))
        return ("stale" if changed else "current"), changed

    def piv_state(self) -> str:
        """ "none" | "current" | "stale" for the velocity field (last full run or PIV-only run)."""
        self.restore_piv()
        candidates = []
        res = self.last_result()
        if res is not None:
            candidates.append(res.summary.get("inputs"))
        if self.piv_preview is not None:
            candidates.append(self.piv_preview["inputs"])
        if not candidates:
            return "none"
        for inputs in candidates:
            if not (self.changed_tables(inputs) & set(PIV_TABLES)):
                return "current"
        return "stale"

    def restore_piv(self) -> None:
        """Take the PIV field of the current inputs that a PIV-only run saved in the output folder when
        no run of this session has one (a PIV run of an earlier session, quit before a section existed)."""
        if self.piv_preview is not None and not (self.changed_tables(self.piv_preview["inputs"]) & set(PIV_TABLES)):
            return

        if not (self.out_dir / PREVIEW_DIR / "piv_cache.npz").is_file():
            return
        d = project_to_dict(self.project)
        key = json.dumps([d.get(t) for t in PIV_TABLES + ("ortho", "water_level")], sort_keys=True, default=str)
        if key == self._cache_looked:
            return
        self._cache_looked = key

        try:
            found = cached_piv(self.project, self.inputs(), self.out_dir)
        except FieldToolError:
            return
        if found is not None:
            self.piv_preview = found

    def calibration_state(self) -> str:
        if self.ui.get("calibration_mode") != "run":
            return "none"
        if self.calibration_run is None:
            return (
                "stale"
                if not self.project.calibration.path
                or not self.project.resolve(self.project.calibration.path).is_file()
                else "current"
            )
        now = project_to_dict(self.project).get("calibration")
        return "current" if now == self.calibration_run["inputs"] else "stale"

    def step_errors(self, step: str) -> list[str]:
        """Messages of the step's fields on the current project values (no file reading beyond
        checking that named files exist)."""
        if step == "filters":
            try:
                FilterStack.from_config(self.project.filters)
            except FieldToolError as e:
                return [str(e)]
            return []
        if step == "calibration" and self.ui.get("calibration_mode") == "run":
            errs = field_errors(fields_for(step, self.ui), self.project)
            if not errs and self.calibration_state() != "current":
                errs.append(
                    "calibration: run the calibration (ctrl+r) so the lens file exists and matches the settings"
                )
            return errs
        errs = field_errors(fields_for(step, self.ui), self.project)
        return errs + [
            str(pr)
            for pr in step_problems(step, self.project)
            if pr.severity == "error" and not any(e.startswith(pr.key) for e in errs)
        ]

    def step_problems(self, step: str, core: bool = True) -> list[str]:
        """Every message against ``step``: its fields and the validation layer (``step_errors``), then
        (when those pass and ``core``) the core's own check of the step (reads the files: clip range,
        level vs bed ...)."""
        errs = self.step_errors(step)
        if not errs and core:
            msg = self.core.message(self, step)
            if msg:
                errs.append(msg)
        return errs

    def step_marks(self) -> dict[str, str]:
        """Sidebar mark per step: "ok" (validates), "todo" (an entry to make), "invalid" (an entry is
        wrong; the reason in ``mark_reasons``), "stale" (changed since the last result). The core
        check of a step runs only when every step before it validates (else its message would be
        the earlier step's)."""
        state, changed = self.result_state()
        marks: dict[str, str] = {}
        self.mark_reasons = {}
        blocked = False
        for s in STEPS:
            if s.id == "results":
                marks[s.id] = {"none": "todo", "current": "ok", "stale": "stale"}[state]
                continue
            msgs = self.step_problems(s.id, core=not blocked)
            if msgs:
                marks[s.id] = "todo" if all(is_missing(m) for m in msgs) else "invalid"
                self.mark_reasons[s.id] = next((m for m in msgs if not is_missing(m)), msgs[0])
                blocked = True
            elif s.id == "piv":
                marks[s.id] = {"none": "todo", "current": "ok", "stale": "stale"}[self.piv_state()]
            elif state == "stale" and set(s.tables) & changed:
                marks[s.id] = "stale"
            else:
                marks[s.id] = "ok"
        return marks


def open_session(path: Path | str) -> Session:
    """Open (or create) a project; a directory means ``DIR/project.toml``."""
    p = Path(path)
    if p.is_dir():
        p = p / "project.toml"
    if p.suffix.lower() != ".toml":
        raise InputFileError(f"{p}: a project file ends in .toml (or give its folder)")
    return Session(p)
