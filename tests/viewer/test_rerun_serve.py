"""`--rerun serve` in Debian's chromium: the web viewer loads and no request leaves 127.0.0.1.

rerun's bundled page links Google Fonts, and its wasm asks api.github.com for releases and
tel.rerun.io for analytics. fieldtool serves the page without the font links and with a
Content-Security-Policy, so the browser sends none of them: every request the browser makes is
logged here and must go to 127.0.0.1; the blocked attempts are reported by the browser console.
"""

import socket
import time
import urllib.request
from urllib.parse import urlparse

import numpy as np
import pytest
from chromium_setup import LAUNCH_ARGS, ensure_chromium

from fieldtool.viewer.rerun_log import RerunObserver

pytestmark = pytest.mark.browser


def _free_ports(n: int) -> list[int]:
    """``n`` different free ports: the sockets are held until all are bound (one closed before the next bind
    may be handed out again)."""
    socks = [socket.socket() for _ in range(n)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


@pytest.fixture(scope="module")
def chromium():
    path, reason = ensure_chromium()
    if path is None:
        pytest.skip(f"chromium unavailable: {reason}")
    return path


def test_served_web_viewer_makes_no_outside_request(chromium):
    from playwright.sync_api import sync_playwright

    grpc, web = _free_ports(2)
    obs = RerunObserver("serve", grpc_port=grpc, web_port=web)
    x, y = np.meshgrid(np.arange(4.0) * 16, np.arange(3.0) * 16)
    obs.frame(0, 0.0, np.zeros((48, 64), np.uint8), np.zeros((48, 64), np.float32))
    obs.pair(0, 0.05, x, y, np.ones_like(x), np.zeros_like(x), np.ones(x.shape, bool))
    url = obs.urls["local"]

    with urllib.request.urlopen(url, timeout=30) as r:  # the page itself: no outside link, a CSP
        page_html = r.read().decode()
        policy = r.headers["Content-Security-Policy"]
    assert "googleapis" not in page_html and "gstatic" not in page_html and "rerun.io" not in page_html
    assert "default-src 'self'" in policy and f"http://*:{grpc}" in policy

    requests, sockets, console = [], [], []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(chromium), args=LAUNCH_ARGS)
        try:
            context = browser.new_context()
            context.on("request", lambda q: requests.append(q.url))
            page = context.new_page()
            page.on("websocket", lambda ws: sockets.append(ws.url))
            page.on("console", lambda m: console.append(m.text))
            page.goto(url)
            t0 = time.time()  # until the viewer asks the gRPC server for the stream, then a while longer
            while not any(f":{grpc}/" in u for u in requests) and time.time() - t0 < 90:
                page.wait_for_timeout(500)
            page.wait_for_timeout(5000)
        finally:
            browser.close()
    assert any(f":{grpc}/" in u for u in requests), requests  # it did connect to the stream
    assert any(u.endswith(".wasm") for u in requests)
    hosts = {urlparse(u).hostname for u in requests + sockets if not u.startswith(("data:", "blob:"))}
    assert hosts == {"127.0.0.1"}, sorted(set(requests + sockets))
    blocked = [c for c in console if "Content Security Policy" in c]
    print(f"{len(requests)} requests, all to 127.0.0.1; attempts blocked by the CSP: {len(blocked)}")
