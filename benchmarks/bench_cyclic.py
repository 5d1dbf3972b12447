"""Drives fed one set point per SYNC (issue 12): bus capacity, the drives' own interpolation, set point timing.

Run: `python -m benchmarks.bench_cyclic [--only capacity|deviation|timing] [--jobs N]`. Every figure is
measured in this run, next to its baseline:
- capacity: the most XtrapulsPac axes (node ids 1..63) at 2, 5 and 10 ms SYNC on 1 Mbit/s within 70 % of
  the bit rate, each with an RPDO of its own (the baseline) against multiplexed frames (4 positions, or 2
  positions with velocities in PV): the bit-accurate budget (bus/budget.py) gives the candidate, and the
  virtual-time bus (every frame arbitrated and timed at its worst-case length) runs a move on that many
  axes to DONE and measures the busiest cycle;
- deviation: the demo path on configs/xtrapuls.toml's axes, per axis, the drive's own interpolation at 10 ms
  in each sub-mode (linear, PV, P3) against the EPOS PVT encoding of the same plan (the baseline), in counts
  at every ms (planner/encoding/cyclic.py, planner.encoding.hermite);
- timing: in real time (drives simulated in this process, python-can virtual bus), the share of set points
  that reached the bus less than 100 us before the SYNC that latches them (the XtrapulsPac's error 50), at
  2 and 10 ms, from the timestamps of bus.log.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from planner.config import AxisConfig, CellConfig, load_cell

ROOT = Path(__file__).resolve().parent.parent
XTRAPULS = ROOT / "configs" / "xtrapuls.toml"
DEMO_JOB = ROOT / "configs" / "jobs" / "demo-path.toml"
LAYOUTS = (  # (label, sub-mode, axes per multiplexed group; 0 = an RPDO per axis)
    ("own RPDO, positions (P3)", "p3", 0),
    ("multiplexed, 4 positions per frame (P3)", "p3", 4),
    ("own RPDO, PV", "pv", 0),
    ("multiplexed, 2 positions + velocities per frame (PV)", "pv", 2),
)


def _axis(base: AxisConfig, node: int, submode: str, group: int) -> AxisConfig:
    return dataclasses.replace(base, name=f"a{node}", node_id=node, ip_submode=submode, mux_group=group)


def capacity_cell(n: int, period_ms: int, submode: str, per_group: int) -> CellConfig:
    cell = load_cell(XTRAPULS)
    base = next(a for a in cell.axes if a.name == "j3")  # 2 rad/s: a 16-bit velocity needs a slow move
    axes = tuple(_axis(base, k, submode, (k - 1) // per_group + 1 if per_group else 0) for k in range(1, n + 1))
    return dataclasses.replace(cell, axes=axes, sync_period_ms=period_ms)


def budget_fits(cell: CellConfig) -> bool:
    from bus.budget import cell_traffic, cycle_budget

    cyclic, bits = cell_traffic(cell)
    b = cycle_budget(len(cell.axes), cell.sync_period_ms, cell.bus.bitrate, 0.7, cell.drive.heartbeat_ms,
                     cyclic_nodes=cyclic, setpoint_bits=bits)
    return b.streamer_bits >= 0


def virtual_run(cell: CellConfig) -> dict[str, Any]:
    """A 0.2 rad move of every axis (slow enough for 16-bit velocities) in virtual time: DONE? busiest cycle?"""
    from planner.job import job_from_dict
    from planner.plan import plan_job
    from streamer import demo

    names = list(cell.axis_names())
    job = job_from_dict({"kind": "move", "axes": names, "target": [0.2] * len(names), "velocity_scale": 0.3},
                        cell)
    traj = plan_job(job, cell)
    with tempfile.TemporaryDirectory() as d:
        report, _ = demo.run_fast(cell, traj, Path(d))
    return {"ok": report["result"] == "done", "load": report["bus_load_peak"], "why": report.get("message", "")}


def capacity() -> None:
    print("capacity: XtrapulsPac axes on 1 Mbit/s within 70 % (node ids 1..63), budget then virtual-time run")
    for period in (2, 5, 10):
        for label, submode, per_group in LAYOUTS:
            n = 0
            while n < 63 and budget_fits(capacity_cell(n + 1, period, submode, per_group)):
                n += 1
            # the virtual bus must agree: DONE and the busiest cycle <= 70 %, else one fewer
            while n > 0:
                r = virtual_run(capacity_cell(n, period, submode, per_group))
                if r["ok"] and r["load"] <= 0.7:
                    break
                n -= 1
            shown = f"{n} axes, busiest cycle {100 * r['load']:.1f} %" if n else "none"
            print(f"  {period:2d} ms, {label}: {shown}" + (" (the node id limit)" if n == 63 else ""))


def deviation() -> None:
    from planner.encoding import cyclic
    from planner.job import load_job
    from planner.plan import plan_job

    cell = load_cell(XTRAPULS)
    epos = dataclasses.replace(cell, axes=tuple(dataclasses.replace(a, profile="epos-ipm", mux_group=0)
                                                for a in cell.axes))
    traj = plan_job(load_job(DEMO_JOB, epos), epos)  # one plan; the EPOS encoding of it is the baseline
    period = cell.sync_period_ms
    print(f"deviation on demo-path ({XTRAPULS.name}'s axes, {traj.duration_s:.2f} s), counts, worst of both "
          f"roundings, at every ms; cyclic sub-modes at {period} ms SYNC:")
    print(f"  {'axis':5s} {'EPOS PVT':>9s} {'linear':>7s} {'PV':>5s} {'P3':>5s}")
    worst = dict.fromkeys(("pvt", "linear", "pv", "p3"), 0)
    for i, name in enumerate(traj.axis_names):
        row = {"pvt": traj.stats[i].max_deviation_counts}
        for m in ("linear", "pv", "p3"):
            sp = cyclic.sample(traj.plan.positions[i], traj.plan.velocities[i], period, pv=m == "pv")
            row[m] = cyclic.deviation(traj.plan.positions[i], sp, m)[0]
        for k, v in row.items():
            worst[k] = max(worst[k], v)
        print(f"  {name:5s} {row['pvt']:9d} {row['linear']:7d} {row['pv']:5d} {row['p3']:5d}")
    print(f"  {'max':5s} {worst['pvt']:9d} {worst['linear']:7d} {worst['pv']:5d} {worst['p3']:5d}")


def timing(jobs: int) -> None:
    import can

    from bus.cob import SYNC_COB_ID
    from bus.families import setpoint_slots
    from planner.job import load_job
    from planner.plan import plan_job
    from streamer import demo
    from streamer.report import decode_setpoints

    print("timing: set points on the bus less than 100 us before the SYNC that latches them (real time, "
          "drives in this process, python-can virtual bus)")
    for period, n_axes in ((2, 3), (10, 6)):  # 2 ms: the 3 axes the bus carries (capacity above)
        cell = dataclasses.replace(load_cell(XTRAPULS).with_axes(n_axes), sync_period_ms=period)
        job = demo.fit_job_to_cell(load_job(DEMO_JOB, load_cell(XTRAPULS)), cell, repeat=True)
        try:
            traj = plan_job(job, cell)
        except Exception as e:  # the drives' interpolation at 2 ms is finer, never coarser
            print(f"  {period} ms: the demo does not plan ({e})")
            continue
        late = total = missing = 0
        margins: list[float] = []
        for _ in range(jobs):
            with tempfile.TemporaryDirectory() as d:
                report, _ = demo.run_realtime(cell, traj, Path(d))
                if report["result"] != "done":
                    print(f"  {period} ms, {n_axes} axes: a job ended {report['result']}: {report.get('message')}")
                syncs = [m.timestamp for m in can.LogReader(str(Path(d) / "bus.log"))
                         if m.arbitration_id == SYNC_COB_ID]
                slots = setpoint_slots(cell.axes)
                start = {n: int(traj.positions[i, 0]) for i, n in enumerate(traj.node_ids)}
                sent = decode_setpoints(Path(d) / "bus.log", slots, start, since_s=report["job_start_s"])
            sync_t = np.array(syncs)
            leaders = {s.members[0] for s in slots.values()}
            for node, rows in sent.items():
                if node not in leaders or not rows:
                    continue  # a multiplexed frame counts once
                times = np.array([r[0] for r in rows])
                # every SYNC interval from the first set point to the last must hold one, at least 100 us
                # before the SYNC that ends it: a frame sent after its SYNC counts as missing for that
                # cycle (the drive's error 50), not as an early one for the next
                k = np.searchsorted(sync_t, times, side="right")  # the SYNC that latches each frame
                k = k[k < sync_t.size]
                for j in range(int(k.min()), int(k.max()) + 1):
                    total += 1
                    in_cycle = times[: k.size][k == j]
                    if in_cycle.size == 0:
                        late += 1
                        missing += 1
                        continue
                    margin = sync_t[j] - float(in_cycle.max())
                    margins.append(margin)
                    late += margin < 100e-6
        if total:
            share = 100.0 * late / total
            print(f"  {period:2d} ms, {n_axes} axes: {late} of {total} cycles without a set point at least 100 us "
                  f"before their SYNC ({share:.3f} %; {missing} with none at all); margin p1 "
                  f"{1e3 * np.percentile(margins, 1):.2f} ms, median {1e3 * np.median(margins):.2f} ms")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--only", choices=("capacity", "deviation", "timing"), default=None)
    p.add_argument("--jobs", type=int, default=3, help="real-time jobs per SYNC period (timing)")
    args = p.parse_args(argv or [])
    if args.only in (None, "deviation"):
        deviation()
    if args.only in (None, "capacity"):
        capacity()
    if args.only in (None, "timing"):
        timing(args.jobs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(__import__("sys").argv[1:]))
