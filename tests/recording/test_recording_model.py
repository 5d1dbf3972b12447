"""The recording's content: what the trace keeps (and does not with record=False), events of cancelled and
failed jobs, a drive family with a set point instead of a FIFO, and the MCAP round trip."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace

import pytest

from bus.events import BufferStatus, Cancel, Emcy, PositionFeedback
from planner.config import CellConfig
from streamer import demo
from streamer.core.coordinator import Coordinator, JobState
from streamer.recording.mcap_io import read_mcap, write_mcap
from streamer.recording.model import (
    AxisInfo,
    AxisSamples,
    Frames,
    JobRecording,
    RecordedEvent,
    RecordingError,
)
from streamer.runtime.trace import JobTrace
from tests.recording.recording_kit import drives_for, record_virtual


def test_trace_keeps_frames_events_and_status_only_when_recording() -> None:
    for record in (True, False):
        trace = JobTrace([(1, "j1")], sync_period_s=0.01, bitrate=1_000_000, record=record, max_frames=2)
        trace.on_sync(0, 0.5)
        for k in range(3):
            trace.on_frame(0x181, 6, bytes([k, 1, 2, 3, 4, 5]), 0.5 + k * 1e-4)
        trace.on_event(BufferStatus(1, 0x1237, 0xC000, 60, 0.5, 0))
        trace.on_event(PositionFeedback(1, 10, 12, 0.5, 0))
        trace.on_event(Emcy(1, 0x8611, 0x20, b"\x00" * 5, 0.5))
        trace.on_event(Emcy(9, 0x8611, 0x20, b"\x00" * 5, 0.5))  # not a node of the job
        trace.on_event(Cancel(0.51))
        trace.on_changes([SimpleNamespace(state=JobState.RUNNING, sync=0, t=0.5, outcome=None)])
        trace.on_setpoint(1, 0, 1234)
        ax = trace.axes[1]
        assert trace.frames == 3 and ax.fill == [4] and ax.actual == [10]  # what the report needs: always
        assert ax.setpoint == [1234]
        if record:
            assert len(trace.frame_log) == 2 and trace.frame_log.dropped == 1
            assert trace.frame_log.frame(1) == (0.5001, 0x181, 6, bytes([1, 1, 2, 3, 4, 5]))
            assert ax.statusword == [0x1237] and ax.buffer_status == [0xC000]
            assert [type(n.event).__name__ for n in trace.noted] == ["Emcy", "Cancel"]
            assert len(trace.changes) == 1
        else:
            assert len(trace.frame_log) == 0 and trace.noted == [] and trace.changes == []
            assert ax.statusword == []


def test_cancelled_job_records_the_cancel_and_the_stop(demo_cell: CellConfig) -> None:
    cell, _job, traj = demo.prepare(axes=3)
    _result, report, rec = record_virtual(cell, traj, cancel_at_s=1.2)
    assert report["result"] == "cancelled"
    kinds = [(e.kind, e.state) for e in rec.events]
    assert ("cancel", None) in kinds
    assert [s for k, s in kinds if k == "state"][-2:] == ["cancelling", "cancelled"]
    cancel = next(e for e in rec.events if e.kind == "cancel")
    assert 1.1 < cancel.t < 1.4
    # after the cancel the drives follow the stop, not the plan: the demand leaves the plan and comes to rest
    for a in rec.axes:
        s = rec.samples[a.name]
        after = [k for k in range(len(s)) if s.t[k] > cancel.t + 0.5]
        assert any(s.demand[k] != s.planned[k] for k in after)
        # the demand at rest, the motor within a count of it (the simulated motor follows with a lag: the
        # jerk-limited demo's stop ends with it one count behind in the last sample)
        assert s.demand[-1] == s.demand[-2] and abs(s.actual[-1] - s.demand[-1]) <= 1


def test_failed_job_records_the_emcy_and_the_fault(tmp_path: Path) -> None:
    cell, _job, traj = demo.prepare(axes=3)
    node = 3
    vcell = drives_for(cell, traj)

    def drag(core: Coordinator, n: int) -> None:  # scenario 8: a load the motor cannot hold
        if core.start_sync is not None and n == core.start_sync + 60:
            vcell.model(node).disturbance_current_a = 25.0
        if core.state is JobState.FAILED:
            vcell.model(node).disturbance_current_a = 0.0

    _result, report, rec = record_virtual(cell, traj, on_sync=drag, vcell=vcell)
    assert report["result"] == "failed"
    emcy = [e for e in rec.events if e.kind == "emcy"]
    fault = [e for e in rec.events if e.kind == "fault"]
    assert emcy and emcy[0].code == "0x8611" and emcy[0].node == node
    assert len(fault) == 1 and fault[0].code == "FOLLOWING_ERROR" and fault[0].node == node
    assert fault[0].state == "failed" and fault[0].t >= emcy[0].t
    assert fault[0].sync is not None and emcy[0].sync is not None and fault[0].sync - emcy[0].sync <= 1
    assert [e.state for e in rec.events if e.kind == "state"][-1] == "failed"
    back = read_mcap(_write(rec, tmp_path / "failed.mcap"))
    assert [(e.kind, e.code, e.node) for e in back.events] == [(e.kind, e.code, e.node) for e in rec.events]


def _write(rec: JobRecording, path: Path) -> Path:
    write_mcap(rec, path)
    return path


def _cyclic_recording() -> JobRecording:
    """An axis of a drive family that takes one set point per SYNC: no FIFO fill, a set point instead."""
    s = AxisSamples()
    for k in range(5):
        s.append(100 + k, k * 0.002, {"planned": 10 * k, "actual": 10 * k - 1, "demand": 10 * k,
                                      "following_error": -1, "setpoint": 10 * k, "statusword": 0x1237})
    return JobRecording(
        job_id="cyc-1", cell="mixed", result="done", sync_period_ms=2, first_sync=100, start_sync=101,
        epoch_s=1_760_000_000.25, axes=(AxisInfo("x", 7, 1000.0),), samples={"x": s},
        events=(RecordedEvent(0.002, 101, "start", message="go"),),
        frames=Frames([0.0], [0x80], [0], [b""]), report={"result": "done", "axes": []},
    )


def test_a_cyclic_family_records_set_points_with_the_same_schema(tmp_path: Path) -> None:
    rec = _cyclic_recording()
    back = read_mcap(_write(rec, tmp_path / "cyc.mcap"))
    s = back.samples["x"]
    assert s.setpoint == [0, 10, 20, 30, 40] and s.fifo_fill == [None] * 5 and s.buffer_status == [None] * 5
    assert back.epoch_s == rec.epoch_s and back.start_sync == 101 and back.underflow_watermark is None
    assert back.frames.data == [b""] and back.frames.cob_id == [0x80]


def test_mcap_round_trip_is_exact(demo_run: tuple[Path, object, object, dict[str, object]], tmp_path: Path) -> None:
    out = demo_run[0]
    rec = read_mcap(out / "job.mcap")
    again = read_mcap(_write(rec, tmp_path / "again.mcap"))
    assert again == rec
    assert (tmp_path / "again.mcap").read_bytes() == (out / "job.mcap").read_bytes()


def test_reading_something_else_fails_with_a_code(tmp_path: Path) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(RecordingError) as err:
        read_mcap(junk)
    assert err.value.code == "NOT_A_RECORDING" and "junk.mcap" in err.value.message
    from mcap.writer import Writer

    other = tmp_path / "other.mcap"
    with open(other, "wb") as f:
        w = Writer(f)
        w.start()
        w.finish()  # type: ignore[no-untyped-call]
    with pytest.raises(RecordingError) as err:
        read_mcap(other)
    assert err.value.code == "NOT_A_RECORDING" and "pvt.job" in err.value.message


def test_recording_rejects_inconsistent_content() -> None:
    rec = _cyclic_recording()
    with pytest.raises(RecordingError, match="no samples for axes"):
        dataclasses.replace(rec, samples={})
    with pytest.raises(RecordingError, match="sync_period_ms"):
        dataclasses.replace(rec, sync_period_ms=0)
    with pytest.raises(RecordingError, match="node_id of axis 'y'"):
        AxisInfo("y", 200, 1.0)
    with pytest.raises(RecordingError, match="event kind"):
        RecordedEvent(0.0, None, "party")
    assert json.loads(json.dumps(rec.axis_summary()))[0]["max_following_error_counts"] == 1
