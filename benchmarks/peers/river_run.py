"""RIVeR (river-cli) end to end, video -> discharge, for benchmarks/time_to_q.py.

Runs in RIVeR's own venv: ``benchmarks/.river-venv/bin/python river_run.py job.json``. The job gives what a RIVeR
user enters for the same clip: the video, the 4 GCPs on the water plane (pixels; RIVeR's oblique view takes the
six distances between them and the east/north of points 1 and 2), the bounding box (the generated project's ROI,
``[x, y, width, height]`` px), the section's two water edges (east, north), the bathymetry (station, bed
elevation), the water level, alpha and the interrogation area. The recipe is RIVeR's own core, as its GUI's
steps and its ``orchestrator`` call it: ``video_to_frames`` (every frame written as a JPEG file) ->
``oblique_view_transformation_matrix`` -> ``run_analyze_all`` (every consecutive pair, its default filters:
grey, CLAHE, the median over the pairs) -> ``update_current_x_section`` (stations along the section, depth from
the bathymetry, the discharge with alpha). Prints one JSON line: {"discharge_m3s": Q, "seconds": wall time,
"pairs": pairs}, and leaves at once (RIVeR's stack segfaults in the interpreter's teardown).
"""

import contextlib
import io
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

t0 = time.perf_counter()
import numpy as np  # noqa: E402
from river.core.compute_section import update_current_x_section  # noqa: E402
from river.core.coordinate_transform import oblique_view_transformation_matrix  # noqa: E402
from river.core.piv_pipeline import run_analyze_all  # noqa: E402
from river.core.video_to_frames import video_to_frames  # noqa: E402

#: stations along the section where RIVeR samples the velocity (the 15 subsections of fieldtool's projects)
NUM_STATIONS = 15
job = json.loads(Path(sys.argv[1]).read_text())
px, xy = np.asarray(job["gcp_px"], float), np.asarray(job["gcp_xy_m"], float)


def transformation():
    """RIVeR's oblique view from the 4 GCPs, and its largest error at them (m). RIVeR places points 3 and 4 on
    one side of the line from point 1 to point 2 (its convention): of the quadrilateral's 8 numberings (turned
    and mirrored), the one a user settles on after looking at RIVeR's rectified view, the one that puts every
    GCP back where it was surveyed."""
    best = None
    for k in range(4):
        for o in ([0, 1, 2, 3], [0, 3, 2, 1]):
            order = [(k + i) % 4 for i in o]
            p, w = px[order], xy[order]

            def d(i, j, w=w):
                return float(np.hypot(*(w[i] - w[j])))

            tm = oblique_view_transformation_matrix(
                *p.ravel().tolist(),
                d12=d(0, 1),
                d23=d(1, 2),
                d34=d(2, 3),
                d41=d(3, 0),
                d13=d(0, 2),
                d24=d(1, 3),
                east1=float(w[0, 0]),
                north1=float(w[0, 1]),
                east2=float(w[1, 0]),
                north2=float(w[1, 1]),
                enforce_d12=False,
            )["transformation_matrix"]
            back = np.c_[p, np.ones(4)] @ np.asarray(tm, float).T
            err = float(np.max(np.hypot(*(back[:, :2] / back[:, 2:] - w).T)))
            if best is None or err < best[1]:
                best = (tm, err)
    return best


with tempfile.TemporaryDirectory(prefix="river_") as tmp:
    work = Path(tmp)
    frames = work / "frames"
    frames.mkdir()  # RIVeR's GUI makes the project's folders; OpenCV writes nothing into a missing one
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        video_to_frames(Path(job["video"]), frames, 0, int(job["n_frames"]), overwrite=True)
        tm, err = transformation()
        ia = int(job["interrogation_area_px"])
        piv = run_analyze_all(
            frames,
            None,
            list(job["bbox_px"]),
            interrogation_area_1=ia,
            interrogation_area_2=ia // 2,
        )
        bath = work / "bathymetry.csv"
        bath.write_text("station,stage\n" + "".join(f"{s},{z}\n" for s, z in job["bathymetry"]))
        (el, nl), (er, nr) = job["edges_en_m"]
        xsec = {
            "CS_1": {
                "east_l": el,
                "north_l": nl,
                "east_r": er,
                "north_r": nr,
                "bath": str(bath),
                "left_station": 0.0,
                "level": float(job["level_m"]),
                "alpha": float(job["alpha"]),
                "num_stations": NUM_STATIONS,
                "rw_length": math.hypot(er - el, nr - nl),
            }
        }
        xsec = update_current_x_section(xsec, piv, np.asarray(tm), 1, float(job["fps"]), 0, interpolate=True)
    q = float(xsec["CS_1"]["total_Q"])
print(json.dumps({"discharge_m3s": q, "gcp_error_m": err, "seconds": time.perf_counter() - t0, "pairs": len(piv["u"])}))
sys.stdout.flush()
os._exit(0)  # river-cli 3.7.0's process segfaults in the interpreter's teardown (exit 139) after the work is done
