"""Figures drawn ahead of ``pipeline.write_outputs``, while the run computes something else.

* The GCP picture (``gcp.png``) and the water-level plot (``water_level.png``) depend on the mapping and the
  level, not on the velocities. During the PIV the caller's thread mostly waits for the decoding and
  standardising threads, so these two are drawn then, in a thread, as PNG bytes in memory.
* The velocity figures (``vectors.png``, ``rectified.png``, ``section.png``) depend on the field and the
  discharge, not on the uncertainty. :meth:`Prerender.fork_results` draws them in a forked child process
  while the parent runs the Monte Carlo (pure Python, one core): on two cores that hides about half a second.
  Only where ``os.fork`` exists; the child's threads of OpenCV are off, and a child that fails or takes more
  than :data:`FORK_TIMEOUT_S` leaves its figures to the parent.

``pipeline.write_outputs`` writes the bytes, and draws a figure itself when its bytes are missing: a figure
that failed here is drawn again there, where its error is reported as before.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import threading
import time
from pathlib import Path
from types import SimpleNamespace

#: the longest the parent waits for the forked figures before it draws them itself (s)
FORK_TIMEOUT_S = 30.0
FORKED = ("vectors.png", "rectified.png", "section.png")


class Prerender:
    """Start drawing at once; :meth:`png` waits for the thread and gives a figure's bytes (or None)."""

    def __init__(self, project, inputs, level, mapping):
        self._png: dict[str, bytes | None] = {}
        self._thread = threading.Thread(target=self._run, args=(project, inputs, level, mapping), daemon=True)
        self._thread.start()

    def _run(self, project, inputs, level, mapping) -> None:
        try:
            from . import report_figures
            from .water_level import plot_level

            result = SimpleNamespace(mapping=mapping, level=level)
            with tempfile.TemporaryDirectory(prefix="fieldtool-fig-") as tmp:
                out = Path(tmp)
                for name, draw in (("gcp.png", lambda: report_figures.write_gcp(out, project, result, inputs)),
                                   ("water_level.png", lambda: plot_level(out / "water_level.png",
                                                                          inputs.cross_section, level))):
                    try:
                        written = draw()
                    except Exception:  # noqa: BLE001 - drawn again by write_outputs, which reports it
                        self._png[name] = None
                        continue
                    self._png[name] = (out / name).read_bytes() if written is not None else b""
        except Exception:  # noqa: BLE001 - as above
            pass

    def png(self, name: str) -> bytes | None:
        """The figure's PNG bytes; b"" when it has nothing to show (no GCPs); None when not drawn here."""
        self._thread.join()
        if name in FORKED:
            self._collect()
        return self._png.get(name)

    _pid: int | None = None
    _dir: str | None = None

    def fork_results(self, inputs, discharge, piv, world_u, world_v, section, mapping, cross_section,
                     before=()) -> None:
        """Start drawing :data:`FORKED` in a child process (nothing where ``os.fork`` is missing). ``before``:
        threads to join first, so that no import or figure is half done in the parent when it forks."""
        if not hasattr(os, "fork") or self._pid is not None:
            return
        self._thread.join()
        for t in before:
            t.join()
        self._dir = tempfile.mkdtemp(prefix="fieldtool-fig-")
        try:
            pid = os.fork()
        except OSError:
            return
        if pid == 0:  # the child: draw, write, leave without running the parent's exit handlers
            code = 1
            try:
                import cv2

                cv2.setNumThreads(0)  # the parent's OpenCV worker threads do not exist here
                from . import discharge as plots

                result = SimpleNamespace(discharge=discharge, piv=piv, world_u=world_u, world_v=world_v,
                                         section=section, mapping=mapping)
                out = Path(self._dir)
                plots.plot_vectors(out / "vectors.png", inputs.first_color, result, inputs)
                plots.plot_rectified(out / "rectified.png", inputs.first_color, result, inputs)
                plots.plot_section(out / "section.png", cross_section, result)
                code = 0
            except BaseException:  # noqa: BLE001 - the parent draws them again and reports the error
                code = 1
            finally:
                os._exit(code)
        self._pid = pid

    def _collect(self) -> None:
        """Wait for the forked child (at most :data:`FORK_TIMEOUT_S`) and read its figures."""
        if self._pid is None:
            return
        pid, self._pid = self._pid, None
        deadline = time.monotonic() + FORK_TIMEOUT_S
        status = None
        while status is None:
            done, st = os.waitpid(pid, os.WNOHANG)
            if done:
                status = st
            elif time.monotonic() > deadline:
                os.kill(pid, 9)
                os.waitpid(pid, 0)
                break
            else:
                time.sleep(0.01)
        try:
            if status is not None and os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0:
                for name in FORKED:
                    f = Path(self._dir) / name
                    if f.is_file():
                        self._png[name] = f.read_bytes()
        finally:
            shutil.rmtree(self._dir, ignore_errors=True)

    def close(self) -> None:
        """Reap a child whose figures were not asked for (a run that failed after forking)."""
        if self._pid is not None:
            self._collect()
