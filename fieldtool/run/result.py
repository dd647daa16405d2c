"""What one run produced (:class:`RunResult`) and its ``summary()``, the content of ``result.json``."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from fieldtool import __version__
from fieldtool.processing import discharge as dq
from fieldtool.processing import ortho
from fieldtool.project.sections import summarize

if TYPE_CHECKING:  # annotations only
    from fieldtool.plots.prerender import Prerender
    from fieldtool.processing.piv import PivResult
    from fieldtool.processing.quality import Quality
    from fieldtool.processing.uncertainty import McResult
    from fieldtool.processing.water_level import LevelResult


@dataclass
class RunResult:
    """Everything one run produced. ``summary()`` is what ``result.json`` holds."""

    discharge: dq.DischargeResult
    q_pairs: np.ndarray
    level: LevelResult
    mapping: ortho.OrthoMapping
    piv: PivResult
    section: dq.SectionGeometry
    world_u: np.ndarray
    world_v: np.ndarray
    out_dir: Path | None
    files: dict[str, str] = field(default_factory=dict)
    timings_s: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    stabilization: dict | None = None
    project: dict = field(default_factory=dict)
    piv_reused: bool = False  # the PIV field came from the output folder's piv_cache.npz
    stiv: dict | None = None  # STIV beside PIV per subsection (stiv_stage.finish); None when [stiv] enabled = false
    uncertainty: McResult | None = None
    quality: Quality | None = None
    sections: list = field(default_factory=list)  # several sections: the main one first (fieldtool.project.sections)
    robust: dict | None = None  # facts of the robust stages (processing/surface.py, robust.py, planning.py)
    piv_fast: dict | None = None  # region box and pair sampling of the fast path (see piv_region / run_piv_fast)
    video: dict = field(default_factory=dict)  # the clip's metadata (records.video_meta.video_info)
    uncertainty_standard: dict | None = None  # ISO 748 and IVE beside the Monte Carlo (run/standard_stage.py)
    prerendered: Prerender | None = None  # figures drawn during the PIV
    overlay: object | None = None  # run.overlay_stage.Recorder (overlay.mp4 drawn as the frames streamed) or None

    def summary(self) -> dict:
        d = self.discharge
        qp = self.q_pairs[np.isfinite(self.q_pairs)]
        lv = self.level
        return {
            "discharge_m3s": d.discharge_m3s,
            "discharge_ci95_m3s": (
                list(self.uncertainty.ci95_m3s)
                if self.uncertainty is not None and np.all(np.isfinite(self.uncertainty.ci95_m3s))
                else None
            ),
            "uncertainty": self.uncertainty.to_dict() if self.uncertainty is not None else None,
            "uncertainty_standard": self.uncertainty_standard,  # ISO 748 and IVE, 2σ (run/standard_stage.py)
            "quality": self.quality.to_dict() if self.quality is not None else None,
            "sections": self.sections or None,
            "sections_summary": sections_summary(self.sections),
            # spread of the discharges of single frame pairs (the sampled pairs, n_pairs_with_vectors of them):
            # not an interval of Q, which averages every pair (see discharge_ci95_m3s)
            "discharge_p05_m3s": float(np.percentile(qp, 5)) if len(qp) else None,
            "discharge_p95_m3s": float(np.percentile(qp, 95)) if len(qp) else None,
            "discharge_pairs_median_m3s": float(np.median(qp)) if len(qp) else None,
            "water_level_m": d.water_level_m,
            "water_level_method": lv.method,
            "water_level_uncertainty_m": lv.uncertainty_m,
            "wetted_area_m2": d.wetted_area_m2,
            "wetted_width_m": d.wetted_width_m,
            "mean_velocity_ms": d.mean_velocity_ms,
            "alpha": d.alpha,
            "alpha_default": d.alpha_default,
            "section_length_m": d.section_length_m,
            "n_pairs": int(getattr(self.piv, "n_pairs", 0) or len(self.q_pairs)),
            "n_pairs_with_vectors": int(len(self.q_pairs)),
            "valid_fraction_mean": float(np.nanmean(self.piv.valid_fraction)),
            "subsections_filled": int(d.velocity_filled.sum()),
            "ortho_method": self.mapping.method,
            "ortho_residual_m": self.mapping.residual_m,
            "ortho_details": self.mapping.details,
            "stabilization": self.stabilization,
            "piv_reused": self.piv_reused,
            "stiv": self.stiv,
            "robust": self.robust,
            **fast_summary(self.piv_fast, int(getattr(self.piv, "n_pairs", 0) or len(self.q_pairs))),
            "video": self.video,
            "overlay": getattr(self.overlay, "info", None),  # overlay.mp4's size, rate, frames (run/overlay_stage.py)
            "warnings": self.warnings + d.warnings,
            "timings_s": self.timings_s,
            "files": self.files,
            "fieldtool_version": __version__,
            "inputs": self.project,
        }


def sections_summary(entries: list) -> dict | None:
    return summarize(entries) if entries else None


def fast_summary(fast: dict | None, n_pairs: int) -> dict:
    """result.json keys of the fast path: pairs_used, converged, piv_region."""
    fast = fast or {}
    out = {"pairs_used": int(fast.get("pairs_used", n_pairs)), "converged": fast.get("converged")}
    if fast:
        out["piv_sampling"] = {
            k: fast.get(k)
            for k in ("pairs_total", "rel_ci", "threshold", "min_pairs", "rounds", "frames_decoded", "frames_in_range")
            if k in fast
        }
        out["piv_region"] = {k: fast.get(k) for k in ("region", "box_px", "roi_px")}
    return out
