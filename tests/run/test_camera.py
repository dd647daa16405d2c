"""The camera check's stage (run/camera.py): when it looks, what it reports, the verdict and the error it explains.
The whole run on a shaken clip is in tests/accuracy/test_corrections_e2e.py."""

from types import SimpleNamespace

import pytest

from fieldtool.errors import GeometryError
from fieldtool.processing.camera_motion import CameraMotion
from fieldtool.processing.quality import Quality
from fieldtool.project.model import Project
from fieldtool.run import camera


def _inputs(shape=(480, 640)):
    return SimpleNamespace(shape=shape, lens=None)


def _project(**stab) -> Project:
    p = Project()
    p.ortho.gcp_px = [[100.0, 100.0], [540.0, 100.0], [540.0, 380.0], [100.0, 380.0]]
    for k, v in stab.items():
        setattr(p.stabilize, k, v)
    return p


def test_the_check_looks_only_where_nobody_chose():
    assert len(camera.boxes(_project(), _inputs())) == 4
    assert camera.boxes(_project(enabled=True), _inputs()) == []
    assert camera.boxes(_project(auto=False), _inputs()) == []
    one = _project()
    one.ortho.gcp_px = [[100.0, 100.0], [2.0, 2.0]]  # the second lies at the edge: one patch is too few
    assert camera.boxes(one, _inputs()) == []
    for p, why in ((_project(enabled=True), "the user's registration"), (_project(auto=False), "as filmed")):
        same, cam = camera.check(p, _inputs(), [], camera.boxes(_project(), _inputs()), [])
        assert same is p and cam.motion is None and why in cam.facts()["why_not"]
        assert cam.facts()["checked"] is False


def _moved(stabilized: bool) -> camera.Camera:
    m = CameraMotion(points=4, frames=20, agree=[0, 1, 2], max_shift_px=2.5, noise_px=0.2, threshold_px=0.6, moved=True)
    return camera.Camera(m, stabilized=stabilized, regions_px=[[1.0, 2.0, 3.0, 4.0]] if stabilized else [])


def test_a_camera_that_moved_and_was_not_registered_makes_the_grade_doubtful():
    q = Quality("good", [])
    camera.add_reason(q, _moved(False).facts())
    assert q.grade == "doubtful" and [r.code for r in q.reasons] == ["camera_moved"]
    assert q.reasons[0].value == 2.5 and q.reasons[0].threshold == 0.6
    for facts in (_moved(True).facts(), camera.Camera(None, "no GCPs").facts(), None):
        q = Quality("good", [])
        camera.add_reason(q, facts)
        assert q.grade == "good" and not q.reasons


def test_the_facts_say_what_was_done():
    f = _moved(True).facts()
    assert f["moved"] and f["stabilized"] and f["regions_px"] == [[1.0, 2.0, 3.0, 4.0]]
    assert f["points_telling"] == 3 and f["max_shift_px"] == 2.5 and f["threshold_px"] == 0.6


def test_a_registration_the_check_chose_that_fails_later_says_whose_it_was():
    with pytest.raises(GeometryError, match="switched on by the camera check.*stabilize.auto = false"):
        with camera.explained(_moved(True)):
            raise GeometryError("stabilize: on frame 150 only 3 of the 40 stable features could be followed")
    with pytest.raises(GeometryError, match="^stabilize: on frame 150"):  # the user's regions: their own message
        with camera.explained(_moved(False)):
            raise GeometryError("stabilize: on frame 150 only 3 of the 40 stable features could be followed")
