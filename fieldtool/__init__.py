"""fieldtool: river discharge from a surface video (LSPIV) and a surveyed cross-section."""

__version__ = "0.1.0"

import os as _os

# FFmpeg inside OpenCV prints its own lines ("moov atom not found") on stderr for a broken clip; the
# message fieldtool gives (one line naming the file) is enough. FIELDTOOL_DEBUG=1 keeps them.
if not _os.environ.get("FIELDTOOL_DEBUG"):
    _os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    _os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")
# OpenBLAS' worker threads spin while they wait for work; fieldtool's BLAS and LAPACK calls are small (fits, a few
# solves), and the run's own threads keep the cores busy. One thread (unless the user sets it): about 0.2 s less
# CPU on a 1080p run, the spinning gone. Read by OpenBLAS when numpy/scipy load it, so only before they import.
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# OpenCV's pool threads spin (sched_yield) after each parallel call, waiting for the next one: at 720p 0.2 s of CPU
# (perf) taken from the run's decoding and standardising on two cores. They sleep at once instead (read when cv2
# loads; benchmarks/tree_ab.py --before-env compares): CPU -0.2 to -0.45 s a run, wall time within the noise.
_os.environ.setdefault("OPENCV_THREAD_POOL_ACTIVE_WAIT_WORKER", "0")
_os.environ.setdefault("OPENCV_THREAD_POOL_ACTIVE_WAIT_MAIN", "0")
# matplotlib's own two lines when HOME is unwritable: a folder of this user's own instead (fieldtool.mplconfig)
from fieldtool.mplconfig import ensure_config_dir as _ensure_mpl_config_dir  # noqa: E402

_ensure_mpl_config_dir()
