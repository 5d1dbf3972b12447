"""Soak (issue 7 section 4): hours of virtual time of back-to-back jobs on 6 axes.

Run: `python -m benchmarks.bench_soak [--hours H] [--axes N] [--tracemalloc]` (default 8 hours of
virtual time, or PVT_SOAK_HOURS). The simulated drives, the virtual bus and the streamer core run one
job after the other in one `VirtualRuntime` (the same objects for the whole soak, as in a long-running
`pvt serve`): the demo pick-and-place path, a jerk-limited move out, a move home, a move to the path's start, again
and again (each planned from the exact end of the previous one).
Reports, against the targets:
- memory growth: resident set size (with --tracemalloc, the Python heap instead: tracemalloc's own
  records inflate the RSS) at the end versus after the warm-up (the first 5% of the virtual time, at
  least 2 jobs), both taken after the last job of a cycle: target < 5%;
- faults: jobs that did not end DONE, plus every EMCY a drive sent: target 0;
- jobs per hour of virtual time, and how fast the soak ran (x real time).
Prints one line per tenth of the run so a long soak shows progress.
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
import time
import tracemalloc
from collections import Counter
from typing import Any


def rss_bytes() -> int:
    """Current resident set size (Linux /proc; falls back to the peak from getrusage)."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        import resource

        return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


def build_jobs(n_axes: int) -> tuple[Any, list[Any]]:
    """The cell and the cycle of trajectories, each planned from the exact end (counts) of the previous."""
    from planner.job import job_from_dict
    from planner.plan import plan_job
    from streamer import demo

    cell, _, path = demo.prepare(axes=n_axes)
    names = list(path.axis_names)
    out_pos = [0.3 * (1 if i % 2 else -1) for i in range(n_axes)]
    move_out = plan_job(job_from_dict({"kind": "move", "axes": names, "target": out_pos}, cell), cell,
                        start=end_of(path))
    move_home = plan_job(job_from_dict({"kind": "move", "axes": names, "target": [0.0] * n_axes}, cell), cell,
                         start=end_of(move_out))
    back = plan_job(job_from_dict({"kind": "move", "axes": names,
                                   "target": list(path.positions[:, 0] / path.counts_per_unit)}, cell), cell,
                    start=end_of(move_home))
    return cell, [path, move_out, move_home, back]


def end_of(traj: Any) -> list[float]:
    """Where a trajectory leaves the axes, user units (exact counts / counts per unit)."""
    return [float(p) for p in traj.positions[:, -1] / traj.counts_per_unit]


def home_from_here(cell: Any, vcell: Any, first: Any) -> Any:
    """After a failed job: a move from where the drives stand back to the first job's start."""
    from planner.job import job_from_dict
    from planner.plan import plan_job

    names = list(first.axis_names)
    here = [vcell.model(a.node_id).position_demand / a.counts_per_unit for a in cell.axes if a.name in names]
    target = list(first.positions[:, 0] / first.counts_per_unit)
    return plan_job(job_from_dict({"kind": "move", "axes": names, "target": target}, cell), cell, start=here)


def soak(hours: float, n_axes: int = 6, *, use_tracemalloc: bool = False, quiet: bool = False) -> dict[str, Any]:
    from bus.sim.virtual import VirtualCell
    from streamer.core import JobState
    from streamer.demo import start_positions
    from streamer.runtime.virtual import VirtualRuntime
    from streamer.splice_planners import make_stop_planner

    if use_tracemalloc:
        tracemalloc.start()  # before anything is built: the heap baseline is the whole live state
    cell, jobs = build_jobs(n_axes)
    stops = [make_stop_planner(cell, t) for t in jobs]
    vcell = VirtualCell(cell, initial_positions=start_positions(cell, jobs[0]))
    rt = VirtualRuntime(cell, vcell=vcell)
    target_s = hours * 3600.0
    warmup_s = max(0.05 * target_s, 2 * sum(t.duration_s for t in jobs[:2]))
    outcomes: Counter[str] = Counter()
    failures: list[str] = []
    base_rss = base_heap = 0
    warm = False
    next_report = target_s / 10
    wall0 = time.perf_counter()
    n = 0
    k = 0
    # whole cycles of jobs, and memory taken at the same point of a cycle (after its last job, with
    # nothing of a job kept but the runtime's last trace), so baseline and end compare like with like
    while rt.now < target_s or k % len(jobs) != 0:
        traj, stop = jobs[k % len(jobs)], stops[k % len(jobs)]
        result = rt.run(traj, stop_planner=stop, settle_s=1.0)
        core = result.coordinator
        n += 1
        k += 1
        key = core.state.value if core.outcome is None or core.outcome.code is None else core.outcome.code
        outcomes[key] += 1
        if core.state is not JobState.DONE:
            if len(failures) < 20:
                failures.append(f"job {n} at {rt.now:.1f} s: {core.outcome}")
            home = home_from_here(cell, vcell, jobs[0])  # a fault: bring the axes back and go on
            rt.run(home, stop_planner=make_stop_planner(cell, home), settle_s=1.0)
            k = 0
        del result, core
        if not warm and rt.now >= warmup_s and k % len(jobs) == 0:
            gc.collect()
            warm = True
            base_rss = rss_bytes()
            base_heap = tracemalloc.get_traced_memory()[0] if use_tracemalloc else 0
        if not quiet and rt.now >= next_report:
            next_report += target_s / 10
            print(f"  {rt.now / 3600:5.2f} h virtual, {n} jobs, {time.perf_counter() - wall0:7.1f} s wall, "
                  f"rss {rss_bytes() / 2**20:.1f} MiB", flush=True)
    wall = time.perf_counter() - wall0
    gc.collect()
    end_rss = rss_bytes()
    end_heap = tracemalloc.get_traced_memory()[0] if use_tracemalloc else 0
    if use_tracemalloc:
        tracemalloc.stop()
    emcy = {node: [hex(f.code) for f in m.fault_log] for node, m in vcell.models.items() if m.fault_log}
    virtual_h = rt.now / 3600.0
    return {
        "axes": n_axes,
        "virtual_hours": virtual_h,
        "jobs": n,
        "jobs_per_hour": n / virtual_h if virtual_h else 0.0,
        "outcomes": dict(outcomes),
        "faults": sum(v for k, v in outcomes.items() if k != "done") + sum(len(v) for v in emcy.values()),
        "failures": failures,
        "drive_emcys": emcy,
        "wall_s": wall,
        "x_real_time": rt.now / wall if wall else 0.0,
        "rss_base_mib": base_rss / 2**20,
        "rss_end_mib": end_rss / 2**20,
        "rss_growth": (end_rss - base_rss) / base_rss if base_rss else 0.0,
        "heap_base_mib": base_heap / 2**20 if use_tracemalloc else None,
        "heap_end_mib": end_heap / 2**20 if use_tracemalloc else None,
        "heap_growth": (end_heap - base_heap) / base_heap if use_tracemalloc and base_heap else None,
        "frames": rt.counters["frames"],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_soak", description=__doc__.split("\n")[0])
    parser.add_argument("--hours", type=float, default=float(os.environ.get("PVT_SOAK_HOURS", "8")),
                        help="virtual hours to soak (default 8, or PVT_SOAK_HOURS)")
    parser.add_argument("--axes", type=int, default=6)
    parser.add_argument("--tracemalloc", action="store_true", help="also measure the Python heap (slower)")
    args = parser.parse_args(argv if argv is not None else [])
    print(f"soak: {args.hours:g} h of virtual time, {args.axes} axes, back-to-back jobs", flush=True)
    r = soak(args.hours, args.axes, use_tracemalloc=args.tracemalloc)
    # under tracemalloc the RSS also holds tracemalloc's own records: judge the heap then
    ok_mem = r["rss_growth"] < 0.05 if r["heap_growth"] is None else r["heap_growth"] < 0.05
    print(f"virtual time      {r['virtual_hours']:.2f} h in {r['wall_s']:.0f} s wall "
          f"({r['x_real_time']:.0f}x real time), {r['frames']} frames")
    print(f"jobs              {r['jobs']} ({r['jobs_per_hour']:.0f} per hour), outcomes {r['outcomes']}")
    why = "" if r["faults"] == 0 else ": " + "; ".join(r["failures"][:3])
    print(f"faults            {r['faults']} (target 0){why}")
    print(f"memory (RSS)      {r['rss_base_mib']:.1f} MiB after warm-up -> {r['rss_end_mib']:.1f} MiB "
          f"({r['rss_growth']:+.2%}, target < 5%)")
    if r["heap_growth"] is not None:
        print(f"memory (heap)     {r['heap_base_mib']:.2f} MiB -> {r['heap_end_mib']:.2f} MiB "
              f"({r['heap_growth']:+.2%}, target < 5%)")
    print("PASS" if ok_mem and r["faults"] == 0 else "FAIL")
    return 0 if ok_mem and r["faults"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
