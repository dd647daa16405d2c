"""Smoke tests on the real clips in ../shared/data (skipped when the folder is absent)."""

import json

import numpy as np
import pytest
from conftest import SHARED_DATA

from fieldtool.errors import GeometryError
from fieldtool.processing.frames import FrameSource
from fieldtool.project.model import project_from_dict
from fieldtool.run.pipeline import run_project

REAL = SHARED_DATA / "real"
pytestmark = pytest.mark.skipif(
    not (REAL / "geul_dk_control.mp4").is_file(),
    reason="../shared/data/real is absent (a user's fresh clone has no test data)",
)


def test_geul_timestamps_from_container():
    frames = list(FrameSource(REAL / "geul_dk_control.mp4"))
    assert len(frames) == 10
    np.testing.assert_allclose([f.t_s for f in frames], np.arange(10) * 0.1, atol=1e-6)


def test_geul_pose_orthorectification_and_piv(tmp_path):
    cfg = json.loads((REAL / "geul_dk_cam_config.json").read_text())
    z0 = cfg["gcps"]["z_0"]
    proj = project_from_dict(
        {
            "video": {"path": str(REAL / "geul_dk_control.mp4")},
            "cross_section": {
                "shape": "trapezoidal",
                "top_width_m": 12.0,
                "bottom_width_m": 6.0,
                "depth_m": 1.2,
                "bank_elevation_m": z0 + 0.73,
            },
            "calibration": {"path": str(REAL / "geul_dk_cam_config.json")},
            "ortho": {"method": "pose", "gcp_px": cfg["gcps"]["src"], "gcp_world_m": cfg["gcps"]["dst"]},
            "water_level": {"method": "value", "value_m": z0},
            "section": {"points_px": [[560.0, 480.0], [1640.0, 520.0]]},
        },
        tmp_path,
    )
    # whole-pixel picks of the authors: GCP 5 misses the water plane by 0.22 m (16 px), over the 0.10 m default
    with pytest.raises(GeometryError, match=r"GCP 5 misses by 0\.2\d+ m"):
        run_project(proj, tmp_path / "out")
    proj.ortho.accept_residual = True
    result = run_project(proj, tmp_path / "out")
    assert "gcp_residual" in {r.code for r in result.quality.reasons} and result.quality.grade != "good"
    assert any("remove_stationary" in w for w in result.warnings)  # 10 frames: too short to standardise
    details = result.mapping.details
    assert details["reprojection_rms_px"] < 5.0  # the authors' integer GCP pixels: ~4.2 px
    assert result.mapping.residual_m < 0.2  # GCPs met on their own planes: 0.12 m RMS (two GCPs ~0.2 m off)
    assert 5.0 < result.discharge.section_length_m < 12.0  # the stream is ~8 m wide here
    # the nodes correlated are those near the section (NaN elsewhere); a quarter of their pairs give a vector on
    # these 10 frames of bank-side water (0.25; over the whole box around the section it was 0.31)
    vf = result.piv.valid_fraction
    assert np.isnan(vf).any() and np.nanmean(vf) > 0.2
    assert np.isfinite(result.discharge.discharge_m3s) and result.discharge.discharge_m3s > 0
