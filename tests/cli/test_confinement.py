"""Files fieldtool writes or embeds stay inside the output folder: rerun.path and report images."""

from __future__ import annotations

import json
import types

import cv2
import numpy as np
import pytest

from fieldtool.errors import ParameterError
from fieldtool.project.model import Project
from fieldtool.project.validation import out_path_problem, validate
from fieldtool.records.report import load_result
from fieldtool.viewer.rerun_log import observer_from_args


@pytest.mark.parametrize("bad", ["/some/file", "../../../x.rrd", "sub/../../x.rrd", "~/x.rrd", "/dev/zero"])
def test_rerun_path_outside_the_output_folder_is_refused(tmp_path, bad):
    assert out_path_problem(bad)
    p = Project(root=tmp_path)
    p.rerun.path = bad
    assert any(pr.key == "rerun.path" and pr.severity == "error" for pr in validate(p, files=False))
    p.rerun.mode = "save"
    with pytest.raises(ParameterError, match="rerun.path"):
        observer_from_args(p, types.SimpleNamespace(rerun=None, rerun_path=None, rerun_url=None), tmp_path / "out")


def test_rerun_path_inside_the_output_folder_is_kept(tmp_path):
    for good in ("run.rrd", "rerun/run.rrd"):
        assert out_path_problem(good) is None


def test_report_embeds_only_the_runs_own_images(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    png = cv2.imencode(".png", np.zeros((4, 4, 3), np.uint8))[1].tobytes()
    (out / "vectors.png").write_bytes(png)
    (tmp_path / "secret_plot.png").write_bytes(png)
    (out / "result.json").write_text(
        json.dumps(
            {
                "discharge_m3s": 1.0,
                "files": {
                    "vectors_png": "vectors.png",
                    "secret_png": "../secret_plot.png",
                    "abs_png": str(tmp_path / "secret_plot.png"),
                    "subsections": "../../etc/passwd",
                },
            }
        )
    )
    _, images, rows = load_result(out)
    assert set(images) == {"vectors_png"} and rows == []
