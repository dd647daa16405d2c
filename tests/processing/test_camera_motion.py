"""The camera check's measurement (processing/camera_motion.py): patches around fixed points, followed over frames."""

import cv2
import numpy as np
import pytest

from fieldtool.processing import camera_motion as cm

SIDE = 72


def _ground(seed: int = 0, shape=(480, 640)) -> np.ndarray:
    """A textured still scene (grey levels 0-255, float32): blobs like stones and markers."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 2.0)
    img = (img - img.min()) / (img.max() - img.min())
    return img * 200.0 + 20.0


def _frame(scene: np.ndarray, dx: float, dy: float, rng, noise: float = 1.0) -> np.ndarray:
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    moved = cv2.warpAffine(scene, m, scene.shape[::-1], flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return np.clip(moved + rng.normal(0, noise, scene.shape), 0, 255).astype(np.uint8)


POINTS = [[120, 100], [520, 110], [140, 380], [500, 360]]


def _patches(frames, boxes):
    return [[f[y0:y1, x0:x1] for x0, y0, x1, y1 in boxes] for f in frames]


def test_a_still_camera_is_not_moved_and_its_noise_is_measured():
    rng = np.random.default_rng(1)
    scene = _ground()
    frames = [_frame(scene, 0.0, 0.0, rng) for _ in range(20)]
    boxes = cm.patch_boxes(POINTS, scene.shape, SIDE)
    got = cm.measure(_patches(frames, boxes))
    assert got.points == 4 and len(got.agree) == 4 and got.frames == 20
    assert not got.moved
    assert got.max_shift_px < got.threshold_px
    assert 0.0 < got.noise_px < 0.1  # sensor noise of 1 grey level: hundredths of a pixel


def test_a_shaking_camera_is_moved_and_its_shift_is_measured():
    rng = np.random.default_rng(2)
    scene = _ground()
    shifts = [(0.0, 0.0)] + [tuple(rng.normal(0, 1.0, 2)) for _ in range(19)]
    frames = [_frame(scene, dx, dy, rng) for dx, dy in shifts]
    boxes = cm.patch_boxes(POINTS, scene.shape, SIDE)
    got = cm.measure(_patches(frames, boxes))
    assert got.moved
    want = np.asarray(shifts)
    assert np.abs(np.asarray(got.shift_px) - want).max() < 0.1  # px: the common shift follows the camera's
    assert got.max_shift_px == pytest.approx(np.linalg.norm(want, axis=1).max(), abs=0.1)


def test_a_point_on_moving_water_is_left_out_and_does_not_make_a_still_camera_move():
    rng = np.random.default_rng(3)
    scene, water = _ground(0), _ground(7)
    frames = []
    for k in range(20):
        f = _frame(scene, 0.0, 0.0, rng)
        w = _frame(water, 2.5 * k, 0.4 * k, rng)  # texture carried by the flow under the fourth point
        x0, y0, x1, y1 = cm.patch_boxes(POINTS, scene.shape, SIDE)[3]
        f[y0:y1, x0:x1] = w[y0:y1, x0:x1]
        frames.append(f)
    boxes = cm.patch_boxes(POINTS, scene.shape, SIDE)
    got = cm.measure(_patches(frames, boxes))
    assert 3 not in got.agree and len(got.agree) == 3
    assert not got.moved


def test_two_points_on_water_moving_alike_do_not_make_a_still_camera_move_but_a_moving_one_still_moves():
    """The far bank's two GCP patches hold water flowing the same way (the 1080p 30 s clip): two points that stayed
    put say the camera did not move. The same water under a camera that moves: no point stays put."""
    rng = np.random.default_rng(4)
    scene, water = _ground(0), _ground(9)
    boxes = cm.patch_boxes(POINTS, scene.shape, SIDE)
    for cam_px in (0.0, 1.5):
        frames = []
        for k in range(20):
            dx = cam_px * np.sin(k) if k else 0.0
            f = _frame(scene, dx, 0.0, rng)
            w = _frame(water, 0.8 * k + dx, 0.1 * k, rng)
            for x0, y0, x1, y1 in boxes[2:]:
                f[y0:y1, x0:x1] = w[y0:y1, x0:x1]
            frames.append(f)
        got = cm.measure(_patches(frames, boxes))
        if cam_px == 0.0:
            assert not got.moved and sorted(got.agree) == [0, 1] and got.max_shift_px < 0.05
        else:
            assert got.moved and got.max_shift_px > 1.0


def test_patches_are_only_where_a_whole_one_fits():
    boxes = cm.patch_boxes([[10, 10], [320, 240], [639, 479], [float("nan"), 5]], (480, 640), SIDE)
    assert boxes == [(320 - SIDE // 2, 240 - SIDE // 2, 320 + SIDE // 2, 240 + SIDE // 2)]
    assert cm.patch_side((720, 1280)) == 72 and cm.patch_side((2160, 3840)) == 216 and cm.patch_side((100, 100)) == 48


def test_too_few_points_or_frames_say_nothing():
    assert cm.measure([]).points == 0
    one = [[np.zeros((SIDE, SIDE), np.uint8)] for _ in range(5)]
    assert cm.measure(one).points == 0 and not cm.measure(one).moved
    flat = [[np.full((SIDE, SIDE), 90, np.uint8)] * 3 for _ in range(5)]  # nothing to follow
    assert cm.measure(flat).points == 0


def test_a_roll_about_the_centre_moves_every_point_and_reads_as_far_as_they_moved():
    """Points on both sides of the centre move in opposite directions: the median of their shift vectors is about
    0, the median of their lengths is the motion."""
    rng, scene = np.random.default_rng(6), _ground()
    boxes = cm.patch_boxes(POINTS, scene.shape, SIDE)
    frames = []
    for k in range(20):
        m = cv2.getRotationMatrix2D((319.5, 239.5), float(rng.normal(0, 0.1)) if k else 0.0, 1.0)
        f = cv2.warpAffine(scene, m, (640, 480), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        frames.append(np.clip(f + rng.normal(0, 1.0, f.shape), 0, 255).astype(np.uint8))
    got = cm.measure(_patches(frames, boxes))
    assert got.moved and len(got.agree) == 4
    assert got.max_shift_px > 0.3  # 0.1 degrees at 250-330 px from the centre: 0.4-0.6 px a degree-tenth
    assert max(np.hypot(*s) for s in got.shift_px) < 0.5 * got.max_shift_px
