"""Figures drawn ahead of ``run.outputs.write_outputs``, in a figure process beside the run.

A run's figures cost matplotlib's import (about 0.5 s) and about a second of drawing. On two cores the run's
own threads (decoding, standardising, correlating) keep both cores busy during the PIV, and only one is busy
while the run starts (imports, inputs, mapping). So the figures are drawn in a process of their own:

* :func:`start` forks it (only where ``os.fork`` exists). ``fieldtool run`` calls it before it imports the
  pipeline, so matplotlib is imported on the idle core while the run starts; ``pipeline.run_project`` calls it
  too (it takes the waiting process, or forks one then).
* :class:`Prerender` gives it three jobs:
  - the input figures (``gcp.png``, ``water_level.png``) as soon as the mapping and the level exist;
  - the field's figure (``rectified.png``: the PIV's field on the water plane, no discharge in it) as soon as
    the field is on the water plane, drawn while the parent runs STIV's analysis;
  - the discharge's figures (``vectors.png``, ``section.png``, ``profile.png`` with ``section_profile.csv``)
    when the discharge is known, drawn while the parent runs the Monte Carlo.
* After the input figures, a warm job imports the modules whose classes the field's and the discharge's jobs
  hold (the PIV's result, the discharge's), so that unpickling them later imports nothing (0.14 s at 720p,
  measured). None of those modules imports SciPy (``piv_engine`` imports ``scipy.fft`` on first use).
* A job's arguments go to the process as a pickle in a private temporary folder. The process writes its files
  there and answers each job on a pipe with what it wrote.

``run.outputs.write_outputs`` copies those files into the output folder, and draws a file itself when it is
missing: a figure that failed in the process, or a process that died or passed :data:`TIMEOUT_S`. Its error is
then reported as before. The process ends when its job pipe closes (:meth:`Prerender.close`, or the parent's
exit) and removes its folder.
"""

from __future__ import annotations

import importlib
import os
import pickle
import selectors
import shutil
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from types import SimpleNamespace

#: the longest the parent waits for a job's answer before it draws the files itself (s)
TIMEOUT_S = 30.0
#: files of the input job, the field's job and the results job
INPUT_FILES = ("gcp.png", "water_level.png")
FIELD_FILES = ("rectified.png",)
RESULT_FILES = ("vectors.png", "section.png", "profile.png", "section_profile.csv")

_waiting: _Process | None = None  # forked by start(), not yet taken by a Prerender


def can_fork() -> bool:
    """Whether figures are drawn in a figure process here (``os.fork`` exists)."""
    return hasattr(os, "fork")


def start() -> None:
    """Fork the figure process now, unless one is waiting (nothing where ``os.fork`` is missing)."""
    global _waiting
    if _waiting is None or not _waiting.alive:
        _waiting = _Process.fork()


def _take() -> _Process | None:
    global _waiting
    start()
    proc, _waiting = _waiting, None
    return proc


class _Process:
    """The parent's handle on the figure process: a job pipe, an answer pipe and the shared folder."""

    def __init__(self, pid: int, jobs_fd: int, answers_fd: int, folder: str):
        self.pid, self.jobs_fd, self.answers_fd, self.folder = pid, jobs_fd, answers_fd, folder
        self.alive = True
        self.answers: dict[int, dict[str, str]] = {}  # job -> file name -> "ok" | "none" | "failed"
        self._pending = b""
        self.n_jobs = 0

    @classmethod
    def fork(cls) -> _Process | None:
        if not can_fork():
            return None
        folder = tempfile.mkdtemp(prefix="fieldtool-fig-")
        jobs_r, jobs_w = os.pipe()
        answers_r, answers_w = os.pipe()
        try:
            pid = os.fork()
        except OSError:
            for fd in (jobs_r, jobs_w, answers_r, answers_w):
                os.close(fd)
            shutil.rmtree(folder, ignore_errors=True)
            return None
        if pid == 0:  # the figure process: serve, then leave without the parent's exit handlers
            code = 1
            try:
                os.setpgid(0, 0)  # a group of its own: Ctrl-C is the run's to handle; a kill takes its child too
                os.close(jobs_w)
                os.close(answers_r)
                _serve(jobs_r, answers_w, Path(folder))
                code = 0
            except BaseException:  # noqa: BLE001 - the parent draws what is missing and reports the error
                code = 1
            finally:
                shutil.rmtree(folder, ignore_errors=True)
                os._exit(code)
        try:
            os.setpgid(pid, pid)  # as the child does (whichever runs first)
        except OSError:
            pass
        os.close(jobs_r)
        os.close(answers_w)
        return cls(pid, jobs_w, answers_r, folder)

    def submit(self, kind: str, args: tuple) -> int | None:
        """Hand a job over; its number, or None when the process is gone."""
        if not self.alive:
            return None
        k = self.n_jobs
        self.n_jobs += 1
        try:
            tmp = Path(self.folder) / f"job{k}.tmp"
            tmp.write_bytes(pickle.dumps((kind, args), protocol=pickle.HIGHEST_PROTOCOL))
            tmp.replace(Path(self.folder) / f"job{k}.pkl")
            os.write(self.jobs_fd, f"{k}\n".encode())
        except (OSError, pickle.PicklingError, TypeError, AttributeError):
            self.stop()
            return None
        return k

    def answer(self, k: int) -> dict[str, str]:
        """What job ``k`` wrote (file name -> "ok" / "none" / "failed"); {} when the process died or timed out."""
        deadline = time.monotonic() + TIMEOUT_S
        while self.alive and k not in self.answers:
            left = deadline - time.monotonic()
            with selectors.DefaultSelector() as sel:
                sel.register(self.answers_fd, selectors.EVENT_READ)
                ready = left > 0 and bool(sel.select(left))
            if not ready:
                self.stop()
                break
            self._read()
        return self.answers.get(k, {})

    def _read(self) -> None:
        """Read what the process answered (blocks until something comes; the pipe closed: the process ended)."""
        chunk = os.read(self.answers_fd, 65536)
        if not chunk:
            self.stop()
            return
        self._pending += chunk
        *lines, self._pending = self._pending.split(b"\n")
        for line in lines:
            job, *files = line.decode().split()
            self.answers[int(job)] = dict(f.split("=", 1) for f in files)

    def stop(self) -> None:
        """Close the job pipe and reap the process (killed when it does not end within a second)."""
        if not self.alive:
            return
        self.alive = False
        for fd in (self.jobs_fd, self.answers_fd):
            try:
                os.close(fd)
            except OSError:
                pass
        deadline = time.monotonic() + 1.0
        while True:
            try:
                done, _ = os.waitpid(self.pid, os.WNOHANG)
            except ChildProcessError:
                break
            if done:
                break
            if time.monotonic() > deadline:
                try:
                    os.killpg(self.pid, 9)  # its group: the process and a child drawing for it
                except OSError:
                    os.kill(self.pid, 9)
                os.waitpid(self.pid, 0)
                break
            time.sleep(0.005)
        shutil.rmtree(self.folder, ignore_errors=True)


def _serve(jobs_fd: int, answers_fd: int, folder: Path) -> None:
    """The figure process: import the plotting modules, then draw each job as it comes."""
    # lazy, and the reason for this process: matplotlib (0.3-0.5 s to import) and OpenCV load here, not in the run
    import cv2

    from fieldtool.plots import discharge, report_figures, water_level

    cv2.setNumThreads(0)  # the run's threads have the cores; a figure's resize needs none of its own

    with os.fdopen(jobs_fd, "rb") as jobs:
        for line in jobs:
            k = int(line)
            path = folder / f"job{k}.pkl"
            kind, args = pickle.loads(path.read_bytes())
            path.unlink()
            out = folder / f"job{k}"
            out.mkdir()
            draws: tuple[tuple[str, Callable[[], object]], ...]  # (file name, draw it) per figure of the job
            if kind == "warm":  # nothing drawn: the imports of a job to come
                for module in args:
                    try:
                        importlib.import_module(module)
                    except Exception:  # noqa: BLE001 - a speed-up only: the job that needs it imports it
                        pass
                draws = ()
            elif kind == "inputs":
                project, inputs, level, mapping = args
                result = SimpleNamespace(mapping=mapping, level=level)
                draws = (
                    ("gcp.png", partial(report_figures.write_gcp, out, project, result, inputs)),
                    (
                        "water_level.png",
                        partial(water_level.plot_level, out / "water_level.png", inputs.cross_section, level),
                    ),
                )
            elif kind == "field":
                inputs, result = args
                draws = (
                    (
                        "rectified.png",
                        partial(discharge.plot_rectified, out / "rectified.png", inputs.first_color, result, inputs),
                    ),
                )
            else:
                inputs, result, cross_section = args
                # in two halves of about equal time (720p: vectors 0.19-0.3 s; profile and section 0.1-0.15 s each):
                # the run waits for both
                draws = (
                    (
                        "vectors.png",
                        partial(discharge.plot_vectors, out / "vectors.png", inputs.first_color, result, inputs),
                    ),
                    ("profile.png", partial(report_figures.write_profile, out, result)),
                    ("section.png", partial(discharge.plot_section, out / "section.png", cross_section, result)),
                )
            status = _draw_in_two(draws, out)
            if "profile.png" in status:
                status["section_profile.csv"] = status["profile.png"]
            os.write(answers_fd, (f"{k} " + " ".join(f"{n}={s}" for n, s in status.items()) + "\n").encode())


def _draw(draws) -> dict[str, str]:
    status = {}
    for name, draw in draws:
        try:
            status[name] = "none" if draw() is None else "ok"
        except Exception:  # noqa: BLE001 - drawn again by write_outputs, which reports it
            status[name] = "failed"
    return status


def _draw_in_two(draws, out: Path) -> dict[str, str]:
    """Draw the first half of ``draws`` in a forked child and the rest here, so that the figures use whatever
    the run leaves of two cores (at the end of a run, its Monte Carlo takes one). A child that fails leaves
    its figures as "failed" (the run draws them)."""
    half = len(draws) // 2
    if half == 0:
        return _draw(draws)
    try:
        pid = os.fork()
    except OSError:
        return _draw(draws)
    if pid == 0:
        code = 1
        try:
            done = _draw(draws[:half])
            (out / "first-half.tmp").write_text(" ".join(f"{n}={st}" for n, st in done.items()))
            (out / "first-half.tmp").replace(out / "first-half")
            code = 0
        finally:
            os._exit(code)
    status = _draw(draws[half:])
    os.waitpid(pid, 0)
    try:
        first = dict(f.split("=", 1) for f in (out / "first-half").read_text().split())
    except OSError:
        first = {}
    return {**{name: first.get(name, "failed") for name, _ in draws[:half]}, **status}


class Prerender:
    """The run's figures, drawn in the figure process. :meth:`file` gives a file's bytes (or None)."""

    def __init__(self, project, inputs, level, mapping, warm: tuple[type, ...] = ()):
        """Start drawing the input figures; ``warm``: classes the velocity figures' job will hold, their modules
        imported by the process once the input figures are drawn."""
        self._proc = _take()
        self._jobs: dict[str, int] = {}
        if self._proc is not None:
            self._submit("inputs", (project, inputs, level, mapping), INPUT_FILES)
            if warm:
                self._submit("warm", tuple(sorted({c.__module__ for c in warm})), ())

    @property
    def active(self) -> bool:
        """A figure process is drawing (False: the parent draws every figure)."""
        return self._proc is not None and self._proc.alive

    def _submit(self, kind: str, args: tuple, names: tuple[str, ...]) -> None:
        k = self._proc.submit(kind, args) if self._proc is not None else None
        if k is not None:
            self._jobs.update(dict.fromkeys(names, k))

    def field(self, inputs, piv, world_u, world_v, section, mapping) -> None:
        """Start drawing :data:`FIELD_FILES` (the PIV's field, ``world_u``/``world_v`` m/s on the water plane,
        and the section: nothing of the discharge, which STIV's analysis may still change)."""
        if self.active:
            result = SimpleNamespace(piv=piv, world_u=world_u, world_v=world_v, section=section, mapping=mapping)
            self._submit("field", (inputs, result), FIELD_FILES)

    def results(self, inputs, discharge, piv, world_u, world_v, section, mapping, cross_section) -> None:
        """Start drawing :data:`RESULT_FILES` (they depend on the field and the discharge, not on the Monte
        Carlo that the parent runs meanwhile)."""
        if self.active:
            result = SimpleNamespace(
                discharge=discharge, piv=piv, world_u=world_u, world_v=world_v, section=section, mapping=mapping
            )
            self._submit("results", (inputs, result, cross_section), RESULT_FILES)

    def file(self, name: str) -> bytes | None:
        """The file's bytes; b"" when it has nothing to show (no GCPs); None when not drawn here."""
        k = self._jobs.get(name)
        if k is None or self._proc is None:
            return None
        status = self._proc.answer(k).get(name)
        if status == "none":
            return b""
        if status != "ok":
            return None
        try:
            return (Path(self._proc.folder) / f"job{k}" / name).read_bytes()
        except OSError:
            return None

    def close(self) -> None:
        """End the figure process (its files are read by then)."""
        if self._proc is not None:
            self._proc.stop()
