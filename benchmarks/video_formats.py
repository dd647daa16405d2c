"""The clips cameras write today: an iPhone's 10-bit HDR HEVC, AV1, ProRes 422, a phone held upright.

    PYTHONPATH=. .venv/bin/python benchmarks/video_formats.py [--scenes oblique_s0_d6,nadir_s0_d6]
        [--unseen /tmp/unseen_scenes] [--workdir /tmp/video_formats] [--results results]

Each scene of ``unseen_scenes.py`` (rendered there first: run it once) is re-encoded by PyAV, frame by frame:

* ``h264``: libx264, CRF 18, 8-bit 4:2:0 (the baseline of the re-encoding's own loss);
* ``hevc10``: libx265, CRF 18, 10-bit 4:2:0, tagged BT.2020 / HLG (an iPhone's default "HDR video");
* ``av1``: SVT-AV1, CRF 30, 8-bit 4:2:0;
* ``prores``: ProRes 422 (prores_ks profile 2), 10-bit 4:2:2, in a .mov;
* ``rotated``: libx264 with every frame stored turned 90 degrees clockwise and a display matrix that turns it
  back (a phone held upright: the frames as the player shows them are the scene's).

Each runs with the defaults. Printed per clip: as ``unseen_scenes.py`` (error against the truth integrated from the
drawn profile, grade, interval, pass rule, run s), the reader (PyAV or OpenCV) and the pass' time.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import av
import cv2
from unseen_scenes import HEAD, derived, derived_args, fmt, row, run_cli

#: kind -> (encoder, pixel format, options, file extension)
KINDS = {
    "h264": ("libx264", "yuv420p", {"crf": "18"}, "mp4"),
    "hevc10": ("libx265", "yuv420p10le", {"crf": "18", "x265-params": "log-level=error"}, "mp4"),
    "av1": ("libsvtav1", "yuv420p", {"crf": "30", "preset": "8"}, "mp4"),
    "prores": ("prores_ks", "yuv422p10le", {"profile": "2"}, "mov"),
    "rotated": ("libx264", "yuv420p", {"crf": "18"}, "mp4"),
}


def make(src: Path, dst: Path, kind: str) -> None:
    codec, pix, opts, ext = KINDS[kind]
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("results*", "before", "after", "river.mp4"))
    with av.open(str(src / "river.mp4")) as inp, av.open(str(dst / f"river.{ext}"), "w") as out:
        ist = inp.streams.video[0]
        st = out.add_stream(codec, rate=ist.average_rate, options=opts)
        w, h = ist.codec_context.width, ist.codec_context.height
        st.width, st.height, st.pix_fmt = (h, w, pix) if kind == "rotated" else (w, h, pix)
        if kind == "hevc10":  # BT.2020 primaries and matrix, HLG transfer
            st.codec_context.color_primaries, st.codec_context.color_trc, st.codec_context.colorspace = 9, 18, 9
        if kind == "rotated":
            st.set_display_rotation(90)  # shown turned 90 degrees counter-clockwise: the scene as drawn
        for fr in inp.decode(ist):
            img = fr.to_ndarray(format="bgr24")
            if kind == "rotated":
                img = cv2.rotate(img, cv2.ROTATE_90_CLOCKWISE)
            nf = av.VideoFrame.from_ndarray(img, format="bgr24").reformat(format=pix)
            nf.pts, nf.time_base = fr.pts, fr.time_base
            for pk in st.encode(nf):
                out.mux(pk)
        for pk in st.encode():
            out.mux(pk)
    text = (dst / "project.toml").read_text().replace('path = "river.mp4"', f'path = "river.{ext}"')
    (dst / "project.toml").write_text(text)


def main() -> int:
    ap = derived_args(__doc__, "oblique_s0_d6,nadir_s0_d6", "/tmp/video_formats")
    ap.add_argument("--kinds", default=",".join(KINDS))
    a = ap.parse_args()
    print(HEAD + f" {'pass s':>6}", flush=True)
    for name, kind, d, q_true in derived(a, a.kinds.split(","), make):
        rc, res, dt = run_cli(d / "project.toml", d / a.results)
        r = row(f"{name} {kind}", 0, rc, res, q_true, dt)
        pass_s = ((res or {}).get("timings_s") or {}).get("frames_and_piv")
        print(fmt(r, f" {pass_s if pass_s is None else round(pass_s, 2)!s:>6}"), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
