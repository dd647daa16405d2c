"""The real Geul clip (../shared/data/real) through the pipeline, as tests/accuracy/test_real_data.py sets it up:
prints the discharge, the grade and the PIV's valid fraction over the correlated nodes (issue 23's check that
the real clip still gives a field), and the velocities behind Q with PIV's, STIV's and the combined discharge.

    .venv/bin/python benchmarks/geul_field.py
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from fieldtool.project.model import project_from_dict
from fieldtool.run.pipeline import run_project

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


def main() -> int:
    if not (REAL / "geul_dk_control.mp4").is_file():
        print(f"no Geul clip under {REAL}")
        return 1
    cfg = json.loads((REAL / "geul_dk_cam_config.json").read_text())
    z0 = cfg["gcps"]["z_0"]
    with tempfile.TemporaryDirectory() as tmp:
        proj = project_from_dict(
            {
                "video": {"path": str(REAL / "geul_dk_control.mp4")},
                "cross_section": {"shape": "trapezoidal", "top_width_m": 12.0, "bottom_width_m": 6.0,
                                  "depth_m": 1.2, "bank_elevation_m": z0 + 0.73},
                "calibration": {"path": str(REAL / "geul_dk_cam_config.json")},
                "ortho": {"method": "pose", "gcp_px": cfg["gcps"]["src"], "gcp_world_m": cfg["gcps"]["dst"],
                          "accept_residual": True},
                "water_level": {"method": "value", "value_m": z0},
                "section": {"points_px": [[560.0, 480.0], [1640.0, 520.0]]},
            },
            Path(tmp),
        )
        r = run_project(proj, Path(tmp) / "out")
        vf = r.piv.valid_fraction
        print(f"Geul: Q {r.discharge.discharge_m3s:.3f} m3/s, grade {r.quality.grade}, "
              f"valid fraction {np.nanmean(vf):.3f} over {int(np.isfinite(vf).sum())} correlated nodes")
        st = r.stiv or {}
        if st:  # the velocities behind Q (section.velocity_source) and each method's own discharge
            print(f"velocities {st.get('velocity_source_used')}: PIV {st.get('discharge_piv_m3s')}, STIV "
                  f"{st.get('discharge_m3s')}, combined {st.get('discharge_combined_m3s')}; "
                  f"disagreement {(st.get('disagreement_reason') or {}).get('message', 'none')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
