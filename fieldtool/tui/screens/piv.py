"""Step 8: PIV parameters and the run (worker with progress, elapsed/remaining time, cancel)."""

from __future__ import annotations

import numpy as np
from textual.app import ComposeResult
from textual.widgets import Static

from fieldtool.tui import jobs, keys
from fieldtool.tui.piv_summary import water_nodes
from fieldtool.tui.screens.base import StepScreen, fieldtool_app
from fieldtool.tui.widgets.plots import VectorGrid


class PivScreen(StepScreen):
    STEP = "piv"
    INTRO = "surface velocities by cross-correlation"
    BINDINGS = [keys.run("Run PIV")]

    def compose_extra(self) -> ComposeResult:
        yield Static("", id="piv-info")
        yield VectorGrid(id="vectors")

    def refresh_view(self) -> None:
        info = self.query_one("#piv-info", Static)
        grid = self.query_one(VectorGrid)
        s = self.session
        state = s.piv_state()
        if state == "none":
            info.update("ctrl+r runs PIV on the clip (every step before this one is used); esc cancels")
            grid.set_field(None, None)
            return
        if state == "stale":
            info.update(
                "[red]! the inputs changed since the last PIV run[/red]: ctrl+r runs it again "
                "(the discharge step also recomputes it when needed)"
            )
            grid.set_field(None, None)
            return
        res = s.last_result()
        if res is not None and not (
            s.changed_tables(res.summary.get("inputs"))
            & set(("video", "calibration", "stabilize", "roi", "filters", "piv"))
        ):
            sm = res.summary
            info.update(
                f"{sm['n_pairs']} pairs · valid vectors {100 * sm['valid_fraction_mean']:.0f} % · "
                f"mean velocity in the section {sm['mean_velocity_ms']:.3f} m/s (depth-averaged)"
            )
            try:
                with np.load(s.out_dir / "mean_field.npz") as z:
                    u, v = z["u_px_s"], z["v_px_s"]
                    vf = z["valid_fraction"] if "valid_fraction" in z.files else None
                grid.set_field(u, v, water_nodes(u, v, vf))
            except (OSError, KeyError, ValueError):
                grid.set_field(None, None)
            return
        st = s.piv_preview["stats"]
        _, _, u, v = st["field"]
        water = st.get("water")
        if water is None:  # a summary of an older session: judged here
            water = water_nodes(u, v)
        ms, mpx = st.get("median_speed_ms"), st.get("median_speed_px_s")
        speed = (
            f"median speed on the water {ms:.3f} m/s"
            if ms is not None
            else f"median speed on the water {mpx:.1f} px/s"
            if mpx is not None
            else "no moving water found"
        )
        n_water = int(np.sum(water))
        info.update(
            f"{st['pairs']} pairs · {n_water} of {st['nodes']} nodes on the water · valid "
            f"{100 * st['valid_fraction']:.0f} % · {speed} · page down: the arrows"
        )
        grid.set_field(u, v, water)

    def action_run(self) -> None:
        msgs = self.errors()
        if msgs:
            self.show_errors(msgs)
            return
        p = jobs.snapshot(self.project)
        full = jobs.has_section(p) and not any(self.session.step_errors(st) for st in ("section",))
        if full:
            out = self.session.out_dir
            fieldtool_app(self).start_job(
                "piv",
                "PIV and discharge",
                lambda job: jobs.run_full(p, out, job),
            )
        else:
            out = self.session.out_dir  # the field is saved there at once (PIV cache)
            fieldtool_app(self).start_job("piv", "PIV", lambda job: jobs.run_piv_only(p, job, out))
