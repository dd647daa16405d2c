"""rerun's web viewer, served with no request leaving the field machine.

rerun bundles its web viewer (wasm, JS) in the SDK, but its ``index.html`` loads the Inter font
from fonts.googleapis.com / fonts.gstatic.com, and the SDK's web server reports an anonymous
"web viewer served" event to tel.rerun.io unless analytics are off. In the field there is often
no internet, and nothing should phone home, so:

- the SDK's analytics are switched off for this process by setting ``CI`` (rerun's own rule: no
  analytics on CI; there is no other per-process switch, and ``rerun analytics disable`` would
  change the user's global configuration);
- rerun's web server runs on an *internal* port (web port + 1; rerun binds it on all interfaces);
  this module's small HTTP server, on the web port the supervisor opens, forwards each GET to it, removes the
  external font links (and the app.rerun.io-only script) from ``index.html``, and sends a
  Content-Security-Policy that lets the page reach only its own server and the gRPC port: anything else
  is refused by the browser.
"""

from __future__ import annotations

import os
import re
import threading
import urllib.request
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import rerun as rr

_EXTERNAL_LINKS = re.compile(r"<link[^>]*(fonts\.googleapis\.com|fonts\.gstatic\.com)[^>]*/?>\s*", re.S)
_RERUN_SITE_SCRIPT = re.compile(r'if \(window\.location\.hostname == "app\.rerun\.io"\) \{.*?\n      \}', re.S)


def disable_rerun_analytics() -> None:
    """Switch rerun's usage analytics off for this process (see the module docstring)."""
    os.environ.pop("FORCE_RERUN_ANALYTICS", None)
    os.environ.setdefault("CI", "fieldtool-no-telemetry")


def offline_index(html: str) -> str:
    """rerun's ``index.html`` without its outside links (fonts; the app.rerun.io-only script)."""
    html = _EXTERNAL_LINKS.sub("", html)
    return _RERUN_SITE_SCRIPT.sub("", html)


def csp(grpc_port: int) -> str:
    """The page may talk only to its own server and to the gRPC port of the same machine."""
    return (
        "default-src 'self'; script-src 'self' 'unsafe-inline' 'unsafe-eval' 'wasm-unsafe-eval'; "
        "style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; font-src 'self' data:; "
        f"worker-src 'self' blob:; connect-src 'self' http://*:{grpc_port} ws://*:{grpc_port}"
    )


class OfflineWebViewer:
    """Serve rerun's web viewer on ``web_port`` (all interfaces, as rerun's own server would) with no
    outside request; rerun's server itself listens on ``internal_port``.

    ``start()`` returns the page URL for a browser on this machine.
    """

    def __init__(
        self, grpc_url: str, grpc_port: int, web_port: int, internal_port: int | None = None, host: str = "0.0.0.0"
    ):
        self.grpc_url, self.grpc_port, self.web_port, self.host = grpc_url, grpc_port, web_port, host
        self.internal_port = internal_port or web_port + 1
        self.server: ThreadingHTTPServer | None = None

    def start(self) -> str:
        disable_rerun_analytics()
        rr.serve_web_viewer(web_port=self.internal_port, open_browser=False, connect_to=self.grpc_url)
        upstream = f"http://127.0.0.1:{self.internal_port}"
        policy = csp(self.grpc_port)

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self):  # noqa: N802 - http.server's name
                path = self.path.split("?", 1)[0] or "/"
                try:
                    with urllib.request.urlopen(upstream + path, timeout=30) as r:  # loopback only
                        body, ctype, status = r.read(), r.headers.get("Content-Type", ""), r.status
                except urllib.error.HTTPError as e:
                    body, ctype, status = b"", "text/plain", e.code
                except OSError:
                    body, ctype, status = b"rerun web viewer not reachable", "text/plain", 502
                if path in ("/", "/index.html") and status == 200:
                    body = offline_index(body.decode("utf-8")).encode("utf-8")
                self.send_response(status)
                self.send_header("Content-Type", ctype or "application/octet-stream")
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Content-Security-Policy", policy)
                self.send_header("Cache-Control", "no-cache")
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args):  # quiet: the CLI prints what matters
                pass

        self.server = ThreadingHTTPServer((self.host, self.web_port), Handler)
        threading.Thread(target=self.server.serve_forever, daemon=True, name="rerun-web").start()
        return f"http://127.0.0.1:{self.web_port}/?url={self.grpc_url.replace('+', '%2B')}"

    def stop(self) -> None:
        if self.server is not None:
            self.server.shutdown()
            self.server.server_close()
