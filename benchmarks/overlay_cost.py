"""Extra wall time of ``fieldtool run --overlay`` over a plain run, and a frame of the overlay from the report's
``<video>`` in headless chromium.

    .venv/bin/python benchmarks/overlay_cost.py [--scene oblique] [--repeats 3] [--screenshot docs/overlay_frame.png]

Each run is a fresh ``fieldtool run`` process into a fresh output folder (no PIV cache), plain and overlay
alternating, ``--repeats`` of each; the medians of the processes' wall times are compared. With
``--screenshot``, the last overlay run's report (``fieldtool report``) is opened in Debian's chromium, the
``<video>`` is sought to the middle of the analysed range and the element is saved as PNG.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from fieldtool.synthetic import presets, render_scene

HERE = Path(__file__).resolve().parent
SEEK = """(t) => new Promise(res => { const v = document.querySelector('#overlay-video'); v.controls = false;
  v.addEventListener('seeked', () => res({w: v.videoWidth, h: v.videoHeight, duration: v.duration,
                                          t: v.currentTime, err: v.error && v.error.code}), {once: true});
  v.currentTime = t; })"""


def run(project: Path, out: Path, overlay: bool) -> float:
    cmd = [sys.executable, "-m", "fieldtool.cli", "run", str(project), "--out", str(out), "--quiet"]
    t0 = time.perf_counter()
    r = subprocess.run(cmd + (["--overlay"] if overlay else []), capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if r.returncode not in (0, 3):
        raise SystemExit(f"{' '.join(cmd)} failed ({r.returncode}): {r.stderr[-800:]}")
    return dt


def screenshot(out: Path, png: Path) -> dict:
    sys.path.insert(0, str(HERE.parent / "tests"))
    from chromium_setup import LAUNCH_ARGS, ensure_chromium
    from playwright.sync_api import sync_playwright

    path, reason = ensure_chromium()
    if path is None:
        raise SystemExit(f"chromium unavailable: {reason}")
    subprocess.run([sys.executable, "-m", "fieldtool.cli", "report", str(out)], check=True, capture_output=True)
    info = json.loads((out / "result.json").read_text())["overlay"]
    t_mid = 0.5 * (info["frames"] / info["fps"])
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(path), args=LAUNCH_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1100, "height": 900})
            page.goto((out / "report.html").as_uri())
            page.wait_for_function("() => document.querySelector('#overlay-video').readyState >= 1", timeout=60000)
            got = page.evaluate(SEEK, t_mid)
            page.wait_for_timeout(300)
            el = page.locator("#overlay-video")
            el.scroll_into_view_if_needed()
            png.parent.mkdir(parents=True, exist_ok=True)
            el.screenshot(path=str(png))
        finally:
            browser.close()
    return got


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default="oblique", help="preset (the demo's is oblique, 5 s)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--screenshot", help="PNG of a frame of the report's <video> (chromium)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        truth = render_scene(presets.get(args.scene), tmp / "scene")
        times: dict[bool, list[float]] = {False: [], True: []}
        last = None
        for k in range(args.repeats):
            for overlay in (False, True):
                out = tmp / f"out_{int(overlay)}_{k}"
                times[overlay].append(run(truth.project_path, out, overlay))
                last = out if overlay else last
        plain, over = statistics.median(times[False]), statistics.median(times[True])
        info = json.loads((last / "result.json").read_text())["overlay"]
        print(f"scene {args.scene}: plain runs {', '.join(f'{t:.1f}' for t in times[False])} s, overlay runs "
              f"{', '.join(f'{t:.1f}' for t in times[True])} s")
        print(f"medians: plain {plain:.2f} s, overlay {over:.2f} s, extra {over - plain:+.2f} s "
              f"({100 * (over - plain) / plain:+.1f} %)")
        print(f"overlay: {info['frames']} frames + {info['card_frames']} card, {info['width_px']}x{info['height_px']} "
              f"at {info['fps']:g} fps; its thread drew and encoded for {info['draw_encode_s']:.2f} s, the frame thread "
              f"spent {info['frame_prep_s']:.2f} s downscaling and waited {info['run_waited_s']:.2f} s on the buffer")
        if args.screenshot:
            got = screenshot(last, Path(args.screenshot))
            print(f"chromium: video {got['w']}x{got['h']}, {got['duration']:.2f} s, frame at {got['t']:.2f} s -> "
                  f"{args.screenshot}")


if __name__ == "__main__":
    main()
