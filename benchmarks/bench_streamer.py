"""Streamer runtime benchmarks (issue 4): virtual-time speed, and the most axes one process sustains
in real time with the simulated drives in the same process.

Run: `python -m benchmarks.bench_streamer [--max-axes N]`. Every ratio is measured in this run:
- virtual-time speed: seconds of motion / seconds of wall time, 6 axes, the default demo path
  (target >= 20x real time);
- real time at 10 ms SYNC: the demo path on N axes, N = 6, 12, 18, 24, 32, ...; an N passes when the
  job is DONE with no underflow warning, no fault and every axis' final position exact. Reports the
  largest N that passes and, for the first that does not, what broke (target >= 24). The streaming
  loop's own cost per SYNC is printed next to it, to show where the time goes.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Any


def virtual_speed(n_axes: int = 6, repeats: int = 3) -> dict[str, Any]:
    from streamer import demo

    cell, _, traj = demo.prepare(axes=n_axes)
    best = float("inf")
    motion_s = 0.0
    with tempfile.TemporaryDirectory() as d:
        for _ in range(repeats):
            from bus.sim.virtual import VirtualCell
            from streamer.runtime.virtual import VirtualRuntime
            from streamer.splice_planners import make_stop_planner

            vcell = VirtualCell(cell, initial_positions=demo.start_positions(cell, traj))
            rt = VirtualRuntime(cell, vcell=vcell)
            t0 = time.perf_counter()
            result = rt.run(traj, stop_planner=make_stop_planner(cell, traj), settle_s=0.0)
            wall = time.perf_counter() - t0
            motion_s = (result.last_sync - result.first_sync + 1) * cell.sync_period_s
            best = min(best, wall)
        del d
    return {"axes": n_axes, "motion_s": motion_s, "wall_s": best, "x_real_time": motion_s / best}


def realtime_run(n_axes: int, bitrate: int | None = None) -> dict[str, Any]:
    from streamer import demo

    cell, _, traj = demo.prepare(axes=n_axes, bitrate=bitrate)
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        try:
            report, _trace = demo.run_realtime(cell, traj, Path(d))
        except Exception as e:  # a timeout or bus error is a result here, not a crash of the benchmark
            return {"axes": n_axes, "ok": False, "why": f"{type(e).__name__}: {e}"}
        wall = time.perf_counter() - t0
    underflows = sum(a["underflow_warnings"] for a in report["axes"])
    final = [a["final_position_error_counts"] for a in report["axes"]]
    why = ""
    if report["result"] != "done":
        why = f"{report['result']}: {report.get('message', '')}"
    elif underflows:
        why = f"{underflows} underflow warnings"
    elif any(f != 0 for f in final):
        why = f"final position errors {final}"
    return {"axes": n_axes, "ok": not why, "why": why, "wall_s": wall, "bus_load_peak": report["bus_load_peak"],
            "min_fifo": min((a["min_fifo"] or 0) for a in report["axes"])}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--max-axes", type=int, default=48)
    args = parser.parse_args(argv)
    v = virtual_speed()
    print("streamer runtime benchmarks")
    print(f"  virtual time, {v['axes']} axes: {v['motion_s']:.2f} s of motion in {v['wall_s']:.3f} s wall = "
          f"{v['x_real_time']:.1f}x real time (target >= 20x)")
    print("  real time, 10 ms SYNC, simulated drives in the same process:")
    for label, bitrate in (("1 Mbit/s budget (a real CAN bus)", None),
                           ("bus budget lifted to 10 Mbit/s (the virtual bus has no bit rate: this "
                            "measures the process, not the wire)", 10_000_000)):
        print(f"   {label}")
        best = 0
        for n in [6, 12, 18, 24, 32, 40, 48, 64]:
            if n > args.max_axes:
                break
            r = realtime_run(n, bitrate)
            if r["ok"]:
                best = n
                print(f"    {n:3d} axes: ok ({r['wall_s']:.1f} s wall, bus load peak {100 * r['bus_load_peak']:.1f}% "
                      f"of the budget's bit rate, min FIFO {r['min_fifo']})")
            else:
                print(f"    {n:3d} axes: BREAKS: {r['why']}")
                break
        print(f"    most axes sustained: {best} (target >= 24)")

if __name__ == "__main__":
    main()
