"""`pvt view` at the command line, against a service on the FakeBackend: it prints the URL with its token,
serves the page and the cell's telemetry there (401 without the token), and stops when told."""

from __future__ import annotations

import contextlib
import http.client
import io
import json
import re
import threading
import time
from collections.abc import Callable

from streamer.cli import build_parser
from streamer.cli.view import run
from tests.api.conftest import Served, serve  # noqa: F401  (the fixture)


def test_pvt_view_serves_the_cell_behind_its_token(serve: Callable[..., Served]) -> None:  # noqa: F811
    served = serve()
    args = build_parser().parse_args(["view", "--connect", served.endpoint, "--cell", "demo", "--port", "0"])
    out = io.StringIO()
    stop = threading.Event()
    status: list[int] = []

    def main() -> None:
        with contextlib.redirect_stdout(out):
            status.append(run(args, stop=stop))

    worker = threading.Thread(target=main)
    worker.start()
    try:
        end = time.monotonic() + 30
        while "open http" not in out.getvalue():
            assert time.monotonic() < end and worker.is_alive(), out.getvalue()
            time.sleep(0.05)
        m = re.search(r"open (http://127\.0\.0\.1:(\d+)/\?token=([\w-]+))", out.getvalue())
        assert m, out.getvalue()
        port, token = int(m.group(2)), m.group(3)
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        conn.request("GET", "/api/state")
        r = conn.getresponse()
        r.read()
        assert r.status == 401
        headers = {"Cookie": f"pvt_view_token={token}"}
        end = time.monotonic() + 30
        while True:
            conn.request("GET", "/api/state", headers=headers)
            r = conn.getresponse()
            state = json.loads(r.read())
            if state["telemetry"] and state["status"].get("cell") == "demo":
                break
            assert time.monotonic() < end, state
            time.sleep(0.1)
        assert state["role"] == "operator"
        assert {a["name"] for a in state["telemetry"][-1]["axes"]} == {a.name for a in served.backend.cell.axes}
    finally:
        stop.set()
        worker.join(timeout=30)
    assert status == [0]
