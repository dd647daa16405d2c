"""The station's series on the rerun stream: each measured clip logs its discharge, interval, level and grade
on the clip's own time (``clip_time``, UTC) and a text line; a failed clip logs its reason.

Entities: ``station/discharge_m3s``, ``station/ci95_low_m3s``, ``station/ci95_high_m3s``,
``station/water_level_m`` (``Scalars``) and ``station/log`` (``TextLog``). The target is a ``.rrd`` file
(saved) or a viewer address ``rerun+http://HOST:PORT/proxy`` (connected); logging never stops the station.
"""

from __future__ import annotations

import uuid
from datetime import datetime
from pathlib import Path

import rerun as rr

from fieldtool.viewer.rerun_log import check_url


class StationSeries:
    """Logs the station's measurements to ``target`` (an .rrd path or a rerun viewer address)."""

    def __init__(self, target: str, site: str = ""):
        self.warnings: list[str] = []
        self.failed = False
        self.rec = rr.RecordingStream("fieldtool-station", recording_id=str(uuid.uuid4()))
        if "://" in target:
            self.target = check_url(target, "--rerun")
            self.rec.connect_grpc(self.target)
        else:
            self.target = str(Path(target).expanduser())
            Path(self.target).parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(self.target)
        self.site = site

    def _guard(self, fn) -> None:
        if self.failed:
            return
        try:
            fn()
        except Exception as e:  # noqa: BLE001 - logging must never stop the station
            self.failed = True
            self.warnings.append(f"rerun logging stopped: {type(e).__name__}: {e}")

    def measurement(
        self,
        time_utc: str,
        q: float | None,
        lo: float | None,
        hi: float | None,
        level_m: float | None,
        grade: str | None,
        label: str,
    ) -> None:
        def log():
            t = datetime.fromisoformat(time_utc.replace("Z", "+00:00"))
            self.rec.set_time("clip_time", timestamp=t)
            for name, v in (
                ("discharge_m3s", q),
                ("ci95_low_m3s", lo),
                ("ci95_high_m3s", hi),
                ("water_level_m", level_m),
            ):
                if v is not None:
                    self.rec.log(f"station/{name}", rr.Scalars(float(v)))
            self.rec.log(
                "station/log",
                rr.TextLog(f"{label}: Q {q} m³/s, level {level_m} m, {grade or 'no grade'}", level="INFO"),
            )

        self._guard(log)

    def failure(self, label: str, reason: str) -> None:
        self._guard(lambda: self.rec.log("station/log", rr.TextLog(f"{label}: failed: {reason}", level="ERROR")))

    def close(self) -> None:
        self._guard(lambda: self.rec.flush())
