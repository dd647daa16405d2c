"""Step 10: the discharge with its spread, level, wetted area and width, mean velocity, the
subsection table, and where the plots and files were written. Recomputed when stale."""

from __future__ import annotations

from textual.app import ComposeResult
from textual.markup import escape
from textual.widgets import DataTable, Static

from .. import keys
from .base import StepScreen

# (header, csv column, decimals)
COLUMNS = (("#", "subsection", None), ("from m", "station_from_m", 2), ("to m", "station_to_m", 2),
           ("A m²", "area_m2", 3), ("d m", "mean_depth_m", 2), ("v m/s", "surface_velocity_ms", 3),
           ("Q m³/s", "discharge_m3s", 3))


class ResultsScreen(StepScreen):
    STEP = "results"
    INTRO = "discharge and export"
    BINDINGS = [keys.run("Recompute")]

    def compose_extra(self) -> ComposeResult:
        yield Static("", id="summary")
        yield DataTable(id="subsections", zebra_stripes=True, cursor_type="row")
        yield Static("", id="files")

    def on_mount(self) -> None:
        super().on_mount()
        table = self.query_one(DataTable)
        for label, _, _ in COLUMNS:
            table.add_column(label)
        self.fill()
        state, _ = self.session.result_state()
        if state != "current" and not self.app.job_running():  # type: ignore[attr-defined]
            self.action_run()

    def refresh_view(self) -> None:
        if self.is_mounted and self.query(DataTable):
            self.fill()

    def fill(self) -> None:
        summary = self.query_one("#summary", Static)
        files = self.query_one("#files", Static)
        table = self.query_one(DataTable)
        table.clear()
        res = self.session.last_result()
        state, changed = self.session.result_state()
        if res is None:
            summary.update("no result yet: ctrl+r computes the discharge (every step is used)")
            files.update("")
            table.display = False
            return
        s = res.summary
        stale = ""
        if state == "stale":
            stale = f"[red]! stale: {', '.join(sorted(changed))} changed since; ctrl+r recomputes[/red]\n"
        p05, p95 = s.get("discharge_p05_m3s"), s.get("discharge_p95_m3s")
        spread = f"  (pairs 5-95 %: {p05:.4f} - {p95:.4f})" if p05 is not None and p95 is not None else ""
        unc = s.get("water_level_uncertainty_m")
        unc_t = f" ± {unc:.3f}" if unc else ""
        alpha_t = " default" if s.get("alpha_default") else ""
        summary.update(
            f"{stale}[b]discharge      {s['discharge_m3s']:.4f} m³/s[/b]{spread}\n"
            f"water level    {s['water_level_m']:.3f}{unc_t} m ({s.get('water_level_method', '')})\n"
            f"wetted area    {s['wetted_area_m2']:.3f} m²    width {s['wetted_width_m']:.3f} m\n"
            f"mean velocity  {s['mean_velocity_ms']:.4f} m/s    alpha {s['alpha']:.2f}{alpha_t}")
        table.display = True
        for row in res.subsections:
            vals = []
            for _, key, dec in COLUMNS:
                v = row.get(key, "")
                try:
                    vals.append(v if dec is None else f"{float(v):.{dec}f}")
                except ValueError:
                    vals.append(v)
            if row.get("velocity_filled") == "1":
                vals[5] += "*"
            table.add_row(*vals)
        filled = any(r.get("velocity_filled") == "1" for r in res.subsections)
        note = "* velocity filled from a neighbour\n" if filled else ""
        names = sorted(set((s.get("files") or {}).values()))
        warn = "".join(f"\n[yellow]warning: {escape(w)}[/yellow]" for w in s.get("warnings", []))
        files.update(f"{note}files in out/ beside {self.session.path.name}: {', '.join(names)}{warn}")

    def action_run(self) -> None:
        from .. import jobs

        bad = [st for st in ("cross_section", "video", "calibration", "ortho", "water_level", "roi", "filters", "piv",
                             "section") if self.session.step_errors(st)]
        if bad:
            self.show_errors([f"step '{st}' is not complete: " + self.session.step_errors(st)[0] for st in bad])
            return
        p = jobs.snapshot(self.project)
        out = self.session.out_dir
        self.app.start_job("results", "Discharge", lambda job: jobs.run_full(p, out, job))  # type: ignore[attr-defined]

    def action_next(self) -> None:
        self.notify("this is the last step; ctrl+b goes back, ctrl+p jumps to any step")
