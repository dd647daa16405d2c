"""Refresh docs/viewer.png: the picking viewer on the synthetic oblique scene, in Debian's chromium.

GCPs clicked 3 px beside each target (snapped to the centres), the section's left edge placed and
its right edge next, the checklist and the legend on the panel.

    PYTHONPATH=. .venv/bin/python docs/make_viewer_png.py [OUT.png]
"""

import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from chromium_setup import LAUNCH_ARGS, ensure_chromium  # noqa: E402
from test_browser_guide import _locate_markers_settled, _screen_of, _wait  # noqa: E402

from fieldtool.synthetic import presets, render_scene  # noqa: E402
from fieldtool.viewer.server import start_viewer  # noqa: E402


def main(out: Path) -> None:
    from playwright.sync_api import sync_playwright

    chromium, why = ensure_chromium()
    if chromium is None:
        raise SystemExit(f"no chromium: {why}")
    work = Path(tempfile.mkdtemp(prefix="viewer_png_"))
    render_scene(presets.get("oblique", duration_s=0.3), work)
    truth = json.loads((work / "truth.json").read_text())
    picked = []
    h = start_viewer(work / "project.toml", port=0, on_pick=lambda f, v: picked.append(f))
    try:
        for mode in ("section", "gcp"):
            h.set_mode(mode)
            h._v._act("clear")
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=str(chromium), args=LAUNCH_ARGS)
            page = browser.new_page(viewport={"width": 1500, "height": 760}, device_scale_factor=1)
            page.goto(h.url)
            page.wait_for_selector("canvas", timeout=30000)
            _locate_markers_settled(page, h)
            for x, y in truth["gcp_px_exact"]:
                n = len(picked)
                page.mouse.click(*_screen_of(page, h, (x + 2.5, y - 2.0)))
                _wait(lambda: len(picked) > n)
            page.get_by_role("button", name="Next pick").click()
            _wait(lambda: h.mode == "section")
            n = len(picked)
            page.mouse.click(*_screen_of(page, h, truth["section_px"][0]))
            _wait(lambda: len(picked) > n)
            page.add_style_tag(content=".mantine-Notifications-root { display: none !important; }")
            time.sleep(1.5)  # software WebGL warning of the headless browser hidden
            page.screenshot(path=str(out))
            browser.close()
    finally:
        h.stop()
    print(f"wrote {out}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parent / "viewer.png")
