"""Benchmark: what the live view (streamer/live/publisher.py) costs the SYNC loop, and how late its samples
reach a client.

The SYNC loop is bench_recording's: the streamer core runs a 6-axis job against minimal loopback drives
(not timed) and the streaming thread's work per event is timed (`trace.on_event`, `core.handle`,
`trace.on_changes`, plus `trace.on_frame` for every frame of the cycle), here paced in real time (one
cycle per 10 ms SYNC period, sleeping between them, as the runtime's streaming thread does), because the
live view's own thread competes with it for the GIL, and that competition is what it costs. Two
conditions, interleaved, in the same run: no live view (the baseline), and a `LivePublisher` following the
job's trace with a Foxglove WebSocket client connected and subscribed to every channel; the client is a
process of its own (tests/live/foxglove_client.py), as the Foxglove app would be. Per condition: the loop's
work per axis per SYNC (median of the runs' means) and the lateness of the loop's wake-ups (p50/p99: a
publishing thread that held the GIL when the SYNC was due shows there), and the ratio of the work.

Delay: the client notes, for every axis sample, its receive time minus the sample's log time, which is
the wall-clock time of the SYNC the sample answers (the loop stamps its SYNC with `time.time()` when it
feeds the trace, as the runtime's frames carry their bus timestamp): from the frame on the bus to the
client, p50/p95.

Run: `python -m benchmarks.bench_live` or call `main()`.
"""

from __future__ import annotations

import json
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.bench_recording import sync_answers
from benchmarks.bench_streamer_core import PERIOD_MS, LoopbackDrive, make_plan
from streamer.core import Coordinator, JobState, StreamerSettings, StreamPlan
from streamer.runtime.trace import JobTrace

CPR = 8192
AXES = 6
DURATION_MS = 3000
ROUNDS = 5
TERMINAL = (JobState.DONE, JobState.CANCELLED, JobState.FAILED)
ROOT = Path(__file__).resolve().parents[1]

CLIENT = r"""
import json, sys, time
sys.path.insert(0, sys.argv[3])
from tests.live.foxglove_client import connect
port, out = int(sys.argv[1]), sys.argv[2]
c = connect("127.0.0.1", port, timeout_s=30)
topics = [f"/axis/a{n}" for n in range(1, int(sys.argv[4]) + 1)] + ["/job/events"]
c.subscribe(list(c.wait_channels(topics, 30).values()))
print("subscribed", flush=True)
delays = []
try:
    while True:
        kind, payload = c.next_message()
        if kind == "close":
            break
        if kind == "data" and payload[0].startswith("/axis/"):
            delays.append(time.time_ns() - payload[1])
except (ConnectionError, OSError):
    pass
json.dump(delays, open(out, "w"))
"""


class PlanView:
    """What the live view reads of a plan (`PvtTrajectory`'s names, nodes, duration and per-ms demand)."""

    def __init__(self, plan: StreamPlan):
        self.node_ids = tuple(plan.node_ids)
        self.axis_names = tuple(f"a{n}" for n in plan.node_ids)
        self.duration_ms = DURATION_MS
        self._demand = np.zeros((len(self.node_ids), DURATION_MS + 1), dtype=np.int64)

    def planned_demand(self) -> Any:
        return self._demand


def run_job(plan: StreamPlan, on_start: Any = None) -> tuple[list[float], list[float]]:
    """One job to its end, paced in real time: (the loop's work per SYNC in motion, per axis, s; the wake-ups'
    lateness, s)."""
    settings = StreamerSettings(counts_per_rev=dict.fromkeys(plan.node_ids, CPR))
    core = Coordinator(plan, settings)
    trace = JobTrace([(n, f"a{n}") for n in plan.node_ids], sync_period_s=PERIOD_MS / 1000, bitrate=1_000_000)
    if on_start is not None:
        on_start(core, trace)
    drives = [LoopbackDrive(node, plan.start_positions[i]) for i, node in enumerate(plan.node_ids)]
    by_node = {d.node: d for d in drives}
    work: list[float] = []
    late: list[float] = []
    clock = time.perf_counter
    period = PERIOD_MS / 1000.0
    due = clock() + period
    for count in range(10_000_000):
        now = clock()
        if due > now:
            time.sleep(due - now)
        late.append(clock() - due)
        due += period
        t = time.time()  # the SYNC on the bus (the runtime's frames carry their Unix-time stamps)
        t0 = clock()
        wire, events = sync_answers(drives, count, t)
        trace.on_sync(count, t)
        sends = []
        for ev in events:
            trace.on_event(ev)
            reaction = core.handle(ev)
            if reaction.changes:
                trace.on_changes(reaction.changes)
            sends += reaction.sends
        for cob_id, data in wire:
            trace.on_frame(cob_id, len(data), data, t)
        spent = clock() - t0
        for send in sends:  # the drives' side: not the loop's work
            by_node[send.cob_id & 0x7F].receive(send)
        if core.state in (JobState.RUNNING, JobState.FINISHING):
            work.append(spent / len(drives))
        if core.state in TERMINAL:
            return work, late
    raise RuntimeError("job did not end")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _with_live(plan: StreamPlan, tmp: Path, k: int) -> tuple[list[float], list[float], list[int], int]:
    from streamer.live.publisher import LiveJob, LivePublisher

    slot: list[LiveJob | None] = [None]
    view = PlanView(plan)
    publisher = LivePublisher([(f"a{n}", n) for n in plan.node_ids], source=lambda: slot[0], port=_free_port())
    publisher.start()
    out = tmp / f"delays-{k}.json"
    client = subprocess.Popen([sys.executable, "-c", CLIENT, str(publisher.port), str(out), str(ROOT),
                               str(len(plan.node_ids))], stdout=subprocess.PIPE, text=True)
    try:
        assert client.stdout is not None
        assert client.stdout.readline().strip() == "subscribed"
        publisher.wait_subscribed(10.0)

        def on_start(core: Any, trace: Any) -> None:
            slot[0] = LiveJob(view, core, trace, PERIOD_MS)

        work, late = run_job(plan, on_start)
    finally:
        publisher.stop(linger_s=0.3)
        client.wait(timeout=30)
    delays = json.loads(out.read_text())
    return work, late, delays, publisher.dropped


def main() -> dict[str, float]:
    import tempfile

    plan = make_plan(AXES, DURATION_MS, (10, 20, 30), seed=7)
    base: list[float] = []
    live: list[float] = []
    late_base: list[float] = []
    late_live: list[float] = []
    delays: list[int] = []
    dropped = 0
    with tempfile.TemporaryDirectory() as tmp:
        run_job(plan)  # warm-up
        for k in range(ROUNDS):
            work, late = run_job(plan)
            base += work
            late_base += late
            work, late, d, drop = _with_live(plan, Path(tmp), k)
            live += work
            late_live += late
            delays += d
            dropped += drop
    b, lv = 1e6 * statistics.median(base), 1e6 * statistics.median(live)
    b_mean, lv_mean = 1e6 * statistics.fmean(base), 1e6 * statistics.fmean(live)

    def pct(values: list[float], q: float) -> float:
        s = sorted(values)
        return s[min(len(s) - 1, int(q * len(s)))]

    result = {
        "base_us_per_axis_sync": b, "live_us_per_axis_sync": lv, "ratio": lv / b, "ratio_of_means": lv_mean / b_mean,
        "late_p50_ms_base": 1e3 * pct(late_base, 0.5), "late_p99_ms_base": 1e3 * pct(late_base, 0.99),
        "late_p50_ms_live": 1e3 * pct(late_live, 0.5), "late_p99_ms_live": 1e3 * pct(late_live, 0.99),
        "delay_p50_ms": pct([d / 1e6 for d in delays], 0.5), "delay_p95_ms": pct([d / 1e6 for d in delays], 0.95),
        "samples_received": float(len(delays)), "dropped": float(dropped),
    }
    print(f"SYNC loop, {AXES} axes, {PERIOD_MS} ms SYNC paced in real time, {ROUNDS} interleaved runs each "
          f"(the loop's work per SYNC in motion, per axis):")
    print("| condition | us per axis per SYNC, median | mean | wake-up late p50 ms | p99 ms |")
    print("|---|---|---|---|---|")
    print(f"| no live view | {b:.2f} | {b_mean:.2f} | {result['late_p50_ms_base']:.3f} | "
          f"{result['late_p99_ms_base']:.3f} |")
    print(f"| live view, one client subscribed | {lv:.2f} | {lv_mean:.2f} | {result['late_p50_ms_live']:.3f} | "
          f"{result['late_p99_ms_live']:.3f} |")
    print(f"ratio of the medians (target <= 1.05): {lv / b:.3f}; of the means: {lv_mean / b_mean:.3f}")
    print(f"frame on the bus -> client: p50 {result['delay_p50_ms']:.1f} ms, p95 {result['delay_p95_ms']:.1f} ms "
          f"({len(delays)} axis samples received, {dropped} dropped by the publisher)")
    return result


if __name__ == "__main__":
    main()
