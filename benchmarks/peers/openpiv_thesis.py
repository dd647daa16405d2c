"""The thesis' own method with OpenPIV's Rust backend, end to end, for benchmarks/time_to_q.py.

Runs in the peers' virtual environment: ``benchmarks/.peers-venv/bin/python openpiv_thesis.py job.json``.
Thesis chapters 7-8 as its application did them, with OpenPIV 0.26 (``backend="rust"``, the fastest backend
it has): every consecutive pair of the clip's grey frames inside the user's ROI, one pass of
``extended_search_area_piv`` (window, overlap and search area from the job), vectors with a peak-to-peak
signal-to-noise ratio under ``s2n_min`` dropped, the time average of each node over the pairs (px/s), the
vectors orthorectified afterwards with the homography of the 4 GCPs (image px -> water-plane m), the closest
node to each subsection's centre (thesis 8.5), its velocity normal to the section, and Q = sum(alpha * v * A)
over the subsections with the subsection areas of the cross-section at the water level. The geometry
(homography, section, areas) comes precomputed in the job: it is the same for every method and costs
microseconds; what is timed is reading the video and the PIV, as the user waits for them.

Prints one JSON line: {"discharge_m3s": Q, "seconds": wall, "pairs": n, "backend": ...}. Axes: x right, y
down, origin at the top-left pixel (OpenPIV 0.26 returns u right and v down, checked on a shifted image).
"""

import json
import sys
import time

t0 = time.perf_counter()
import cv2  # noqa: E402
import numpy as np  # noqa: E402
from openpiv import pyprocess  # noqa: E402

job = json.load(open(sys.argv[1]))
W, O = int(job["window_px"]), int(job["overlap_px"])
S = int(job.get("search_px") or W)
backend = job.get("backend", "rust")
x0, y0, x1, y1 = (int(v) for v in job["roi_px"])
fps = float(job["fps"])
cap = cv2.VideoCapture(job["video"])
prev, acc_u, acc_v, cnt, pairs = None, None, None, None, 0
n_max = int(job["n_frames"])
k = 0
while k < n_max:
    ok, bgr = cap.read()
    if not ok:
        break
    k += 1
    g = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)[y0:y1, x0:x1].astype(np.int32)
    if prev is not None:
        u, v, s2n = pyprocess.extended_search_area_piv(prev, g, window_size=W, overlap=O, search_area_size=S,
                                                       dt=1.0 / fps, sig2noise_method="peak2peak", backend=backend)
        ok_ = np.isfinite(u) & np.isfinite(v) & (s2n >= float(job["s2n_min"]))
        if acc_u is None:
            acc_u, acc_v, cnt = np.zeros_like(u), np.zeros_like(v), np.zeros(u.shape)
        acc_u += np.where(ok_, u, 0.0)
        acc_v += np.where(ok_, v, 0.0)
        cnt += ok_
        pairs += 1
    prev = g
cap.release()
with np.errstate(invalid="ignore", divide="ignore"):
    um, vm = acc_u / cnt, acc_v / cnt  # px/s, time average of the valid vectors
x, y = pyprocess.get_coordinates(prev.shape, S, O)
x, y = x + x0, y + y0  # back to full-frame pixels
H = np.asarray(job["H"], float)


def to_world(px):
    p = cv2.perspectiveTransform(np.asarray(px, np.float64).reshape(-1, 1, 2), H)
    return p.reshape(-1, 2)


good = np.isfinite(um) & np.isfinite(vm)
if not good.any():  # every vector under the threshold: no discharge
    print(json.dumps({"discharge_m3s": None, "seconds": time.perf_counter() - t0, "pairs": pairs, "backend": backend}))
    sys.exit(0)
nodes = np.c_[x[good], y[good]]
uu, vv = um[good], vm[good]
normal = np.asarray(job["normal"], float)
q = 0.0
for (cx, cy), area in zip(job["centres_px"], job["areas_m2"]):
    i = int(np.argmin((nodes[:, 0] - cx) ** 2 + (nodes[:, 1] - cy) ** 2))  # the closest vector (thesis 8.5)
    p = nodes[i]
    a, b = to_world([p, p + np.array([uu[i], vv[i]]) / fps])
    vel = (b - a) * fps  # m/s on the water plane
    q += float(job["alpha"]) * float(vel @ normal) * float(area)
print(json.dumps({"discharge_m3s": abs(q), "seconds": time.perf_counter() - t0, "pairs": pairs,
                  "backend": backend}))
