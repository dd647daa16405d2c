"""Who may load the picking page and open its WebSocket: same-origin, known host, per-launch key.

A web page open in the operator's browser can open a WebSocket to any ``ws://127.0.0.1:PORT``
(WebSockets are not bound by the same-origin policy) and, through DNS rebinding, even load the
page under its own domain name. The viewer refuses both:

- **Host**: the ``Host`` header must name the loopback (``127.0.0.1``, ``localhost``, ``[::1]``),
  or the address the viewer was told to bind with ``--host`` (for a wildcard bind, any IP literal
  or this machine's name). Any port is accepted, so an SSH tunnel to another local port works.
  A DNS-rebinding page arrives with its own domain name and is refused.
- **Origin**: a WebSocket handshake must carry ``Origin: http://<the same Host>``; an HTTP request
  carrying an Origin must match too. A page from another site sends its own Origin: refused.
- **Key**: a random token (new at every launch) is the first segment of the URL the CLI and the TUI
  print, ``http://127.0.0.1:PORT/<token>/``; the page's WebSocket URL is derived from its address,
  so it carries the token as its path. Anything without it gets 403.

:func:`install` wraps the ``process_request`` hook of the ``websockets`` server that viser 1.1
starts (viser serves its page and its WebSocket on one port through that hook).
"""

from __future__ import annotations

import asyncio
import contextlib
import getpass
import hmac
import ipaddress
import logging
import secrets
import socket
import sys
import threading
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from http import HTTPStatus
from pathlib import Path
from urllib.parse import urlsplit

import viser
import websockets.asyncio.server as wss
from websockets.datastructures import Headers
from websockets.frames import CloseCode
from websockets.http11 import Request, Response

LOOPBACK_NAMES = ("127.0.0.1", "localhost", "::1")
WILDCARDS = ("0.0.0.0", "::", "")


def _split_host(value: str) -> str | None:
    """Host name of a ``Host`` header value (``name``, ``name:port``, ``[v6]:port``), lower case;
    None when malformed."""
    value = value.strip().lower()
    if not value:
        return None
    try:
        parts = urlsplit("//" + value)
        host = parts.hostname
        _ = parts.port  # raises ValueError on a bad port
    except ValueError:
        return None
    return host or None


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
        return True
    except ValueError:
        return False


@dataclass
class AccessGuard:
    """The rules for one launch of the viewer.

    Parameters
    ----------
    bind_host : the address the server listens on (``127.0.0.1`` by default).
    token : the URL key; a new random one when not given.
    """

    bind_host: str = "127.0.0.1"
    token: str = field(default_factory=lambda: secrets.token_urlsafe(18))
    refused: list[str] = field(default_factory=list)  # why recent requests were refused (last 20)
    hooked: bool = False  # set once the check sits in front of viser's server

    def __post_init__(self) -> None:
        names = {n.lower() for n in LOOPBACK_NAMES}
        self._any_ip = self.bind_host in WILDCARDS
        if self.bind_host not in WILDCARDS:
            names.add(self.bind_host.strip("[]").lower())
        if self._any_ip:
            for n in (socket.gethostname(), socket.getfqdn()):
                if n:
                    names.add(n.lower())
        self._names = frozenset(names)
        self._lock = threading.Lock()

    @property
    def prefix(self) -> str:
        """The URL path every request must start with: ``/<token>``."""
        return "/" + self.token

    def host_allowed(self, host_header: str | None) -> bool:
        name = _split_host(host_header or "")
        if name is None:
            return False
        if name in self._names:
            return True
        if _is_ip(name):
            ip = ipaddress.ip_address(name)
            return ip.is_loopback or self._any_ip
        return False

    def origin_allowed(self, origin: str | None, host_header: str | None) -> bool:
        """Same origin: ``scheme://`` + exactly the Host the request was sent to."""
        if not origin or not host_header:
            return False
        o = origin.strip().lower()
        h = host_header.strip().lower()
        return o in (f"http://{h}", f"https://{h}")

    def _key_of(self, path: str) -> tuple[bool, str]:
        """(token matched, rest of the path after the token) for a request path."""
        path = path.partition("?")[0]
        first, sep, rest = path.lstrip("/").partition("/")
        ok = hmac.compare_digest(first.encode(), self.token.encode())
        return ok, "/" + rest if sep else ""

    def check(self, path: str, headers, websocket: bool) -> tuple[HTTPStatus, str] | None:
        """None when the request may pass; else the status and the reason to answer with. Two ``Host`` or
        two ``Origin`` headers are a malformed request (400), said in one log line."""
        for name in ("Host", "Origin"):
            values = _all(headers, name)
            if len(values) > 1:
                why = f"{len(values)} {name} headers in one request"
                log_once("duplicate-header", f"fieldtool view: refused a request with {why} (400)")
                return self._refuse(HTTPStatus.BAD_REQUEST, why)
        hosts, origins = _all(headers, "Host"), _all(headers, "Origin")
        host = hosts[0] if hosts else None
        origin = origins[0] if origins else None
        if not self.host_allowed(host):
            return self._refuse(HTTPStatus.FORBIDDEN, f"host {host!r} is not this viewer's address")
        if (websocket or origin is not None) and not self.origin_allowed(origin, host):
            return self._refuse(HTTPStatus.FORBIDDEN, f"origin {origin!r} is not the viewer's page")
        ok, _rest = self._key_of(path)
        if not ok:
            return self._refuse(
                HTTPStatus.FORBIDDEN,
                "the URL lacks the viewer's access key: open the address "
                "printed by `fieldtool view` or shown in the TUI",
            )
        return None

    def _refuse(self, status: HTTPStatus, why: str) -> tuple[HTTPStatus, str]:
        with self._lock:
            self.refused.append(why)
            del self.refused[:-20]
        return status, why


def _all(headers, name: str) -> list[str]:
    """Every value of header ``name`` (websockets' Headers, or a plain mapping)."""
    get_all = getattr(headers, "get_all", None)
    if get_all is not None:
        return list(get_all(name))
    v = headers.get(name)
    return [] if v is None else [v]


# ---------------------------------------------------------------------------------------------
# one log line per kind of refusal

MAX_MESSAGE_BYTES = 4 * 1024 * 1024  # a WebSocket message from the page: clicks and GUI values, a few kB
_said: dict[str, int] = {}
_said_lock = threading.Lock()


def log_once(kind: str, line: str) -> None:
    """Print ``line`` on stderr the first time a refusal of ``kind`` happens; later ones are only counted
    (``refusal_counts``), so that a flood of bad requests cannot flood the terminal."""
    with _said_lock:
        n = _said.get(kind, 0)
        _said[kind] = n + 1
    if n == 0:
        print(line + " (further ones are refused silently)", file=sys.stderr, flush=True)


def refusal_counts() -> dict[str, int]:
    with _said_lock:
        return dict(_said)


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text[:200]}" if text else type(e).__name__


def guard_handler(inner: Callable) -> Callable:
    """viser's WebSocket handler, with a malformed message (not MessagePack, an unknown message type, wrong
    fields) ending its connection with one log line instead of websockets' "connection handler failed"
    traceback; errors of the tasks that handle a message are said the same way (the loop's exception
    handler)."""

    async def handler(connection) -> None:
        loop = asyncio.get_running_loop()
        if not getattr(loop, "_fieldtool_quiet", False):
            loop.set_exception_handler(_loop_exception)
            loop._fieldtool_quiet = True  # type: ignore[attr-defined]
        try:
            await inner(connection)
        except Exception as e:  # noqa: BLE001 - a client's bad message must not reach the log as a traceback
            log_once(
                "malformed-message",
                f"fieldtool view: closed a connection that sent a malformed message ({_one_line(e)})",
            )
            with contextlib.suppress(Exception):
                await connection.close(1007, "malformed message")
        finally:
            _say_if_oversized(connection)

    return handler


def _say_if_oversized(connection) -> None:
    """One log line when websockets closed ``connection`` for a message over MAX_MESSAGE_BYTES (close code
    1009, sent by websockets itself: viser's handler takes that close as an ordinary disconnect, silently)."""
    close = getattr(getattr(connection, "protocol", None), "close_sent", None)
    if close is not None and close.code == CloseCode.MESSAGE_TOO_BIG:
        log_once(
            "oversized-message",
            f"fieldtool view: closed a connection that sent a message over {MAX_MESSAGE_BYTES // 2**20} MB "
            f"(the page sends a few kB; WebSocket close 1009: {close.reason or 'message too big'})",
        )


class OneLineLogger(logging.LoggerAdapter):
    """The websockets server's logger: its errors ("opening handshake failed" for a malformed request, "connection
    handler failed") as one line each kind (:func:`log_once`) with the exception's own message, no traceback;
    its debug and info lines dropped."""

    def __init__(self) -> None:
        super().__init__(logging.getLogger("fieldtool.viewer.websockets"), {})

    def isEnabledFor(self, level: int) -> bool:
        return level >= logging.WARNING

    def log(self, level: int, msg, *args, exc_info=None, **kwargs) -> None:
        if level < logging.WARNING:
            return
        e = sys.exc_info()[1] if exc_info is True else exc_info if isinstance(exc_info, BaseException) else None
        text = str(msg) % args if args else str(msg)
        log_once(f"websockets:{text}", f"fieldtool view: {text}" + (f" ({_one_line(e)})" if e is not None else ""))


def _loop_exception(loop, context: dict) -> None:
    e = context.get("exception")
    if isinstance(e, Exception):
        log_once("message-handler", f"fieldtool view: ignored a message the viewer could not handle ({_one_line(e)})")
        return
    loop.default_exception_handler(context)


# ---------------------------------------------------------------------------------------------
# the hook into viser's websockets server

SECURITY_HEADERS = {
    "X-Frame-Options": "DENY",  # no framing by another site (clickjacking)
    "Content-Security-Policy": "frame-ancestors 'none'",
    "Referrer-Policy": "no-referrer",  # the key never leaves in a Referer
    "Cache-Control": "no-store",
}

_INSTALL_LOCK = threading.Lock()


def make_process_request(
    guard: AccessGuard, inner: Callable | None, extra_routes: Callable[[str, Request], Response | None] | None = None
) -> Callable:
    """A ``process_request(connection, request)`` for websockets that applies ``guard``, strips
    the key from the path and hands the request to viser's own file server (``inner``).

    ``extra_routes(rest_of_path, request)`` may answer paths itself (a Response) or return None."""

    def refuse(status: HTTPStatus, why: str) -> Response:
        body = f"{status.value} {status.phrase}: {why}\n".encode()
        return Response(
            status.value,
            status.phrase,
            Headers(
                {"Content-Type": "text/plain; charset=utf-8", "Content-Length": str(len(body)), **SECURITY_HEADERS}
            ),
            body,
        )

    def process_request(connection, request: Request):
        is_ws = (request.headers.get("Upgrade") or "").lower() == "websocket"
        verdict = guard.check(request.path, request.headers, websocket=is_ws)
        if verdict is not None:
            return refuse(*verdict)
        _, rest = guard._key_of(request.path)
        if is_ws:
            return None  # accepted: viser's handler takes the connection
        if rest == "":  # /<token> -> /<token>/ so that the page's relative URLs keep the key
            return Response(
                HTTPStatus.FOUND.value,
                "Found",
                Headers({"Location": guard.prefix + "/", "Content-Length": "0", **SECURITY_HEADERS}),
                b"",
            )
        query = request.path.partition("?")[2]
        if extra_routes is not None:
            answer = extra_routes(rest + ("?" + query if query else ""), request)
            if answer is not None:
                for k, v in SECURITY_HEADERS.items():
                    answer.headers[k] = v
                return answer
        if inner is None:
            return refuse(HTTPStatus.NOT_FOUND, "nothing here")
        stripped = Request(rest + ("?" + query if query else ""), request.headers)
        answer = inner(connection, stripped)
        if answer is not None:
            for k, v in SECURITY_HEADERS.items():
                answer.headers[k] = v
        return answer

    return process_request


@contextlib.contextmanager
def install(guard: AccessGuard, extra_routes: Callable | None = None) -> Iterator[None]:
    """While inside, a ``websockets.asyncio.server.serve`` call made by viser gets its
    ``process_request`` wrapped by ``guard``. Create the ``viser.ViserServer`` inside: it binds
    its socket before its constructor returns, so the patch is in place exactly for that call."""
    original = wss.serve

    class guarded_serve(original):  # type: ignore[misc, valid-type]
        def __init__(self, *args, **kwargs):
            inner = kwargs.get("process_request")
            if inner is not None and getattr(inner, "__name__", "") == "viser_http_server":
                kwargs["process_request"] = make_process_request(guard, inner, extra_routes)
                kwargs["max_size"] = MAX_MESSAGE_BYTES  # viser allows 50 MB; the page sends a few kB
                kwargs["logger"] = OneLineLogger()  # a malformed request: one line, no traceback
                if args:
                    args = (guard_handler(args[0]), *args[1:])
                guard.hooked = True
            super().__init__(*args, **kwargs)

    # a client's message with wrong field types: viser warns in two lines per message; the handler that then
    # fails says it in one line (_loop_exception)
    warnings.filterwarnings("ignore", message=r"\[viser\] .* does not match annotation", category=UserWarning)
    with _INSTALL_LOCK:
        # setattr: mypy refuses an assignment to a class name, and rebinding websockets' serve is the point here
        setattr(wss, "serve", guarded_serve)  # noqa: B010
        try:
            yield
        finally:
            setattr(wss, "serve", original)  # noqa: B010


def ssh_hint(port: int, user: str | None = None, host: str | None = None) -> str:
    """The exact command that forwards the viewer's ``port`` from this machine to the operator's
    computer: ``ssh -L PORT:127.0.0.1:PORT user@host`` (then open ``http://127.0.0.1:PORT/KEY/``
    there). ``user`` and ``host`` default to this account and this machine's name."""
    if user is None:
        try:
            user = getpass.getuser()
        except Exception:  # noqa: BLE001 - no login name (container): leave a placeholder
            user = "USER"
    if not host:  # "localhost" would name the operator's own computer there: this machine's name, or a placeholder
        names = [n for n in (socket.getfqdn(), socket.gethostname()) if n and n.split(".")[0] not in ("localhost", "")]
        host = names[0] if names else "THIS-MACHINE"
    return f"ssh -L {int(port)}:127.0.0.1:{int(port)} {user}@{host}"


def page_path() -> Path:
    """viser's bundled, self-contained page."""
    return Path(viser.__file__).resolve().parent / "client" / "build" / "index.html"
