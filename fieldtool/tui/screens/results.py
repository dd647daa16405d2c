"""Step 10: the discharge with its spread, level, wetted area and width, mean velocity, the
subsection table, and where the plots and files were written. Recomputed when stale."""

from __future__ import annotations

from rich.text import Text
from textual.app import ComposeResult
from textual.markup import escape
from textual.widgets import DataTable, Static

from fieldtool.errors import FieldToolError
from fieldtool.project.model import atomic_write_bytes
from fieldtool.records.report import load_result, render_html, render_pdf
from fieldtool.records.report_content import velocities_text
from fieldtool.tui import jobs, keys
from fieldtool.tui.screens.base import StepScreen, fieldtool_app
from fieldtool.tui.steps import MEASUREMENT
from fieldtool.tui.widgets.field_row import FieldRow

# (header, csv column, decimals)
COLUMNS = (
    ("#", "subsection", None),
    ("from m", "station_from_m", 2),
    ("to m", "station_to_m", 2),
    ("A m²", "area_m2", 3),
    ("d m", "mean_depth_m", 2),
    ("v m/s", "surface_velocity_ms", 3),
    ("Q m³/s", "discharge_m3s", 3),
)


GRADE_STYLE = {"good": "green", "doubtful": "yellow", "unusable": "bold red"}


def discharge_lines(s: dict) -> list[str]:
    """Markup lines for Q with its 95 % interval and the quality grade with its reasons (the keys
    ``discharge_ci95_m3s`` and ``quality``; without them the pairs' spread, as older results have)."""
    q = s["discharge_m3s"]
    ci = s.get("discharge_ci95_m3s")
    if isinstance(ci, (list, tuple)) and len(ci) == 2 and all(isinstance(v, (int, float)) for v in ci):
        lo, hi = ci  # the interval is not symmetric about Q: both ends are shown
        lines = [f"[b]discharge      {q:.4f} m³/s[/b]  95 %: {lo:.3f} .. {hi:.3f}"]
    else:
        p05, p95 = s.get("discharge_p05_m3s"), s.get("discharge_p95_m3s")
        spread = f"  [dim](pairs 5-95 %: {p05:.4f} - {p95:.4f})[/dim]" if p05 is not None and p95 is not None else ""
        lines = [f"[b]discharge      {q:.4f} m³/s[/b]{spread}"]
    quality = s.get("quality")
    if isinstance(quality, dict) and quality.get("grade"):
        grade = str(quality["grade"])
        style = GRADE_STYLE.get(grade, "")
        reasons = [
            str(r.get("message", r.get("code", ""))) if isinstance(r, dict) else str(r)
            for r in quality.get("reasons") or []
        ]
        text = f"quality        [{style}]{escape(grade)}[/{style}]" if style else f"quality        {escape(grade)}"
        lines.append(text + (": " + escape("; ".join(reasons)) if reasons else " (no reason for doubt found)"))
    std = s.get("uncertainty_standard")  # ISO 748 and IVE beside the Monte Carlo (issue 27)
    if isinstance(std, dict):
        parts = [
            f"{name} ±{100 * b['u95_rel']:.1f} % ({escape(str(b.get('rating') or '–'))}) "
            f"{b['ci95_m3s'][0]:.3f} .. {b['ci95_m3s'][1]:.3f}"
            for key, name in (("iso748", "ISO 748"), ("ive", "IVE"))
            if isinstance(b := std.get(key), dict) and b.get("ci95_m3s") and b.get("u95_rel") is not None
        ]
        if parts:
            lines.append("standard 2σ    " + "  ·  ".join(parts))
    sm = s.get("sections_summary")
    if isinstance(sm, dict) and sm.get("n"):
        each = ", ".join(
            f"{escape(str(e.get('name')))} {e['discharge_m3s']:.3f}"
            for e in s.get("sections") or []
            if isinstance(e.get("discharge_m3s"), (int, float))
        )
        cv = sm.get("cv")
        lines.append(
            f"sections       mean {sm['mean_m3s']:.3f} m³/s, std {sm['std_m3s']:.3f}, CV {100 * cv:.1f} % ({each})"
            if isinstance(cv, (int, float))
            else f"sections       {each}"
        )
    return lines


def overlay_line(s: dict) -> str:
    """Where the overlay video is, or how to make it (markup)."""
    ov = s.get("overlay")
    name = (s.get("files") or {}).get("overlay")
    if isinstance(ov, dict) and name:
        return (
            f"overlay video  {escape(str(name))}: {ov.get('frames', '?')} frames + {ov.get('card_frames', 0)} of the "
            f"closing card, {ov.get('width_px', '?')}x{ov.get('height_px', '?')} ({ov.get('view', '')} view); "
            "ctrl+l renders it again"
        )
    return "[dim]ctrl+l renders the overlay video (overlay.mp4: vectors, section and Q drawn on the clip)[/dim]"


# the steps a discharge run needs, checked before the run (and the overlay's run) starts
RUN_STEPS = ("cross_section", "video", "calibration", "ortho", "water_level", "roi", "filters", "piv", "section")


class ResultsScreen(StepScreen):
    STEP = "results"
    INTRO = "discharge and export"
    BINDINGS = [keys.run("Recompute"), *keys.RESULTS]

    def compose_extra(self) -> ComposeResult:
        yield Static("", id="summary")
        yield Static("", id="table-hint")
        yield DataTable(id="subsections", zebra_stripes=True, cursor_type="row")
        yield Static("", id="files")
        yield Static(
            Text("The measurement, on the report (ctrl+g writes report.html and report.pdf in out/):", style="bold"),
            id="measurement-head",
        )
        for f in MEASUREMENT:  # below the result: Q and its warnings stay at the top of the 80 x 24 screen
            row = FieldRow(f)
            self.rows.append(row)
            yield row

    def on_mount(self) -> None:
        super().on_mount()
        table = self.query_one(DataTable)
        for label, _, _ in COLUMNS:
            table.add_column(label)
        self.fill()
        state, _ = self.session.result_state()
        if state != "current" and not fieldtool_app(self).job_running():
            self.action_run()

    def focus_first(self) -> None:
        self.query_one(DataTable).focus()

    def focus_help(self, widget) -> str:
        if isinstance(widget, DataTable):
            return (
                "↑ / ↓ / page up / page down scroll the subsections · ctrl+r recomputes · ctrl+l renders the "
                "overlay video · ctrl+b goes back"
            )
        return super().focus_help(widget)

    def refresh_view(self) -> None:
        if self.is_mounted and self.query(DataTable):
            self.fill()

    def computing(self) -> bool:
        """Whether the running job computes the discharge."""
        job = fieldtool_app(self).job
        return job is not None and job.name in ("results", "piv", "overlay")

    def fill(self) -> None:
        summary = self.query_one("#summary", Static)
        files = self.query_one("#files", Static)
        table = self.query_one(DataTable)
        table.clear()
        res = self.session.last_result()
        state, changed = self.session.result_state()
        now = (
            "[b]computing the discharge…[/b] (progress in the status line below; esc cancels)"
            if self.computing()
            else None
        )
        if res is None:
            summary.update(now or "no result yet: ctrl+r computes the discharge (every step is used)")
            files.update("")
            table.display = False
            self.query_one("#table-hint", Static).display = False
            return
        s = res.summary
        head = ""
        if now is not None:
            head = now + "\n"
        elif state == "stale":
            head = f"[red]! stale: {', '.join(sorted(changed))} changed since; ctrl+r recomputes[/red]\n"
        unc = s.get("water_level_uncertainty_m")
        unc_t = f" ± {unc:.3f}" if unc else ""
        alpha_t = " default" if s.get("alpha_default") else ""
        src_t = f"    from {escape(velocities_text(s, short=True))}" if s.get("stiv") else ""  # the velocities of Q
        warnings = [str(w) for w in s.get("warnings") or []]
        warn_head = []
        if warnings:  # next to Q, on the first screen: one line, the first warning cut to fit, how many and where
            lead = f"⚠ {len(warnings)} warning{'s' if len(warnings) > 1 else ''} (in full below the table): "
            room = max(self.query_one("#summary", Static).size.width or 54, 30) - len(lead) - 4  # ⚠ may take 2 cells
            first = warnings[0] if len(warnings[0]) <= room else warnings[0][: room - 1] + "…"
            warn_head = [f"[yellow]{escape(lead)}{escape(first)}[/yellow]"]
        summary.update(
            head
            + "\n".join(
                [
                    *discharge_lines(s),
                    *warn_head,
                    f"water level    {s['water_level_m']:.3f}{unc_t} m ({s.get('water_level_method', '')})",
                    f"wetted area    {s['wetted_area_m2']:.3f} m²    width {s['wetted_width_m']:.3f} m",
                    f"mean velocity  {s['mean_velocity_ms']:.4f} m/s    alpha {s['alpha']:.2f}{alpha_t}{src_t}",
                ]
            )
        )
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
        files.update(
            f"{note}files in out/ beside {self.session.path.name}: {', '.join(names)}\n{overlay_line(s)}{warn}"
        )
        self.call_after_refresh(self.update_hint)

    def update_hint(self) -> None:
        """Which subsections the table shows, and how to see the others."""
        table = self.query_one(DataTable)
        hint = self.query_one("#table-hint", Static)
        n = table.row_count
        shown = max(table.scrollable_content_region.height - 1, 0)  # less the header
        if n == 0 or shown >= n:
            hint.update(f"{n} subsections" if n else "")
            hint.display = bool(n)
            return
        first = int(table.scroll_y) + 1
        last = min(n, first + shown - 1)
        hint.display = True
        hint.update(Text(f"subsections {first}-{last} of {n} · ↑/↓ scroll the table", style="dim"))

    def on_data_table_row_highlighted(self, event: DataTable.RowHighlighted) -> None:
        self.call_after_refresh(self.update_hint)

    def on_job_finished(self, name: str, result) -> None:
        super().on_job_finished(name, result)
        self.focus_first()

    def _steps_incomplete(self) -> bool:
        """Show the errors of the steps a run needs that are not complete; True when there are any."""
        bad = [st for st in RUN_STEPS if self.session.step_errors(st)]
        if bad:
            self.show_errors([f"step '{st}' is not complete: " + self.session.step_errors(st)[0] for st in bad])
        return bool(bad)

    def action_run(self) -> None:
        if self._steps_incomplete():
            return
        p = jobs.snapshot(self.project)
        out = self.session.out_dir
        if fieldtool_app(self).start_job("results", "Discharge", lambda job: jobs.run_full(p, out, job)):
            self.fill()

    def action_overlay(self) -> None:
        """Run again with ``[overlay] enabled`` for this run only: overlay.mp4 beside the other results (the PIV
        field of the last run is reused when its inputs did not change; the clip is then read once)."""
        if self._steps_incomplete():
            return
        p = jobs.snapshot(self.project)
        p.overlay.enabled = True
        out = self.session.out_dir
        if fieldtool_app(self).start_job("overlay", "Overlay video", lambda job: jobs.run_full(p, out, job)):
            self.fill()

    def action_next(self) -> None:
        self.notify("this is the last step; ctrl+b goes back, ctrl+p jumps to any step")

    def action_report(self) -> None:
        """Write report.html and report.pdf of the last result into out/, with the name, site, station and
        operator as they are now (typed after the run: they do not change Q, so the run is not redone)."""
        out = self.session.out_dir
        try:
            summary, images, rows = load_result(out)
        except FieldToolError as e:
            fieldtool_app(self).status = (f"no report: {e}", True)
            fieldtool_app(self).show_status(self)
            return
        inputs = dict(summary.get("inputs") or {})
        for f in MEASUREMENT:
            inputs[f.key] = getattr(self.project, f.key)
        summary["inputs"] = inputs
        try:
            atomic_write_bytes(out / "report.html", render_html(summary, images, rows).encode("utf-8"))
            atomic_write_bytes(out / "report.pdf", render_pdf(summary, images, rows))
        except (OSError, FieldToolError) as e:
            fieldtool_app(self).status = (f"report NOT written: {e}", True)
        else:
            fieldtool_app(self).status = (f"wrote out/report.html and out/report.pdf ({self.project.name})", False)
        fieldtool_app(self).show_status(self)
