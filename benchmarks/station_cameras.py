"""Two views a gauging station's camera has that no preset draws: an interlaced camera, and a bridge camera.

    PYTHONPATH=. .venv/bin/python benchmarks/station_cameras.py [--workdir /tmp/station_cameras] [--results results]

* **interlaced**: each base view rendered at 50 fps (6 s), then woven as a 50i camera delivers it: frame k of the
  25 fps clip holds the even rows of the render's frame 2k and the odd rows of frame 2k+1 (H.264, crf 18). The
  progressive 50 fps render is run beside it.
* **bridge**: the oblique scene filmed from a bridge on the river's centre line, looking upstream (the camera
  16 m downstream of the section, 7 m above the water) and downstream (16 m upstream), and from higher up
  (12 m downstream, 12 m above): the flow runs along the image's vertical, foreshortened.

Each clip is rendered once into WORKDIR/<name>/ (kept) and run through ``fieldtool run`` with the defaults as
``unseen_scenes.py`` runs its scenes (same columns, same pass rule). The truth is the generator's.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from dataclasses import replace
from pathlib import Path

import av
from unseen_scenes import HEAD, fmt, row, run_cli

from fieldtool.synthetic import Camera, presets, render_scene

#: (name, camera position, target), metres from (the section's X, the river's centre line, the water level)
BRIDGES = (
    ("bridge_looking_upstream", (16.0, 0.0, 7.0), (-2.0, 0.0, 0.0)),
    ("bridge_looking_downstream", (-16.0, 0.0, 7.0), (2.0, 0.0, 0.0)),
    ("bridge_high", (12.0, 0.0, 12.0), (-1.0, 0.0, 0.0)),
)


def weave(src: Path, dst: Path) -> None:
    """``src`` (50 fps) as a 25 fps interlaced camera's frames: even rows from frame 2k, odd rows from 2k+1."""
    with av.open(str(src)) as inp, av.open(str(dst), "w") as out:
        ist = inp.streams.video[0]
        st = out.add_stream("libx264", rate=25)
        st.width, st.height, st.pix_fmt = ist.codec_context.width, ist.codec_context.height, "yuv420p"
        st.options = {"crf": "18"}
        top = None
        for k, fr in enumerate(inp.decode(ist)):
            img = fr.to_ndarray(format="rgb24")
            if k % 2 == 0:
                top = img
                continue
            woven = top.copy()
            woven[1::2] = img[1::2]
            for pk in st.encode(av.VideoFrame.from_ndarray(woven, format="rgb24")):
                out.mux(pk)
        for pk in st.encode():
            out.mux(pk)


def scenes(root: Path):
    """(label, seed, scene folder) of every clip, rendered (and woven) where missing."""
    for seed, view in enumerate(presets.NAMES):
        prog = root / f"{view}_50p"
        if not (prog / "truth.json").exists():
            render_scene(presets.get(view, seed=seed, fps=50, duration_s=6.0), prog)
        woven = root / f"{view}_50i"
        if not (woven / "truth.json").exists():
            shutil.copytree(prog, woven, ignore=shutil.ignore_patterns("results*", "river.mp4"), dirs_exist_ok=True)
            weave(prog / "river.mp4", woven / "river.mp4")
            (woven / "truth.json").write_text((prog / "truth.json").read_text())
        yield f"{view} 50p", seed, prog
        yield f"{view} 25i (woven)", seed, woven
    for seed, (name, pos, tgt) in enumerate(BRIDGES, start=len(presets.NAMES)):
        d = root / name
        if not (d / "truth.json").exists():
            spec = presets.get("oblique", seed=seed, duration_s=6.0)
            r = spec.river
            cam = Camera(
                position_m=(r.x_section_m + pos[0], pos[1], r.level_m + pos[2]),
                target_m=(r.x_section_m + tgt[0], tgt[1], r.level_m + tgt[2]),
                hfov_deg=70.0,
            )
            render_scene(replace(spec, camera=cam, name=name), d)
        yield name, seed, d


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", default="/tmp/station_cameras")
    ap.add_argument("--results", default="results")
    a = ap.parse_args()
    print(HEAD, flush=True)
    rows = []
    for label, seed, d in scenes(Path(a.workdir)):
        q_true = json.loads((d / "truth.json").read_text())["discharge_m3s"]
        rc, res, dt = run_cli(d / "project.toml", d / a.results)
        rows.append(row(label, seed, rc, res, q_true, dt))
        print(fmt(rows[-1]), flush=True)
    print(f"{sum(r['pass'] for r in rows)}/{len(rows)} pass")
    return 0 if all(r["pass"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
