"""streamer/view/server.py without a browser: the page and its scripts come from the server (nothing from
elsewhere, uPlot's license beside it), files outside static/ are not served, the state carries the telemetry
after a sequence number, and the verbs go to the client for an operator and never for an observer."""

from __future__ import annotations

import http.client
import json
import re
from collections.abc import Callable
from typing import Any

import pytest

from streamer.view.server import STATIC, ViewServer


class _Sub:
    def undeclare(self) -> None:
        pass


class _Session:
    def __init__(self) -> None:
        self.callbacks: dict[str, Callable[[Any], None]] = {}

    def declare_subscriber(self, key: str, callback: Callable[[Any], None]) -> _Sub:
        self.callbacks[key] = callback
        return _Sub()


class _Client:
    """What ViewServer uses of a MotionClient; records the verbs it was asked for."""

    cell = "demo"

    def __init__(self) -> None:
        self.session = _Session()
        self.calls: list[str] = []

    def service_status(self, timeout: float | None = None) -> dict[str, Any]:
        return {"held": False, "queue": []}

    def stop(self, *, emergency: bool = False, timeout: float | None = None) -> dict[str, Any]:
        self.calls.append("estop" if emergency else "stop")
        return {"held": True, "message": "stopped"}

    def hold(self, timeout: float | None = None) -> dict[str, Any]:
        self.calls.append("hold")
        return {"held": True}

    def resume(self, *, reset: bool = False, timeout: float | None = None) -> dict[str, Any]:
        self.calls.append("resume")
        return {"held": False}


def _get(port: int, path: str) -> tuple[int, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    conn.request("GET", path)
    r = conn.getresponse()
    return r.status, r.read()


def _post(port: int, path: str, header: bool = True) -> tuple[int, dict[str, Any]]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    conn.request("POST", path, headers={"X-Pvt-View": "1"} if header else {})
    r = conn.getresponse()
    return r.status, json.loads(r.read())


def test_the_page_needs_nothing_but_the_server() -> None:
    with ViewServer(_Client(), port=0) as view:
        code, page = _get(view.port, "/")
        assert code == 200
        html = page.decode()
        refs = re.findall(r'(?:src|href)="([^"]+)"', html)
        assert refs and all(r.startswith("/static/") for r in refs), refs
        for ref in refs:
            assert _get(view.port, ref)[0] == 200, ref
        assert (STATIC / "uplot" / "LICENSE").read_text().startswith("The MIT License")
        assert _get(view.port, "/static/../server.py")[0] == 404
        assert _get(view.port, "/etc/passwd")[0] == 404


def test_state_carries_the_telemetry_after_a_sequence_number() -> None:
    client = _Client()
    with ViewServer(client, port=0, watermarks=(5, 50)) as view:
        for seq in range(1, 4):
            view._add_telemetry({"seq": seq, "t": 100.0 + seq, "axes": [{"name": "j1", "position": 0.1 * seq}]})
        code, body = _get(view.port, "/api/state?after=1")
        state = json.loads(body)
        assert code == 200
        assert [m["seq"] for m in state["telemetry"]] == [2, 3]
        assert state["watermarks"] == {"underflow": 5, "overflow": 50, "fifo_size": 64}
        assert state["role"] == "operator" and state["verbs"] == ["stop", "estop", "hold", "resume"]
        assert _get(view.port, "/api/state?after=x")[0] == 400


@pytest.mark.parametrize("role", ["operator", "observer"])
def test_verbs_reach_the_client_only_for_an_operator(role: str) -> None:
    client = _Client()
    with ViewServer(client, port=0, role=role) as view:
        assert _post(view.port, "/api/stop", header=False)[0] == 403  # what a cross-site form would send
        answers = {v: _post(view.port, f"/api/{v}") for v in ("stop", "estop", "hold", "resume")}
    if role == "operator":
        assert client.calls == ["stop", "estop", "hold", "resume"]
        assert all(code == 200 for code, _ in answers.values())
    else:
        assert client.calls == []
        assert all(code == 403 and a["error"] == "PERMISSION_DENIED" for code, a in answers.values())


def test_with_a_token_nothing_is_served_without_it() -> None:
    client = _Client()
    with ViewServer(client, port=0, token="s3cret-token") as view:
        assert view.entry_url.endswith("/?token=s3cret-token")
        assert _get(view.port, "/")[0] == 401
        assert _get(view.port, "/api/state")[0] == 401
        assert _get(view.port, "/static/view.js")[0] == 401
        assert _get(view.port, "/?token=wrong")[0] == 401
        assert _post(view.port, "/api/stop")[0] == 401
        conn = http.client.HTTPConnection("127.0.0.1", view.port, timeout=10)
        conn.request("GET", "/?token=s3cret-token")
        r = conn.getresponse()
        r.read()
        assert r.status == 303 and r.getheader("Location") == "/"
        cookie = r.getheader("Set-Cookie") or ""
        assert "HttpOnly" in cookie and "SameSite=Strict" in cookie
        jar = cookie.split(";", 1)[0]
        conn.request("GET", "/api/state", headers={"Cookie": jar})
        r = conn.getresponse()
        assert r.status == 200 and json.loads(r.read())["cell"] == "demo"
        conn.request("POST", "/api/hold", headers={"Cookie": jar, "X-Pvt-View": "1"})
        r = conn.getresponse()
        r.read()
        assert r.status == 200
        conn.request("POST", "/api/stop", headers={"Cookie": "pvt_view_token=guess", "X-Pvt-View": "1"})
        r = conn.getresponse()
        r.read()
        assert r.status == 401
    assert client.calls == ["hold"]
