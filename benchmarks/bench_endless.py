"""An endless (velocity) job in virtual time (issue 23 item 10): what the master holds as it runs.

Two axes turn at constant velocity with position limits far away (no braking chunk), for `minutes` of
motion (default 60; `python -m benchmarks.bench_endless 10` for a shorter look), cancelled at the end. Every
simulated minute it prints what grows with the job's length: the core's pieces (one per 2 s chunk) and the
records they hold, the records and frames the feeders keep, the feedback log's samples (the report's input)
and the trace's, and the process' peak RSS. Flat memory would show these as constants after the ramp; the
growth per hour is printed as a ratio against the first minute's (measured in the same run)."""

from __future__ import annotations

import dataclasses
import resource
import sys
import time


def main(argv: list[str] | None = None) -> int:
    from bus.sim.virtual import VirtualCell
    from planner.config import load_cell
    from planner.job import job_from_dict
    from planner.plan import plan_job
    from streamer.runtime.virtual import VirtualRuntime

    minutes = float(argv[0]) if argv else 60.0
    cell = load_cell("configs/demo.toml").with_axes(2)
    cell = dataclasses.replace(cell, axes=tuple(dataclasses.replace(a, position_min=-1e4, position_max=1e4)
                                                for a in cell.axes))
    job = job_from_dict({"kind": "move", "axes": ["j1", "j2"], "mode": "velocity", "velocity": [0.4, -0.3],
                         "start": [0.0, 0.0]}, cell)
    traj = plan_job(job, cell)
    rt = VirtualRuntime(cell, vcell=VirtualCell(cell))
    per_minute = round(60.0 / cell.sync_period_s)
    rows: list[tuple[int, ...]] = []

    def on_sync(core: object, m: int) -> None:
        if m % per_minute:
            return
        c = core  # the coordinator (read only)
        pieces = c.pieces  # type: ignore[attr-defined]
        feeders = c._axes  # type: ignore[attr-defined]
        rows.append((
            m // per_minute, len(pieces), sum(len(r) for _, p in pieces for r in p.records),
            sum(len(getattr(f, "records", ())) for f in feeders),
            sum(len(log.sync) for log in c.report().feedback.values()),  # type: ignore[attr-defined]
            sum(len(ax.pos_sync) + len(ax.fill_sync) for ax in rt.trace.axes.values()),  # type: ignore[union-attr]
            resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024,
        ))
        r = rows[-1]
        print(f"minute {r[0]:4d}: pieces {r[1]:5d}, their records {r[2]:7d}, feeder records {r[3]:7d}, "
              f"feedback samples {r[4]:8d}, trace samples {r[5]:8d}, peak RSS {r[6]} MiB", flush=True)

    t0 = time.perf_counter()
    result = rt.run(traj, cancel_at_s=minutes * 60.0, on_sync=on_sync, max_s=minutes * 60.0 + 60.0)
    print(f"{minutes:g} min of motion in {time.perf_counter() - t0:.0f} s, job {result.coordinator.state.value}")
    if len(rows) >= 2:
        first, last = rows[0], rows[-1]
        names = ("pieces", "piece records", "feeder records", "feedback samples", "trace samples", "peak RSS")
        print("growth, last minute / first minute: " + ", ".join(
            f"{n} {b / a:.1f}x" for n, a, b in zip(names, first[1:], last[1:], strict=True) if a))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
