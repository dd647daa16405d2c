"""The station's time series for the docs (docs/station_timeseries.png): 6 clips an hour apart, the level
from a level file (a small flood: the same clip each time, so Q follows the wetted area only).

    PYTHONPATH=. .venv/bin/python benchmarks/station_demo.py   # writes /tmp/st_docs/out/timeseries.png
"""
import os
import shutil
from pathlib import Path

from fieldtool.synthetic import presets, render_scene
from fieldtool.project.model import load_project
from fieldtool.records.sites import create_site, load_site
from fieldtool.records.history import History
from fieldtool.records import station as st

root = Path("/tmp/st_docs"); shutil.rmtree(root, ignore_errors=True)
truth = render_scene(presets.get("oblique", duration_s=1.0, seed=5), root / "scene")
p = load_project(truth.project_path)
create_site("cam1", p, root / "sites")
inc = root / "incoming"; inc.mkdir()
t0 = 1717228800  # 2024-06-01T08:00Z
levels = [10.0, 10.03, 10.08, 10.05, 10.02, 10.0]
with open(root / "levels.csv", "w") as fh:
    fh.write("time,level\n")
    for k, h in enumerate(levels):
        fh.write(f"{t0 + 3600 * k},{h}\n")
v = p.resolve(p.video.path)
for k in range(len(levels)):
    c = inc / f"cam1_{k:02d}.mp4"
    shutil.copy(v, c)
    os.utime(c, (t0 + 3600 * k + 60, t0 + 3600 * k + 60))
site = load_site("cam1", root / "sites")
with History(root / "h.sqlite") as h:
    cfg = st.station_config(site, level_file=str(root / "levels.csv"), stable_s=0.2, poll_s=0.2)
    s = st.Station(site, root / "sites", inc, h, cfg, out_root=root / "out")
    s.run(max_idle_s=1.0)
print(open(root / "out" / "timeseries.csv").read())
