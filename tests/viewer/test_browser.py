"""Real browser: chromium (Debian's, driven by Playwright) clicks four GCPs on the viser page.

The frame carries four coloured discs at known pixel positions. The test finds them on a
screenshot of the page, clicks their centres, and checks that the project file holds the known
pixel coordinates within 1 px. It also checks that the page asks nothing from the internet.
"""

import re
import time

import cv2
import numpy as np
import pytest
from chromium_setup import LAUNCH_ARGS, ensure_chromium

from fieldtool.project.model import load_project
from fieldtool.viewer.mapping import pixel_to_scene
from fieldtool.viewer.server import start_viewer

pytestmark = pytest.mark.browser

# disc centres (px) and colours (RGB) that the page itself never uses
MARKERS = [
    ((70.0, 64.0), (255, 0, 255)),
    ((262.0, 52.0), (0, 255, 255)),
    ((246.0, 203.0), (0, 255, 0)),
    ((84.0, 190.0), (255, 255, 0)),
]


@pytest.fixture(scope="session")
def chromium():
    path, reason = ensure_chromium()
    if path is None:
        pytest.skip(f"chromium unavailable: {reason}")
    return path


def _marker_project(tmp_path):
    img = np.full((240, 320, 3), 70, np.uint8)
    img[:] += np.random.default_rng(0).integers(0, 25, img.shape, dtype=np.uint8)
    for (x, y), rgb in MARKERS:
        cv2.circle(img, (int(x), int(y)), 6, rgb[::-1], -1, lineType=cv2.LINE_AA)
    (tmp_path / "frames").mkdir()
    cv2.imwrite(str(tmp_path / "frames" / "f000.png"), img)
    path = tmp_path / "project.toml"
    path.write_text('[video]\npath = "frames/*.png"\nframe_interval_s = 0.1\n')
    return path


def _find(shot_rgb, rgb, tol=40):
    m = np.all(np.abs(shot_rgb.astype(int) - np.array(rgb)) < tol, axis=2).astype(np.uint8)
    n, lab, stats, cent = cv2.connectedComponentsWithStats(m)
    if n < 2:
        return None
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return cent[k] if stats[k, cv2.CC_STAT_AREA] >= 20 else None


def _locate_markers(page, timeout_s=30.0):
    """Marker centres on screen (CSS px), once two screenshots in a row agree (camera settled)."""
    prev, t0 = None, time.time()
    while time.time() - t0 < timeout_s:
        shot = cv2.cvtColor(
            cv2.imdecode(np.frombuffer(page.screenshot(), np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB
        )
        found = [_find(shot, rgb) for _, rgb in MARKERS]
        if all(f is not None for f in found):
            cur = np.array(found)
            if prev is not None and np.abs(cur - prev).max() < 0.2:
                return cur
            prev = cur
        time.sleep(0.5)
    raise AssertionError("the four markers did not appear on the page")


def _wait(cond, timeout_s=10.0):
    """Whether ``cond()`` came true within ``timeout_s`` (polled every 50 ms)."""
    t0 = time.time()
    while time.time() - t0 < timeout_s:
        if cond():
            return True
        time.sleep(0.05)
    return False


def _screen_of(page, handle, px) -> tuple[float, float]:
    """Where raw pixel ``px`` is on the page, from the camera the page reported to the server."""
    client = next(iter(handle._v.server.get_clients().values()))
    cam = client.camera
    pos, look, up = (np.asarray(v, float) for v in (cam.position, cam.look_at, cam.up_direction))
    pt = pixel_to_scene([px], handle._v.plane)[0]
    f = (look - pos) / np.linalg.norm(look - pos)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    v = pt - pos
    t = np.tan(cam.fov / 2)
    left, top, w, h = page.evaluate(
        "(() => { const c = [...document.querySelectorAll('canvas')].sort((a, b) => "
        "b.clientWidth * b.clientHeight - a.clientWidth * a.clientHeight)[0]; "
        "const r = c.getBoundingClientRect(); return [r.left, r.top, r.width, r.height]; })()"
    )
    nx = v @ r / (v @ f) / (t * w / h)
    ny = v @ u / (v @ f) / t
    return left + (nx + 1) / 2 * w, top + (1 - ny) / 2 * h


def _camera_settled(page, handle, probes=None, timeout_s=60.0):
    """Wait until clicks where ``_screen_of`` puts the pixels ``probes`` land there (within 1.5 px: the mouse sits
    on whole CSS pixels): the page's camera is fitted (the refit once the page has docked its panel included) and
    the server knows it. The default probes are the image centre and a point towards its lower right corner: a
    camera that differs only in scale about the centre (a refit the server has not heard of yet) passes the centre
    and fails the other. Screen positions taken from screenshots before that may be of the camera the page had
    first. Clicks are probed in view-only mode, where they are reported, not saved."""
    if probes is None:
        h, w = handle._v.display.rgb.shape[:2]
        probes = [(w / 2, h / 2), (0.8 * w, 0.8 * h)]
    mode = handle.mode
    handle.set_mode(None)
    t0 = time.time()
    try:
        while time.time() - t0 < timeout_s:
            if handle._v.server.get_clients() and all(_click_lands(page, handle, probe) for probe in probes):
                return
            time.sleep(0.2)
        raise AssertionError(f"the page's clicks never landed where its camera says: {handle.status}")
    finally:
        handle.set_mode(mode)


def _click_lands(page, handle, probe) -> bool:
    """A view-only click where ``_screen_of`` puts pixel ``probe`` is reported within 1.5 px of it."""
    before = handle.status
    page.mouse.click(*_screen_of(page, handle, probe))
    if _wait(lambda: handle.status != before and "clicked" in handle.status, 3):
        m = re.search(r"clicked \(([-\d.]+), ([-\d.]+)\)", handle.status)
        if m and np.hypot(float(m[1]) - probe[0], float(m[2]) - probe[1]) < 1.5:
            return True
    handle._v.set_status("")
    return False


def test_four_clicks_in_chromium_store_gcp_pixels(tmp_path, chromium):
    from playwright.sync_api import sync_playwright

    path = _marker_project(tmp_path)
    picked = []
    handle = start_viewer(path, on_pick=lambda f, v: picked.append(f))
    try:
        handle.set_mode("gcp")
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=str(chromium), args=LAUNCH_ARGS)
            try:
                page = browser.new_page(viewport={"width": 1280, "height": 800}, device_scale_factor=1)
                outside = []
                page.on(
                    "request",
                    lambda r: (
                        outside.append(r.url)
                        if r.url.startswith(("http:", "https:", "ws:", "wss:")) and "127.0.0.1" not in r.url
                        else None
                    ),
                )
                page.goto(handle.url)
                page.wait_for_selector("canvas", timeout=30000)
                _camera_settled(page, handle)  # the page's final camera, not the one it had before docking its panel
                screen = _locate_markers(page)
                for sx, sy in screen:
                    n = len(picked)
                    page.mouse.click(float(sx), float(sy))
                    t0 = time.time()
                    while len(picked) == n and time.time() - t0 < 30:
                        time.sleep(0.05)
                    assert len(picked) > n, handle.status
            finally:
                browser.close()
    finally:
        handle.stop()
    gcp = np.array(load_project(path).ortho.gcp_px)
    assert gcp.shape == (4, 2), handle.status
    np.testing.assert_allclose(gcp, [m[0] for m in MARKERS], atol=1.0)
    assert outside == [], f"the page fetched from outside: {outside}"
