"""fieldtool/__init__.py's process settings for the libraries it loads: set before they import, the user's own
values kept."""

import json
import os
import subprocess
import sys

KEYS = ("OPENBLAS_NUM_THREADS", "OPENCV_THREAD_POOL_ACTIVE_WAIT_WORKER", "OPENCV_THREAD_POOL_ACTIVE_WAIT_MAIN")
PROBE = (
    "import json, os, sys; import fieldtool; "
    "assert 'cv2' not in sys.modules and 'numpy' not in sys.modules, 'loaded before the settings'; "
    f"print(json.dumps({{k: os.environ.get(k) for k in {KEYS!r}}}))"
)


def _probe(env: dict) -> dict:
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def test_settings_are_set_before_the_libraries_load():
    env = {k: v for k, v in os.environ.items() if k not in KEYS}
    got = _probe(env)
    assert got == {
        "OPENBLAS_NUM_THREADS": "1",
        "OPENCV_THREAD_POOL_ACTIVE_WAIT_WORKER": "0",
        "OPENCV_THREAD_POOL_ACTIVE_WAIT_MAIN": "0",
    }


def test_the_users_own_values_are_kept():
    env = {k: v for k, v in os.environ.items() if k not in KEYS}
    env.update(OPENBLAS_NUM_THREADS="2", OPENCV_THREAD_POOL_ACTIVE_WAIT_WORKER="2000")
    got = _probe(env)
    assert got["OPENBLAS_NUM_THREADS"] == "2"
    assert got["OPENCV_THREAD_POOL_ACTIVE_WAIT_WORKER"] == "2000"
    assert got["OPENCV_THREAD_POOL_ACTIVE_WAIT_MAIN"] == "0"
