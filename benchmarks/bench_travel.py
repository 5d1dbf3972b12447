"""Travel-command planning time (planner/motion/travel.py, planner/motion/stop.py), as ratios against the planner's own
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

And a velocity job streamed (10 s in virtual time, 3 axes of the demo cell, the extender timed on the side):
- the queue margin the extension keeps: the least the stream reached ahead of the drives, against the
  `extend_need_ms` the core must keep (target >= 1), and the least FIFO fill against the underflow
  watermark (target >= 1);
- the core's own part of an extension (on the SYNC thread: validating, packing and appending the chunk, the
  dry run) against planning the chunk (what the real-time runtime moves to a worker thread): target <= 1;
  also printed against the 10 ms SYNC period.
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
from planner.motion.stop import plan_emergency_stop_from_wire, plan_stop_from_wire
from planner.motion.travel import MotionState, extend_velocity, plan_velocity
from planner.plan import plan_job, warm_up

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
    # its steep jerk makes the encoder work harder on some of them (planner/motion/stop.py)
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
    out.update(_velocity_stream())
    return out


def _velocity_stream() -> dict[str, Any]:
    """10 s of a velocity job on 3 axes in virtual time: the queue margin and the core's part of an extension."""
    from bus.events import Cancel
    from bus.sim.virtual import VirtualCell
    from streamer import demo
    from streamer.core.coordinator import Coordinator
    from streamer.runtime.virtual import VirtualRuntime
    from streamer.splice_planners import make_stop_planner

    cell = load_cell(ROOT / "configs" / "demo.toml")
    axes = ["j1", "j2", "j3"]
    job = job_from_dict({"kind": "move", "axes": axes, "mode": "velocity", "velocity": [0.1, -0.08, 0.09]}, cell)
    traj = plan_job(job, cell, start=[0.0] * 3)
    vcell = VirtualCell(cell, initial_positions=demo.start_positions(cell, traj))
    rt = VirtualRuntime(cell, vcell=vcell)
    plan_s: list[float] = []
    keep_s: list[float] = []
    ahead: list[float] = []

    def extender(t: Any) -> Any:
        t0 = time.perf_counter()
        chunk = extend_velocity(t)
        plan_s.append(time.perf_counter() - t0)
        return chunk

    def on_sync(core: Coordinator, sync: int) -> None:
        if "_keep_open" not in core.__dict__:  # time the core's extension step (instance attribute wraps it)
            inner = core._keep_open

            def timed(m: int, t: float) -> None:
                n, t0 = core.extensions, time.perf_counter()
                inner(m, t)
                if core.extensions > n:
                    keep_s.append(time.perf_counter() - t0 - sum(plan_s[-(core.extensions - n):]))

            core._keep_open = timed  # type: ignore[method-assign]
        if core.start_sync is not None and core.open_ended and sync > core.start_sync:
            ahead.append(core.stream_duration_ms - (sync - core.start_sync) * cell.sync_period_ms)

    def feed(core: Coordinator, sync: int, t: float) -> list[object]:
        s = core.start_sync
        return [Cancel(t)] if s is not None and (sync - s) * cell.sync_period_ms == 10_000 else []

    result = rt.run(traj, stop_planner=make_stop_planner(cell, traj), on_sync=on_sync, feed=feed, extender=extender)
    core = result.coordinator
    need = core.extend_need_ms
    min_fill = min(a.min_fifo for a in core.telemetry() if a.min_fifo is not None)
    u = rt.settings.underflow_watermark
    keep_ms = statistics.median(keep_s) * 1000.0
    plan_ms = statistics.median(plan_s) * 1000.0
    print(f"velocity job, 10 s, 3 axes: {core.extensions} chunks appended")
    print(f"{'least stream ahead / extend_need_ms':38} {min(ahead):8.0f} {need:11.0f} {min(ahead) / need:7.2f} "
          f"{'>=1':>7} {_mark(min(ahead) >= need)}  (most {max(ahead):.0f} ms)")
    print(f"{'least FIFO fill / underflow watermark':38} {min_fill:8d} {u:11d} {min_fill / u:7.2f} {'>=1':>7} "
          f"{_mark(min_fill >= u)}")
    print(f"{'core part of an extension / planning':38} {keep_ms:8.2f} {plan_ms:11.2f} {keep_ms / plan_ms:7.2f} "
          f"{'<=1':>7} {_mark(keep_ms <= plan_ms)}  (planning = {plan_ms / cell.sync_period_ms:.0%} of a "
          f"{cell.sync_period_ms} ms SYNC period, the core's part {keep_ms / cell.sync_period_ms:.0%})")
    return {"velocity stream": {"chunks": core.extensions, "least_ahead_ms": min(ahead), "extend_need_ms": need,
                                "least_fifo": min_fill, "underflow_watermark": u, "core_ms": keep_ms,
                                "planning_ms": plan_ms}}


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])
