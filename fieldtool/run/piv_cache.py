"""Reuse of the PIV field between runs into the same output folder.

PIV works in image pixels, so its field depends only on the clip, the lens model, stabilisation,
ROI/masks, filters and PIV parameters (and on the speed limit, which goes through the mapping). Changing
the GCPs, the water level, the section or the velocity index then recomputes the discharge in well under
a second instead of re-running PIV. The cache file ``piv_cache.npz`` carries a key over all those inputs
(file sizes and modification times included) and the fieldtool version; any difference means a new run.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
from pathlib import Path
from typing import Any

import numpy as np

from fieldtool import __version__
from fieldtool.processing.frames import sequence_files
from fieldtool.processing.piv import REVISION, PivParams, PivResult
from fieldtool.project.model import Project, atomic_write_bytes, project_to_dict

FILE = "piv_cache.npz"


def _stat(path: Path) -> list:
    """Size and modification time of a file, or of every image of a sequence, as the frame reader sees it."""
    files = sequence_files(path)
    if files is None:
        st = path.stat()
        return [path.name, st.st_size, st.st_mtime_ns]
    return [[f.name, f.stat().st_size, f.stat().st_mtime_ns] for f in files]


def piv_key(project: Project, max_speed_px_s: np.ndarray | None, box_px=None, near=None) -> str:
    """Hash of everything the PIV field depends on; ``box_px`` is the correlated box and ``near`` the section
    segments and reaches of its nodes (``[piv] region = "section"`` derives both from the section, so a moved
    section recomputes the field)."""
    d = project_to_dict(project)
    parts = {k: d.get(k) for k in ("video", "calibration", "stabilize", "roi", "filters", "piv")}
    parts["video_file"] = _stat(project.resolve(project.video.path))
    if project.calibration.path:
        parts["calibration_file"] = _stat(project.resolve(project.calibration.path))
    elif (
        project.ortho.method == "pose" and project.ortho.fit_lens
    ):  # the lens (frames' undistortion) comes from the GCPs
        parts["lens_from_gcps"] = [project.ortho.gcp_px, project.ortho.gcp_world_m]
    if max_speed_px_s is not None:
        speed = np.ascontiguousarray(max_speed_px_s, dtype=np.float64)
        # numpy's stubs give ndarray the buffer protocol (__buffer__) only for Python >= 3.12
        parts["max_speed"] = hashlib.sha256(speed).hexdigest()  # type: ignore[arg-type]
    if box_px is not None:
        parts["box_px"] = [int(c) for c in box_px]
    if near is not None:
        parts["near"] = [
            [np.round(np.asarray(sg, float), 3).tolist() for sg in near[0]],
            [round(r, 3) for r in near[1]],
        ]
    parts["version"] = __version__
    parts["engine_revision"] = REVISION
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()


def save(folder: Path, key: str, res, stabilization: dict | None, extra: dict | None = None) -> None:
    """Write the PIV result (arrays and parameters) with its key, atomically."""
    arrays: dict[str, Any] = {}
    for f in dataclasses.fields(res):
        v = getattr(res, f.name)
        if isinstance(v, np.ndarray):
            arrays[f.name] = v
    meta = {
        "key": key,
        "params": dataclasses.asdict(res.params),
        "n_pairs": res.n_pairs,
        "stabilization": stabilization,
        "extra": extra,
    }
    buf = io.BytesIO()
    np.savez(buf, meta=np.array(json.dumps(meta)), **arrays)
    atomic_write_bytes(folder / FILE, buf.getvalue())


def load(folder: Path, key: str, with_extra: bool = False):
    """``(PivResult, stabilization report)`` saved under ``key``, or None (absent, other key, unreadable);
    ``with_extra``: ``(PivResult, stabilization report, extra)``."""
    path = folder / FILE
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            if meta.get("key") != key:
                return None
            arrays = {k: z[k] for k in z.files if k != "meta"}
    except (OSError, ValueError, KeyError):
        return None  # a damaged cache is only a cache: PIV runs again and rewrites it
    res = PivResult(params=PivParams(**meta["params"]), n_pairs=meta.get("n_pairs"), **arrays)
    if with_extra:
        return res, meta.get("stabilization"), meta.get("extra")
    return res, meta.get("stabilization")
