"""The camera check's stage (run/camera.py): when it looks, what it reports, the verdict and the error it explains.
The whole run on a shaken clip is in tests/accuracy/test_corrections_e2e.py."""

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from fieldtool.errors import GeometryError
from fieldtool.processing import camera_motion as cm
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


class _Source:
    """What :func:`camera.later` reads of a FrameSource: the watched crops, the first frames', and watch(None) to
    stop."""

    def __init__(self, watched, watch_first=20):
        self.watched, self.watch_first = watched, watch_first

    def watch(self, boxes, first=0, every=1):
        assert boxes is None
        self.watched = {}


def _ground(seed, shape=(480, 640)):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 2.0)
    return (img - img.min()) / (img.max() - img.min()) * 200.0 + 20.0


def _crops(scene, boxes, dx, rng):
    m = np.float32([[1, 0, dx], [0, 1, 0.4 * dx]])
    f = cv2.warpAffine(scene, m, scene.shape[::-1], flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    f = np.clip(f + rng.normal(0, 1.0, f.shape), 0, 255).astype(np.uint8)
    return tuple(f[y0:y1, x0:x1].copy() for x0, y0, x1, y1 in boxes)


@pytest.mark.parametrize("bump_px", [0.0, 3.0])
def test_a_camera_still_at_first_that_moves_later_is_said(bump_px):
    """The first 20 frames still, then (bump_px > 0) the picture drifts from frame 100 on: the warning names the
    time and the regions to stabilise on, and the verdict is doubtful; a camera still throughout says nothing."""
    rng, scene = np.random.default_rng(5), _ground(0)
    pts = [[120, 100], [520, 110], [140, 380], [500, 360]]
    boxes = cm.patch_boxes(pts, scene.shape, 72)
    watched = {k: (k / 30.0, _crops(scene, boxes, 0.0, rng)) for k in range(20)}
    for k in range(20, 240, 5):
        watched[k] = (k / 30.0, _crops(scene, boxes, bump_px * max(0, k - 100) / 30.0, rng))
    first = cm.measure([list(watched[k][1]) for k in range(20)])
    assert not first.moved
    cam = camera.Camera(first, boxes=boxes)
    inputs, warnings = SimpleNamespace(source=_Source(watched)), []
    camera.later(cam, inputs, warnings)
    assert inputs.source.watched == {}  # the crops are let go
    facts, q = cam.facts(), Quality("good", [])
    camera.add_reason(q, facts)
    if bump_px == 0.0:
        assert facts["later"] == {"frames": 44, "checked": True, "moved": False} and not warnings
        assert q.grade == "good"
    else:
        late = facts["later"]
        assert late["moved"] and 100 / 30.0 < late["from_s"] <= 110 / 30.0
        assert late["regions_px"] == [[float(c) for c in b] for b in boxes]
        assert len(warnings) == 1 and "moved later in the clip" in warnings[0] and "stabilize.regions_px" in warnings[0]
        assert q.grade == "doubtful" and q.reasons[0].code == "camera_moved"
