"""Keystrokes from `fieldtool init` to a discharge of the demo scene in the TUI at 80 x 24.

A scripted Pilot walk, as an operator would do it: `fieldtool init` in a folder holding the demo's
clip and cross-section, then the TUI by keys only, step by step, with the fewest keys the TUI allows
(tabs counted until the wanted field has the focus; a field holding a value is cleared first when
focusing it does not select its content; a file name typed until the field offers it, then →).
Two variants:

* ``keys``  : every value typed, pixel points included;
* ``viewer``: pixel points picked in the viewer (ctrl+o opens it; clicks counted separately).

Usage (from the repository root; run it on another tree with PYTHONPATH to compare)::

    PYTHONPATH=. .venv/bin/python benchmarks/tui_keystrokes.py [--duration 1.0]
"""

from __future__ import annotations

import argparse
import asyncio
import shutil
import tempfile
import time
from pathlib import Path

from fieldtool.project.model import load_project
from fieldtool.synthetic import presets, render_scene
from fieldtool.project.template import write_template
from fieldtool.tui.app import FieldToolApp
from fieldtool.tui.fields import fmt_num, fmt_point
from fieldtool.tui.widgets.field_row import FieldRow


class Walk:
    def __init__(self, app, pilot):
        self.app, self.pilot = app, pilot
        self.keys = 0
        self.clicks = 0

    async def press(self, *keys: str) -> None:
        self.keys += len(keys)
        for k in keys:
            await self.pilot.press(k)
        await self.pilot.pause()

    def focused_key(self) -> str | None:
        node = self.app.focused
        while node is not None and not isinstance(node, FieldRow):
            node = node.parent
        return node.field.key if node is not None else None

    async def focus(self, key: str) -> None:
        for _ in range(60):
            if self.focused_key() == key:
                return
            await self.press("tab")
        raise AssertionError(f"{key} never got the focus on {self.app.screen.STEP}")

    async def type(self, key: str, text: str) -> None:
        await self.focus(key)
        inp = self.app.focused
        sel = getattr(inp, "selection", None)
        selected_all = sel is not None and abs(sel.end - sel.start) == len(inp.value)
        if inp.value and not selected_all:
            await self.press("end", "ctrl+u")
        await self.press(*text)

    async def type_path(self, key: str, text: str) -> None:
        """Type a file name until the field offers it, then accept it with → (when it does)."""
        await self.focus(key)
        inp = self.app.focused
        sel = getattr(inp, "selection", None)
        if inp.value and not (sel is not None and abs(sel.end - sel.start) == len(inp.value)):
            await self.press("end", "ctrl+u")
        for i, ch in enumerate(text):
            await self.press(ch)
            await self.pilot.pause(0.05)
            if i + 1 < len(text) and getattr(inp, "_suggestion", "") == text:
                await self.press("right")
                break
        assert inp.value == text, inp.value

    async def next(self, step: str) -> None:
        await self.press("ctrl+n")
        await self.pilot.pause(0.2)
        assert self.app.screen.STEP == step, (self.app.screen.STEP, step)


async def walk(folder: Path, demo, variant: str) -> dict:
    app = FieldToolApp(folder / "project.toml")
    async with app.run_test(size=(80, 24)) as pilot:
        w = Walk(app, pilot)
        await pilot.pause(0.5)
        t0 = time.monotonic()
        assert app.screen.STEP == "cross_section"
        await w.type_path("cross_section.path", "cross_section.csv")
        await w.next("video")
        await w.type_path("video.path", "river.mp4")
        await w.next("calibration")
        await w.next("ortho")
        if variant == "viewer":
            await w.press("ctrl+o")
            await w.focus("ortho.gcp_px[0]")  # the viewer switches to the GCP mode
            app.viewer_picked("ortho.gcp_px", demo.ortho.gcp_px)
            w.clicks += 4
            await pilot.pause()
        else:
            for i, pt in enumerate(demo.ortho.gcp_px):
                await w.type(f"ortho.gcp_px[{i}]", fmt_point(pt))
        for i, d in enumerate(demo.ortho.distances_m):
            await w.type(f"ortho.distances_m[{i}]", fmt_num(d))
        await w.next("water_level")
        await w.type("water_level.value_m", fmt_num(demo.water_level.value_m))
        await w.next("roi")
        await w.next("filters")
        await w.next("piv")
        await w.next("section")
        if variant == "viewer":
            await w.focus("section.points_px[0]")
            app.viewer_picked("section.points_px", demo.section.points_px)
            w.clicks += 2
            await pilot.pause()
        else:
            for i, pt in enumerate(demo.section.points_px):
                await w.type(f"section.points_px[{i}]", fmt_point(pt))
        await w.next("results")  # the discharge is computed on arrival
        while app.job is not None:
            await pilot.pause(0.2)
        await pilot.pause(0.2)
        res = app.session.last_result()
        assert res is not None, "no discharge"
        if app.viewer is not None:
            app.viewer.stop()
        return {"keys": w.keys, "clicks": w.clicks, "discharge_m3s": res.summary["discharge_m3s"],
                "seconds": time.monotonic() - t0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=1.0, help="demo clip length in seconds (default 1)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        scene = Path(tmp) / "scene"
        render_scene(presets.get("oblique", duration_s=args.duration), scene)
        demo = load_project(scene / "project.toml")
        for variant in ("keys", "viewer"):
            folder = Path(tmp) / variant
            folder.mkdir()
            for f in ("river.mp4", "cross_section.csv"):
                shutil.copy(scene / f, folder / f)
            write_template(folder)
            r = asyncio.run(walk(folder, demo, variant))
            print(f"{variant:6s}: {r['keys']} keys, {r['clicks']} viewer clicks, discharge "
                  f"{r['discharge_m3s']:.4f} m³/s, walk {r['seconds']:.1f} s")


if __name__ == "__main__":
    main()
