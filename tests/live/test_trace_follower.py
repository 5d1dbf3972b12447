"""streamer/live/publisher.TraceFollower on a JobTrace fed by hand: each poll gives what was appended since the
last one, once, with the plan's demand at each SYNC; a sample waits (a few SYNCs at most) for its SYNC's FIFO
fill; when the follower fell behind it skips the oldest samples (counted) rather than publish a growing
backlog."""

from __future__ import annotations

from typing import Any

import numpy as np

from bus.events import BufferStatus, PositionFeedback
from streamer.live.publisher import LiveJob, TraceFollower
from streamer.runtime.trace import JobTrace


class _Plan:
    node_ids = (1,)
    axis_names = ("x",)
    duration_ms = 100

    def planned_demand(self) -> Any:
        return np.arange(101, dtype=np.int64).reshape(1, 101) * 10  # 10 counts per ms


class _Core:
    start_sync: int | None = 2


def _job() -> tuple[JobTrace, TraceFollower]:
    trace = JobTrace([(1, "x")], sync_period_s=0.01, bitrate=1_000_000)
    return trace, TraceFollower(LiveJob(_Plan(), _Core(), trace, 10))


def _sync(trace: JobTrace, n: int, *, fill: bool = True, position: bool = True) -> None:
    t = 100.0 + n * 0.01
    trace.on_sync(n, t)
    if fill:
        trace.on_event(BufferStatus(1, 0x1637, 0x8000, 64 - n, t, n))
    if position:
        trace.on_event(PositionFeedback(1, 1000 + n, 1000 + n + 1, t, n))


def test_each_poll_gives_the_new_samples_once_with_the_plan() -> None:
    trace, follower = _job()
    for n in range(5):
        _sync(trace, n)
    samples, events = follower.poll()
    got = samples["x"]
    assert [m["sync"] for m in got] == [0, 1, 2, 3, 4]
    assert [m["planned"] for m in got] == [0, 0, 0, 100, 200]  # from the start SYNC 2, 10 ms a SYNC
    assert got[3] == {"t": 0.03, "sync": 3, "node": 1, "planned": 100, "actual": 1003, "demand": 1004,
                      "following_error": -1, "fifo_fill": 3, "statusword": 0x1637, "buffer_status": 0x8000}
    assert [e["kind"] for e in events] == ["start"] and events[0]["sync"] == 2
    assert follower.poll() == ({"x": []}, [])
    _sync(trace, 5)
    assert [m["sync"] for m in follower.poll()[0]["x"]] == [5]


def test_a_sample_waits_for_its_fifo_fill_a_few_syncs_at_most() -> None:
    trace, follower = _job()
    _sync(trace, 0)
    _sync(trace, 1, fill=False)  # its TPDO1 not in yet
    assert [m["sync"] for m in follower.poll()[0]["x"]] == [0]
    trace.on_event(BufferStatus(1, 0x1637, 0, 60, 100.01, 1))
    (late,) = follower.poll()[0]["x"]
    assert late["sync"] == 1 and late["fifo_fill"] == 4
    for n in range(2, 6):
        _sync(trace, n, fill=False)  # a drive that never sends it: published without, 3 SYNCs late
    assert [m["sync"] for m in follower.poll()[0]["x"]] == [2]
    assert [m["sync"] for m in follower.poll(final=True)[0]["x"]] == [3, 4, 5]  # the job ended: no wait


def test_behind_it_drops_the_oldest_rather_than_delay() -> None:
    trace = JobTrace([(1, "x")], sync_period_s=0.01, bitrate=1_000_000)
    follower = TraceFollower(LiveJob(_Plan(), _Core(), trace, 10), max_batch=4)
    for n in range(10):
        _sync(trace, n)
    assert [m["sync"] for m in follower.poll()[0]["x"]] == [6, 7, 8, 9]
    assert follower.dropped == 6
