"""pyorc (pyopenrivercam) end to end, video -> discharge, for benchmarks/time_to_q.py.

Runs in the peers' virtual environment (never the project's): ``benchmarks/.peers-venv/bin/python pyorc_run.py
job.json``. The job gives what a pyorc user enters for the same clip: the video, the 4 GCPs (pixels and x, y on
the water plane, 2-D as pyorc takes 4 points), the water level, the bounding box around the cross-section (world
metres), the cross-section as x, y, z points and the velocity index. The recipe follows pyorc's documented
API: CameraConfig(gcps, bbox, resolution, window_size) -> Video -> get_frames -> frames.project -> frames.get_piv
(ffpiv numba engine) -> velocimetry masks -> get_transect -> transect.get_q -> transect.get_river_flow; the
median over time ("quantile" 0.5). Prints one JSON line: {"discharge_m3s": Q, "seconds": wall time}.
"""

import json
import sys
import time

t0 = time.perf_counter()
import numpy as np  # noqa: E402
import pyorc  # noqa: E402
from shapely.geometry import Polygon  # noqa: E402

job = json.load(open(sys.argv[1]))
cam = pyorc.CameraConfig(
    height=int(job["height"]), width=int(job["width"]),
    gcps={"src": job["gcp_px"], "dst": job["gcp_xy_m"], "z_0": float(job["level_m"]), "h_ref": float(job["level_m"])},
    window_size=int(job["window_size"]), resolution=float(job["resolution_m"]),
    bbox=Polygon(job["bbox_xy_m"]),
)
video = pyorc.Video(job["video"], camera_config=cam, h_a=float(job["level_m"]), start_frame=0,
                    end_frame=int(job["n_frames"]), progress=False)
da = video.get_frames()
proj = da.frames.project(method="cv")  # pyorc's OpenCV projection: -22 % against -34 % for "numpy" on the 720p clip
piv = proj.frames.get_piv(engine="numba")
piv.velocimetry.mask.minmax(inplace=True, s_max=float(job.get("s_max", 5.0)))
piv.velocimetry.mask.corr(inplace=True)
piv.velocimetry.mask.outliers(inplace=True)
xs, ys, zs = (np.asarray(job["transect_xyz_m"], float).T).tolist()
tr = piv.velocimetry.get_transect(xs, ys, zs, rolling=4, quantiles=[0.5])
tr.transect.get_q(v_corr=float(job["alpha"]), fill_method="log_interp")
tr.transect.get_river_flow()
q = float(np.abs(tr["river_flow"].sel(quantile=0.5)))
print(json.dumps({"discharge_m3s": q, "seconds": time.perf_counter() - t0,
                  "pyorc": pyorc.__version__}))
