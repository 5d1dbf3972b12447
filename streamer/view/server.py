"""`pvt view`'s loopback HTTP server: one page that shows a cell live and, for an operator, stops, holds and
resumes it through the job API.

The page reads and acts through the Zenoh job API with the user's identity (docs/security.md), so it
shows what that identity may read. `ViewServer` is the user's `MotionClient` plus a `ThreadingHTTPServer`
on 127.0.0.1: rings of recent telemetry and events, `GET /` the page with vendored scripts, `GET
/api/state?after=SEQ` what is new, `POST /api/stop|estop|hold|resume` (403 for an observer). With a
`token` (random, in the printed URL) every request needs it, kept in an HttpOnly SameSite=Strict cookie,
so another user or site can neither read nor act. Nothing here touches the bus.
"""

from __future__ import annotations

import collections
import json
import logging
import secrets
import threading
import time
from collections.abc import Mapping
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlparse

STATIC = Path(__file__).resolve().parent / "static"
TOKEN_COOKIE = "pvt_view_token"
ROLES = ("operator", "observer")
VERBS = ("stop", "estop", "hold", "resume")
_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
          ".css": "text/css; charset=utf-8"}

log = logging.getLogger(__name__)


def _plain(obj: Any) -> Any:
    """msgpack's values as JSON's (bytes as hex)."""
    if isinstance(obj, Mapping):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v) for v in obj]
    if isinstance(obj, bytes):
        return obj.hex()
    if isinstance(obj, float) and obj != obj:  # NaN
        return None
    return obj


class ViewServer:
    """See the module docstring. `client`: a connected `MotionClient` (closed by the caller)."""

    def __init__(self, client: Any, *, role: str = "operator", host: str = "127.0.0.1", port: int = 8080,
                 watermarks: tuple[int, int] = (4, 60), fifo_size: int = 64, keep_s: float = 30.0,
                 keep_events: int = 50, status_period_s: float = 0.5, token: str | None = None):
        if role not in ROLES:
            raise ValueError(f"role must be one of {', '.join(ROLES)}, got {role!r}")
        self.client = client
        self.role = role
        self.host = host
        self.requested_port = port
        self.watermarks = watermarks
        self.fifo_size = fifo_size
        self.keep_s = keep_s
        self.status_period_s = status_period_s
        self.token = token
        self._lock = threading.Lock()
        self._telemetry: collections.deque[dict[str, Any]] = collections.deque()
        self._events: collections.deque[dict[str, Any]] = collections.deque(maxlen=keep_events)
        self._status: dict[str, Any] = {}
        self._subs: list[Any] = []
        self._http: ThreadingHTTPServer | None = None
        self._threads: list[threading.Thread] = []
        self._stop = threading.Event()

    # ---- life
    def start(self) -> ViewServer:
        from streamer.api import keys
        from streamer.api.payload import unpack

        cell = self.client.cell

        def on_telemetry(sample: Any) -> None:
            msg = unpack(sample.payload.to_bytes())
            if isinstance(msg, Mapping):
                self._add_telemetry(_plain(msg))

        def on_event(sample: Any) -> None:
            msg = unpack(sample.payload.to_bytes())
            if isinstance(msg, Mapping):
                with self._lock:
                    self._events.append(_plain(msg))

        session = self.client.session
        self._subs.append(session.declare_subscriber(keys.telemetry(cell), on_telemetry))
        self._subs.append(session.declare_subscriber(keys.job_events_any(cell), on_event))
        self._http = ThreadingHTTPServer((self.host, self.requested_port), self._handler())
        self._http.daemon_threads = True
        for target, name in ((self._http.serve_forever, "pvt-view-http"), (self._poll_status, "pvt-view-status")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        return self

    @property
    def port(self) -> int:
        if self._http is None:
            raise RuntimeError("the view server is not started")
        return int(self._http.server_address[1])

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/"

    @property
    def entry_url(self) -> str:
        """The URL to open: with the token, when there is one."""
        return self.url + (f"?token={self.token}" if self.token else "")

    def allowed(self, cookie_header: str | None) -> bool:
        """Whether a request with this Cookie header may see the page (always, without a token)."""
        if not self.token:
            return True
        from http.cookies import CookieError, SimpleCookie

        cookies: SimpleCookie = SimpleCookie()
        try:
            cookies.load(cookie_header or "")
        except CookieError:
            return False
        morsel = cookies.get(TOKEN_COOKIE)
        return morsel is not None and secrets.compare_digest(morsel.value, self.token)

    def close(self) -> None:
        self._stop.set()
        if self._http is not None:
            self._http.shutdown()
            self._http.server_close()
            self._http = None
        for t in self._threads:
            t.join(timeout=5.0)
        self._threads.clear()
        for sub in self._subs:
            sub.undeclare()
        self._subs.clear()

    def __enter__(self) -> ViewServer:
        return self.start() if self._http is None else self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- state
    def _add_telemetry(self, msg: dict[str, Any]) -> None:
        with self._lock:
            self._telemetry.append(msg)
            newest = msg.get("t")
            if isinstance(newest, int | float):
                while self._telemetry and isinstance(self._telemetry[0].get("t"), int | float) \
                        and newest - self._telemetry[0]["t"] > self.keep_s:
                    self._telemetry.popleft()

    def _poll_status(self) -> None:
        while not self._stop.is_set():
            try:
                status = _plain(self.client.service_status(timeout=2.0))
            except Exception as e:  # no service for now: say so on the page, keep asking
                status = {"error": f"{type(e).__name__}: {e}"}
            with self._lock:
                self._status = status
            self._stop.wait(self.status_period_s)

    def state(self, after: float = -1.0) -> dict[str, Any]:
        """What the page polls: telemetry samples with seq > `after`, the last events, the status."""
        with self._lock:
            samples = [m for m in self._telemetry if isinstance(m.get("seq"), int | float) and m["seq"] > after]
            events = list(self._events)
            status = dict(self._status)
        return {"cell": self.client.cell, "role": self.role, "verbs": list(VERBS) if self.role == "operator" else [],
                "watermarks": {"underflow": self.watermarks[0], "overflow": self.watermarks[1],
                               "fifo_size": self.fifo_size},
                "telemetry": samples, "events": events, "status": status, "now": time.time()}

    def verb(self, name: str) -> tuple[int, dict[str, Any]]:
        """Run an operator verb through the job API; (HTTP status, answer)."""
        from streamer.api.errors import MotionError

        if name not in VERBS:
            return HTTPStatus.NOT_FOUND, {"error": f"no verb {name!r}; verbs are {', '.join(VERBS)}"}
        if self.role != "operator":
            return HTTPStatus.FORBIDDEN, {"error": "PERMISSION_DENIED", "message": "this page is an observer's"}
        try:
            if name == "stop":
                answer = self.client.stop(timeout=5.0)
            elif name == "estop":
                answer = self.client.stop(emergency=True, timeout=5.0)
            elif name == "hold":
                answer = self.client.hold(timeout=5.0)
            else:
                answer = self.client.resume(timeout=5.0)
        except MotionError as e:
            return HTTPStatus.CONFLICT, {"error": e.code, "message": str(e)}
        return HTTPStatus.OK, _plain(answer)

    # ---- HTTP
    def _handler(self) -> type[BaseHTTPRequestHandler]:
        view = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, format: str, *args: Any) -> None:
                log.debug("view: " + format, *args)

            def _send(self, code: int, body: bytes, ctype: str) -> None:
                self.send_response(code)
                self.send_header("Content-Type", ctype)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(body)

            def _json(self, code: int, obj: Any) -> None:
                self._send(code, json.dumps(obj, allow_nan=False, default=str).encode(), "application/json")

            def _admitted(self, url: Any) -> bool:
                if view.allowed(self.headers.get("Cookie")):
                    return True
                given = parse_qs(url.query).get("token", [""])[0]
                if view.token and url.path == "/" and given and secrets.compare_digest(given, view.token):
                    self.send_response(HTTPStatus.SEE_OTHER)
                    self.send_header("Set-Cookie", f"{TOKEN_COOKIE}={view.token}; Path=/; HttpOnly; SameSite=Strict")
                    self.send_header("Location", "/")
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return False
                self._send(HTTPStatus.UNAUTHORIZED, b"pvt view: open the URL `pvt view` printed (it has the token)",
                           "text/plain; charset=utf-8")
                return False

            def do_GET(self) -> None:
                url = urlparse(self.path)
                if not self._admitted(url):
                    return
                if url.path == "/api/state":
                    after = parse_qs(url.query).get("after", ["-1"])[0]
                    try:
                        since = float(after)
                    except ValueError:
                        self._json(HTTPStatus.BAD_REQUEST, {"error": f"after={after!r} is not a number"})
                        return
                    self._json(HTTPStatus.OK, view.state(since))
                    return
                name = "index.html" if url.path in ("/", "/index.html") else url.path.removeprefix("/static/")
                path = (STATIC / name).resolve()
                if (url.path not in ("/", "/index.html") and not url.path.startswith("/static/")) or \
                        STATIC not in path.parents or not path.is_file():
                    self._send(HTTPStatus.NOT_FOUND, b"not found", "text/plain")
                    return
                self._send(HTTPStatus.OK, path.read_bytes(), _TYPES.get(path.suffix, "application/octet-stream"))

            def do_POST(self) -> None:
                url = urlparse(self.path)
                if not view.allowed(self.headers.get("Cookie")):
                    self._json(HTTPStatus.UNAUTHORIZED, {"error": "no token"})
                    return
                if not url.path.startswith("/api/"):
                    self._send(HTTPStatus.NOT_FOUND, b"not found", "text/plain")
                    return
                # a form on another site cannot post here with this header (no CORS preflight passes)
                if self.headers.get("X-Pvt-View") != "1":
                    self._json(HTTPStatus.FORBIDDEN, {"error": "missing X-Pvt-View header"})
                    return
                code, answer = view.verb(url.path.removeprefix("/api/"))
                self._json(code, answer)

        return Handler
