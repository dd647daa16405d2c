#!/bin/bash
# 20 clips dropped at once: in-process, then on a Dask cluster whose scheduler and workers are separate processes.
#   PY=.venv/bin/python DASK=.venv/bin/dask bash benchmarks/station_20_clips.sh   (prints done/pending/failed and the history rows)
set -e
export PYTHONPATH="$(cd "$(dirname "$0")/.." && pwd)"
PY=${PY:-python}
DASK=${DASK:-dask}
R=/tmp/st20; rm -rf $R; mkdir -p $R
$PY - <<'PYEOF'
from fieldtool.synthetic import presets, render_scene
from fieldtool.project.model import load_project
from fieldtool.records.sites import create_site
import shutil, pathlib
t = render_scene(presets.get("oblique", duration_s=0.5, seed=11), "/tmp/st20/scene")
p = load_project(t.project_path); p.uncertainty.n_draws = 60
create_site("cam1", p, "/tmp/st20/sites")
for d in ("in_local", "in_dask"):
    inc = pathlib.Path("/tmp/st20") / d; inc.mkdir()
    for i in range(20):
        shutil.copy(p.resolve(p.video.path), inc / f"clip{i:02d}.mp4")
PYEOF
cd $R
/usr/bin/time -f "in-process wall %e s" $PY -m fieldtool.cli station cam1 --incoming in_local --sites sites --db local.sqlite --gauge 10.0 --stable-s 0.5 --poll-s 0.2 --exit-when-idle 2 > local.log 2>&1 || true
tail -3 local.log
$DASK scheduler --host 127.0.0.1 --port 8799 --no-dashboard > sched.log 2>&1 & SP=$!
sleep 5
$DASK worker tcp://127.0.0.1:8799 --nthreads 1 --nworkers 2 --no-dashboard > worker.log 2>&1 & WP=$!
sleep 8
/usr/bin/time -f "dask wall %e s" $PY -m fieldtool.cli station cam1 --incoming in_dask --sites sites --db dask.sqlite --gauge 10.0 --stable-s 0.5 --poll-s 0.2 --exit-when-idle 2 --dask tcp://127.0.0.1:8799 > dask.log 2>&1 || true
tail -3 dask.log
kill $WP; sleep 3; kill $SP
for d in local dask; do $PY -m fieldtool.cli station status cam1 --incoming in_$d --sites sites --db $d.sqlite | grep -E "^(done|pending|failed)"; $PY -c "
import sqlite3; c=sqlite3.connect('$d.sqlite'); print('$d history rows', c.execute('select count(*), count(distinct video_path), min(discharge_m3s), max(discharge_m3s) from measurements').fetchone())"; wc -l < in_$d/fieldtool_station/timeseries.csv; done
