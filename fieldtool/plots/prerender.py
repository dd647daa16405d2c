"""Figures that need only the inputs, drawn in a background thread while the PIV runs.

The GCP picture (``gcp.png``) and the water-level plot (``water_level.png``) depend on the mapping and the
level, not on the velocities. During the PIV the caller's thread mostly waits for the decoding and
standardising threads, so these two are drawn then, as PNG bytes in memory; ``pipeline.write_outputs`` writes
the bytes (and draws a figure itself when its bytes are missing: a figure that failed here is drawn again
there, where its error is reported as before).
"""

from __future__ import annotations

import tempfile
import threading
from pathlib import Path
from types import SimpleNamespace


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
        return self._png.get(name)
