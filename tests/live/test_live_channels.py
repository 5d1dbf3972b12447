"""The live channels (streamer/live/publisher.py) at the protocol level: a raw Foxglove WebSocket client
(tests/live/foxglove_client.py, subprotocol foxglove.sdk.v1) subscribes to `pvt demo --fast --live PORT` and
gets every axis' samples of every SYNC of the job, with the values the run's report.json and job.mcap hold."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from streamer.recording.mcap_io import read_mcap
from tests.live.foxglove_client import connect

ROOT = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _collect(port: int, topics: list[str], timeout_s: float) -> tuple[str, dict[str, list[dict[str, Any]]]]:
    """Subscribe to `topics` and read until the server closes; (subprotocol, topic -> messages)."""
    client = connect("127.0.0.1", port, timeout_s=120.0)
    got: dict[str, list[dict[str, Any]]] = {t: [] for t in topics}
    try:
        ids = client.wait_channels(topics, timeout_s=30.0)
        client.subscribe(list(ids.values()))
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            try:
                kind, payload = client.next_message()
            except (ConnectionError, OSError):
                break
            if kind == "close":
                break
            if kind == "data":
                topic, log_time, msg = payload
                got[topic].append({**msg, "_log_time": log_time})
        return client.protocol, got
    finally:
        client.close()


@pytest.mark.parametrize("fast", [pytest.param(True, marks=pytest.mark.slow, id="virtual-time"),
                                  pytest.param(False, marks=pytest.mark.realtime, id="real-time")])
def test_demo_live_channels_carry_every_sync_of_every_axis(tmp_path: Path, fast: bool) -> None:
    port = free_port()
    out = tmp_path / "out"
    mode = ["--fast"] if fast else []
    proc = subprocess.Popen([sys.executable, "-m", "streamer.cli", "demo", *mode, "--quiet", "--live", str(port),
                             "--out", str(out)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        axes = [f"j{i}" for i in range(1, 7)]
        topics = [f"/axis/{a}" for a in axes] + ["/job/events"]
        protocol, got = _collect(port, topics, timeout_s=240.0)
        output, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, output
    assert protocol == "foxglove.sdk.v1"
    report = json.loads((out / "report.json").read_text())
    recording = read_mcap(out / "job.mcap")
    for a in report["axes"]:
        msgs = got[f"/axis/{a['name']}"]
        by_sync = {m["sync"]: m for m in msgs}
        job_syncs = range(a["start_sync"], a["end_sync"] + 1)
        assert all(s in by_sync for s in job_syncs), f"axis {a['name']}: SYNCs missing live"
        assert all(m["node"] == a["node_id"] for m in msgs)
        during = [by_sync[s] for s in job_syncs]
        # what the report says of the job, from the live samples (positions in counts)
        assert max(abs(m["following_error"]) for m in msgs) == pytest.approx(a["max_following_error_counts"], abs=2)
        assert max(m["fifo_fill"] for m in during) == a["max_fifo"]
        assert max(abs(m["demand"] - m["planned"]) for m in during) <= a["max_deviation_counts"] + 1
        last = msgs[-1]
        assert last["actual"] - last["planned"] == a["final_position_error_counts"]
        # the motion itself: the recording's samples, SYNC for SYNC (both key the drives' answers by the SYNC the
        # core attributed them to, in real time too, where an answer may arrive after the next SYNC)
        near = 0
        rec = recording.samples[a["name"]]
        moved = max(m["planned"] for m in during) - min(m["planned"] for m in during)
        assert moved > 1000, f"axis {a['name']} hardly moves: the comparison would say little"
        compared = 0
        for k, s in enumerate(rec.sync):
            live = by_sync.get(s)
            if live is None or rec.actual[k] is None:
                continue
            assert live["planned"] == rec.planned[k]
            around = [j for j in range(max(0, k - near), min(len(rec), k + near + 1)) if rec.actual[j] is not None]
            assert min(abs(live["actual"] - rec.actual[j]) for j in around) <= 2, (a["name"], s, live)
            assert min(abs(live["demand"] - rec.demand[j]) for j in around) <= 2, (a["name"], s, live)
            assert live["t"] == pytest.approx(rec.t[k], abs=1e-6)
            assert live.get("fifo_fill") in [rec.fifo_fill[j] for j in around]
            # log time: the wall clock of that SYNC, as the recording's (its epoch is taken a moment later)
            assert abs(live["_log_time"] / 1e9 - (recording.epoch_s + rec.t[k])) < 0.5
            compared += 1
        assert compared >= len(job_syncs)
    events = got["/job/events"]
    starts = [e for e in events if e["kind"] == "start"]
    assert [e["sync"] for e in starts] == [report["axes"][0]["start_sync"]]
    states = [e["state"] for e in events if e["kind"] == "state"]
    assert states[-1] == "done" and "running" in states


@pytest.mark.slow
def test_serve_live_publishes_telemetry_and_the_jobs_samples(tmp_path: Path) -> None:
    """`pvt serve --sim --live PORT`: telemetry before any job, then a submitted move's per-SYNC samples on its
    axes' channels (the plan goes to the target, the drive follows it there) and its events, live."""
    import threading

    from planner.config import load_cell
    from streamer.api.client import MotionClient
    from tests.api.conftest import free_port as zenoh_port
    from tests.cli.conftest import start_pvt

    cell = load_cell(ROOT / "configs" / "demo.toml")
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{zenoh_port()}"
    proc = start_pvt("serve", "--config", str(ROOT / "configs" / "demo.toml"), "--sim", "--listen", endpoint,
                     "--store", str(tmp_path / "s"), "--no-record", "--log-level", "WARNING", "--live", str(port))
    client = None
    try:
        assert proc.stdout is not None
        lines = [proc.stdout.readline(), proc.stdout.readline()]
        assert any(f"live channels on ws://127.0.0.1:{port}" in line for line in lines), lines
        assert any("ready" in line for line in lines), lines
        client = connect("127.0.0.1", port, timeout_s=30.0)
        topics = ["/cell/telemetry", "/axis/j1", "/axis/j2", "/job/events"]
        ids = client.wait_channels(topics, timeout_s=30.0)
        client.subscribe(list(ids.values()))
        got: dict[str, list[dict[str, Any]]] = {t: [] for t in topics}

        def read_until(stop: Callable[[], bool], timeout_s: float) -> None:
            end = time.monotonic() + timeout_s
            while time.monotonic() < end and not stop():
                kind, payload = client.next_message()
                if kind == "data":
                    got[payload[0]].append(payload[2])

        read_until(lambda: len(got["/cell/telemetry"]) >= 3, 30.0)
        before = got["/cell/telemetry"][-1]
        assert [a["name"] for a in before["axes"]] == [a.name for a in cell.axes]
        target = [0.3, -0.2]
        done: list[Any] = []

        def submit() -> None:
            with MotionClient(connect=endpoint, cell="demo") as api:
                api.wait_for_service(timeout=30)
                done.append(api.submit({"kind": "move", "axes": ["j1", "j2"], "target": target,
                                        "mode": "absolute"}).wait(timeout=60))

        worker = threading.Thread(target=submit)
        worker.start()
        read_until(lambda: bool(done), 90.0)
        read_until(lambda: False, 1.0)  # the job's last samples and the telemetry after it
        worker.join(timeout=60)
        assert done and done[0].state.value == "done", done
        for name, goal in zip(["j1", "j2"], target, strict=True):
            samples = got[f"/axis/{name}"]
            counts = round(goal * cell.axis(name).counts_per_unit)
            assert len(samples) > 50, (name, len(samples))
            syncs = [m["sync"] for m in samples]
            assert syncs == sorted(syncs)
            planned = [m["planned"] for m in samples]
            assert abs(planned[-1] - counts) <= 1 and abs(planned[0] - counts) > 1000, (name, planned[0], planned[-1])
            assert abs(samples[-1]["actual"] - counts) <= 1, (name, samples[-1], counts)
            positions = [m["actual"] for m in samples]
            assert len(set(positions)) > 20  # it moved, and was seen moving
        after = got["/cell/telemetry"][-1]
        seen = {a["name"]: a for a in after["axes"]}
        assert seen["j1"]["position"] == pytest.approx(target[0], abs=1e-3), after
        states = [e.get("state") for e in got["/job/events"] if e["kind"] == "state"]
        assert states and states[-1] == "done", got["/job/events"]
    finally:
        if client is not None:
            client.close()
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)
