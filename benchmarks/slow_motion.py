"""Phone slow motion: a clip filmed at 120-240 frames per second and written to play at 30.

    PYTHONPATH=. .venv/bin/python benchmarks/slow_motion.py [--views oblique,nadir,far_bank] [--fps 120,240]
        [--duration 2] [--workdir /tmp/slow_motion] [--results results]

A phone's slow motion writes the frames it filmed at, say, 240 per second 1/30 s apart, so that the clip plays 8
times slower, and the rate it filmed at in the tag ``com.android.capture.fps``. A tool that trusts the file's
clock measures the river 8 times slower than it is. Each scene draws a base view (its preset's river) filmed at
the rate, once into WORKDIR/<view>_f<fps>_d<duration>/, then writes its frames, not re-encoded, as a clip that
plays at 30 frames per second: ``tagged.mp4`` with the tag, ``plain.mp4`` without (as a phone that does not
write it, or a file an editor re-wrote). Runs, with the defaults:

* ``tagged``: the tag read (processing/frames.py ``filming_clock``);
* ``plain``: no tag, the file's clock (what every run did before the tag was read);
* ``plain+key``: no tag, ``video.capture_fps`` set to the filming rate.

Printed per run: exit code, error against the truth integrated from the drawn profile, grade, 95 % interval's
half-width, the frame step the run took (processing/decorrelation.py) and the pass rule of ``unseen_scenes.py``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import tomlkit
from unseen_scenes import HEAD, fmt, row, run_cli

from fieldtool.synthetic import presets, render_scene
from fieldtool.synthetic.retime import replayed

PLAY_FPS = 30


def project_for(scene: Path, name: str, video: str, capture_fps: float | None) -> Path:
    doc = tomlkit.parse((scene / "project.toml").read_text())
    doc["video"]["path"] = video
    if capture_fps is not None:
        doc["video"]["capture_fps"] = capture_fps
    out = scene / f"{name}.toml"
    out.write_text(tomlkit.dumps(doc))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", default="oblique,nadir,far_bank")
    ap.add_argument("--fps", default="120,240", help="frames per second filmed")
    ap.add_argument("--duration", type=float, default=2.0, help="seconds filmed")
    ap.add_argument("--workdir", default="/tmp/slow_motion")
    ap.add_argument("--results", default="results")
    a = ap.parse_args()
    print(HEAD + f" {'step':>4}", flush=True)
    seed, rows = 100, []
    for view in a.views.split(","):
        for fps in [int(s) for s in a.fps.split(",")]:
            d = Path(a.workdir) / f"{view}_f{fps}_d{a.duration:g}"
            if not (d / "truth.json").exists():
                render_scene(presets.get(view, seed=seed, duration_s=a.duration, fps=float(fps)), d)
            seed += 1
            slower = fps // PLAY_FPS
            for name, tag in (("tagged", f"{fps:.6f}"), ("plain", None)):
                if not (d / f"{name}.mp4").exists():
                    replayed(d / "river.mp4", d / f"{name}.mp4", slower, tag)
            q_true = json.loads((d / "truth.json").read_text())["discharge_m3s"]
            for name, video, key in (
                ("tagged", "tagged.mp4", None),
                ("plain", "plain.mp4", None),
                ("plain+key", "plain.mp4", float(fps)),
            ):
                proj = project_for(d, name.replace("+", "_"), video, key)
                rc, res, dt = run_cli(proj, d / a.results / name.replace("+", "_"))
                r = row(f"{view} {fps} {name}", seed - 1, rc, res, q_true, dt)
                step = (((res or {}).get("robust") or {}).get("gates") or {}).get("frame_step", "-")
                rows.append(r)
                print(fmt(r, f" {step!s:>4}"), flush=True)
    for name in ("tagged", "plain", "plain+key"):
        mine = [r for r in rows if r["preset"].endswith(" " + name)]
        errs = [abs(r["err"]) for r in mine if r["err"] is not None]
        print(
            f"{name}: {sum(r['pass'] for r in mine)}/{len(mine)} pass, max |error| "
            f"{max(errs, default=float('nan')):.1f} %, graded good {sum(r['grade'] == 'good' for r in mine)}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
