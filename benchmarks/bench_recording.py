"""Benchmark: the cost of recording every job, on the SYNC loop and after the job.

On the SYNC loop the recording costs only what `JobTrace(record=True)` adds to what the loop does
anyway: per event `trace.on_event` (the TPDO1 status words, the noted events), the core's state
changes (`on_changes`), and per frame `trace.on_frame` with its data and time (in the real-time
runtime that one runs on the adapter's receive thread, in the same process, so it is counted too).
Measured as in bench_streamer_core.py: the streamer core runs jobs against a minimal loopback drive
(not timed) and only the streaming thread's work per event is timed: `trace.on_event`, `core.handle`
and `trace.on_changes` ("SYNC loop"), plus `trace.on_frame` for every frame of the cycle ("+ frame
tap": SYNC, TPDO1 and TPDO2 of each drive, everything the core sent). The baseline is the same loop
with `JobTrace(record=False)` (the trace the report needs), measured in the same run, interleaved,
median of 5; the ratio is the portable number.

After the job (off the SYNC loop, on the service's executor thread between jobs): building the
`JobRecording` from the trace, writing the MCAP file, and rendering the HTML report, per second of
job, with the file size.

Between jobs SYNC keeps running: on python-can's virtual bus it is a Python thread, and the cell's
simulated drives run in the same process (`pvt serve --sim`). The last table is the SYNC interval
(from the frames' timestamps) while the demo job's recording is written over and over: in this
process (`RecordingWriter(in_process=True)`) and in the service's worker process, against idle
windows, interleaved; gaps > 30 ms are what the simulated drives report as SYNC lost (EMCY 0x8780).

Run: `python -m benchmarks.bench_recording` or call `main()`.
"""

from __future__ import annotations

import io
import itertools
import statistics
import time

from benchmarks.bench_streamer_core import PERIOD_MS, LoopbackDrive, make_plan
from bus.cob import SYNC_COB_ID, unpack_tpdo1, unpack_tpdo2
from bus.events import BufferStatus, PositionFeedback, Sync
from streamer.core import Coordinator, JobState, StreamerSettings, StreamPlan
from streamer.runtime.trace import JobTrace

CPR = 8192
TERMINAL = (JobState.DONE, JobState.CANCELLED, JobState.FAILED)


def sync_answers(drives: list[LoopbackDrive], count: int, t: float) -> tuple[list[tuple[int, bytes]], list[object]]:
    """SYNC `count` at time `t` and the loopback drives' answers: the frames on the wire, the core's events."""
    frames = [d.sync() for d in drives]
    wire: list[tuple[int, bytes]] = [(SYNC_COB_ID, b"")]
    events: list[object] = [Sync(count, t)]
    for d, (tp1, _) in zip(drives, frames, strict=True):
        sw, free = unpack_tpdo1(tp1)
        events.append(BufferStatus(d.node, sw, 0x8000 if sw & 0x1000 else 0, free, t, count))
        wire.append((0x180 + d.node, tp1))
    for d, (_, tp2) in zip(drives, frames, strict=True):
        actual, demand = unpack_tpdo2(tp2)
        events.append(PositionFeedback(d.node, actual, demand, t, count))
        wire.append((0x280 + d.node, tp2))
    return wire, events


def run_job(plan: StreamPlan, record: bool) -> tuple[float, float, int, JobTrace]:
    """One job to its end: (s in the loop's work, s in the frame tap, axis-SYNCs in motion, trace)."""
    settings = StreamerSettings(counts_per_rev=dict.fromkeys(plan.node_ids, CPR))
    core = Coordinator(plan, settings)
    trace = JobTrace([(n, f"a{n}") for n in plan.node_ids], sync_period_s=PERIOD_MS / 1000, bitrate=1_000_000,
                     record=record)
    drives = [LoopbackDrive(node, plan.start_positions[i]) for i, node in enumerate(plan.node_ids)]
    by_node = {d.node: d for d in drives}
    in_loop = 0.0
    in_tap = 0.0
    axis_syncs = 0
    clock = time.perf_counter
    for count in range(10_000_000):
        t = count * PERIOD_MS / 1000.0
        wire, events = sync_answers(drives, count, t)
        trace.on_sync(count, t)
        for ev in events:
            t0 = clock()
            trace.on_event(ev)
            reaction = core.handle(ev)
            if reaction.changes:
                trace.on_changes(reaction.changes)
            in_loop += clock() - t0
            for send in reaction.sends:
                by_node[send.cob_id & 0x7F].receive(send)
                wire.append((send.cob_id, send.data))
        t0 = clock()
        for cob_id, data in wire:
            trace.on_frame(cob_id, len(data), data, t)
        in_tap += clock() - t0
        if core.state in (JobState.RUNNING, JobState.FINISHING):
            axis_syncs += len(drives)
        if core.state in TERMINAL:
            return in_loop, in_tap, axis_syncs, trace
    raise RuntimeError("job did not end")


def _after_job(n_axes: int, duration_ms: int) -> dict[str, float]:
    """Build + write the MCAP, and render the HTML, for a job run in virtual time on the simulated drives."""
    from planner.config import load_cell
    from planner.job import job_from_dict
    from planner.plan import plan_job
    from streamer.demo import ROOT, start_positions
    from streamer.recording.export import job_figure
    from streamer.recording.html import figure_to_html
    from streamer.recording.mcap_io import write_mcap_stream
    from streamer.recording.model import build_recording
    from streamer.report import build_report
    from streamer.runtime.virtual import VirtualRuntime
    from streamer.splice_planners import make_stop_planner

    cell = load_cell(ROOT / "configs" / "demo.toml").with_axes(n_axes)
    names = cell.axis_names()
    rows = []
    t = 0.0
    k = 0
    while t * 1000 < duration_ms:  # a back-and-forth timed job of the requested length
        rows.append([0.3 * (k % 2) * (1 if i % 2 else -1) for i in range(n_axes)])
        t += 1.0
        k += 1
    rows.append([0.0] * n_axes)
    job = job_from_dict({"kind": "timed", "axes": list(names), "times": [float(i) for i in range(len(rows))],
                         "positions": rows}, cell)
    traj = plan_job(job, cell)
    from bus.sim.virtual import VirtualCell

    rt = VirtualRuntime(cell, vcell=VirtualCell(cell, initial_positions=start_positions(cell, traj)))
    result = rt.run(traj, stop_planner=make_stop_planner(cell, traj))
    core = result.coordinator.report()
    report = build_report(traj, core, result.trace, sync_period_ms=cell.sync_period_ms,
                          first_sync=result.first_sync, last_sync=result.last_sync)
    t0 = time.perf_counter()
    rec = build_recording(traj, result.trace, report, first_sync=result.first_sync, start_sync=core.start_sync,
                          sync_period_ms=cell.sync_period_ms, epoch_s=time.time(),
                          underflow_watermark=cell.drive.underflow_warning,
                          overflow_watermark=cell.drive.overflow_warning)
    t1 = time.perf_counter()
    buf = io.BytesIO()
    messages = write_mcap_stream(rec, buf)
    t2 = time.perf_counter()
    figure_to_html(job_figure(rec))
    t3 = time.perf_counter()
    seconds = rec.duration_s
    return {"job_s": seconds, "build_ms": (t1 - t0) * 1e3, "write_ms": (t2 - t1) * 1e3, "html_ms": (t3 - t2) * 1e3,
            "bytes": float(len(buf.getvalue())), "messages": float(messages)}


def main() -> dict[str, float]:
    results: dict[str, float] = {}
    print("recording cost on the SYNC loop (virtual time, 10 ms SYNC; median of 5, interleaved)")
    print(f"{'case':<26}{'loop us/axis/SYNC':>19}{'with rec':>10}{'ratio':>7}{'+ frame tap':>13}"
          f"{'with rec':>10}{'ratio':>7}")
    for n_axes, label in ((6, "6 axes, dt 10-40 ms"), (16, "16 axes, dt 10-30 ms")):
        plan = make_plan(n_axes, 30_000, (10, 20, 30, 40) if n_axes == 6 else (10, 20, 30), seed=n_axes)
        loop: dict[bool, list[float]] = {False: [], True: []}
        total: dict[bool, list[float]] = {False: [], True: []}
        for _ in range(5):
            for record in (False, True):
                in_loop, in_tap, axis_syncs, trace = run_job(plan, record)
                loop[record].append(in_loop / axis_syncs * 1e6)
                total[record].append((in_loop + in_tap) / axis_syncs * 1e6)
                if record:
                    assert len(trace.frame_log) == trace.frames and trace.changes
        base, rec = statistics.median(loop[False]), statistics.median(loop[True])
        tbase, trec = statistics.median(total[False]), statistics.median(total[True])
        print(f"{label:<26}{base:>19.2f}{rec:>10.2f}{rec / base:>7.3f}{tbase:>13.2f}{trec:>10.2f}{trec / tbase:>7.3f}")
        results[f"loop_ratio_with_recording[{label}]"] = rec / base
        results[f"loop_plus_tap_ratio_with_recording[{label}]"] = trec / tbase
        results[f"us_per_axis_sync_with_recording[{label}]"] = trec
    print()
    print("after the job (executor thread, between jobs): build the recording, write the MCAP, render the HTML")
    print(f"{'job':<22}{'build ms':>10}{'MCAP ms':>9}{'HTML ms':>9}{'MCAP bytes':>12}{'messages':>10}"
          f"{'ms per job s':>14}{'kB per job s':>14}")
    _after_job(1, 1_000)  # warm-up: imports (plotly, mcap) and first-call costs are not per job
    for n_axes, duration_ms in ((6, 10_000), (6, 30_000)):
        r = _after_job(n_axes, duration_ms)
        per_s = (r["build_ms"] + r["write_ms"]) / r["job_s"]
        label = f"{n_axes} axes, {r['job_s']:.1f} s"
        print(f"{label:<22}{r['build_ms']:>10.1f}{r['write_ms']:>9.1f}{r['html_ms']:>9.1f}{r['bytes']:>12.0f}"
              f"{r['messages']:>10.0f}{per_s:>14.1f}{r['bytes'] / 1000 / r['job_s']:>14.1f}")
        results[f"record_ms_per_job_s[{label}]"] = per_s
        results[f"mcap_kb_per_job_s[{label}]"] = r["bytes"] / 1000 / r["job_s"]
    print()
    print("SYNC interval between jobs while recordings are written (10 ms SYNC, 6 simulated drives in-process,")
    print("4 x 2 s windows each, interleaved)")
    print(f"{'while':<28}{'SYNCs':>7}{'p50 ms':>8}{'p99 ms':>8}{'max ms':>8}{'> 30 ms':>9}")
    for kind, row in _sync_jitter().items():
        print(f"{kind:<28}{row['n']:>7.0f}{row['p50']:>8.1f}{row['p99']:>8.1f}{row['max']:>8.1f}{row['gaps']:>9.0f}")
        results[f"sync_p99_ms[{kind}]"] = row["p99"]
    return results


def _sync_jitter() -> dict[str, dict[str, float]]:
    import tempfile
    from pathlib import Path

    import can

    from planner.config import load_cell
    from streamer import demo
    from streamer.recording.files import RecordingFiles
    from streamer.recording.writer import RecordingWriter
    from streamer.runtime.bus_backend import RuntimeBackend

    folder = Path(tempfile.mkdtemp(prefix="pvt-bench-rec-"))
    cell, _job, traj = demo.prepare()
    demo.run_fast(cell, traj, folder / "demo")
    from streamer.recording.mcap_io import read_mcap

    rec = read_mcap(folder / "demo" / "job.mcap")
    files = RecordingFiles(folder / "rec")
    writers = {"writing in this process": RecordingWriter(files, in_process=True),
               "writing in the worker": RecordingWriter(files)}
    writers["writing in the worker"].start()
    backend = RuntimeBackend(load_cell(demo.ROOT / "configs" / "demo.toml"), sim=True)
    stamps: list[float] = []

    class Syncs(can.Listener):
        def on_message_received(self, msg: can.Message) -> None:
            if msg.arbitration_id == SYNC_COB_ID:
                stamps.append(msg.timestamp)

    backend.adapter.add_listener(Syncs())
    gaps: dict[str, list[float]] = {"idle": [], **{k: [] for k in writers}}
    try:
        time.sleep(1.0)
        for _ in range(4):
            for kind in gaps:
                t0 = time.time()
                while time.time() - t0 < 2.0:
                    if kind == "idle":
                        time.sleep(0.05)
                    else:
                        writers[kind].save("bench", rec, cell="demo")
                t1 = time.time()
                sel = [t for t in stamps if t0 <= t <= t1]
                gaps[kind] += [b - a for a, b in itertools.pairwise(sel)]
    finally:
        backend.close()
        for w in writers.values():
            w.close()
    out = {}
    for kind, d in gaps.items():
        d.sort()
        out[kind] = {"n": len(d), "p50": d[len(d) // 2] * 1e3, "p99": d[int(len(d) * 0.99)] * 1e3,
                     "max": d[-1] * 1e3, "gaps": sum(g > 0.030 for g in d)}
    return out


if __name__ == "__main__":
    main()
