"""`pvt demo` writes demo-out/job.mcap; read back with the mcap library's own reader (not ours), it agrees
with report.json, and its CAN frames carry exactly the PVT records of the plan (issue 16, must show)."""

from __future__ import annotations

import itertools
import json
from collections import defaultdict
from pathlib import Path
from typing import Any

from mcap.reader import make_reader

from bus.cob import RPDO2_BASE, SYNC_COB_ID
from planner.encoding.record import unpack
from streamer.cli import main as pvt
from streamer.report import decode_candump

IP_ACTIVE = 1 << 15


def _read(path: Path) -> tuple[dict[str, list[dict[str, Any]]], dict[str, str], dict[str, Any], dict[str, Any]]:
    """(messages per topic, the pvt.job metadata, schemas by name, the report.json attachment)."""
    topics: dict[str, list[dict[str, Any]]] = defaultdict(list)
    schemas: dict[str, Any] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            assert channel.message_encoding == "json"
            assert schema is not None and schema.encoding == "jsonschema"
            schemas[schema.name] = json.loads(schema.data)
            assert message.publish_time == message.log_time
            topics[channel.topic].append(json.loads(message.data))
        assert summary.statistics.message_count == sum(len(v) for v in topics.values())
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        attachments = {a.name: json.loads(a.data) for a in reader.iter_attachments()}
    return dict(topics), meta["pvt.job"], schemas, attachments["report.json"]


def _conforms(msg: dict[str, Any], schema: dict[str, Any]) -> None:
    props = schema["properties"]
    assert set(schema["required"]) <= set(msg), (msg, schema["title"])
    assert set(msg) <= set(props), (msg, schema["title"])
    for key, value in msg.items():
        kind = props[key]["type"]
        if kind == "integer":
            assert isinstance(value, int) and not isinstance(value, bool), (key, value)
        elif kind == "number":
            assert isinstance(value, int | float), (key, value)
        elif kind == "string":
            assert isinstance(value, str), (key, value)


def test_demo_mcap_agrees_with_report_json(demo_run: tuple[Path, Any, Any, dict[str, Any]]) -> None:
    out, cell, traj, report = demo_run
    on_disk = json.loads((out / "report.json").read_text())
    assert on_disk == report
    topics, meta, schemas, attached = _read(out / "job.mcap")
    assert attached == report
    assert set(schemas) == {"pvt.AxisSample", "pvt.JobEvent", "pvt.CanFrame"}
    assert meta["result"] == report["result"] == "done"
    assert int(meta["sync_period_ms"]) == report["sync_period_ms"] == cell.sync_period_ms
    axes_meta = json.loads(meta["axes"])
    assert [(a["name"], a["node_id"]) for a in axes_meta] == [(a["name"], a["node_id"]) for a in report["axes"]]

    # every frame of the job is on /can/frames: as many as the report counts, SYNCs included
    frames = topics["/can/frames"]
    assert len(frames) == report["frames"]
    for f in frames[:50]:
        _conforms(f, schemas["pvt.CanFrame"])
    syncs = [f for f in frames if f["id"] == SYNC_COB_ID]
    assert len(syncs) == report["syncs"]
    assert all(a["t"] <= b["t"] for a, b in itertools.pairwise(frames))
    # the PVT records on /can/frames are the plan's records, in order, and what bus.log holds
    logged = decode_candump(out / "bus.log", traj.node_ids, report["job_start_s"])
    for i, node in enumerate(traj.node_ids):
        sent = [unpack(bytes.fromhex(f["data"])) for f in frames if f["id"] == RPDO2_BASE + node]
        assert sent == traj.records(i) == logged[node]

    tolerance = int(meta["tolerance_counts"])
    for ax in report["axes"]:
        samples = topics[f"/axis/{ax['name']}"]
        assert len(samples) >= report["syncs"] - 1
        for s in samples:
            _conforms(s, schemas["pvt.AxisSample"])
            assert s["node"] == ax["node_id"]
            assert s["following_error"] == s["actual"] - s["demand"]
        # the start SYNC is the first one answered with ip mode active; the end is after the last one
        active = [s["sync"] for s in samples if s["buffer_status"] & IP_ACTIVE]
        assert active[0] == ax["start_sync"] == int(meta["start_sync"])
        assert active[-1] + 1 == ax["end_sync"]
        assert max(abs(s["following_error"]) for s in samples) == ax["max_following_error_counts"]
        assert samples[-1]["actual"] - samples[-1]["planned"] == ax["final_position_error_counts"] == 0
        fills_running = [s["fifo_fill"] for s in samples if s["sync"] >= ax["start_sync"]]
        assert ax["min_fifo"] in fills_running and ax["max_fifo"] in fills_running
        assert min(fills_running) <= ax["min_fifo"] <= ax["max_fifo"] == max(fills_running)
        # the drive's demand at every SYNC against the plan: within what the report says and the tolerance
        sampled = max(abs(s["demand"] - s["planned"]) for s in samples)
        assert sampled <= ax["max_deviation_counts"] <= tolerance

    events = topics["/job/events"]
    for e in events:
        _conforms(e, schemas["pvt.JobEvent"])
    states = [e["state"] for e in events if e["kind"] == "state"]
    assert states == ["priming", "starting", "running", "finishing", "done"]
    (start,) = [e for e in events if e["kind"] == "start"]
    assert start["sync"] == report["axes"][0]["start_sync"]
    assert not [e for e in events if e["kind"] in ("fault", "emcy", "cancel")]


def test_log_times_are_wall_clock_nanoseconds(demo_run: tuple[Path, Any, Any, dict[str, Any]]) -> None:
    out = demo_run[0]
    with open(out / "job.mcap", "rb") as f:
        reader = make_reader(f)
        stats = reader.get_summary().statistics  # type: ignore[union-attr]
        meta = next(dict(m.metadata) for m in reader.iter_metadata() if m.name == "pvt.job")
    epoch = float(meta["epoch_s"])
    assert 1.7e9 < epoch < 4e9  # a date, not seconds since the run started
    assert stats is not None
    assert abs(stats.message_start_time / 1e9 - epoch) < 0.01
    assert 1.0 < (stats.message_end_time - stats.message_start_time) / 1e9 < 60.0


def test_cli_demo_writes_job_mcap(tmp_path: Path) -> None:
    assert pvt(["demo", "--fast", "--quiet", "--axes", "2", "--out", str(tmp_path)]) == 0
    topics, meta, _schemas, report = _read(tmp_path / "job.mcap")
    assert meta["job_id"] == "demo" and meta["cell"] == "demo"
    assert set(topics) == {"/axis/j1", "/axis/j2", "/job/events", "/can/frames"}
    assert report == json.loads((tmp_path / "report.json").read_text())
