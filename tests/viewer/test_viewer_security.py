"""Only the viewer's own page may use it: real HTTP and WebSocket clients with a foreign Origin, a
foreign Host (DNS rebinding) or no key are refused; the page's own requests pass."""

import http.client
import urllib.error
import urllib.request

import numpy as np
import pytest
import viser
from test_viewer_server import _tiny_project
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from fieldtool.errors import ParameterError
from fieldtool.project.model import load_project
from fieldtool.viewer.guard import AccessGuard, ssh_hint
from fieldtool.viewer.server import start_viewer

PROTOCOL = [f"viser-v{viser.__version__}"]


@pytest.fixture
def viewer(tmp_path):
    h = start_viewer(_tiny_project(tmp_path), port=0)
    yield h
    h.stop()


def _ws(h, path, origin, host="127.0.0.1"):
    return connect(f"ws://{host}:{h.port}{path}", origin=origin, subprotocols=PROTOCOL, open_timeout=10, proxy=None)


def _get(h, path, headers=None):
    conn = http.client.HTTPConnection("127.0.0.1", h.port, timeout=10)
    try:
        conn.request("GET", path, headers=headers or {})
        r = conn.getresponse()
        return r.status, r.read()
    finally:
        conn.close()


def test_websocket_from_a_foreign_origin_is_refused(viewer):
    with pytest.raises(InvalidStatus) as e:
        _ws(viewer, f"/{viewer.token}", "http://evil.example.com")
    assert e.value.response.status_code == 403
    assert any("origin" in why for why in viewer.refused)


def test_websocket_without_the_key_or_without_origin_is_refused(viewer):
    origin = f"http://127.0.0.1:{viewer.port}"
    for path in ("/", "/wrong-key", f"/{viewer.token[:-1]}"):
        with pytest.raises(InvalidStatus) as e:
            _ws(viewer, path, origin)
        assert e.value.response.status_code == 403
    with pytest.raises(InvalidStatus):
        _ws(viewer, f"/{viewer.token}", None)  # a non-browser client must still prove same-origin


def test_the_pages_own_websocket_is_served(viewer):
    with _ws(viewer, f"/{viewer.token}", f"http://127.0.0.1:{viewer.port}") as ws:
        first = ws.recv(timeout=10)  # the scene starts streaming
    assert len(first) > 0
    with _ws(viewer, f"/{viewer.token}", f"http://localhost:{viewer.port}", "localhost") as ws:
        assert len(ws.recv(timeout=10)) > 0
    with pytest.raises(InvalidStatus):  # the page on 127.0.0.1 but the socket named localhost: not same-origin
        _ws(viewer, f"/{viewer.token}", f"http://localhost:{viewer.port}")


def test_http_needs_the_key_and_the_viewers_own_host(viewer):
    status, body = _get(viewer, "/")
    assert status == 403 and b"access key" in body
    status, _ = _get(viewer, "/index.html")
    assert status == 403
    # DNS rebinding: the right key, but the browser sends the attacker's host name
    status, _ = _get(viewer, f"/{viewer.token}/", {"Host": f"evil.example.com:{viewer.port}"})
    assert status == 403
    status, _ = _get(viewer, f"/{viewer.token}/", {"Origin": "http://evil.example.com"})
    assert status == 403
    status, body = _get(viewer, f"/{viewer.token}/")
    assert status == 200 and b'<div id="root">' in body and b"zoom?x=" in body
    html = urllib.request.urlopen(viewer.url, timeout=10)
    assert html.headers["X-Frame-Options"] == "DENY"
    # a URL through an SSH tunnel on another local port is still the loopback
    status, _ = _get(viewer, f"/{viewer.token}/", {"Host": "127.0.0.1:9999"})
    assert status == 200


def test_the_zoom_request_needs_the_key(viewer):
    with pytest.raises(urllib.error.HTTPError) as e:
        urllib.request.urlopen(f"http://127.0.0.1:{viewer.port}/zoom?x=0&y=0&f=0.5", timeout=10)
    e.value.close()  # its connection, left open, would hold the viewer's stop for the server's close timeout
    assert e.value.code == 403
    status, _ = _get(viewer, f"/{viewer.token}/zoom?x=0&y=0&f=0.5")
    assert status == 204


def test_every_launch_has_a_new_key(tmp_path):
    a = start_viewer(_tiny_project(tmp_path), port=0)
    try:
        b = start_viewer(a._v.path, port=0)
        try:
            assert a.token != b.token and len(a.token) >= 20
            assert a.url.endswith(f"/{a.token}/")
        finally:
            b.stop()
    finally:
        a.stop()


def test_guard_rules():
    g = AccessGuard("127.0.0.1", token="k")
    assert g.host_allowed("127.0.0.1:8080") and g.host_allowed("localhost:1") and g.host_allowed("[::1]:80")
    assert not g.host_allowed("evil.example.com:8080") and not g.host_allowed("") and not g.host_allowed(None)
    assert not g.host_allowed("192.168.1.4:8080")  # bound to the loopback: no LAN address
    assert g.origin_allowed("http://127.0.0.1:8080", "127.0.0.1:8080")
    assert not g.origin_allowed("http://127.0.0.1:8081", "127.0.0.1:8080")
    assert not g.origin_allowed("null", "127.0.0.1:8080")
    wide = AccessGuard("0.0.0.0", token="k")
    assert wide.host_allowed("192.168.1.4:8080") and not wide.host_allowed("evil.example.com:8080")


def test_port_is_remembered_per_project_and_a_taken_port_is_refused(tmp_path):
    path = _tiny_project(tmp_path)
    a = start_viewer(path)  # no port anywhere: a free one, remembered
    try:
        assert load_project(path).viewer.port == a.port
        assert any("remembered" in n for n in a.notes)
        with pytest.raises(ParameterError, match="in use"):
            start_viewer(path, port=a.port)
        b = start_viewer(path)  # the remembered port is busy: another one this time, not remembered
        try:
            assert b.port != a.port and any("in use" in n for n in b.notes)
        finally:
            b.stop()
        assert load_project(path).viewer.port == a.port
    finally:
        a.stop()
    c = start_viewer(path)  # the next launch gets the same port again (same tunnel)
    try:
        assert c.port == a.port
    finally:
        c.stop()
    with pytest.raises(ParameterError, match="1024"):
        start_viewer(path, port=80)
    d = start_viewer(path, port=0)  # 0: a free port this time, the remembered one stays
    try:
        assert load_project(path).viewer.port == a.port
    finally:
        d.stop()


def test_ssh_hint_is_the_exact_tunnel_line():
    assert ssh_hint(8765, user="ana", host="field-pc") == "ssh -L 8765:127.0.0.1:8765 ana@field-pc"
    assert ssh_hint(8765).startswith("ssh -L 8765:127.0.0.1:8765 ")


def test_zoom_keeps_the_point_under_the_cursor():
    from fieldtool.viewer.mapping import camera_pose, fit_plane, ray_to_pixel, zoom_about_cursor

    plane = fit_plane(640, 480)
    fov, aspect = np.deg2rad(50), 1.6
    pos, look, up = camera_pose(plane, fov, aspect)

    def pixel_at(p, t, ndc):
        f = (t - p) / np.linalg.norm(t - p)
        r = np.cross(f, up)
        r /= np.linalg.norm(r)
        u = np.cross(r, f)
        h = np.tan(fov / 2)
        return ray_to_pixel(p, f + ndc[0] * h * aspect * r + ndc[1] * h * u, plane)

    ndc = (0.43, -0.27)
    before = pixel_at(pos, look, ndc)
    p2, t2 = zoom_about_cursor(pos, look, up, fov, aspect, ndc, 0.5, plane)
    np.testing.assert_allclose(pixel_at(p2, t2, ndc), before, atol=1e-6)
    assert np.linalg.norm(p2 - t2) == pytest.approx(0.5 * np.linalg.norm(pos - look))
    # another point moved away from the cursor's: it is a zoom, not a no-op
    assert np.linalg.norm(pixel_at(p2, t2, (0.0, 0.0)) - pixel_at(pos, look, (0.0, 0.0))) > 10


def test_fieldtool_view_prints_the_tunnel_line_and_the_keyed_url(tmp_path):
    import os
    import subprocess
    import sys
    import time
    from pathlib import Path

    path = _tiny_project(tmp_path)
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    proc = subprocess.Popen(
        [sys.executable, "-m", "fieldtool.cli.main", "view", str(path), "--port", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    try:
        lines, t0 = [], time.time()
        while time.time() - t0 < 60 and not any("then open" in ln for ln in lines):
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
        text = "".join(lines)
        port = int(text.split("picking viewer at http://127.0.0.1:")[1].split("/")[0])
        assert f"ssh -L {port}:127.0.0.1:{port} " in text
        key = text.split(f"http://127.0.0.1:{port}/")[1].split("/")[0]
        assert len(key) >= 20 and f"then open http://127.0.0.1:{port}/{key}/" in text
    finally:
        proc.terminate()
        proc.wait(timeout=20)
