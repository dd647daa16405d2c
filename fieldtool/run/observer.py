"""What a run tells the world while it runs: the ``progress(stage, done, total)`` callback's type, the
:class:`Observer` (the rerun logger is one) and :class:`Guarded`, which calls an observer so that its
failures become warnings: logging never fails a measurement."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # for the annotation only: result imports nothing of the observer
    from fieldtool.run.result import RunResult

Progress = Callable[[str, int, int], None]


class Observer:
    """Receives what the pipeline computes, as it computes it. Every method is optional; an
    observer must never raise (the pipeline guards it anyway and reports a warning)."""

    def stage(self, name: str) -> None: ...

    def frame(self, index: int, t_s: float, raw: np.ndarray, filtered: np.ndarray) -> None: ...

    def geometry(self, pair_discharge: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], float]) -> None:
        """Called once before PIV: ``pair_discharge(x, y, u_px_s, v_px_s) -> m³/s`` for live discharge."""

    def pair(
        self,
        i: int,
        t_s: float,
        x: np.ndarray,
        y: np.ndarray,
        u_px_s: np.ndarray,
        v_px_s: np.ndarray,
        valid: np.ndarray,
    ) -> None: ...

    def result(self, result: RunResult) -> None: ...

    def warning(self, message: str) -> None: ...

    def wants_every_frame(self) -> bool:
        """True while the observer wants ``every_frame`` (the overlay video: run/overlay_stage.py)."""
        return False

    def every_frame(self, index: int, t_s: float, image: np.ndarray) -> None:
        """Every working frame (lens, stabilisation) while ``wants_every_frame()``; ``frames_done()`` ends a pass."""

    def frames_done(self) -> None: ...


class Guarded:
    """Calls an observer, turning its failures into warnings: logging never fails a run."""

    def __init__(self, obs: Observer | None, warnings: list[str]):
        self.obs, self.warnings, self.failed = obs, warnings, False

    def __call__(self, method: str, *args) -> None:
        if self.obs is None or self.failed:
            return
        try:
            getattr(self.obs, method)(*args)
        except Exception as e:  # noqa: BLE001 - a logger must not break a measurement
            self.failed = True
            self.warnings.append(f"live logging stopped: {type(e).__name__}: {e}")

    @property
    def active(self) -> bool:
        """An observer is attached and has not failed."""
        return self.obs is not None and not self.failed

    def wants_every_frame(self) -> bool:
        return self.active and bool(getattr(self.obs, "wants_every_frame", bool)())
