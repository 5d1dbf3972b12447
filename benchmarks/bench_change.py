"""Changing a running motion (issue 15): how soon a change acts, against the lead time, and what planning one
costs, against planning a stop.

Run: `python -m benchmarks.bench_change`. In virtual time on configs/demo.toml's six simulated EPOS drives
(10 ms SYNC): a 6-axis move, and at several moments of it a change to a new target (buffer "aborting").
- reaction: from the SYNC at which the core takes the request to the first ms of the new plan (the change
  acts after what is already queued), in ms of motion, for leads of 200 (the default), 100, 50 and 30 ms;
  printed with the ratio to the lead. The feeders keep (repair_syncs + underflow watermark) segments
  queued whatever the lead, so with the move planned as usual (segments up to 255 ms: the baseline) the
  lead changes nothing; planned with its segments bounded for the lead
  (`StreamerSettings.segment_cap_ms`, `plan_job(max_segment_ms=...)`) the reaction follows the lead, at
  the cost of more PVT points per second (printed).
- planning: wall time of `plan_change_from_wire` (ruckig to a target + the PVT encoding), against
  `plan_stop_from_wire` (the stop a cancel plans) from the same states, the baseline, measured in this run.
"""

from __future__ import annotations

import dataclasses
import statistics
import time
from pathlib import Path

import numpy as np

from bus.sim.virtual import VirtualCell
from planner.config import load_cell
from planner.job import job_from_dict
from planner.motion.stop import plan_change_from_wire, plan_stop_from_wire
from planner.plan import plan_job
from streamer import demo
from streamer.core.coordinator import Coordinator
from streamer.core.plan_source import Change
from streamer.core.settings import StreamerSettings
from streamer.runtime.virtual import VirtualRuntime
from streamer.splice_planners import ChangePlanner, make_stop_planner

ROOT = Path(__file__).resolve().parent.parent
AXES = ["j1", "j2", "j3", "j4", "j5", "j6"]
FIRST = [2.0, -1.5, 1.8, -1.0, 1.2, -0.8]
SECOND = [-0.5, 0.6, -0.8, 0.4, -0.3, 0.2]
LEADS = (200, 100, 50, 30)
AT_MS = (200, 400, 600)


def reaction(lead_ms: int, at_ms: int, bounded: bool) -> tuple[float, float, float]:
    """(reaction ms, planning s, PVT points per s) of one change at `at_ms` into the move, with the job's
    lead `lead_ms`; `bounded`: the move planned with segments bounded for that lead (segment_cap_ms)."""
    cell = load_cell(ROOT / "configs" / "demo.toml")
    settings = StreamerSettings.from_cell(cell, lead_ms=lead_ms)
    cap = settings.segment_cap_ms() if bounded else None
    traj = plan_job(job_from_dict({"kind": "move", "axes": AXES, "target": FIRST}, cell), cell, start=[0.0] * 6,
                    max_segment_ms=cap)
    rt = VirtualRuntime(cell, vcell=VirtualCell(cell, initial_positions=demo.start_positions(cell, traj)))
    rt.ensure_readings()
    rt.settings = dataclasses.replace(rt.settings, lead_ms=lead_ms)
    planners: list[ChangePlanner] = []

    def feed(core: Coordinator, sync: int, t: float) -> list[object]:
        s = core.start_sync
        if planners or s is None or (sync - s) * cell.sync_period_ms < at_ms:
            return []
        planners.append(ChangePlanner(cell, traj, dict(zip(AXES, SECOND, strict=True))))
        return [Change(t, planners[0])]

    result = rt.run(traj, stop_planner=make_stop_planner(cell, traj), feed=feed)
    core = result.coordinator
    (res,) = core.change_results
    assert res.accepted and res.time_ms is not None and res.sync is not None and core.start_sync is not None, res
    fed_ms = (res.sync - core.start_sync) * cell.sync_period_ms
    return float(res.time_ms - fed_ms), planners[0].planning_s, traj.n_points / traj.duration_s


def planning(repeats: int = 20) -> tuple[float, float]:
    """Median wall time (s) of a change and of a stop planned from the same mid-motion states."""
    cell = load_cell(ROOT / "configs" / "demo.toml")
    traj = plan_job(job_from_dict({"kind": "move", "axes": AXES, "target": FIRST}, cell), cell, start=[0.0] * 6)
    knots = np.linspace(2, traj.n_segments - 2, repeats).astype(int)
    change_s, stop_s = [], []
    for k in knots:
        p, v = traj.positions[:, k].tolist(), traj.velocities[:, k].tolist()
        t0 = time.perf_counter()
        plan_stop_from_wire(cell, AXES, p, v, None, tolerance_counts=traj.tolerance_counts)
        t1 = time.perf_counter()
        plan_change_from_wire(cell, AXES, p, v, None, SECOND, tolerance_counts=traj.tolerance_counts)
        t2 = time.perf_counter()
        stop_s.append(t1 - t0)
        change_s.append(t2 - t1)
    return statistics.median(change_s), statistics.median(stop_s)


def main() -> int:
    print("change reaction (virtual time, 6 EPOS axes, 10 ms SYNC): request -> first ms of the new plan")
    print("  plan: the move as planned for any lead (the baseline), or with its segments bounded for the lead")
    print(f"{'lead ms':>8} {'plan':>9} {'reaction ms (at ' + ', '.join(map(str, AT_MS)) + ' ms)':>34} {'mean':>7} "
          f"{'/ lead':>7} {'points/s':>9}")
    for lead in LEADS:
        for bounded in (False, True):
            runs = [reaction(lead, at, bounded) for at in AT_MS]
            values = [r[0] for r in runs]
            mean = statistics.mean(values)
            print(f"{lead:>8} {'bounded' if bounded else 'as is':>9} {', '.join(f'{v:.0f}' for v in values):>34} "
                  f"{mean:>7.1f} {mean / lead:>7.2f} {runs[0][2]:>9.1f}")
    change_s, stop_s = planning()
    print(f"planning (median of 20 states, 6 axes): change {1000 * change_s:.2f} ms, stop (baseline) "
          f"{1000 * stop_s:.2f} ms, ratio {change_s / stop_s:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
