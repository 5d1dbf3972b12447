"""An endless (velocity) job holds what it needs, not what it streamed (issue 23 item 10).

A velocity job in virtual time on two EPOS axes, a little over four minutes of motion until the closed chunk
that brakes it before j1's position limit: what the core holds of the stream (records, frames, segment ends,
pieces) is the same after four minutes as after one (records consumed long ago are retired:
streamer/core/window.py, `Coordinator._retire`); the per-SYNC logs (the core's feedback log, the trace)
hold at most one block per column in memory (streamer/core/spool.py) while the report and the recording
built after the job still cover the whole run, from the start SYNC to the end, sample for sample. Held
objects are counted, never RSS or time."""

from __future__ import annotations

import dataclasses
import itertools
import pickle
from array import array
from pathlib import Path
from typing import Any

import pytest

from bus.sim.virtual import VirtualCell
from planner.config import load_cell
from planner.job import job_from_dict
from planner.plan import plan_job
from streamer import demo
from streamer.core import JobResult
from streamer.core.coordinator import Coordinator
from streamer.core.spool import BLOCK, Column
from streamer.core.window import Window, bisect_right
from streamer.recording.model import build_recording
from streamer.report import build_report
from streamer.runtime.spill import temp_store
from streamer.runtime.virtual import VirtualRuntime
from streamer.splice_planners import make_stop_planner

ROOT = Path(__file__).resolve().parents[2]


def held_records(core: Coordinator) -> dict[str, int]:
    """What the core holds of the stream, counted on today's structures too (a list holds all of it)."""
    feeders = core._feeders  # read only
    return {
        "records": sum(getattr(f.records, "held", len(f.records)) for f in feeders),
        "frames": sum(getattr(f.sends, "held", len(f.sends)) for f in feeders),
        "ends": getattr(core._ends, "held", len(core._ends)),
        "pieces": len(core.pieces),
    }


def held_samples(core: Coordinator, rt: VirtualRuntime) -> tuple[int, int]:
    """(feedback log samples, trace samples) in memory."""
    fb = sum(getattr(log, "held", 3 * len(log.sync)) for log in core.report().feedback.values())
    assert rt.trace is not None
    tr = 0
    for ax in rt.trace.axes.values():
        for k, v in vars(ax).items():
            if k not in ("node_id", "name"):
                tr += getattr(v, "held", len(v))
    return fb, tr


@pytest.fixture(scope="module")
def endless() -> dict[str, Any]:
    cell = load_cell(ROOT / "configs" / "demo.toml").with_axes(2)
    cell = dataclasses.replace(cell, axes=tuple(dataclasses.replace(a, position_min=-100.0, position_max=100.0)
                                                for a in cell.axes))
    job = job_from_dict({"kind": "move", "axes": ["j1", "j2"], "mode": "velocity", "velocity": [0.4, -0.3],
                         "start": [0.0, 0.0]}, cell)
    traj = plan_job(job, cell)
    assert traj.open_ended
    rt = VirtualRuntime(cell, vcell=VirtualCell(cell, initial_positions=demo.start_positions(cell, traj)))
    per_minute = round(60.0 / cell.sync_period_s)
    seen: dict[int, tuple[dict[str, int], tuple[int, int]]] = {}

    def on_sync(core: Coordinator, m: int) -> None:
        s = core.start_sync
        if s is not None and m > s and (m - s) % per_minute == 0:
            seen[(m - s) // per_minute] = (held_records(core), held_samples(core, rt))

    from planner.motion.travel import extend_velocity

    kept = demo.KeptChunks(extend_velocity)
    result = rt.run(traj, stop_planner=make_stop_planner(cell, traj), on_sync=on_sync, extender=kept,
                    max_s=6 * 60.0)
    whole = demo.whole_stream(traj, kept.chunks, result.coordinator)
    core_report = result.coordinator.report()
    report = build_report(whole, core_report, result.trace, sync_period_ms=cell.sync_period_ms,
                          first_sync=result.first_sync, last_sync=result.last_sync, readings=rt.settings.readings)
    recording = build_recording(whole, result.trace, report, first_sync=result.first_sync,
                                start_sync=core_report.start_sync, sync_period_ms=cell.sync_period_ms,
                                feedback=core_report.feedback)
    # as the service builds it: the trace and the logs pickled to the recording's process
    inputs = pickle.loads(pickle.dumps((result.trace, core_report.feedback)))
    remote = build_recording(whole, inputs[0], report, first_sync=result.first_sync,
                             start_sync=core_report.start_sync, sync_period_ms=cell.sync_period_ms, feedback=inputs[1])
    return {"cell": cell, "result": result, "seen": seen, "report": report, "recording": recording, "remote": remote,
            "core_report": core_report, "whole": whole, "per_minute": per_minute}


@pytest.mark.slow
def test_the_records_an_endless_job_holds_do_not_grow_with_its_length(endless: dict[str, Any]) -> None:
    seen = endless["seen"]
    assert {1, 4} <= set(seen)
    first, last = seen[1][0], seen[4][0]
    assert first["records"] > 0
    for name in ("records", "frames", "ends", "pieces"):
        assert last[name] <= first[name], (name, first, last)
    # and the job went on to its end: the closed chunk before the limit, appended after the retired past
    assert endless["result"].coordinator.state.value == JobResult.DONE.value
    streamed = sum(t.points_sent for t in endless["core_report"].axes)
    assert streamed > 10 * last["records"]


@pytest.mark.slow
def test_the_per_sync_logs_of_an_endless_job_stay_bounded_in_memory(endless: dict[str, Any]) -> None:
    fb, tr = endless["seen"][4][1]
    core_report = endless["core_report"]
    total = sum(len(log.sync) for log in core_report.feedback.values())
    nodes = len(core_report.feedback)
    # one block per column (sync, demand, actual, late), while the log holds more than that
    assert fb <= 4 * BLOCK * nodes < total
    trace = endless["result"].trace
    columns = sum(len(vars(ax)) - 2 for ax in trace.axes.values())
    assert tr <= columns * BLOCK < sum(len(ax.pos_sync) for ax in trace.axes.values()) * 5


@pytest.mark.slow
def test_the_report_and_recording_of_an_endless_job_cover_the_whole_run(endless: dict[str, Any]) -> None:
    core_report, report, recording = endless["core_report"], endless["report"], endless["recording"]
    start = core_report.start_sync
    per_minute = endless["per_minute"]
    end_sync = start + 4 * per_minute  # the job ran at least this long before the stop
    for ax_rep, info in zip(report["axes"], recording.axes, strict=True):
        node = ax_rep["node_id"]
        log = core_report.feedback[node]
        syncs = list(log.sync)
        assert syncs[0] <= start + 2 and syncs[-1] >= end_sync  # the first and the last SYNC
        assert all(b > a for a, b in itertools.pairwise(syncs))
        assert len(log.demand) == len(log.actual) == len(syncs)
        assert ax_rep["end_sync"] is not None and ax_rep["end_sync"] >= end_sync
        assert ax_rep["final_position_error_counts"] is not None
        s = recording.samples[info.name]
        rows = {sy: (d, p) for sy, d, p in zip(s.sync, s.demand, s.planned, strict=True) if d is not None}
        assert set(syncs) <= set(rows)  # every attributed sample is recorded, the first minute's too
        assert [rows[sy][0] for sy in syncs] == list(log.demand)
        assert min(rows) <= start + 2 and max(rows) >= end_sync
        r = endless["remote"].samples[info.name]
        assert (r.sync, r.demand, r.fifo_fill) == (s.sync, s.demand, s.fifo_fill)
        # the report's max deviation is over the whole run: the recording's worst sample within the plan
        plan_end = start + int(endless["whole"].duration_ms) // endless["cell"].sync_period_ms + 1
        worst = max(abs(d - p) for sy, (d, p) in rows.items() if start <= sy <= plan_end and p is not None)
        assert ax_rep["max_deviation_counts"] >= worst


def test_a_window_keeps_stream_indices_after_its_past_is_dropped() -> None:
    w: Window[int] = Window([10, 20, 30, 40, 50])
    assert w.drop_before(2) == 2
    assert (len(w), w.base, w.held, w[2], w[-1], w[2:4]) == (5, 2, 3, 30, 50, [30, 40])
    with pytest.raises(IndexError, match="dropped"):
        w[1]
    w.truncate(3)
    w.extend([35, 45])
    assert (len(w), w[3], w[4]) == (5, 35, 45)
    assert bisect_right(w, 30) == 3 and bisect_right(w, 25) == 2 and bisect_right(w, 99) == 5
    with pytest.raises(IndexError):
        bisect_right(w, 15)  # before the last dropped item: not placeable
    trial = w.spliced(4, [1000])
    assert (list(trial[2:]), list(w[2:])) == ([30, 35, 1000], [30, 35, 45])


def test_a_spilled_column_reads_every_sample_back_and_holds_one_block() -> None:
    c = Column("q", temp_store, block=16)
    ref = array("q", (i * i - 7 for i in range(1000)))
    for v in ref:
        c.append(v)
    assert c.held < 16 and len(c) == 1000
    assert list(c) == list(ref) and c.array() == ref
    assert (c[0], c[15], c[16], c[999], c[-1]) == (ref[0], ref[15], ref[16], ref[999], ref[-1])
    assert (c[10:40], c[-5:], c[990:2000], c[3:3], c[0:7:3]) == (
        list(ref[10:40]), list(ref[-5:]), list(ref[990:]), [], list(ref[0:7:3]))
    plain = Column("q")
    for v in ref:
        plain.append(v)
    assert plain.held == 1000 and list(plain) == list(ref)
    # pickled to the recording's process (streamer/recording/writer.py), it reads the same there
    back = pickle.loads(pickle.dumps(c))
    assert list(back) == list(ref) and back.held == c.held and back[17] == ref[17]
