"""`pvt view`'s page (streamer/view) in headless Chromium, driven through the DevTools protocol, during a real
job of `pvt serve --sim`: the plotted positions change and are the telemetry's; the stop button stops the job
and the queue holds (the next job stays queued); an observer's page has no buttons and its server refuses the
verbs. Screenshots are kept in the test's tmp_path."""

from __future__ import annotations

import http.client
import json
import queue
import signal
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from streamer.api.client import MotionClient
from streamer.api.payload import unpack
from tests.api.conftest import free_port
from tests.cli.conftest import start_pvt
from tests.live.cdp import Browser, chromium

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def service(tmp_path: Path) -> Iterator[str]:
    """`pvt serve --sim` on the demo cell, real time, on a free loopback port; its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = start_pvt("serve", "--config", str(ROOT / "configs" / "demo.toml"), "--sim", "--listen", endpoint,
                     "--store", str(tmp_path / "s"), "--no-record", "--log-level", "WARNING")
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert "ready" in line, line
        yield endpoint
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)


def _post(port: int, verb: str) -> tuple[int, dict[str, Any]]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    conn.request("POST", f"/api/{verb}", headers={"X-Pvt-View": "1"})
    r = conn.getresponse()
    return r.status, json.loads(r.read())


@pytest.mark.slow
def test_the_page_plots_the_motion_and_its_stop_button_stops_the_job(service: str, tmp_path: Path) -> None:
    from streamer.api import keys
    from streamer.view.server import ViewServer

    chromium()  # skips here when there is none
    shots = tmp_path / "screenshots"
    shots.mkdir()
    with MotionClient(connect=service, cell="demo") as client:
        client.wait_for_service(timeout=30)
        seen: queue.Queue[dict[str, Any]] = queue.Queue()
        sub = client.session.declare_subscriber(keys.telemetry("demo"),
                                                lambda s: seen.put(unpack(s.payload.to_bytes())))
        browser = None
        try:
            with ViewServer(client, role="operator", port=0, token="page-test-token") as view:
                browser = Browser(tmp_path / "profile")
                browser.goto(view.entry_url)  # the token becomes the page's cookie
                browser.wait_for("window.pvtView && window.pvtView.polls > 2 && !!window.pvtView.axes.j1")
                assert browser.evaluate("document.getElementById('btn-stop') !== null")
                moving = client.submit({"kind": "move", "axes": ["j1", "j2"], "target": [2.5, -2.0],
                                        "velocity_scale": 0.2, "mode": "absolute"})
                queued = client.submit({"kind": "move", "axes": ["j1"], "target": [0.0], "mode": "absolute"})
                try:
                    browser.wait_for("window.pvtView.last && window.pvtView.last.job_state === 'running' && "
                                     "window.pvtView.last.progress > 0.15", timeout_s=60)
                except TimeoutError as e:  # say where the job was: it failed, or the page saw nothing of it
                    events = [(ev.type, ev.data.get("error")) for ev in moving.history(timeout=5)]
                    last = browser.evaluate("JSON.stringify(window.pvtView.last)")
                    raise AssertionError(f"{e}; the job: {moving.status(timeout=5)}; its events: {events}; "
                                         f"the page's last: {last}") from e
                plotted_1 = browser.evaluate("Array.from(window.pvtView.charts.j1.position.data[1])")
                browser.wait_for(f"window.pvtView.charts.j1.position.data[1].slice(-1)[0] > {plotted_1[-1] + 0.05}",
                                 timeout_s=30)
                browser.screenshot(shots / "moving.png")
                # what the page plots is the telemetry: its newest sample, and the curve's last point
                page = browser.evaluate("({seq: window.pvtView.last.seq, t: window.pvtView.last.t, "
                                        "pos: window.pvtView.last.axes.map(a => a.position), "
                                        "plotted: window.pvtView.charts.j1.position.data[1].slice(-1)[0], "
                                        "n: window.pvtView.charts.j1.position.data[1].length})")
                samples: dict[int, dict[str, Any]] = {}
                while not seen.empty():
                    m = seen.get_nowait()
                    samples[m["seq"]] = m
                assert page["seq"] in samples
                telemetry = samples[page["seq"]]
                assert page["pos"] == pytest.approx([a["position"] for a in telemetry["axes"]], abs=1e-9)
                assert page["plotted"] == pytest.approx(telemetry["axes"][0]["position"], abs=1e-9)
                assert page["n"] > 20  # the last seconds, not one point
                assert 0.05 < page["plotted"] < 2.5  # on its way
                # the stop button: the job stops, the queue holds the next one
                browser.evaluate("document.getElementById('btn-stop').click()")
                final = moving.wait(timeout=60)
                assert final.state.value == "cancelled"
                browser.wait_for("document.getElementById('message').textContent.indexOf('stop:') === 0")
                status = client.service_status(timeout=5)
                assert status["held"] is True
                assert status["queued_jobs"] == [queued.job_id]
                browser.wait_for("document.getElementById('ready').textContent.indexOf('HELD') >= 0")
                browser.wait_for(f"document.getElementById('queue').textContent.indexOf('{queued.job_id}') >= 0")
                after = client.telemetry(timeout=5)["axes"][0]["position"]
                assert after < 2.5 - 0.01  # stopped short of the target
                browser.wait_for(f"Math.abs(window.pvtView.last.axes[0].position - {after}) < 1e-3")
                browser.screenshot(shots / "stopped.png")
        finally:
            if browser is not None:
                browser.close()
            sub.undeclare()
            client.stop(timeout=5)  # nothing moves after the test (the queued job is held, then the service ends)
    assert (shots / "moving.png").stat().st_size > 10_000
    assert (shots / "stopped.png").stat().st_size > 10_000


@pytest.mark.slow
def test_an_observers_page_has_no_buttons_and_its_server_refuses_the_verbs(service: str, tmp_path: Path) -> None:
    from streamer.view.server import ViewServer

    chromium()
    with MotionClient(connect=service, cell="demo") as client:
        client.wait_for_service(timeout=30)
        browser = None
        with ViewServer(client, role="observer", port=0) as view:
            try:
                browser = Browser(tmp_path / "profile")
                browser.goto(view.url)
                browser.wait_for("window.pvtView && window.pvtView.polls > 2 && !!window.pvtView.axes.j1")
                assert browser.evaluate("window.pvtView.role") == "observer"
                assert browser.evaluate("document.querySelectorAll('#verbs button').length") == 0
                assert browser.evaluate("document.getElementById('btn-stop') === null") is True
                browser.screenshot(tmp_path / "observer.png")
                for verb in ("stop", "estop", "hold", "resume"):
                    code, answer = _post(view.port, verb)
                    assert code == 403 and answer["error"] == "PERMISSION_DENIED", (verb, code, answer)
                assert client.service_status(timeout=5)["held"] is False  # nothing reached the service
            finally:
                if browser is not None:
                    browser.close()
    assert (tmp_path / "observer.png").stat().st_size > 10_000
