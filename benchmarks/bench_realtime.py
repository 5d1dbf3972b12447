"""Real time on a loaded machine (issue 22): late set points, the cycle's latency, EPOS readings, EPOS capacity.

Run: `python -m benchmarks.bench_realtime [--only timing|epos|capacity|priority] [--scale F] [--hogs 0,1,2]`. Every
figure is measured in this run, next to its baseline measured in the same run:

- timing: XtrapulsPac cells (as many axes as the bus carries at the period, one RPDO each, sub-mode PV) at
  1, 2, 5 and 10 ms SYNC run one long back-and-forth path each (100,000 cycles at 1 and 2 ms, 20,000 at 5 and
  10 ms, times --scale), idle and with one and two busy processes beside them (`--hogs`). Judged from the bus
  (the candump log: the drives' view): a cycle is late when its set point reached the bus less than 100 us
  before the SYNC that latches it, or not at all (the XtrapulsPac's error 50). The cycle engine's own
  figures: the latency from a SYNC to the last frame of that cycle and the SYNC's delay against its
  schedule (p50 / p99.9 / max). Baseline: the runtime before the engine (drives and master in one process,
  python-can virtual bus, frames sent by the streaming thread), on the same cell and job, for a tenth of the
  cycles (it ends on its first late set point).
- epos: for the reference drive and every EPOS reading of docs/drive-model.md (tests/runtime/test_variants.py
  VARIANTS: TPDO latency 9 ms of a 10 ms period included), --jobs real-time jobs at 10 ms (a 3-axis move there
  and back) with one busy process beside them, the drives in their own process: false faults (a job not
  DONE) and missed guarantees (`pvt demo`'s); benchmarks/bench_drives.py `false-faults` is the baseline (the
  drives in the master's process, no engine).
- priority: the streaming thread above the receive thread (as now) against below it (as before), alternating
  runs of one cyclic job at 5 ms on an idle machine: the master's smallest lead per run as the cycle engine saw
  it (`EngineStats.lead_us`), runs with a batch too late for its set point, runs done.
- capacity: the most EPOS axes on 1 Mbit/s at 10 ms that run the demo path in real time with the drives out
  of process (target >= 24, the bus's figure from benchmarks/bench_drives.py), against the budget's figure.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from planner.config import CellConfig, load_cell

ROOT = Path(__file__).resolve().parent.parent
XTRAPULS = ROOT / "configs" / "xtrapuls.toml"
DEMO = ROOT / "configs" / "demo.toml"
DEMO_JOB = ROOT / "configs" / "jobs" / "demo-path.toml"
CYCLES = {1: 100_000, 2: 100_000, 5: 20_000, 10: 20_000}
PRIORITY_BEFORE = 50  # the streaming thread's SCHED_FIFO priority before it ranked above the receive thread


@contextlib.contextmanager
def hogs(n: int) -> Iterator[None]:
    """`n` busy processes beside the run (each spins one core at normal priority)."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait()


def cyclic_cell(period_ms: int) -> CellConfig:
    """XtrapulsPac axes with an RPDO each, sub-mode PV, as many as 1 Mbit/s carries at the period (70 %)."""
    from benchmarks.bench_cyclic import budget_fits, capacity_cell

    n = 1
    while n < 8 and budget_fits(capacity_cell(n + 1, period_ms, "pv", 0)):
        n += 1
    base = load_cell(XTRAPULS)
    return dataclasses.replace(base.with_axes(n), sync_period_ms=period_ms)


def shuttle_job(cell: CellConfig, seconds: float) -> Any:
    """A path back and forth on every axis, about `seconds` long (within each axis' limits)."""
    from planner.job import job_from_dict

    names = list(cell.axis_names())
    a = [0.0] * len(names)
    b = [min(0.6, 0.5 * ax.position_max) for ax in cell.axes]
    legs = max(2, int(seconds / 1.1))
    waypoints = [a if k % 2 == 0 else b for k in range(legs + 1)]
    return job_from_dict({"kind": "path", "axes": names, "waypoints": waypoints, "velocity_scale": 0.5}, cell)


def late_setpoints(log: Path, cell: CellConfig, traj: Any, since_s: float | None) -> tuple[int, int, list[float]]:
    """(late cycles, cycles, margins s) of a run's candump log: every SYNC interval from the first set point to
    the last must hold one at least 100 us before the SYNC that ends it (a frame after its SYNC counts as
    missing for that cycle, not as an early one for the next)."""
    import can

    from bus.cob import SYNC_COB_ID
    from bus.families import setpoint_slots
    from streamer.report import decode_setpoints

    syncs = np.array([m.timestamp for m in can.LogReader(str(log)) if m.arbitration_id == SYNC_COB_ID])
    slots = setpoint_slots(cell.axes)
    start = {n: int(traj.positions[i, 0]) for i, n in enumerate(traj.node_ids)}
    sent = decode_setpoints(log, slots, start, since_s=since_s)
    leaders = {s.members[0] for s in slots.values()}
    late = total = 0
    margins: list[float] = []
    for node, rows in sent.items():
        if node not in leaders or not rows or syncs.size == 0:
            continue
        times = np.array([r[0] for r in rows])
        k = np.searchsorted(syncs, times, side="right")  # the SYNC that latches each frame
        keep = k < syncs.size
        k, times = k[keep], times[keep]
        if k.size == 0:
            continue
        for j in range(int(k.min()), int(k.max()) + 1):
            total += 1
            in_cycle = times[k == j]
            if in_cycle.size == 0:
                late += 1
                continue
            margin = float(syncs[j] - in_cycle.max())
            margins.append(margin)
            late += margin < 100e-6
    return late, total, margins


def _engine_run(cell: CellConfig, traj: Any, out: Path,
                streaming_priority: int | None = None) -> tuple[dict[str, Any], Any]:
    """The product's real-time path (drives out of process, the cycle engine) with the engine's statistics;
    `streaming_priority` overrides the streaming thread's SCHED_FIFO priority (the `priority` comparison)."""
    from streamer import demo

    stats: dict[str, Any] = {}

    def keep(adapter: Any) -> None:
        stats["engine"] = adapter.engine
        adapter.engine.stats(reset=True)

    import streamer.runtime.realtime as rt_module

    close = rt_module.RealtimeRuntime.close

    def closing(self: Any) -> None:  # the statistics before the engine stops
        if self.adapter.engine is not None:
            stats["stats"] = self.adapter.engine.stats()
        close(self)

    rt_module.RealtimeRuntime.close = closing  # type: ignore[method-assign]
    try:
        def runtime(rt: Any) -> None:
            if streaming_priority is not None:
                rt.streaming_priority = streaming_priority

        report, _ = demo.run_realtime(cell, traj, out, on_engine=keep, on_runtime=runtime, plot=False)
    finally:
        rt_module.RealtimeRuntime.close = close  # type: ignore[method-assign]
    return report, stats.get("stats")


def _baseline_run(cell: CellConfig, traj: Any, out: Path) -> dict[str, Any]:
    """Before the engine: drives and master in one process on python-can's virtual bus, the streaming thread
    sending each frame when the core returns it."""
    from bus.network import MasterAdapter
    from bus.sim.node import SimulatedCell
    from streamer import demo
    from streamer.runtime.realtime import RealtimeRuntime
    from streamer.splice_planners import make_stop_planner

    out.mkdir(parents=True, exist_ok=True)
    with SimulatedCell(cell, initial_positions=demo.start_positions(cell, traj),
                       sync_gap_factor=demo.IN_PROCESS_SYNC_GAP_FACTOR), MasterAdapter(None, cell) as adapter:
        adapter.configure_drives()
        rt = RealtimeRuntime(cell, adapter, log_path=out / "bus.log")
        try:
            result = rt.run(traj, stop_planner=make_stop_planner(cell, traj))
        finally:
            rt.close()
    report, _ = demo._finish(cell, traj, result.coordinator, result.trace, result.first_sync, result.last_sync,
                             out, rt.settings.readings)
    return report


def platform_gaps(seconds: float = 0.9) -> float:
    """The longest time (s) a SCHED_FIFO 99 thread that never sleeps did not run, over `seconds` (kept under
    the kernel's 0.95 s real-time budget): what no priority in this system can get below (another vCPU's
    host, SMIs). Runs in a process of its own; 0.0 when real-time priority is refused."""
    code = ("import os, time\n"
            "try:\n    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(99))\n"
            "except OSError:\n    print(0.0); raise SystemExit\n"
            f"end = time.time() + {seconds}; last = time.time(); worst = 0.0\n"
            "while last < end:\n    t = time.time(); worst = max(worst, t - last); last = t\n"
            "print(worst)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30)
    return float(out.stdout.strip() or 0.0)


def _pct(values: list[int]) -> str:
    if not values:
        return "-"
    a = np.array(values)
    return f"{np.percentile(a, 50):.0f} / {np.percentile(a, 99.9):.0f} / {a.max():.0f} us"


def _margins() -> str:
    """What this machine's margins, where set, change (README, "Real-time priority": a machine that freezes a CPU
    for tens of ms), or "" where none is set."""
    from streamer.runtime.realtime import HOST_STALL_MS

    margins_set = {k: os.environ[k] for k in ("PVT_HOST_STALL_MS", "PVT_SIM_SYNC_GAP_FACTOR") if k in os.environ}
    if not margins_set:
        return ""
    return (f"with this machine's margins {margins_set}: the simulated drives take SYNCs up to "
            f"{os.environ.get('PVT_SIM_SYNC_GAP_FACTOR', '1.5')} periods apart, the master waits {HOST_STALL_MS:.0f} "
            "ms for an answer and runs that far ahead")


def timing(scale: float, hog_levels: list[int], periods: list[int]) -> None:
    from planner.plan import plan_job

    print("timing: cycles whose set point reached the bus less than 100 us before its SYNC (or not at all), from "
          "the bus; the engine's SYNC -> last frame of the cycle, and its SYNC delay, p50 / p99.9 / max")
    margins = _margins()
    if margins:
        print(f"  {margins}; a set point's 100 us before its SYNC is judged as always")
    for period in periods:
        cell = cyclic_cell(period)
        cycles = int(CYCLES[period] * scale)
        job = shuttle_job(cell, cycles * period / 1000.0)
        traj = plan_job(job, cell)
        print(f"  {period} ms, {len(cell.axes)} axes, {traj.duration_s:.0f} s job:")
        for n in hog_levels:
            with hogs(n):
                floor = max(platform_gaps() for _ in range(3))
            print(f"    {n} busy: the platform: a SCHED_FIFO 99 spinner was held up {1e3 * floor:.2f} ms at most "
                  "(3 x 0.9 s)", flush=True)
            with hogs(n), tempfile.TemporaryDirectory() as d:
                report, st = _engine_run(cell, traj, Path(d))
                late, total, margins = late_setpoints(Path(d) / "bus.log", cell, traj, report.get("job_start_s"))
            ok = report["result"]
            lat = _pct(st.cycle_latency_us) if st else "-"
            delay = _pct(st.sync_delay_us) if st else "-"
            m1 = f"{1e3 * np.percentile(margins, 0.1):.2f} ms" if margins else "-"
            print(f"    {n} busy: engine {late} late of {total} cycles ({ok}); latency {lat}; SYNC delay {delay}; "
                  f"margin p0.1 {m1}; the master's lead {_lead(st)}"
                  + (f"; {report.get('message')}" if ok != "done" else ""), flush=True)
            base_traj = plan_job(shuttle_job(cell, max(1.0, cycles * period / 10000.0)), cell)
            with hogs(n), tempfile.TemporaryDirectory() as d:
                try:
                    base = _baseline_run(cell, base_traj, Path(d))
                    b_late, b_total, _ = late_setpoints(Path(d) / "bus.log", cell, base_traj, base.get("job_start_s"))
                    b_ok = base["result"]
                except Exception as e:  # the baseline may not even start at 1 ms
                    b_late, b_total, b_ok = 0, 0, f"error {type(e).__name__}: {e}"
            print(f"    {n} busy: baseline {b_late} late of {b_total} cycles ({b_ok})", flush=True)


def _lead(st: Any) -> str:
    """How far ahead of its SYNC each batch reached the engine (`EngineStats.lead_us`): p0.1 / min."""
    if st is None or not st.lead_us:
        return "-"
    a = np.array(st.lead_us) / 1000.0
    return f"p0.1 {np.percentile(a, 0.1):.1f} / min {a.min():.1f} ms"


def priority(runs: int, period_ms: int = 5) -> None:
    """The streaming thread above the receive thread (STREAMING_PRIORITY) against below it (PRIORITY_BEFORE, as before),
    in alternating runs of the same cyclic job on an otherwise idle machine: the master's lead as the engine saw
    it (a set point is late once a batch comes less than 100 us before the SYNC after its own), and the runs
    done. The lead is the cell's cyclic default (`default_ahead_ms`)."""
    from planner.plan import plan_job
    from streamer.runtime.realtime import STREAMING_PRIORITY, default_ahead_ms

    cell = dataclasses.replace(load_cell(XTRAPULS).with_axes(3), sync_period_ms=period_ms)
    traj = plan_job(shuttle_job(cell, 6.0), cell)
    print(f"priority: {runs} runs each, {len(cell.axes)} XtrapulsPac axes at {period_ms} ms, a {traj.duration_s:.0f} s "
          f"job, lead {default_ahead_ms(cell):.0f} ms; the streaming thread at {STREAMING_PRIORITY} (above the "
          f"receive thread) and at {PRIORITY_BEFORE} (below it, as before), alternating")
    seen: dict[int, list[tuple[float, str]]] = {STREAMING_PRIORITY: [], PRIORITY_BEFORE: []}
    for _ in range(runs):
        for prio in seen:
            with tempfile.TemporaryDirectory() as d:
                report, st = _engine_run(cell, traj, Path(d), streaming_priority=prio)
            worst = min(st.lead_us) / 1000.0 if st and st.lead_us else float("nan")
            seen[prio].append((worst, str(report["result"]) if report["result"] == "done" else
                               str(report.get("message"))[:70]))
    for prio, rows in seen.items():
        leads = sorted(w for w, _ in rows)
        late = sum(w < -(period_ms - 0.1) for w in leads)
        done = sum(r == "done" for _, r in rows)
        print(f"  streaming at {prio}: the master's smallest lead per run {', '.join(f'{w:.1f}' for w in leads)} ms "
              f"(median {np.median(leads):.1f}); {late} of {runs} runs with a batch too late for its set point; "
              f"{done} of {runs} done {[r for _, r in rows if r != 'done']}", flush=True)


def _report(cell: CellConfig, traj: Any, result: Any, readings: Any) -> dict[str, Any]:
    from streamer.report import build_report

    core = result.coordinator
    return build_report(traj, core.report(), result.trace, sync_period_ms=cell.sync_period_ms,
                        first_sync=result.first_sync, last_sync=result.last_sync, readings=readings,
                        time_stamp=cell.time_stamp, setpoints={n: core.setpoints(n) for n in traj.node_ids})


def epos(jobs: int, only: list[str] | None = None) -> None:
    from bus.errors import BusError
    from planner.job import job_from_dict
    from planner.plan import plan_job
    from planner.readings import SimDriveOptions
    from streamer import demo
    from streamer.cli.demo import guarantees
    from streamer.runtime.realtime import RealtimeRuntime
    from streamer.splice_planners import make_stop_planner
    from tests.runtime.test_variants import VARIANTS

    print(f"epos: {jobs} real-time jobs per reading at 10 ms, 3 axes (a move there and back), one busy process "
          "beside them, the drives in a process of their own, the cycle engine")
    margins = _margins()
    if margins:
        print(f"  {margins}")
    base = load_cell(DEMO).with_axes(3)
    there = {"kind": "move", "axes": ["j1", "j2", "j3"], "target": [0.3, -0.2, 0.25], "mode": "absolute"}
    back = {"kind": "move", "axes": ["j1", "j2", "j3"], "target": [0.0, 0.0, 0.0], "mode": "absolute"}
    readings = {"reference": {}, **VARIANTS}
    unknown = sorted(set(only or ()) - set(readings))
    if unknown:
        raise SystemExit(f"--readings: no reading {', '.join(unknown)} (known: {', '.join(readings)})")
    for name, options in readings.items():
        if only and name not in only:
            continue
        cell = dataclasses.replace(base, axes=tuple(dataclasses.replace(a, sim=SimDriveOptions(**options))
                                                    for a in base.axes))
        faults = missed = done = 0
        reasons: dict[str, int] = {}
        t0 = time.perf_counter()
        with hogs(1), demo.realtime_cell(cell) as adapter:
            rt = RealtimeRuntime(adapter.cell, adapter)
            try:
                rt.ensure_readings()
                planned = dataclasses.replace(cell, axes=tuple(
                    dataclasses.replace(a, probed=dataclasses.replace(a.probed, rounding=rt.known[a.node_id].rounding))
                    for a in cell.axes))
                trajs = [plan_job(job_from_dict(there, planned), planned, start=[0.0] * 3),
                         plan_job(job_from_dict(back, planned), planned, start=[0.3, -0.2, 0.25])]
                for k in range(jobs):
                    traj = trajs[k % 2]
                    result = rt.run(traj, stop_planner=make_stop_planner(planned, traj), settle_s=0.5)
                    report = _report(planned, traj, result, rt.settings.readings)
                    problems = guarantees(report, traj.tolerance_counts)
                    if report["result"] != "done":
                        faults += 1
                        key = str(report.get("message"))[:60]
                        reasons[key] = reasons.get(key, 0) + 1
                        break  # the drives are faulted: this reading stops here
                    if problems:
                        missed += 1
                        reasons[problems[0][:60]] = reasons.get(problems[0][:60], 0) + 1
                    done += 1
            except BusError as e:  # the probe failed (a drive faulted while measured): no job for this reading
                faults += 1
                reasons[f"probe: {e}"[:60]] = 1
            finally:
                rt.close()
        print(f"  {name:24s} {done}/{jobs} jobs done, {faults} false faults, {missed} missed guarantees "
              f"({time.perf_counter() - t0:.0f} s) {reasons or ''}", flush=True)


def capacity(max_axes: int) -> None:
    from bus.budget import cell_feedback_every
    from planner.job import load_job
    from planner.plan import plan_job
    from streamer import demo
    from streamer.cli.demo import guarantees

    print("capacity: EPOS axes on 1 Mbit/s at 10 ms in real time, drives out of process, the demo path")
    best = 0
    for n in (6, 12, 18, 24, 30):
        if n > max_axes:
            break
        cell = load_cell(DEMO).with_axes(n)
        job = demo.fit_job_to_cell(load_job(DEMO_JOB, load_cell(DEMO)), cell, repeat=True)
        traj = plan_job(job, cell)
        with tempfile.TemporaryDirectory() as d:
            try:
                report, _ = demo.run_realtime(cell, traj, Path(d), job=job)
                problems = guarantees(report, job.tolerance_counts)
            except Exception as e:
                report, problems = {"result": "error", "bus_load_peak": 0.0}, [f"{type(e).__name__}: {e}"]
        ok = report["result"] == "done" and not problems
        best = n if ok else best
        print(f"  {n:2d} axes (TPDO2 every {cell_feedback_every(cell)} SYNCs): {report['result']}, peak bus load "
              f"{100 * report.get('bus_load_peak', 0):.1f} %" + ("" if ok else f"; {problems[:2]}"), flush=True)
        if not ok:
            break
    print(f"  most axes in real time: {best} (target >= 24)")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--only", choices=("timing", "epos", "capacity", "priority"), default=None)
    p.add_argument("--scale", type=float, default=1.0, help="share of the cycle counts to run (timing)")
    p.add_argument("--hogs", default="0,1,2", help="busy processes beside the run, e.g. 0,1,2 (timing)")
    p.add_argument("--periods", default="1,2,5,10", help="SYNC periods in ms (timing)")
    p.add_argument("--jobs", type=int, default=200, help="real-time jobs per EPOS reading (epos)")
    p.add_argument("--readings", default="", help="epos: only these readings, e.g. reference,tpdo_latency")
    p.add_argument("--max-axes", type=int, default=30, help="capacity: stop above this many axes")
    p.add_argument("--runs", type=int, default=6, help="runs of each streaming priority (priority)")
    args = p.parse_args(argv or [])
    if args.only in (None, "timing"):
        timing(args.scale, [int(x) for x in args.hogs.split(",")], [int(x) for x in args.periods.split(",")])
    if args.only in (None, "capacity"):
        capacity(args.max_axes)
    if args.only in (None, "epos"):
        epos(args.jobs, [r for r in args.readings.split(",") if r])
    if args.only in (None, "priority"):
        priority(args.runs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
