"""Click-to-pixel mapping of the viewer (fieldtool.viewer.mapping) and the plot axes."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fieldtool.viewer.mapping import (
    ImagePlane,
    PlotAxes,
    camera_pose,
    fit_plane,
    inside,
    pixel_to_scene,
    ray_to_pixel,
)


def _plane(rot=None, pos=(0.0, 0.0, 0.0)):
    R = np.eye(3) if rot is None else Rotation.from_euler("xyz", rot, degrees=True).as_matrix()
    return ImagePlane(640, 480, 6.4, 4.8, tuple(pos), R)


def _local_to_scene(plane, local):
    return np.asarray(plane.rotation) @ np.asarray(local, float) + np.asarray(plane.position)


@pytest.mark.parametrize("rot,pos", [(None, (0, 0, 0)), ((20, -35, 70), (1.5, -2.0, 3.0)), ((180, 0, 0), (0, 0, 5))])
def test_corners_and_centre_of_the_drawn_rectangle(rot, pos):
    """The rectangle's corners are the outer edges of the corner pixels (-0.5 and W - 0.5), its
    centre the middle of the pixel grid; y grows towards the rectangle's local +y."""
    plane = _plane(rot, pos)
    origin = _local_to_scene(plane, [0.7, -0.3, -9.0])  # a viewer on the local -z side, off axis
    cases = {
        (-3.2, -2.4): (-0.5, -0.5),
        (3.2, -2.4): (639.5, -0.5),
        (3.2, 2.4): (639.5, 479.5),
        (0.0, 0.0): (319.5, 239.5),
        (-3.2, 2.4): (-0.5, 479.5),
        (0.01, 0.0): (320.5, 239.5),
    }
    for (lx, ly), expected in cases.items():
        target = _local_to_scene(plane, [lx, ly, 0.0])
        px = ray_to_pixel(origin, target - origin, plane)
        np.testing.assert_allclose(px, expected, atol=1e-9)


def test_ray_direction_length_does_not_matter_and_misses_return_none():
    plane = _plane()
    o = np.array([0.0, 0.0, -5.0])
    d = np.array([0.1, 0.2, 1.0])
    np.testing.assert_allclose(ray_to_pixel(o, d, plane), ray_to_pixel(o, 7.5 * d, plane))
    assert ray_to_pixel(o, [1.0, 0.0, 0.0], plane) is None  # parallel to the image
    assert ray_to_pixel(o, [0.0, 0.0, -1.0], plane) is None  # looking away from it


def test_pixel_to_scene_and_back_from_random_viewpoints():
    rng = np.random.default_rng(3)
    plane = _plane((10, 20, 30), (1, 2, 3))
    px = rng.uniform([-0.5, -0.5], [639.5, 479.5], size=(50, 2))
    pts = pixel_to_scene(px, plane)
    for p, expect in zip(pts, px, strict=True):
        origin = _local_to_scene(plane, rng.uniform([-5, -5, -20], [5, 5, -2]))
        np.testing.assert_allclose(ray_to_pixel(origin, p - origin, plane), expect, atol=1e-8)


def test_lift_moves_overlays_towards_the_viewer_only():
    plane = _plane((0, 0, 90), (0, 0, 1))
    a, b = pixel_to_scene([[10, 20]], plane), pixel_to_scene([[10, 20]], plane, lift=0.25)
    normal_to_viewer = np.asarray(plane.rotation) @ np.array([0.0, 0.0, -1.0])
    np.testing.assert_allclose(b - a, 0.25 * normal_to_viewer[None], atol=1e-12)


def test_inside():
    plane = fit_plane(100, 50)
    assert inside(plane, (-0.5, -0.5)) and inside(plane, (99.5, 49.5))
    assert not inside(plane, (-0.6, 10)) and not inside(plane, (10, 49.6))


def test_fit_plane_keeps_the_aspect_ratio():
    p = fit_plane(1280, 720, size=10.0)
    assert p.render_width == pytest.approx(10.0)
    assert p.render_height == pytest.approx(10.0 * 720 / 1280)
    with pytest.raises(ValueError):
        fit_plane(0, 10)


@pytest.mark.parametrize("aspect", [0.8, 1.333, 2.2])
def test_camera_pose_shows_the_whole_image_upright(aspect):
    """Project the image corners with an independent pinhole model of the pose."""
    plane = _plane((5, -10, 15), (2, 1, -1))
    fov = np.deg2rad(50)
    pos, look, up = camera_pose(plane, fov, aspect, margin=1.1)
    f = look - pos
    f /= np.linalg.norm(f)
    right = np.cross(f, up)
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, f)
    corners = pixel_to_scene([[-0.5, -0.5], [639.5, -0.5], [639.5, 479.5], [-0.5, 479.5]], plane)
    rel = corners - pos
    depth = rel @ f
    sx = (rel @ right) / depth / (np.tan(fov / 2) * aspect)
    sy = (rel @ cam_up) / depth / np.tan(fov / 2)
    assert np.all(np.abs(sx) <= 1.0) and np.all(np.abs(sy) <= 1.0)
    assert max(np.abs(sx).max(), np.abs(sy).max()) == pytest.approx(1 / 1.1, rel=1e-6)
    assert sy[0] > sy[3] and sx[1] > sx[0]  # top row at the top, x to the right


def test_plot_axes_round_trip_and_orientation():
    ax = PlotAxes(90, 970, 50, 530, x_min=-2.0, x_max=18.0, y_min=97.0, y_max=101.0)
    np.testing.assert_allclose(ax.data_to_px([[-2.0, 101.0], [18.0, 97.0]]), [[90, 50], [970, 530]])
    pts = np.array([[3.3, 99.1], [17.9, 97.2]])
    np.testing.assert_allclose(ax.px_to_data(ax.data_to_px(pts)), pts)
    assert ax.contains_px((100, 60)) and not ax.contains_px((80, 60))


def test_rendered_plot_axes_locate_the_drawn_line():
    """A horizontal line drawn at y = 99.25 must be found at that elevation through the axes."""
    from fieldtool.viewer.plot_image import Curve, render_plot

    x = np.linspace(0.0, 10.0, 50)
    bed = Curve("bed", x, 98.0 + 0.02 * (x - 5) ** 2, (0, 0, 0))
    line = Curve("level", x, np.full_like(x, 99.25), (255, 0, 0))
    img, ax = render_plot([bed, line], size=(800, 500), vlines=[(6.5, (0, 0, 255), "v")])
    red = (img[..., 0] > 200) & (img[..., 1] < 60) & (img[..., 2] < 60)
    rows = np.nonzero(red[:, int(ax.left_px) + 50 : int(ax.right_px) - 250].any(axis=1))[0]
    assert ax.px_to_data([[ax.left_px, rows.mean()]])[0, 1] == pytest.approx(99.25, abs=(ax.y_max - ax.y_min) / 480)
    blue = (img[..., 2] > 200) & (img[..., 0] < 60) & (img[..., 1] < 60)
    cols = np.nonzero(blue[int(ax.top_px) + 30 : int(ax.bottom_px)].any(axis=0))[0]
    assert ax.px_to_data([[cols.mean(), ax.top_px]])[0, 0] == pytest.approx(6.5, abs=(ax.x_max - ax.x_min) / 700)
