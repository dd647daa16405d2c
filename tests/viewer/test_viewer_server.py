"""The viser picking server without a browser: clicks arrive as rays, picks land in the project file."""

import threading
import urllib.request

import cv2
import numpy as np
import pytest

from fieldtool.project.model import load_project, save_project
from fieldtool.viewer.mapping import pixel_to_scene
from fieldtool.viewer.server import start_viewer


def _tiny_project(tmp_path, w=320, h=240):
    (tmp_path / "frames").mkdir()
    rng = np.random.default_rng(1)
    for i in range(2):
        cv2.imwrite(str(tmp_path / "frames" / f"f{i}.png"), rng.integers(0, 255, (h, w, 3), dtype=np.uint8))
    path = tmp_path / "project.toml"
    path.write_text('[video]\npath = "frames/*.png"\nframe_interval_s = 0.1\n')
    return path


def _ray_at(handle, px, depth=7.0):
    """A ray from a viewpoint in front of the image through display pixel ``px``."""
    v = handle._v
    target = pixel_to_scene([px], v.plane)[0]
    origin = target + np.asarray(v.plane.rotation) @ np.array([0.3, -0.2, -depth])
    return origin, target - origin


@pytest.fixture
def viewer(tmp_path):
    path = _tiny_project(tmp_path)
    events = []
    h = start_viewer(path, on_pick=lambda f, v: events.append((f, v)))
    h.events, h.path = events, path
    yield h
    h.stop()


def test_serves_the_bundled_page_on_loopback_with_a_free_port(viewer):
    assert viewer.url.startswith("http://127.0.0.1:") and viewer.port > 0 and viewer.warning is None
    html = urllib.request.urlopen(viewer.url, timeout=10).read().decode()
    assert '<div id="root">' in html


def test_clicks_as_rays_save_gcps_to_the_project_and_call_on_pick(viewer):
    viewer.set_mode("gcp")
    truth = [[12.3, 40.7], [300.2, 35.0], [280.6, 220.1], [20.0, 200.9]]
    for px in truth:
        viewer._v.on_ray(*_ray_at(viewer, px))
    np.testing.assert_allclose(load_project(viewer.path).ortho.gcp_px, truth, atol=0.01)
    assert viewer.events[-1][0] == "ortho.gcp_px" and len(viewer.events) == 4
    viewer._v._act("undo")
    assert len(load_project(viewer.path).ortho.gcp_px) == 3


def test_clicks_outside_the_image_or_without_a_mode_change_nothing(viewer):
    viewer._v.on_ray(*_ray_at(viewer, [100, 100]))
    assert "choose a pick mode" in viewer.status
    viewer.set_mode("section")
    viewer._v.on_ray(*_ray_at(viewer, [-20, 100]))
    assert viewer.status == "click on the image"
    assert load_project(viewer.path).section.points_px == [] and viewer.events == []


def test_mode_on_an_image_the_project_lacks_says_why(viewer):
    viewer.set_mode("edges1")  # angle-and-height image 1 is not configured
    assert "water_level.image1" in viewer.status and viewer.image == "frame"
    viewer.click(50, 50)
    assert "switch the image" in viewer.status
    with pytest.raises(ValueError):
        viewer.set_mode("nonsense")


def test_concurrent_clicks_are_all_saved(viewer):
    viewer.set_mode("masks")
    pts = [(20 + 5 * i, 30 + (i % 7) * 20) for i in range(24)]
    threads = [threading.Thread(target=viewer.click, args=p) for p in pts]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    viewer._v._act("close")
    masks = load_project(viewer.path).roi.masks_px
    assert len(masks) == 1 and sorted(map(tuple, masks[0])) == sorted(map(tuple, map(list, pts)))


def test_picks_keep_other_fields_written_meanwhile(viewer):
    """Each pick re-reads the file: a value saved by the TUI in between is not lost."""
    viewer.set_mode("roi")
    p = load_project(viewer.path)
    p.piv.window_px = 48
    save_project(p, viewer.path)
    viewer.click(10, 20)
    viewer.click(200, 150)
    back = load_project(viewer.path)
    assert back.roi.rect_px == [10, 20, 200, 150] and back.piv.window_px == 48


def test_other_host_warns(tmp_path):
    path = _tiny_project(tmp_path)
    with pytest.warns(UserWarning, match="anyone who can reach"):
        h = start_viewer(path, host="0.0.0.0")
    try:
        assert h.warning and h.url.startswith("http://127.0.0.1:")
    finally:
        h.stop()


def test_ortho_map_clicks_map_back_to_raw_frame_pixels(short_scene, tmp_path):
    """On the orthorectified map a click is stored in raw-frame pixels: clicking where the map shows
    a known raw pixel stores that pixel."""
    proj = load_project(short_scene.project_path)
    proj.section.points_px = []
    path = short_scene.project_path.parent / "view_project.toml"
    save_project(proj, path)
    h = start_viewer(path)
    try:
        h.show_image("ortho")
        assert h.image == "ortho"
        truth = np.array(short_scene.section_px, float)
        h.set_mode("section")
        assert h.image == "ortho"  # the map is a frame-like display: picks can be made on it
        for raw in truth:
            disp = h._v.display.to_display(raw[None])[0]
            h._v.on_ray(*_ray_at(h, disp))
        np.testing.assert_allclose(load_project(path).section.points_px, truth, atol=0.02)
    finally:
        h.stop()


def test_dem_plot_click_gives_the_station_under_it(tmp_path):
    """The DEM-vs-bed plot is drawn with known axes: clicking the drawn bed at a known station (found
    in the picture by its colour) stores that station."""
    import tifffile

    path = _tiny_project(tmp_path)
    st = np.linspace(0.0, 10.0, 41)
    bed = 100.0 - 2.0 * np.sin(np.pi * st / 10.0)
    (tmp_path / "xs.csv").write_text(
        "station_m,elevation_m\n" + "".join(f"{s},{z}\n" for s, z in zip(st, bed, strict=True))
    )
    x = np.linspace(0.0, 4.0, 80, endpoint=False) + 0.025
    dem = np.tile(np.interp(x, st, bed) + np.where(x < 2.0, 0.0, 0.3), (5, 1))  # diverges beyond 2 m
    tifffile.imwrite(tmp_path / "dem.tif", dem.astype(np.float32))
    p = load_project(path)
    p.cross_section.path = "xs.csv"
    p.water_level.dem_path = "dem.tif"
    p.water_level.dem_x_m, p.water_level.dem_y_m = [0.0, 4.0], [0.0, 0.25]
    save_project(p, path)
    h = start_viewer(path)
    try:
        h.set_mode("divergence")
        assert h.image == "dem_plot", h.status
        rgb = h._v.display.rgb
        ax = h._v.display.axes
        # the bed curve is drawn in dark grey (40, 40, 40): take its column at station 7 m by colour
        col = int(round(ax.left_px + (7.0 - ax.x_min) / (ax.x_max - ax.x_min) * (ax.right_px - ax.left_px)))
        dark = np.nonzero(np.all(np.abs(rgb[:, col].astype(int) - 40) < 30, axis=1))[0]
        dark = dark[(dark > ax.top_px) & (dark < ax.bottom_px)]
        h._v.on_ray(*_ray_at(h, [col, dark.mean()]))
        got = load_project(path).water_level.divergence_station_m
        assert got == pytest.approx(7.0, abs=(ax.x_max - ax.x_min) / (ax.right_px - ax.left_px))
        h._v._act("undo")
        assert load_project(path).water_level.divergence_station_m is None
    finally:
        h.stop()


def test_angle_and_height_edges_are_picked_on_their_own_images(tmp_path):
    path = _tiny_project(tmp_path)
    for k, (w, h) in ((1, (200, 150)), (2, (160, 120))):
        cv2.imwrite(str(tmp_path / f"nadir{k}.png"), np.full((h, w, 3), 40 * k, np.uint8))
    p = load_project(path)
    p.water_level.image1, p.water_level.image2 = "nadir1.png", "nadir2.png"
    save_project(p, path)
    h = start_viewer(path)
    try:
        h.set_mode("edges1")
        assert h.image == "image1" and h._v.plane.width_px == 200
        for px in ([20.0, 75.0], [180.0, 70.0]):
            h._v.on_ray(*_ray_at(h, px))
        h.set_mode("edges2")
        assert h.image == "image2" and h._v.plane.width_px == 160
        h._v.on_ray(*_ray_at(h, [30.0, 60.0]))
        back = load_project(path).water_level
        assert back.edges1_px == [[20.0, 75.0], [180.0, 70.0]] and back.edges2_px == [[30.0, 60.0]]
        assert back.edges_px == []  # the image-method edges are a different field
    finally:
        h.stop()


def _conflict(viewer):
    """The same GCP placed here and, meanwhile, by another program (the viewer's file watch held off so that
    the click's save meets the other program's value): the file's value is kept and the page asks."""
    from fieldtool.project.sync import ProjectSync

    viewer._v._stopped.set()  # the file watch stops (the server stays up)
    viewer._v._watcher.join(timeout=10)
    viewer.set_mode("gcp")
    ProjectSync(viewer.path).set_keys({"ortho.gcp_px": [[5.0, 6.0]]})  # the TUI's P1
    viewer.click(100.0, 50.0)  # the viewer's P1, placed before it saw the TUI's
    assert [c.key for c in viewer.conflicts] == ["ortho.gcp_px[0]"], viewer.status
    assert "CONFLICT" in viewer.status and "[5, 6]" in viewer.status and "[100, 50]" in viewer.status
    assert load_project(viewer.path).ortho.gcp_px == [[5.0, 6.0]]  # the file's value is kept meanwhile
    assert viewer._v._question is not None and not viewer._v._question.closed  # the page asks


def test_a_conflict_asks_and_mine_puts_the_viewers_value_back(viewer):
    _conflict(viewer)
    n = len(viewer.events)
    assert "put yours back" in viewer.resolve_conflicts(True)
    assert load_project(viewer.path).ortho.gcp_px == [[100.0, 50.0]]
    assert viewer.events[n:] == [("ortho.gcp_px", [[100.0, 50.0]])]  # the TUI is told
    assert viewer._v._question is None and viewer.conflicts == []
    assert viewer._v.states["gcp"].value() == [[100.0, 50.0]]  # and the viewer draws it


def test_a_conflict_asks_and_keep_leaves_the_files_value(viewer):
    _conflict(viewer)
    n = len(viewer.events)
    assert "kept the file's value of ortho.gcp_px[0]" in viewer.resolve_conflicts(False)
    assert load_project(viewer.path).ortho.gcp_px == [[5.0, 6.0]]
    assert viewer._v.states["gcp"].value() == [[5.0, 6.0]] and viewer.events[n:] == []
    assert viewer._v._question is None and viewer.conflicts == []


def test_a_reload_while_a_pick_is_saved_puts_back_none_of_the_other_editors_points(viewer, monkeypatch):
    """The TUI moves P2 while the viewer saves its P4, and the viewer's file watch takes the TUI's save in at
    that moment: the pick's save still holds the viewer's lock, so the reload waits, and the save merges the
    TUI's P2 (the viewer put its old P2 back when the reload ran between the click and the save: 4 of 50 edits
    lost in tests/tui/test_two_editors.py under load)."""
    import sys

    from fieldtool.project.sync import ProjectSync

    viewer._v._stopped.set()  # the file watch stops: this test calls reload itself, at the worst moment
    viewer._v._watcher.join(timeout=10)
    viewer.set_mode("gcp")
    for px in ((10.0, 10.0), (50.0, 10.0), (50.0, 50.0)):
        viewer.click(*px)
    state_cls = type(viewer._v.states["gcp"])
    orig = state_cls.value
    waited = []

    def value(self):
        if sys._getframe(1).f_code.co_name == "_save_state" and not waited:  # the pick's save reads its value
            ProjectSync(viewer.path).set_keys({"ortho.gcp_px": [[10.0, 10.0], [70.0, 20.0], [50.0, 50.0]]})
            t = threading.Thread(target=viewer._v.reload)
            t.start()
            t.join(timeout=0.5)
            waited.append(t.is_alive())  # still waiting for the lock
        return orig(self)

    monkeypatch.setattr(state_cls, "value", value)
    viewer.click(10.0, 50.0)
    assert load_project(viewer.path).ortho.gcp_px == [[10.0, 10.0], [70.0, 20.0], [50.0, 50.0], [10.0, 50.0]]
    assert waited == [True]
