"""An endless (velocity) job in virtual time (issue 23 item 10): what the master holds as it runs.

Two axes turn at constant velocity with position limits far away (no braking chunk), for `--minutes` of
motion (default 60; `python -m benchmarks.bench_endless --minutes 10` for a shorter look), cancelled at the
end. Every simulated minute it prints what would grow with the job's length: what the core holds of the
stream (`Coordinator.held`: segment ends, the feeders' records and frames, the pieces and their records,
the feedback log's samples in memory) and the trace's samples in memory, next to the process' RSS now
(MiB, /proc/self/statm). Flat memory shows these as constants after the first minute (the samples in
memory as a saw-tooth under one block per column); the end prints the records and samples the job covered
(all of them still readable: the report and recording read the spilled ones back), RSS at the first and
last minute and the growth per minute, and the last minute's held counts as ratios against the first
minute's (measured in the same run: 1.0x is flat).

Measured (2 axes, demo.toml, this VM): before the core retired its past (8efa25a), 15 min: RSS 171.7 ->
227.2 MiB (+3.97 MiB/min), held records 530 -> 7250; after, 60 min: RSS 169.1 -> 169.3 MiB (+0.004 MiB/min),
held records 36 -> 36, feedback and trace samples in memory at most 24k and 74k while 720k of each were
kept whole."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from typing import Any


def rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def main(argv: list[str] | None = None) -> int:
    from bus.sim.virtual import VirtualCell
    from planner.config import load_cell
    from planner.job import job_from_dict
    from planner.plan import plan_job
    from streamer.runtime.virtual import VirtualRuntime

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("minutes_pos", nargs="?", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--minutes", type=float, default=60.0, help="minutes of virtual motion (default 60)")
    args = ap.parse_args(argv)
    minutes = args.minutes_pos if args.minutes_pos is not None else args.minutes
    cell = load_cell("configs/demo.toml").with_axes(2)
    cell = dataclasses.replace(cell, axes=tuple(dataclasses.replace(a, position_min=-1e4, position_max=1e4)
                                                for a in cell.axes))
    job = job_from_dict({"kind": "move", "axes": ["j1", "j2"], "mode": "velocity", "velocity": [0.4, -0.3],
                         "start": [0.0, 0.0]}, cell)
    traj = plan_job(job, cell)
    rt = VirtualRuntime(cell, vcell=VirtualCell(cell))
    per_minute = round(60.0 / cell.sync_period_s)
    rows: list[tuple[float, ...]] = []

    def on_sync(core: object, m: int) -> None:
        if m % per_minute:
            return
        held = getattr(core, "held", None)
        if held is None:  # a commit before the core counted what it holds (the baseline): count its lists
            c: Any = core
            held = {"ends": len(c._ends), "records": sum(len(f.records) for f in c._feeders),
                    "frames": sum(len(f.sends) for f in c._feeders), "pieces": len(c.pieces),
                    "piece_records": sum(len(r) for _, p in c.pieces for r in p.records), "retired": 0,
                    "feedback_samples": 3 * sum(len(log.sync) for log in c.report().feedback.values())}
        tr = rt.trace
        assert tr is not None
        times = tr.sync_times
        trace = sum(getattr(ax, "held", None) or sum(len(v) for k, v in vars(ax).items() if isinstance(v, list))
                    for ax in tr.axes.values()) + getattr(tr.frame_log, "held", len(tr.frame_log)) \
            + getattr(times, "held", len(times))
        rows.append((m // per_minute, held["ends"], held["records"], held["frames"], held["pieces"],
                     held["piece_records"], held["feedback_samples"], trace, held["retired"], rss_mib()))
        r = rows[-1]
        print(f"minute {r[0]:4.0f}: held ends {r[1]:5.0f}, records {r[2]:5.0f}, frames {r[3]:5.0f}, pieces {r[4]:3.0f} "
              f"({r[5]:4.0f} records), feedback samples {r[6]:6.0f}, trace samples {r[7]:6.0f}; retired {r[8]:8.0f}; "
              f"RSS {r[9]:.1f} MiB", flush=True)

    t0 = time.perf_counter()
    result = rt.run(traj, cancel_at_s=minutes * 60.0, on_sync=on_sync, max_s=minutes * 60.0 + 60.0)
    core = result.coordinator
    report = core.report()
    samples = sum(len(log.sync) for log in report.feedback.values())
    records = sum(t.points_sent for t in core.telemetry())
    print(f"{minutes:g} min of motion in {time.perf_counter() - t0:.0f} s, job {core.state.value}: {records} records "
          f"streamed, {samples} feedback samples and {sum(len(ax.pos_sync) for ax in result.trace.axes.values())} "
          f"trace position samples kept (readable whole)")
    if len(rows) >= 2:
        first, last = rows[0], rows[-1]
        span = last[0] - first[0]
        print(f"RSS {first[9]:.1f} MiB at minute {first[0]:.0f}, {last[9]:.1f} MiB at minute {last[0]:.0f}: "
              f"{(last[9] - first[9]) / span:+.3f} MiB/min")
        print(f"samples in memory, most at any minute: feedback {max(r[6] for r in rows):.0f}, trace "
              f"{max(r[7] for r in rows):.0f} (spilled columns hold at most one block each, so these rise and "
              f"fall within a bound; the ratios below for them compare two points of that saw-tooth)")
        names = ("ends", "records", "frames", "pieces", "piece records", "feedback samples", "trace samples")
        print("held, last minute / first minute: " + ", ".join(
            f"{n} {b / a:.1f}x" for n, a, b in zip(names, first[1:8], last[1:8], strict=True) if a))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
