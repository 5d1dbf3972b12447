"""Travel-command planning time (planner/travel.py, planner/stop.py), as ratios against the planner's own
stop measured in the same run (`python -m benchmarks travel`, part of `make bench`).

The streaming side plans these while a motion runs, from the state at the end of what is queued: the
time they take is part of the reaction time of a change. The baseline is `plan_stop_from_wire` from the
same state (what a cancel already plans there). Medians of interleaved runs on the demo cell, 6 axes,
from states near full speed in the middle of a move:

- extend_velocity (the next 2 s cruise chunk of an endless move): target <= 0.5 x the stop;
- plan_velocity from the moving state (a change into velocity mode): target <= 3 x the stop;
- plan_emergency_stop_from_wire, median over 20 random states: target <= 3 x the stop (its steep jerk
  makes the encoder retry on some states; also printed: its duration over the normal stop's);
- an additive move planned with plan_job against the same move given as an absolute target: target
  <= 1.1 (resolving the target costs nothing next to planning).
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from planner.config import load_cell
from planner.job import job_from_dict
from planner.plan import plan_job, warm_up
from planner.stop import plan_emergency_stop_from_wire, plan_stop_from_wire
from planner.travel import MotionState, extend_velocity, plan_velocity

ROOT = Path(__file__).resolve().parent.parent
RUNS = 15
EMERGENCY_STATES = 20


def _median_ms(fns: Sequence[Callable[[], Any]], runs: int) -> list[float]:
    """Median wall time (ms) of each function, run interleaved so load on the machine hits all alike."""
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(runs):
        for i, fn in enumerate(fns):
            t0 = time.perf_counter()
            fn()
            times[i].append((time.perf_counter() - t0) * 1000.0)
    return [statistics.median(t) for t in times]


def _mark(ok: bool) -> str:
    return "ok" if ok else "MISS"


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    runs = RUNS if not argv else int(argv[0])
    warm_up()
    cell = load_cell(ROOT / "configs" / "demo.toml")
    axes = list(cell.axis_names())
    move = plan_job(job_from_dict({"kind": "move", "axes": axes, "target": [2.5, -1.8, 2.2, -3.0, 1.9, 2.0]}, cell),
                    cell, start=[0.0] * 6)
    k = int(np.argmax(np.abs(move.velocities[0])))
    state = MotionState.from_knot(move, k)
    velocity_job = job_from_dict({"kind": "move", "axes": axes, "mode": "velocity",
                                  "velocity": [-0.5, 0.4, -0.3, 0.6, -0.2, 0.1]}, cell)
    endless = plan_velocity(velocity_job, cell, MotionState.at_rest([0] * 6))
    here = (move.positions[:, -1] / move.counts_per_unit).tolist()
    offset = [0.1, -0.1, 0.1, -0.1, 0.1, -0.1]
    additive = job_from_dict({"kind": "move", "axes": axes, "mode": "additive", "target": offset}, cell)
    absolute = job_from_dict({"kind": "move", "axes": axes,
                              "target": (np.array(here) + np.array(offset)).tolist()}, cell)

    stop_ms, ext_ms, vel_ms, add_ms, abs_ms = _median_ms([
        lambda: plan_stop_from_wire(cell, axes, state.positions_counts, state.velocities_rpm, state.accelerations),
        lambda: extend_velocity(endless),
        lambda: plan_velocity(velocity_job, cell, state),
        lambda: plan_job(additive, cell, start=here, last_target=here),
        lambda: plan_job(absolute, cell, start=here),
    ], runs)
    # the emergency stop from EMERGENCY_STATES random states (velocities and accelerations up to the limits):
    # its steep jerk makes the encoder work harder on some of them (planner/stop.py)
    rng = np.random.default_rng(5)
    cpu = move.counts_per_unit
    conv = move.counts_per_rev / 60000.0
    vmax = np.array([cell.axis(a).velocity for a in axes])
    amax = np.array([cell.axis(a).acceleration for a in axes])
    ratios, durations = [], []
    for _ in range(EMERGENCY_STATES):
        v = np.round(rng.uniform(-1, 1, 6) * vmax * cpu / 1000.0 / conv).astype(np.int64).tolist()
        a = (rng.uniform(-1, 1, 6) * amax * cpu / 1.0e6).tolist()
        p = [0] * 6
        base, emcy = _median_ms([lambda: plan_stop_from_wire(cell, axes, p, v, a),  # noqa: B023
                                 lambda: plan_emergency_stop_from_wire(cell, axes, p, v, a)], 3)  # noqa: B023
        ratios.append(emcy / base)
        durations.append(plan_emergency_stop_from_wire(cell, axes, p, v, a).duration_ms
                         / plan_stop_from_wire(cell, axes, p, v, a).duration_ms)
    emcy_ratio = statistics.median(ratios)
    rows = [
        ("extend_velocity (2 s chunk) / stop", ext_ms, stop_ms, 0.5),
        ("plan_velocity from motion / stop", vel_ms, stop_ms, 3.0),
        ("additive move / absolute move", add_ms, abs_ms, 1.1),
    ]
    print(f"{'planning time (6 axes, demo cell)':38} {'ms':>8} {'baseline ms':>11} {'ratio':>7} {'target':>7}")
    out: dict[str, Any] = {}
    for name, ms, base, target in rows:
        ratio = ms / base
        print(f"{name:38} {ms:8.2f} {base:11.2f} {ratio:7.2f} {'<=' + format(target, 'g'):>7} {_mark(ratio <= target)}")
        out[name] = {"ms": ms, "baseline_ms": base, "ratio": ratio, "target": target}
    print(f"{'emergency stop / stop, median of ' + str(EMERGENCY_STATES):38} {'':8} {'':11} {emcy_ratio:7.2f} "
          f"{'<=3':>7} {_mark(emcy_ratio <= 3.0)}  (worst {max(ratios):.2f}; its duration / the stop's: median "
          f"{statistics.median(durations):.2f})")
    out["emergency stop / stop"] = {"ratio": emcy_ratio, "worst": max(ratios), "target": 3.0,
                                    "duration_ratio": statistics.median(durations)}
    chunk = extend_velocity(endless)
    print(f"a 2 s cruise chunk: {chunk.n_points} PVT points per axis ({chunk.n_points / chunk.duration_s:.1f} per s)")
    return out


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])
