"""Planner benchmark: encoding efficiency, duration against the optimum and planning latency, as ratios
against baselines measured in the same run (`python -m benchmarks planner`, part of `make bench`).

Two tables: every example job of configs/jobs/ plus a 20-waypoint 6-axis path, then a corpus of random
jobs of each kind (`--jobs`, default 200 per kind: paths, paths with sharp corners, moves, timed, pvt,
and small paths: 2-200 counts between waypoints, as in fine positioning).

- points / uniform: the encoding's PVT points over those of the coarsest uniform grid that meets the same
  tolerance on the same plan (planner/encoding/uniform.py: rounded values, checked at every ms). Target <= 1 for
  every job; <= 0.35 on moves and paths. `>1 (margins)` counts the jobs above the coarsest uniform grid
  that also keeps the planner's velocity/acceleration margins (what the property test guarantees).
- duration / optimum: paths against raw toppra on the same geometric path (the blended segments, or the
  spline for `geometry = "spline"`; one solve per run between exact stops): joint velocity and
  acceleration constraints, seidel, ParametrizeConstAccel, on the planner's own gridpoints with every
  interval halved (toppra's default gridpoints miss the small blends altogether and report a duration
  up to 30 % too short). Moves against ruckig's continuous optimum along the line. Target <= 1.02.
- planning time / raw toppra: plan + encode + verify (planner.plan_job) over raw toppra on the same
  path and gridpoints, CPU time of the thread (medians of interleaved runs for bench-20, with where
  plan_job's time goes: time-optimal solves (planner/motion/topp.py), chain fits, encodings, the rest; median, 90th
  percentile and worst of single runs for the corpus paths). Target <= 1.5.
- refused: the share of random jobs the planner rejects (every random job is feasible).
"""

from __future__ import annotations

import argparse
import logging
import statistics
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from planner.config import CellConfig, load_cell
from planner.encoding.encoder import Knots, planned_demand, reconstruct
from planner.encoding.uniform import coarsest_uniform
from planner.errors import PlanningError
from planner.job import (
    Job,
    PathData,
    effective_limits,
    job_from_dict,
    job_to_dict,
    path_tolerance,
    read_job_file,
    with_jerk_limited,
)
from planner.plan import _merge_close, axis_configs, axis_scales, lines_geometry, plan_job, snap, warm_up
from planner.trajectory import PvtTrajectory

ROOT = Path(__file__).resolve().parent.parent
LATENCY_RUNS = 11
KINDS = ("path", "path-sharp", "move", "timed", "pvt", "path-small")
DURATION_BANDS = ((0.0, 5.0), (5.0, 10.0), (10.0, 20.0), (20.0, 1.0e9))


def benchmark_path(cell: CellConfig, n_waypoints: int = 20, seed: int = 7, *, jerk_limited: bool | None = False) -> Job:
    """A deterministic 6-axis path of `n_waypoints` waypoints: a random walk inside the joint limits; the
    acceleration-only plan unless `jerk_limited` says otherwise (None: the default, jerk-limited)."""
    rng = np.random.default_rng(seed)
    lo = np.array([a.position_min for a in cell.axes]) * 0.6
    hi = np.array([a.position_max for a in cell.axes]) * 0.6
    wp = [np.zeros(len(cell.axes))]
    for _ in range(n_waypoints - 1):
        wp.append(np.clip(wp[-1] + rng.uniform(-0.45, 0.45, len(cell.axes)), lo, hi))
    data = {"kind": "path", "job_id": "bench-20", "axes": list(cell.axis_names()), "waypoints": np.array(wp).tolist()}
    return job_from_dict(with_jerk_limited(data, jerk_limited), cell)


def example_jobs(cell: CellConfig, jerk_limited: bool | None = False) -> list[tuple[str, Job]]:
    """The example jobs of configs/jobs/ by file name, their paths as the acceleration-only plan unless
    `jerk_limited` says otherwise (None: as the file has it)."""
    return [(p.name, job_from_dict(with_jerk_limited(read_job_file(p), jerk_limited), cell))
            for p in sorted((ROOT / "configs" / "jobs").iterdir())]


# ----------------------------------------------------------------------------------------------------
# baselines


def uniform_points(job: Job, cell: CellConfig, traj: PvtTrajectory, margins: bool = False) -> tuple[int, int]:
    scales = axis_scales(axis_configs(job.axes, cell), effective_limits(job, cell))
    first = Knots(np.array([0]), traj.positions[:, :1], traj.velocities[:, :1])
    return coarsest_uniform(traj.plan, scales, traj.tolerance_counts, first, margins)


def path_geometry(job: Job, cell: CellConfig) -> list[Any]:
    """The geometric path(s) the planner traverses for this path job (its runs between exact stops)."""
    from planner.encoding.encoder import segment_bounds
    from planner.motion.path import SplineGeometry

    assert isinstance(job.data, PathData)
    lim = effective_limits(job, cell)
    cfg = axis_configs(job.axes, cell)
    cpu = np.array([c.counts_per_unit for c in cfg])
    wp = _merge_close(np.array(job.data.waypoints, dtype=np.float64), cpu)
    wp[0], wp[-1] = snap(wp[0], cpu), snap(wp[-1], cpu)
    if job.data.geometry == "spline":
        return [SplineGeometry(wp, lim.velocity)]
    scales = axis_scales(cfg, lim)
    box = (np.array([c.position_min for c in cfg]), np.array([c.position_max for c in cfg]))
    runs, _chain = lines_geometry(
        wp, cpu, lim.velocity, lim.acceleration, path_tolerance(job, cell), job.tolerance_counts,
        segment_bounds(scales, float(job.tolerance_counts)), box, {},
    )
    return list(runs)


def raw_toppra(job: Job, cell: CellConfig, *, refine: bool = True) -> tuple[float, float]:
    """(CPU time s, duration s) of plain toppra on the job's geometric path (every run)."""
    from toppra.algorithm import TOPPRA
    from toppra.constraint import JointAccelerationConstraint, JointVelocityConstraint

    from planner.motion.topp import toppra_path

    lim = effective_limits(job, cell)
    vlim, alim = lim.velocity, lim.acceleration
    elapsed, duration = 0.0, 0.0
    for geom in path_geometry(job, cell):
        grid = geom.gridpoints()
        if refine:
            grid = np.unique(np.concatenate([grid, 0.5 * (grid[:-1] + grid[1:])]))
        constraints = [
            JointVelocityConstraint(np.vstack([-vlim, vlim]).T),
            JointAccelerationConstraint(np.vstack([-alim, alim]).T),
        ]
        t0 = time.thread_time()
        traj = TOPPRA(
            constraints, toppra_path(geom, geom.dof, geom.length), gridpoints=grid, solver_wrapper="seidel",
            parametrizer="ParametrizeConstAccel",
        ).compute_trajectory()
        elapsed += time.thread_time() - t0
        if traj is None:
            raise RuntimeError("raw toppra failed on a benchmark path")
        duration += float(traj.duration)
    return elapsed, duration


def optimum_s(job: Job, cell: CellConfig, traj: PvtTrajectory) -> float | None:
    if job.kind == "path" and "optimal_s" in traj.info:
        return raw_toppra(job, cell)[1]
    if job.kind == "move" and traj.info.get("line_optimal_s", 0.0) > 0.0:
        return float(traj.info["line_optimal_s"])
    return None


# ----------------------------------------------------------------------------------------------------
# random jobs (every one feasible: inside the limits, user timings within them)


def _axes(rng: np.random.Generator, cell: CellConfig, most: int = 6) -> list[str]:
    n = int(rng.integers(1, min(most, len(cell.axes)) + 1))
    return [str(a) for a in rng.permutation(cell.axis_names())[:n]]


def _inside(rng: np.random.Generator, cell: CellConfig, axes: Sequence[str], lo: float, hi: float) -> np.ndarray:
    mn = np.array([cell.axis(a).position_min for a in axes])
    mx = np.array([cell.axis(a).position_max for a in axes])
    out: np.ndarray = mn + (mx - mn) * rng.uniform(lo, hi, len(axes))
    return out


def random_job(kind: str, rng: np.random.Generator, cell: CellConfig) -> dict[str, Any]:
    if kind in ("path", "path-sharp"):
        axes = _axes(rng, cell)
        rows = int(rng.integers(3, 11))
        if kind == "path":
            wp = [_inside(rng, cell, axes, 0.15, 0.85) for _ in range(rows)]
        else:  # zig-zag: every corner turns by more than 120 degrees on the first axis pair
            wp = []
            for k in range(rows):
                p = _inside(rng, cell, axes, 0.15, 0.85)
                side = (0.1, 0.25) if k % 2 == 0 else (0.75, 0.9)
                edge = _inside(rng, cell, axes[:1], *side)
                p[0] = edge[0]
                wp.append(p)
        job: dict[str, Any] = {"kind": "path", "axes": axes, "waypoints": np.array(wp).tolist()}
    elif kind == "path-small":  # fine positioning: 2-200 counts between waypoints, either way on each axis
        axes = _axes(rng, cell, 3)
        rows = int(rng.integers(3, 40))
        cpu = np.array([cell.axis(a).counts_per_unit for a in axes])
        counts = np.exp(rng.uniform(np.log(2.0), np.log(200.0))) * rng.uniform(0.3, 1.0, (rows - 1, len(axes)))
        steps = rng.choice([-1.0, 1.0], size=(rows - 1, len(axes))) * counts / cpu
        wp = _inside(rng, cell, axes, 0.4, 0.6) + np.vstack([np.zeros(len(axes)), np.cumsum(steps, axis=0)])
        job = {"kind": "path", "axes": axes, "waypoints": wp.tolist()}
    elif kind == "move":
        axes = _axes(rng, cell)
        job = {
            "kind": "move", "axes": axes, "start": _inside(rng, cell, axes, 0.2, 0.8).tolist(),
            "target": _inside(rng, cell, axes, 0.1, 0.9).tolist(),
        }
    elif kind == "timed":
        axes = _axes(rng, cell)
        rows = int(rng.integers(2, 7))
        pos = [_inside(rng, cell, axes, 0.35, 0.65) for _ in range(rows)]
        vel = np.array([cell.axis(a).velocity for a in axes])
        acc = np.array([cell.axis(a).acceleration for a in axes])
        times = [0.0]
        for k in range(1, rows):
            dq = np.abs(pos[k] - pos[k - 1])
            need = float(np.max(np.maximum(3.0 * dq / vel, np.sqrt(20.0 * dq / acc))))
            times.append(round(times[-1] + need + float(rng.uniform(0.05, 0.6)), 4))
        job = {"kind": "timed", "axes": axes, "times": times, "positions": np.array(pos).tolist()}
    else:  # pvt rows sampled from a slowed-down straight move, so the rows respect the limits
        axes = _axes(rng, cell)
        move = job_from_dict(
            {"kind": "move", "axes": axes, "start": _inside(rng, cell, axes, 0.4, 0.6).tolist(),
             "target": _inside(rng, cell, axes, 0.3, 0.7).tolist(), "velocity_scale": 0.5,
             "acceleration_scale": 0.4},
            cell,
        )
        traj = plan_job(move, cell)
        step = int(rng.integers(25, 121))
        m = traj.duration_ms
        ticks = list(range(0, m, step))
        if len(ticks) > 1 and m - ticks[-1] < step // 2:
            ticks.pop()
        ticks.append(m)
        cpu = traj.counts_per_unit[:, None]
        pos = (traj.plan.positions[:, ticks] / cpu).T
        velo = (traj.plan.velocities[:, ticks] * 1000.0 / cpu).T
        velo[0] = 0.0
        velo[-1] = 0.0
        job = {"kind": "pvt", "axes": axes, "times": [t / 1000.0 for t in ticks], "positions": pos.tolist(),
               "velocities": velo.tolist()}
    if rng.random() < 0.3:
        job["tolerance_counts"] = int(rng.integers(1, 4))
    if job["kind"] in ("path", "move") and rng.random() < 0.3:
        job["velocity_scale"] = float(rng.uniform(0.3, 1.0))
    return job


# ----------------------------------------------------------------------------------------------------
# measurements


def measure(job: Job, cell: CellConfig) -> dict[str, Any]:
    t0 = time.thread_time()
    traj = plan_job(job, cell)
    elapsed = time.thread_time() - t0
    dt, uniform = uniform_points(job, cell, traj)
    _mdt, strict = uniform_points(job, cell, traj, margins=True)
    row: dict[str, Any] = {
        "kind": job.kind, "duration_s": traj.duration_s, "points": traj.n_points, "uniform_dt_ms": dt,
        "uniform_points": uniform, "efficiency": traj.n_points / uniform, "plan_s": elapsed,
        "efficiency_margins": traj.n_points / strict,
        "max_excess_pct": 100 * max(s.acceleration_excess_share for s in traj.stats),
        "time_scale": traj.info.get("time_scale", 1.0),
    }
    opt = optimum_s(job, cell, traj)
    if opt is not None and opt > 0:
        row["optimum_s"] = opt
        row["duration_ratio"] = traj.duration_s / opt
    if job.kind == "path":
        raw_s, _ = raw_toppra(job, cell, refine=False)
        row["toppra_ms"] = 1000 * raw_s
        row["time_ratio"] = elapsed / raw_s
    return row


def latency(cell: CellConfig, job: Job, runs: int = LATENCY_RUNS) -> dict[str, float]:
    """Median plan_job time against raw toppra's (interleaved runs), and where plan_job's time goes: its
    time-optimal solves, chain fits and encodings, timed by wrapping planner.motion.topp.solve,
    planner.encoding.chain.fit_chain and planner.pipeline.encode during the measurement. CPU time of this thread
    (time.thread_time) throughout: on a shared machine, wall time also counts the other processes."""
    import planner.encoding.chain
    import planner.motion.topp
    import planner.pipeline

    spent: dict[str, float] = {"topp": 0.0, "chain": 0.0, "encode": 0.0}

    def timed(name: str, fn: Any) -> Any:
        def run(*args: Any, **kwargs: Any) -> Any:
            t0 = time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[name] += time.thread_time() - t0

        return run

    patches = [
        (planner.motion.topp, "solve", "topp"),
        (planner.encoding.chain, "fit_chain", "chain"),
        (planner.pipeline, "encode", "encode"),
    ]
    plan_job(job, cell)  # warm up imports and caches
    raw_toppra(job, cell, refine=False)
    ours, raw = [], []
    stages: dict[str, list[float]] = {k: [] for k in spent}
    saved = [getattr(owner, attr) for owner, attr, _ in patches]
    for owner, attr, name in patches:
        setattr(owner, attr, timed(name, getattr(owner, attr)))
    try:
        for _ in range(runs):  # interleaved, so a slow spell of the machine hits both alike
            spent.update(dict.fromkeys(spent, 0.0))
            t0 = time.thread_time()
            plan_job(job, cell)
            ours.append(time.thread_time() - t0)
            for k, v in spent.items():
                stages[k].append(v)
            raw.append(raw_toppra(job, cell, refine=False)[0])
    finally:
        for (owner, attr, _), fn in zip(patches, saved, strict=True):
            setattr(owner, attr, fn)
    med_ours, med_raw = statistics.median(ours), statistics.median(raw)
    out = {"plan_ms": 1000 * med_ours, "toppra_ms": 1000 * med_raw, "ratio": med_ours / med_raw}
    out.update({f"stage_{k}_ms": 1000 * statistics.median(v) for k, v in stages.items()})
    return out


def corpus(cell: CellConfig, kind: str, count: int, seed: int) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    rows: list[dict[str, Any]] = []
    refused: list[str] = []
    for _ in range(count):
        data = with_jerk_limited(random_job(kind, rng, cell), False)  # against raw toppra: no jerk limit
        try:
            rows.append(measure(job_from_dict(data, cell), cell))
        except PlanningError as e:
            refused.append(f"{e.code}: {e.message[:100]}")
    eff = [r["efficiency"] for r in rows]
    dur = [r["duration_ratio"] for r in rows if "duration_ratio" in r]
    tim = [r["time_ratio"] for r in rows if "time_ratio" in r]
    return {
        "kind": kind, "jobs": count, "refused": len(refused) / count, "refusals": refused[:5],
        "eff_median": statistics.median(eff) if eff else float("nan"), "eff_worst": max(eff, default=float("nan")),
        "over_uniform": sum(1 for e in eff if e > 1.0),
        "over_margins": sum(1 for r in rows if r["efficiency_margins"] > 1.0),
        "dur_median": statistics.median(dur) if dur else float("nan"), "dur_worst": max(dur, default=float("nan")),
        "over_1_02": sum(1 for d in dur if d > 1.02),
        "time_median": statistics.median(tim) if tim else float("nan"),
        "time_p90": float(np.quantile(tim, 0.9)) if tim else float("nan"),
        "time_worst": max(tim, default=float("nan")),
        "timed_rows": [(r["duration_s"], r["time_ratio"]) for r in rows if "time_ratio" in r],
        "slowed": sum(1 for r in rows if r["time_scale"] > 1.0),
    }


# ----------------------------------------------------------------------------------------------------
# jerk-limited paths (issue 26): each ratio against its baseline, measured in the same run


def stop_at_corners_s(job: Job, cell: CellConfig) -> float:
    """Duration (s) of the jerk-limited moves (ruckig, along the line) from waypoint to waypoint, stopping at
    every corner: what a user gets today who wants the jerk limits kept along a path."""
    from planner.motion.stop_moves import stop_moves

    lim = effective_limits(job, cell)
    cpu = np.array([c.counts_per_unit for c in axis_configs(job.axes, cell)])
    wp = _merge_close(np.array(job.data.waypoints, dtype=np.float64), cpu)  # type: ignore[union-attr]
    wp = np.array([snap(w, cpu) for w in wp])
    return stop_moves(wp, cpu, lim.velocity, lim.acceleration, lim.jerk).duration_ms / 1000.0


def uniform_jerk_points(job: Job, cell: CellConfig, traj: PvtTrajectory, tries: int = 20) -> tuple[int, bool]:
    """Points of the coarsest uniform grid that meets the tolerance and keeps the same jerk bound as the
    encoding `traj` (its largest in-segment jerk or knot step over the limit, planner/encoding/continuity.py's
    `worst_ratio`), its values chosen as the encoder's are for a jerk-limited plan (`smooth_values`), and True.
    When none of the `tries` coarsest grids that meet the tolerance does: the points of the finest of them and
    False (a grid that keeps the bound, if any does, is finer still: `traj`'s points over these are then an
    upper bound of the ratio)."""
    from planner.encoding.continuity import smooth_values, worst_ratio
    from planner.encoding.uniform import uniform_knots

    scales = axis_scales(axis_configs(job.axes, cell), effective_limits(job, cell))
    jerk = np.array([s.jerk_limit for s in traj.stats]) * traj.counts_per_unit / 1.0e9
    ours = worst_ratio(Knots(traj.knot_times_ms, traj.positions, traj.velocities), scales, jerk)
    first = Knots(np.array([0]), traj.positions[:, :1], traj.velocities[:, :1])
    ref = traj.plan
    m = ref.duration_ms
    want = planned_demand(ref, scales.toward_zero)
    finest = 0
    for dt in range(min(255, max(m, 1)), 0, -1):
        knots = uniform_knots(ref, scales, dt, first)
        if (np.abs(reconstruct(knots, scales).demand - want) > traj.tolerance_counts).any():
            continue
        tries -= 1
        finest = int(knots.times_ms.size)
        smooth = smooth_values(ref, knots, scales, float(traj.tolerance_counts), jerk)
        if worst_ratio(smooth, scales, jerk) <= ours * (1.0 + 1e-9):
            return finest, True
        if tries == 0:
            break
    return finest or m + 1, False  # no grid met the tolerance: every ms is the finest there is


def jerk_measure(job: Job, cell: CellConfig) -> dict[str, Any]:
    """One path job planned three ways (acceleration-only, jerk-limited "smooth" and "fastest"): duration,
    points and CPU time; the jerk bounds of the drive's motion (the fastest timing's: `fast_*`)."""
    d = job_to_dict(job)
    plans = {}
    for key, flag, timing in (("acc", False, None), ("smooth", True, None), ("fastest", True, "fastest")):
        d["jerk_limited"] = flag
        if timing is not None:
            d["jerk_timing"] = timing
        j = job_from_dict(d, cell)
        t0 = time.thread_time()
        traj = plan_job(j, cell)
        plans[key] = (traj, time.thread_time() - t0, j)
    acc_traj, _acc_s, _ = plans["acc"]
    traj, elapsed, jjob = plans["smooth"]
    fast, fast_s, fjob = plans["fastest"]
    _dt, uniform = uniform_points(jjob, cell, traj)
    _dt, fast_uniform = uniform_points(fjob, cell, fast)
    same_jerk, found = uniform_jerk_points(jjob, cell, traj)
    raw_s, _ = raw_toppra(job, cell, refine=False)
    stops_s = stop_at_corners_s(job, cell)
    return {
        "duration_s": traj.duration_s,
        "acc_ratio": traj.duration_s / acc_traj.duration_s,
        "stop_ratio": traj.duration_s / stops_s,
        "fast_acc_ratio": fast.duration_s / acc_traj.duration_s,
        "fast_smooth_ratio": fast.duration_s / traj.duration_s,
        "fast_stop_ratio": fast.duration_s / stops_s,
        "fast_efficiency": fast.n_points / fast_uniform,
        "fast_time_ratio": fast_s / raw_s,
        "fast_drive_jerk": max(s.peak_jerk / s.jerk_limit for s in fast.stats),
        "fast_knot_step": max(s.knot_acceleration_step * 1000.0 / s.jerk_limit for s in fast.stats),
        "points": traj.n_points,
        "uniform_points": uniform,
        "efficiency": traj.n_points / uniform,
        "jerk_efficiency": traj.n_points / same_jerk,  # an upper bound where not `found`
        "no_uniform": not found,
        "time_ratio": elapsed / raw_s,
        "plan_jerk": max(s.planned_peak_jerk / s.jerk_limit for s in traj.stats),
        "drive_jerk": max(s.peak_jerk / s.jerk_limit for s in traj.stats),
        "knot_step": max(s.knot_acceleration_step * 1000.0 / s.jerk_limit for s in traj.stats),
        "acc_knot_step": max(s.knot_acceleration_step * 1000.0 / s.jerk_limit for s in acc_traj.stats),
    }


def jerk_corpus(cell: CellConfig, jobs: Sequence[tuple[str, Job]]) -> dict[str, Any]:
    rows: list[dict[str, Any]] = []
    refused: list[str] = []
    for _name, job in jobs:
        try:
            rows.append(jerk_measure(job, cell))
        except PlanningError as e:
            refused.append(f"{e.code}: {e.message[:100]}")

    def med(key: str) -> float:
        return statistics.median(r[key] for r in rows) if rows else float("nan")

    def worst(key: str) -> float:
        return max((r[key] for r in rows), default=float("nan"))

    out: dict[str, Any] = {"jobs": len(jobs), "refused": len(refused), "refusals": refused[:3], "rows": rows}
    out["no_uniform"] = sum(1 for r in rows if r["no_uniform"])
    for key in ("acc_ratio", "stop_ratio", "efficiency", "jerk_efficiency", "time_ratio", "plan_jerk", "drive_jerk",
                "knot_step", "acc_knot_step", "fast_acc_ratio", "fast_smooth_ratio", "fast_stop_ratio",
                "fast_efficiency", "fast_time_ratio", "fast_drive_jerk", "fast_knot_step"):
        out[key] = (med(key), worst(key))
    return out


def print_jerk(cell: CellConfig, examples: Sequence[tuple[str, Job]], count: int, seed: int) -> list[dict[str, Any]]:
    head = (f"{'corpus':12} {'jobs':>4} {'ref.':>4} {'dur/acc-opt med':>15} {'worst':>6} {'dur/stops med':>13} "
            f"{'worst':>6} {'pts/unif med':>12} {'worst':>6} {'pts/unif-jerk med':>17} {'worst':>6} {'none':>4} "
            f"{'plan/toppra med':>15} {'worst':>6} "
            f"{'plan jerk':>9} {'drive jerk':>10} {'knot step med':>13} {'worst':>6} {'(acc-only)':>10}")
    print("jerk-limited paths (jerk_limited = true) against, in the same run: the acceleration-only plan of the same "
          "job, jerk-limited moves stopping at every corner, the coarsest uniform grid meeting the tolerance on the "
          "same plan (unif) and the coarsest that also keeps the same jerk bound (unif-jerk; none: the jobs where no "
          "uniform grid of the 20 coarsest that meet the tolerance does; their ratio is over the finest of those 20, "
          "an upper bound, as a grid that keeps the bound is finer still), raw toppra's solve; jerk columns: worst "
          "peak / limit (knot step: the largest acceleration step at a knot over the 1 ms tick / limit, per job: the "
          "median job's and the worst job's)")
    print(head)
    print("-" * len(head))
    out = []
    sets: list[tuple[str, Sequence[tuple[str, Job]]]] = [("examples", examples)]
    for k, kind in enumerate(("path", "path-sharp", "path-small")):
        rng = np.random.default_rng(seed + k)
        # the jobs as their acceleration-only plan: jerk_measure plans each both ways from it
        sets.append((kind, [(str(i), job_from_dict(with_jerk_limited(random_job(kind, rng, cell), False), cell))
                            for i in range(count)]))
    # the random paths again as splines through their waypoints (`geometry = "spline"`: the FIR re-timing)
    splines = [{**job_to_dict(j), "geometry": "spline"} for _n, j in sets[1][1]]
    sets.append(("path-spline", [(str(i), job_from_dict({k: v for k, v in d.items() if k != "path_tolerance"}, cell))
                                 for i, d in enumerate(splines)]))
    for name, jobs in sets:
        s = jerk_corpus(cell, jobs)
        out.append({"corpus": name, **s})
        print(f"{name:12} {s['jobs']:4d} {s['refused']:4d} {s['acc_ratio'][0]:15.3f} {s['acc_ratio'][1]:6.3f} "
              f"{s['stop_ratio'][0]:13.3f} {s['stop_ratio'][1]:6.3f} {s['efficiency'][0]:12.3f} "
              f"{s['efficiency'][1]:6.3f} {s['jerk_efficiency'][0]:17.3f} {s['jerk_efficiency'][1]:6.3f} "
              f"{s['no_uniform']:4d} {s['time_ratio'][0]:15.2f} {s['time_ratio'][1]:6.2f} "
              f"{s['plan_jerk'][1]:9.3f} {s['drive_jerk'][1]:10.3f} {s['knot_step'][0]:13.2f} {s['knot_step'][1]:6.2f} "
              f"{s['acc_knot_step'][1]:10.1f}")
        for r in s["refusals"]:
            print(f"    refused: {r}")
    print("targets (issue 26): dur/acc-opt median <= 1.10, dur/stops < 1, pts/unif <= 0.5, jerk <= 1.05, knot step "
          "<= 1.05")
    print()
    head = (f"{'corpus':12} {'dur/acc-opt med':>15} {'worst':>6} {'dur/smooth med':>14} {'worst':>6} "
            f"{'dur/stops med':>13} {'worst':>6} {'pts/unif med':>12} {'plan/toppra med':>15} {'worst':>6} "
            f"{'drive jerk':>10} {'knot step med':>13} {'worst':>6}")
    print('the same jobs planned with jerk_timing = "fastest" (the third-order time-optimal speed along the same '
          'geometry, planner/motion/jerk_scp.py), against the same baselines and the "smooth" plan above')
    print(head)
    print("-" * len(head))
    for s in out:
        print(f"{s['corpus']:12} {s['fast_acc_ratio'][0]:15.3f} {s['fast_acc_ratio'][1]:6.3f} "
              f"{s['fast_smooth_ratio'][0]:14.3f} {s['fast_smooth_ratio'][1]:6.3f} {s['fast_stop_ratio'][0]:13.3f} "
              f"{s['fast_stop_ratio'][1]:6.3f} {s['fast_efficiency'][0]:12.3f} {s['fast_time_ratio'][0]:15.2f} "
              f"{s['fast_time_ratio'][1]:6.2f} {s['fast_drive_jerk'][1]:10.3f} {s['fast_knot_step'][0]:13.2f} "
              f"{s['fast_knot_step'][1]:6.2f}")
    return out


# the drive's units against the knot-step bound J x 1 ms (issue 26): what one count and one rpm do, and the
# smallest step a steady cruise at the worst fractional rpm can keep on the drive's cubic
UNIT_TIMES = (10, 20, 30, 50, 75, 100, 150, 200, 255)


def cruise_floor(cpu: float, jerk: float, acc: float, counts_per_rev: int, t_ms: int, tol: float,
                 segments: int = 24) -> float:
    """Largest knot step / (J x 1 ms) that the knot values' search (planner/encoding/continuity.py) leaves on a
    cruise at n + f rpm (the worst f of 0, 0.1, .., 0.5) on knots every `t_ms` ms; inf: no values keep the
    tolerance and the jerk (+5 %)."""
    from planner.encoding import hermite
    from planner.encoding.continuity import _axis, knot_steps
    from planner.encoding.reconstruction import AxisScales

    q = counts_per_rev / 60000.0
    bound = jerk * cpu / 1.0e9
    one = np.ones(1)
    scales = AxisScales(q * one, one, one, one, one, one)
    worst = 0.0
    for frac in np.linspace(0.0, 0.5, 6):
        x = 50.0 + frac
        t = np.arange(segments * t_ms + 1, dtype=np.float64)
        pos = 0.37 + x * q * t
        want = hermite.round_counts_array(pos)
        times = np.arange(0, t.size, t_ms)
        got = _axis(want, np.full(t.size, x * q), times, hermite.round_counts_array(pos[times]),
                    np.full(times.size, int(np.floor(x + 0.5))), np.zeros(times.size - 1), q, 1e9, 1e9,
                    0.05 * acc * cpu / 1.0e6, bound, tol, 0.0)
        if got is None:
            return float("inf")
        steps = knot_steps(Knots(times, got[0][None, :], got[1][None, :]), scales)[1]
        worst = max(worst, float(np.abs(steps[0, 3:-3]).max()) / bound)
    return worst


def cruise_free_times(cpu: float, jerk: float, counts_per_rev: int, x_rpm: float, lo: int, hi: int,
                      horizon: int = 300, tol: int = 1) -> float:
    """The smallest largest knot step / (J x 1 ms) over a cruise at `x_rpm` when the knot *times* are free
    too (whole ms, segments of lo..hi ms; whole counts within `tol` of the plan; the two rpm around x;
    in-segment jerk within 1.05 J): a bottleneck shortest path over pairs of knots. Slow (tens of s)."""
    from planner.encoding import hermite

    q = counts_per_rev / 60000.0
    bound = jerk * cpu / 1.0e9
    want = hermite.round_counts_array(0.37 + x_rpm * q * np.arange(horizon + 1, dtype=np.float64))
    rpms = (int(np.floor(x_rpm)), int(np.floor(x_rpm)) + 1)
    by_t = {t: [(t, int(want[t]) + d, v) for d in (-1, 0, 1) for v in rpms] for t in range(horizon + 1)}
    memo: dict[Any, tuple[bool, float, float]] = {}

    def segment(a: tuple[int, int, int], b: tuple[int, int, int]) -> tuple[bool, float, float]:
        if (a, b) not in memo:
            (t0, p0, v0), (t1, p1, v1) = a, b
            tt, dp, w0, w1 = t1 - t0, p1 - p0, v0 * q, v1 * q
            bb = (-3 * dp + tt * (2 * w1 + w0)) / tt**2
            aa = (-2 * dp + tt * (w1 + w0)) / tt**3
            tau = np.arange(1, tt, dtype=np.float64) - tt
            pos = ((aa * tau + bb) * tau + w1) * tau + p1
            ok = abs(6 * aa) <= 1.05 * bound and bool(
                (np.abs(hermite.round_counts_array(pos) - want[t0 + 1 : t1]) <= tol).all())
            memo[(a, b)] = (ok, -6 * aa * tt + 2 * bb, 2 * bb)
        return memo[(a, b)]

    best: dict[Any, float] = {}
    for a in by_t[0]:
        for tt in range(lo, min(hi, horizon) + 1):
            for b in by_t[tt]:
                if segment(a, b)[0]:
                    best[(a, b)] = 0.0
    for t in range(lo, horizon + 1):
        for (a, b), c in [(k, v) for k, v in best.items() if k[1][0] == t]:
            acc_end = segment(a, b)[2]
            for tt in range(lo, hi + 1):
                if t + tt > horizon:
                    break
                for nb in by_t[t + tt]:
                    ok, acc_start, _ = segment(b, nb)
                    if ok:
                        m = max(c, abs(acc_start - acc_end) / bound)
                        if m < best.get((b, nb), np.inf):
                            best[(b, nb)] = m
    ends = [v for k, v in best.items() if k[1][0] >= horizon - hi]
    return min(ends) if ends else float("inf")


def print_units(cell: CellConfig, free_times: bool) -> None:
    from planner.encoding.continuity import knot_step_units
    from planner.encoding.reconstruction import AxisScales

    print("the drive's units against the knot step bound J x 1 ms, per axis and segment length T (ms): "
          "1 count of a neighbour's position / 1 rpm of the knot's own velocity, over the bound; then the "
          "largest step the knot values' search leaves on a cruise at the worst fractional rpm on knots every "
          "T ms (tolerance 1 count; inf: none keeps the tolerance and the jerk)")
    ts = np.array(UNIT_TIMES)
    for a in cell.axes:
        q = a.counts_per_rev / 60000.0
        bound = a.jerk * a.counts_per_unit / 1.0e9
        one = np.ones(1)
        per_count, per_rpm = knot_step_units(AxisScales(q * one, one, one, one, one, one), bound * one, ts)
        units = " ".join(f"{t}:{c:.2f}/{r:.2f}" for t, c, r in zip(ts, per_count[0], per_rpm[0], strict=True))
        floor = " ".join(
            f"{t}:{cruise_floor(a.counts_per_unit, a.jerk, a.acceleration, a.counts_per_rev, int(t), 1.0):.2f}"
            for t in ts)
        print(f"  {a.name:4} J {a.jerk:g}/s^3 = {bound:.5f} counts/ms^2 per ms; count/rpm {units}")
        print(f"  {'':4} cruise floor on uniform knots {floor}")
        if free_times:
            for lo, hi in ((15, 45), (30, 80)):
                got = cruise_free_times(a.counts_per_unit, a.jerk, a.counts_per_rev, 50.5, lo, hi)
                print(f"  {'':4} cruise at 50.5 rpm, knot times free in {lo}..{hi} ms: {got:.2f}")


def _mark(ok: bool | None) -> str:
    return "n/a" if ok is None else ("ok" if ok else "MISS")


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_planner", description=__doc__.split("\n")[0])
    parser.add_argument("--jobs", type=int, default=200, help="random jobs per kind (default 200)")
    parser.add_argument("--seed", type=int, default=13)
    parser.add_argument("--jerk-jobs", type=int, default=40,
                        help="random paths per kind for the jerk rows (default 40)")
    parser.add_argument("--units", choices=("off", "on", "free-times"), default="on",
                        help="the drive's units against the knot step bound (free-times: also the search with free "
                             "knot times, a minute per axis)")
    args = parser.parse_args(list(argv) if argv is not None else [])
    logging.getLogger("toppra").setLevel(logging.CRITICAL)
    warm_up()  # the solvers' first import (~0.7 s) would otherwise count as the first path's planning
    cell = load_cell(ROOT / "configs" / "demo.toml")
    bench = benchmark_path(cell)
    jobs = example_jobs(cell)  # the acceleration-only plans (measured against raw toppra; jerk: print_jerk)
    jobs.append(("bench-20 (6 axes, 20 waypoints)", bench))
    rows = [{"job": name, **measure(job, cell)} for name, job in jobs]

    head = (f"{'job':32} {'kind':5} {'dur s':>7} {'points':>6} {'uniform':>12} {'pts/unif':>8} {'target':>6} "
            f"{'optimum s':>9} {'dur/opt':>7} {'<=1.02':>6} {'plan/toppra':>11} {'acc exc%':>8}")
    print(head)
    print("-" * len(head))
    for r in rows:
        target = 0.35 if r["kind"] in ("path", "move") else 1.0
        dur = (f"{r['optimum_s']:9.3f} {r['duration_ratio']:7.4f} {_mark(r['duration_ratio'] <= 1.02):>6}"
               if "duration_ratio" in r else f"{'':9} {'':7} {'':6}")
        tim = f"{r['time_ratio']:11.2f}" if "time_ratio" in r else f"{'':11}"
        print(f"{r['job'][:32]:32} {r['kind']:5} {r['duration_s']:7.3f} {r['points']:6d} "
              f"{r['uniform_points']:6d} @{r['uniform_dt_ms']:3d}ms {r['efficiency']:8.3f} "
              f"{_mark(r['efficiency'] <= target):>6} {dur} {tim} {r['max_excess_pct']:8.1f}")
    print("uniform: the coarsest uniform grid (rounded values) meeting the same tolerance on the same plan; "
          "target <= 0.35 for paths and moves, <= 1 for the rest")
    lat = latency(cell, bench)
    print(f"planning latency on bench-20: plan+encode median {lat['plan_ms']:.1f} ms, raw toppra median "
          f"{lat['toppra_ms']:.1f} ms, ratio {lat['ratio']:.2f} (target <= 1.5: {_mark(lat['ratio'] <= 1.5)})")
    rest = lat["plan_ms"] - lat["stage_topp_ms"] - lat["stage_chain_ms"] - lat["stage_encode_ms"]
    print(f"  where plan+encode's time goes (CPU ms, medians): time-optimal solves {lat['stage_topp_ms']:.1f}, "
          f"chain fits {lat['stage_chain_ms']:.1f}, encodings (retries included) {lat['stage_encode_ms']:.1f}, "
          f"the rest (geometry, re-timing, checks, statistics) {rest:.1f}")
    print()

    stats = []
    if args.jobs > 0:
        head = (f"{'corpus':10} {'jobs':>4} {'refused':>7} {'pts/unif med':>12} {'worst':>6} {'>1':>3} "
                f"{'(margins)':>9} {'dur/opt med':>11} {'worst':>6} {'>1.02':>5} {'plan/toppra med':>15} "
                f"{'p90':>5} {'worst':>6} {'slowed':>6}")
        print(head)
        print("-" * len(head))
        for k, kind in enumerate(KINDS):
            s = corpus(cell, kind, args.jobs, args.seed + k)
            stats.append(s)
            print(f"{kind:10} {s['jobs']:4d} {100 * s['refused']:6.1f}% {s['eff_median']:12.3f} "
                  f"{s['eff_worst']:6.3f} {s['over_uniform']:3d} {s['over_margins']:9d} {s['dur_median']:11.4f} "
                  f"{s['dur_worst']:6.4f} {s['over_1_02']:5d} {s['time_median']:15.2f} {s['time_p90']:5.2f} "
                  f"{s['time_worst']:6.2f} {s['slowed']:6d}")
            for r in s["refusals"]:
                print(f"    refused: {r}")
        print("slowed: jobs played slower than planned because the encoding needed it (encode_with_retries)")
        print("path-small: a few ms per rest-to-rest run, each with its phases on whole ms (about 1 ms more than its "
              "optimum), and slowed where the quantisation needs it; a uniform grid of long segments covers a motion "
              "of a few counts with few points, so the 0.35 target is not theirs")
        timed = [x for s in stats if s["kind"] in ("path", "path-sharp") for x in s["timed_rows"]]
        if timed:
            # every ms of the motion is verified, toppra's solve does not depend on the duration
            parts = []
            for lo, hi in DURATION_BANDS:
                band = [ratio for d, ratio in timed if lo <= d < hi]
                if band:
                    label = f"{lo:g}-{hi:g} s" if hi < 1.0e9 else f"over {lo:g} s"
                    parts.append(f"{label}: {statistics.median(band):.2f} (p90 "
                                 f"{float(np.quantile(band, 0.9)):.2f}, {len(band)} paths)")
            print("plan/toppra by the motion's duration (path, path-sharp), medians: " + "; ".join(parts))
    jerk_rows = []
    if args.jerk_jobs >= 0:
        print()
        examples = [(n, j) for n, j in jobs if j.kind == "path"]
        jerk_rows = print_jerk(cell, examples, args.jerk_jobs, args.seed + 100)
    if args.units != "off":
        print()
        print_units(cell, args.units == "free-times")
    return {"rows": rows, "latency": lat, "corpus": stats, "jerk": jerk_rows}


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])
