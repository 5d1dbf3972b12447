"""Planner benchmark: encoding efficiency, duration overhead and planning latency, as ratios against
baselines measured in the same run (`python -m benchmarks planner`, part of `make bench`).

- encoding efficiency: adaptive PVT points / points of the coarsest uniform grid that meets the same
  tolerance on the same plan (values chosen by the same joint P/V search, checked at every ms).
  Target <= 0.35, for every example job.
- duration overhead: encoded duration / toppra's own optimal duration for the same path (raw toppra:
  the standard joint velocity and acceleration constraints, its default gridpoints, seidel,
  ParametrizeConstAccel). Target <= 1.01 for the path jobs.
- planning latency: plan + encode + verify (planner.plan_job) / raw toppra (compute_trajectory) on the
  same 6-axis 20-waypoint path, medians of interleaved runs. Target ratio <= 2.
"""

from __future__ import annotations

import logging
import statistics
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from planner.config import CellConfig, load_cell
from planner.encoder import AxisScales, Knots, _choose_values, _refine, planned_demand, reconstruct
from planner.job import Job, PathData, effective_limits, job_from_dict, load_job
from planner.plan import axis_configs, axis_scales, plan_job
from planner.reference import Reference
from planner.trajectory import PvtTrajectory

ROOT = Path(__file__).resolve().parent.parent
LATENCY_RUNS = 21


def benchmark_path(cell: CellConfig, n_waypoints: int = 20, seed: int = 7) -> Job:
    """A deterministic 6-axis path of `n_waypoints` waypoints: a random walk inside the joint limits."""
    rng = np.random.default_rng(seed)
    lo = np.array([a.position_min for a in cell.axes]) * 0.6
    hi = np.array([a.position_max for a in cell.axes]) * 0.6
    wp = [np.zeros(len(cell.axes))]
    for _ in range(n_waypoints - 1):
        wp.append(np.clip(wp[-1] + rng.uniform(-0.45, 0.45, len(cell.axes)), lo, hi))
    return job_from_dict(
        {"kind": "path", "job_id": "bench-20", "axes": list(cell.axis_names()), "waypoints": np.array(wp).tolist()},
        cell,
    )


def _scales(job: Job, cell: CellConfig) -> AxisScales:
    return axis_scales(axis_configs(job.axes, cell), effective_limits(job, cell))


def _uniform_ok(ref: Reference, scales: AxisScales, tol: int, start: Knots, dt: int, joint: bool) -> bool:
    """Does a uniform grid of `dt` ms meet the tolerance? Values rounded (joint=False: the plain
    encoder) or chosen by the same joint P/V search as the adaptive encoder (joint=True)."""
    m = ref.duration_ms
    times = np.unique(np.concatenate([np.arange(0, m, dt), [m]])).astype(np.int64)
    n = ref.n_axes
    want = planned_demand(ref)
    if not joint:
        pos = want[:, times].copy()
        vel = np.round(ref.velocities[:, times] / scales.counts_per_ms_per_rpm[:, None]).astype(np.int64)
        pos[:, 0], vel[:, 0] = start.positions[:, 0], start.velocities_rpm[:, 0]
        vel[:, -1] = 0
        dev = np.abs(reconstruct(Knots(times, pos, vel), scales).demand - want)
        return not bool((dev > tol).any())
    fixed = {0: (start.positions[:, 0], start.velocities_rpm[:, 0]),
             times.size - 1: (want[:, -1], np.zeros(n, dtype=np.int64))}
    pos, vel = _choose_values(ref, times, scales, float(tol), fixed)
    knots = Knots(times, pos, vel)
    dev = np.abs(reconstruct(knots, scales).demand - want)
    if (dev > tol).any():
        bad = np.nonzero((dev > tol).any(axis=0))[0]
        segs = np.unique(np.clip(np.searchsorted(times, bad, side="left") - 1, 0, times.size - 2))
        knots = _refine(ref, knots, scales, float(tol), segs, {0, times.size - 1})
        dev = np.abs(reconstruct(knots, scales).demand - want)
    return not bool((dev > tol).any())


def coarsest_uniform(traj: PvtTrajectory, scales: AxisScales, *, joint: bool = False) -> tuple[int, int]:
    """(dt_ms, points) of the coarsest uniform grid that meets the trajectory's tolerance on its plan."""
    ref = traj.plan
    start = Knots(np.array([0]), traj.positions[:, :1], traj.velocities[:, :1])
    m = ref.duration_ms
    ladder = [d for d in (255, 200, 160, 128, 100, 80, 64, 50, 40, 32, 25, 20, 16, 12, 10, 8, 6, 5, 4, 3, 2, 1)
              if d <= max(m, 1)]
    best = 1
    prev_fail = min(255, max(m, 1)) + 1
    for d in ladder:
        if _uniform_ok(ref, scales, traj.tolerance_counts, start, d, joint):
            best = d
            break
        prev_fail = d
    for d in range(prev_fail - 1, best, -1):  # refine between the first pass and the last failure
        if _uniform_ok(ref, scales, traj.tolerance_counts, start, d, joint):
            best = d
            break
    return best, -(-m // best) + 1


def raw_toppra(job: Job, cell: CellConfig) -> tuple[float, float]:
    """(wall time s, duration s) of plain toppra on the job's path (the planner's own geometry)."""
    import toppra as ta
    from toppra.algorithm import TOPPRA
    from toppra.constraint import JointAccelerationConstraint, JointVelocityConstraint

    from planner.path import PathGeometry

    assert isinstance(job.data, PathData)
    lim = effective_limits(job, cell)
    vlim, alim = lim["velocity"], lim["acceleration"]
    geom = PathGeometry(np.asarray(job.data.waypoints), vlim)
    t0 = time.perf_counter()
    path = ta.SplineInterpolator(geom.ss, geom.waypoints)
    constraints = [JointVelocityConstraint(np.vstack([-vlim, vlim]).T),
                   JointAccelerationConstraint(np.vstack([-alim, alim]).T)]
    traj = TOPPRA(constraints, path, solver_wrapper="seidel", parametrizer="ParametrizeConstAccel").compute_trajectory()
    elapsed = time.perf_counter() - t0
    if traj is None:
        raise RuntimeError("raw toppra failed on the benchmark path")
    return elapsed, float(traj.duration)


def efficiency_rows(cell: CellConfig, jobs: Sequence[tuple[str, Job]]) -> list[dict[str, Any]]:
    rows = []
    for name, job in jobs:
        traj = plan_job(job, cell)
        dt, uniform_points = coarsest_uniform(traj, _scales(job, cell))
        jdt, joint_points = coarsest_uniform(traj, _scales(job, cell), joint=True)
        row: dict[str, Any] = {
            "job": name, "kind": job.kind, "duration_s": traj.duration_s, "points": traj.n_points,
            "uniform_dt_ms": dt, "uniform_points": uniform_points,
            "efficiency": traj.n_points / uniform_points,
            "joint_uniform_dt_ms": jdt, "joint_uniform_points": joint_points,
            "efficiency_vs_joint": traj.n_points / joint_points,
            "max_excess_pct": 100 * max(s.acceleration_excess_share for s in traj.stats),
        }
        if job.kind == "path":
            _t, optimal = raw_toppra(job, cell)
            row["toppra_s"] = optimal
            row["duration_ratio"] = traj.duration_s / optimal
        if job.kind == "pvt":  # the rows are the user's: passed through, nothing to place
            row["efficiency"] = row["efficiency_vs_joint"] = float("nan")
        rows.append(row)
    return rows


def latency(cell: CellConfig, job: Job, runs: int = LATENCY_RUNS) -> dict[str, float]:
    plan_job(job, cell)  # warm up imports and caches
    raw_toppra(job, cell)
    ours, raw = [], []
    for _ in range(runs):  # interleaved, so load from other processes hits both alike
        t0 = time.perf_counter()
        plan_job(job, cell)
        ours.append(time.perf_counter() - t0)
        raw.append(raw_toppra(job, cell)[0])
    med_ours, med_raw = statistics.median(ours), statistics.median(raw)
    return {"plan_ms": 1000 * med_ours, "toppra_ms": 1000 * med_raw, "ratio": med_ours / med_raw}


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    logging.getLogger("toppra").setLevel(logging.CRITICAL)
    cell = load_cell(ROOT / "configs" / "demo.toml")
    bench = benchmark_path(cell)
    jobs = [(p.name, load_job(p, cell)) for p in sorted((ROOT / "configs" / "jobs").iterdir())]
    jobs.append(("bench-20 (6 axes, 20 waypoints)", bench))
    rows = efficiency_rows(cell, jobs)
    lat = latency(cell, bench)

    head = (f"{'job':32} {'kind':5} {'dur s':>7} {'points':>6} {'uniform':>12} {'eff.':>6} {'<=0.35':>6} "
            f"{'unif.+joint':>12} {'eff.':>6} {'toppra s':>8} {'dur/opt':>7} {'<=1.01':>6} {'acc exc%':>8}")
    print(head)
    print("-" * len(head))
    for r in rows:
        dur = (f"{r['toppra_s']:8.3f} {r['duration_ratio']:7.4f} "
               f"{('ok' if r['duration_ratio'] <= 1.01 else 'MISS'):>6}") if "duration_ratio" in r else \
            f"{'':8} {'':7} {'':6}"
        print(f"{r['job'][:32]:32} {r['kind']:5} {r['duration_s']:7.3f} {r['points']:6d} "
              f"{r['uniform_points']:6d} @{r['uniform_dt_ms']:3d}ms {r['efficiency']:6.3f} "
              f"{('n/a' if r['kind'] == 'pvt' else 'ok' if r['efficiency'] <= 0.35 else 'MISS'):>6} "
              f"{r['joint_uniform_points']:6d} @{r['joint_uniform_dt_ms']:3d}ms {r['efficiency_vs_joint']:6.3f} "
              f"{dur} {r['max_excess_pct']:8.1f}")
    print("uniform: the coarsest uniform grid with rounded values meeting the same tolerance; "
          "unif.+joint: the same with the adaptive encoder's joint P/V choice")
    print()
    print(f"planning latency on bench-20: plan+encode median {lat['plan_ms']:.1f} ms, raw toppra median "
          f"{lat['toppra_ms']:.1f} ms, ratio {lat['ratio']:.2f} (target <= 2: {'ok' if lat['ratio'] <= 2 else 'MISS'})")
    return {"rows": rows, "latency": lat}


if __name__ == "__main__":
    main()
