"""The live channels (streamer/live/publisher.py) at the protocol level: a raw Foxglove WebSocket client
(tests/live/foxglove_client.py, subprotocol foxglove.sdk.v1) subscribes to `pvt demo --fast --live PORT` and
gets every axis' samples of every SYNC of the job, with the values the run's report.json and job.mcap hold."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
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
                topic, _log_time, msg = payload
                got[topic].append(msg)
        return client.protocol, got
    finally:
        client.close()


@pytest.mark.slow
def test_demo_live_channels_carry_every_sync_of_every_axis(tmp_path: Path) -> None:
    port = free_port()
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "streamer.cli", "demo", "--fast", "--quiet", "--live", str(port),
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
        # the motion itself: the recording's samples, SYNC for SYNC (the recording attributes TPDOs as the core
        # did; live they carry their arrival SYNC, the same here, where every drive answers within its SYNC)
        rec = recording.samples[a["name"]]
        moved = max(m["planned"] for m in during) - min(m["planned"] for m in during)
        assert moved > 1000, f"axis {a['name']} hardly moves: the comparison would say little"
        compared = 0
        for k, s in enumerate(rec.sync):
            live = by_sync.get(s)
            if live is None or rec.actual[k] is None:
                continue
            assert live["planned"] == rec.planned[k]
            assert abs(live["actual"] - rec.actual[k]) <= 2
            assert abs(live["demand"] - rec.demand[k]) <= 2
            assert live["t"] == pytest.approx(rec.t[k], abs=1e-6)
            assert live.get("fifo_fill") == rec.fifo_fill[k]
            compared += 1
        assert compared >= len(job_syncs)
    events = got["/job/events"]
    starts = [e for e in events if e["kind"] == "start"]
    assert [e["sync"] for e in starts] == [report["axes"][0]["start_sync"]]
    states = [e["state"] for e in events if e["kind"] == "state"]
    assert states[-1] == "done" and "running" in states
