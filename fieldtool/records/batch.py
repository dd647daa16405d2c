"""Batch runs: many measurements, each a task, on local cores or a Dask distributed cluster.

Items are project files: either given as a list, or written from a site for every video of a folder
(with the water level of each video from a CSV, or one level for all). Each item runs
:func:`fieldtool.run.pipeline.run_project` into its own output folder; a failing item is reported with
its reason and does not stop the others.

Executors:

- local (default): a ``concurrent.futures.ProcessPoolExecutor`` with one process per core
  (``workers``); ``workers=1`` runs in this process. A worker process that dies (out of memory, a
  crash in a native library) breaks the pool: the unfinished items are retried once in a fresh pool,
  then reported as failed.
- Dask (``scheduler="tcp://HOST:PORT"``): ``distributed.Client(scheduler)``; ``dask[distributed]``
  is imported only then. The workers must see the same paths as this machine (a shared file
  system): they read the videos and write the output folders.

Only this process writes the history (SQLite must not be shared over a network file system): the
workers return each run's summary and the results are recorded as they arrive.
"""

from __future__ import annotations

import csv
import json
import math
import multiprocessing as mp
import os
import sys
import time
import traceback
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path

import cv2

from fieldtool.errors import FieldToolError, InputFileError, ParameterError
from fieldtool.processing.piv import set_fft_workers
from fieldtool.project.model import load_project, project_to_dict
from fieldtool.project.textfile import read_text
from fieldtool.records.history import History, input_hash, video_datetime
from fieldtool.records.report import write_report
from fieldtool.records.sites import Site, new_measurement
from fieldtool.run.outputs import json_default
from fieldtool.run.pipeline import run_project

VIDEO_EXTS = {".mp4", ".mov", ".avi", ".mkv", ".m4v", ".mts", ".m2ts", ".mpg", ".mpeg", ".wmv", ".webm", ".3gp"}


@dataclass
class BatchItem:
    """One measurement to run: a project file and the folder its results go to."""

    label: str  # what the user calls it (video or project file name)
    project_path: str
    out_dir: str
    site: str = ""  # site recorded in the history
    error: str | None = None  # refused before running (e.g. no water level for this video)


@dataclass
class ItemResult:
    """What became of one item. ``summary`` is the run's result.json dict when ``ok``."""

    item: BatchItem
    ok: bool
    summary: dict | None = None
    error: str | None = None
    input_hash: str = ""
    video_path: str = ""
    video_time: tuple[str | None, str | None] = (None, None)
    seconds: float = 0.0  # wall time of the run in its worker (s)
    cpu_s: float = 0.0  # CPU time of the worker process during the run, all its threads (s)
    history_id: int | None = None
    skipped: bool = False  # already in the history with the same input hash


@dataclass
class BatchResult:
    results: list[ItemResult] = field(default_factory=list)
    wall_s: float = 0.0
    executor: str = ""

    @property
    def failed(self) -> list[ItemResult]:
        return [r for r in self.results if not r.ok]

    @property
    def succeeded(self) -> list[ItemResult]:
        return [r for r in self.results if r.ok]


# ---------------------------------------------------------------------------------------------
# planning


def read_levels(path: Path | str) -> dict[str, float]:
    """Water levels per video from a CSV: a header with a video column (``video``, ``file`` or
    ``name``) and a level column (``water_level_m``, ``level_m`` or ``level``); comma or semicolon.
    Keys are video file names (as written, and their stem)."""
    path = Path(path)

    text = read_text(path, "levels file")
    head = text.splitlines()[0] if text.strip() else ""
    try:
        dialect = csv.Sniffer().sniff(head or ",", delimiters=",;\t")
    except csv.Error:
        raise InputFileError(
            f"{path}: the header {head[:60]!r} has no ',' ';' or tab between columns; write "
            "'video,water_level_m' and one line per video"
        ) from None
    rows = list(csv.DictReader(text.splitlines(), dialect=dialect))
    if not rows:
        raise InputFileError(f"{path}: no rows; write a header 'video,water_level_m' and one line per video")
    cols = {c.strip().lower(): c for c in rows[0].keys() if c}
    vcol = next((cols[c] for c in ("video", "file", "name") if c in cols), None)
    lcol = next((cols[c] for c in ("water_level_m", "level_m", "level") if c in cols), None)
    if vcol is None or lcol is None:
        raise InputFileError(f"{path}: needs the columns 'video' and 'water_level_m' (found: {', '.join(cols)})")
    out: dict[str, float] = {}
    for i, r in enumerate(rows, 2):
        name = (r.get(vcol) or "").strip()
        if not name:
            continue
        try:
            level = float((r.get(lcol) or "").strip().replace(",", "."))
        except ValueError:
            raise InputFileError(
                f"{path}, line {i}: water level {r.get(lcol)!r} of {name} is not a number (m)"
            ) from None
        if not math.isfinite(level) or abs(level) > 1e5:
            raise InputFileError(f"{path}, line {i}: water level {r.get(lcol)!r} of {name} is not a level in metres")
        out[name] = level
        out.setdefault(Path(name).stem, level)
    return out


def plan_site_folder(
    site: Site,
    folder: Path | str,
    out_root: Path | str,
    *,
    levels: dict[str, float] | None = None,
    level_m: float | None = None,
    level_uncertainty_m: float | None = None,
) -> list[BatchItem]:
    """One item per video in ``folder``: writes ``out_root/<video stem>/project.toml`` from the site.

    A video without a level (not in ``levels`` and no ``level_m``) becomes an item that fails with
    that reason; a level listed for a video that is not in the folder, too."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputFileError(f"{folder}: not a folder of videos")
    videos = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_EXTS)
    if not videos:
        raise InputFileError(f"{folder}: no video files ({', '.join(sorted(VIDEO_EXTS))})")
    out_root = Path(out_root)
    items = []
    for v in videos:
        out_dir = out_root / v.stem
        item = BatchItem(
            label=v.name, project_path=str(out_dir / "project.toml"), out_dir=str(out_dir / "results"), site=site.name
        )
        lv = level_m
        if levels is not None:
            lv = levels.get(v.name, levels.get(v.stem, level_m))
        if lv is None:
            item.error = f"no water level for {v.name}: add it to the levels file (or give --level)"
        else:
            try:
                new_measurement(site, v, lv, out_dir, level_uncertainty_m=level_uncertainty_m, force=True)
            except FieldToolError as e:
                item.error = str(e)
        items.append(item)
    if levels is not None:
        have = {v.name for v in videos} | {v.stem for v in videos}
        for name in sorted(k for k in levels if k not in have and Path(k).stem not in have and "." in k):
            items.append(
                BatchItem(
                    label=name,
                    project_path="",
                    out_dir="",
                    site=site.name,
                    error=f"{name} is in the levels file but not in {folder}",
                )
            )
    return items


def plan_projects(paths: list[Path | str], *, out_root: Path | str | None = None, site: str = "") -> list[BatchItem]:
    """One item per project file. Results go to ``out_root/<n>_<project folder name>/`` when given,
    else to ``out/`` beside each project file (as `fieldtool run`)."""
    items = []
    for i, p in enumerate(paths):
        p = Path(p)
        if out_root is not None:
            out = Path(out_root) / f"{i + 1:03d}_{p.resolve().parent.name}_{p.stem}"
        else:
            out = p.resolve().parent / "out"
        item = BatchItem(label=str(p), project_path=str(p), out_dir=str(out), site=site)
        if not p.is_file():
            item.error = f"{p}: project file not found"
        items.append(item)
    return items


def read_list(path: Path | str) -> list[str]:
    """Project files listed one per line in a text file ('#' comments; relative to the list's folder)."""
    path = Path(path)

    lines = read_text(path, "list of projects").splitlines()
    out = []
    for ln in lines:
        ln = ln.split("#", 1)[0].strip()
        if ln:
            p = Path(ln).expanduser()
            out.append(str(p if p.is_absolute() else path.resolve().parent / p))
    return out


# ---------------------------------------------------------------------------------------------
# the task


def _single_threaded() -> None:
    """One OpenCV and one FFT thread in this process: the batch already uses every core."""
    cv2.setNumThreads(1)
    set_fft_workers(1)


def run_item(item: BatchItem, single_thread: bool = False) -> ItemResult:
    """Run one item: load the project, hash its inputs, run it into ``item.out_dir``. ``single_thread``
    for a worker that shares the machine with others (Dask). Never raises: failures come back as
    ``ok=False`` with the reason."""
    t0, c0 = time.perf_counter(), time.process_time()
    res = ItemResult(item=item, ok=False)
    try:
        if single_thread:
            _single_threaded()

        project = load_project(item.project_path)
        res.video_path = str(project.resolve(project.video.path)) if project.video.path else ""
        res.input_hash = input_hash(project_to_dict(project), project.root)
        if res.video_path:
            res.video_time = video_datetime(res.video_path)
        result = run_project(project, item.out_dir)
        res.summary = json.loads(json.dumps(result.summary(), default=json_default))
        res.ok = True
    except FieldToolError as e:
        res.error = str(e)
    except MemoryError:
        res.error = "out of memory; use a shorter clip (video.end_s), a larger video.step, or fewer workers"
    except Exception as e:  # noqa: BLE001 - one item's bug must not stop the batch; it is reported
        tb = traceback.extract_tb(e.__traceback__)
        where = f" (at {Path(tb[-1].filename).name}:{tb[-1].lineno})" if tb else ""
        res.error = f"{type(e).__name__}: {e}{where}"
    res.seconds = time.perf_counter() - t0
    res.cpu_s = time.process_time() - c0
    return res


def _init_worker() -> None:
    """One thread per worker process: the pool already uses every core."""
    _single_threaded()


# ---------------------------------------------------------------------------------------------
# executors

OnDone = Callable[[ItemResult, int, int], None]


# imported once by the fork server, so that each worker process starts with them loaded
_PRELOAD = [
    "fieldtool.run.pipeline",
    "fieldtool.processing.piv",
    "fieldtool.plots.discharge",
    "fieldtool.records.batch",
]


def _mp_context():
    """Fork server where there is one (safe with threads, and workers fork from a process that has
    already imported numpy, OpenCV, SciPy and matplotlib), else spawn."""
    if "forkserver" in mp.get_all_start_methods() and sys.platform != "darwin":
        ctx = mp.get_context("forkserver")
        ctx.set_forkserver_preload(_PRELOAD)
        return ctx
    return mp.get_context("spawn")


def _run_local(items: list[BatchItem], workers: int, emit: Callable[[ItemResult], None]) -> None:
    if workers <= 1:
        for it in items:
            emit(run_item(it))
        return
    pending = list(items)
    for attempt in (1, 2):
        if not pending:
            return
        lost: list[BatchItem] = []
        with ProcessPoolExecutor(
            max_workers=min(workers, len(pending)), mp_context=_mp_context(), initializer=_init_worker
        ) as pool:
            futs: dict[Future, BatchItem] = {pool.submit(run_item, it): it for it in pending}
            todo = set(futs)
            while todo:
                done, todo = wait(todo, return_when=FIRST_COMPLETED)
                for f in done:
                    try:
                        r = f.result()
                    except BrokenProcessPool:
                        lost.append(futs[f])
                        continue
                    except Exception as e:  # noqa: BLE001 - e.g. a result that cannot travel back
                        r = ItemResult(item=futs[f], ok=False, error=f"the worker failed: {type(e).__name__}: {e}")
                    r.item = futs[f]  # the original, not the copy that travelled
                    emit(r)
        if lost and attempt == 2:
            for it in lost:
                emit(
                    ItemResult(
                        item=it,
                        ok=False,
                        error="the worker process died while running it (out of memory "
                        "or a crash in a native library); it failed twice",
                    )
                )
        pending = lost


def _run_dask(items: list[BatchItem], scheduler: str, emit: Callable[[ItemResult], None]) -> None:
    try:
        from distributed import Client, as_completed  # lazy: Dask (optional, 0.2-0.4 s) only for --scheduler
    except ImportError as e:
        raise ParameterError(
            "--scheduler needs Dask distributed on this machine: pip install 'dask[distributed]' "
            "(the workers need it and fieldtool too)"
        ) from e
    try:
        client = Client(scheduler, timeout="20s", set_as_default=False)
    except (OSError, TimeoutError) as e:
        raise ParameterError(
            f"--scheduler {scheduler}: cannot reach the Dask scheduler ({e}); start it with "
            "`dask scheduler` and workers with `dask worker ADDRESS --nthreads 1`"
        ) from e
    try:
        futs = {
            client.submit(run_item, it, True, key=f"fieldtool-batch-{i}-{os.getpid()}-{time.time_ns()}", pure=False): it
            for i, it in enumerate(items)
        }
        for f in as_completed(list(futs), loop=client.loop):
            try:
                r = f.result()
            except Exception as e:  # noqa: BLE001 - KilledWorker, lost connection, unpicklable result...
                r = ItemResult(item=futs[f], ok=False, error=f"the Dask task failed: {type(e).__name__}: {e}")
            r.item = futs[f]  # the original, not the copy that travelled
            emit(r)
    finally:
        client.close()


def check_distinct_outputs(items: list[BatchItem]) -> None:
    """Refuse two items writing into the same output folder (the second would replace the first's
    results while both are recorded as done)."""
    seen: dict[str, BatchItem] = {}
    for it in items:
        if not it.out_dir or it.error:
            continue
        k = str(Path(it.out_dir).resolve())
        if k in seen:
            raise ParameterError(
                f"{seen[k].label} and {it.label} both write into {k}; give each project its own "
                "output folder (or use --out ROOT, which makes one per project)"
            )
        seen[k] = it


def run_batch(
    items: list[BatchItem],
    *,
    history: History | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    skip_existing: bool = False,
    reports: bool = False,
    on_done: OnDone | None = None,
) -> BatchResult:
    """Run ``items``; record every success in ``history`` (when given) as it arrives.

    Parameters
    ----------
    items : from :func:`plan_site_folder`, :func:`plan_projects`.
    history : where results are recorded (None = not recorded).
    workers : local processes (None = all cores); ignored with ``scheduler``.
    scheduler : Dask scheduler address ``tcp://HOST:PORT``; None = local processes.
    skip_existing : skip items whose input hash is already in ``history`` (hashes the videos here).
    reports : also write ``report.html`` into each output folder.
    on_done : called with (result, done, total) after each item.

    Returns
    -------
    BatchResult, results in the order of ``items``.
    """
    check_distinct_outputs(items)
    t0 = time.perf_counter()
    total = len(items)
    by_item: dict[int, ItemResult] = {}
    runnable: list[BatchItem] = []

    def emit(r: ItemResult) -> None:
        if r.ok and history is not None and not r.skipped and r.summary is not None:
            try:
                r.history_id = history.record_summary(
                    r.summary,
                    site=r.item.site,
                    output_dir=Path(r.item.out_dir).resolve(),
                    video_path=r.video_path,
                    video_time=r.video_time,
                    input_hash=r.input_hash,
                )
            except FieldToolError as e:
                r.ok, r.error = False, f"ran, but could not be recorded in the history: {e}"
        if r.ok and reports and not r.skipped:
            try:
                m = history.get(r.history_id) if history is not None and r.history_id else None
                write_report(r.item.out_dir, measurement=m)
            except FieldToolError as e:
                if r.summary is not None:
                    r.summary.setdefault("warnings", []).append(f"report not written: {e}")
        by_item[id(r.item)] = r
        if on_done is not None:
            on_done(r, len(by_item), total)

    for it in items:
        if it.error:
            emit(ItemResult(item=it, ok=False, error=it.error))
            continue
        if skip_existing and history is not None:
            try:
                p = load_project(it.project_path)
                h = input_hash(project_to_dict(p), p.root)
            except FieldToolError as e:
                emit(ItemResult(item=it, ok=False, error=str(e)))
                continue
            old = history.query(input_hash=h, limit=1)
            if old:
                emit(
                    ItemResult(
                        item=it,
                        ok=True,
                        skipped=True,
                        input_hash=h,
                        history_id=old[0].id,
                        summary={"discharge_m3s": old[0].discharge_m3s, "water_level_m": old[0].water_level_m},
                    )
                )
                continue
        runnable.append(it)

    if runnable:
        if scheduler:
            _run_dask(runnable, scheduler, emit)
            executor = f"dask {scheduler}"
        else:
            n = workers or os.cpu_count() or 1
            _run_local(runnable, n, emit)
            executor = f"local, {min(n, len(runnable))} process(es)" if n > 1 else "local, in this process"
    else:
        executor = "nothing to run"
    return BatchResult([by_item[id(it)] for it in items], time.perf_counter() - t0, executor)
