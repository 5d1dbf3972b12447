"""Hypothesis property tests: random feasible jobs of every kind on 1..8 axes, and stops from random states.

Every trajectory must satisfy `assert_invariants` (planner_checks.py): deviation within tolerance at every ms,
segment times whole ms in 1..255 on one shared grid, C1 at the knots, limits respected, exact end at
rest, no NaN.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from planner_checks import assert_invariants, assert_not_more_than_uniform, assert_path_within

from planner import plan_job
from planner.config import CellConfig
from planner.errors import PlanningError
from planner.job import job_from_dict
from planner.motion.stop import plan_stop

SETTINGS = settings()  # the profile of tests/conftest.py (60 examples, no deadline)


def _axes(draw: st.DrawFn, cell: CellConfig, max_axes: int = 8) -> list[str]:
    n = draw(st.integers(1, min(max_axes, len(cell.axes))))
    return list(draw(st.permutations(cell.axis_names()))[:n])


def _position(draw: st.DrawFn, cell: CellConfig, name: str, lo: float = 0.1, hi: float = 0.9) -> float:
    ax = cell.axis(name)
    u = draw(st.floats(lo, hi))
    return ax.position_min + u * (ax.position_max - ax.position_min)


def _counts(cell: CellConfig, axes: list[str], x: np.ndarray) -> np.ndarray:
    cpu = np.array([cell.axis(a).counts_per_unit for a in axes])
    return np.round(np.asarray(x) * cpu).astype(np.int64)


def _scales(draw: st.DrawFn, job: dict[str, Any], n: int) -> None:
    if draw(st.booleans()):
        job["velocity_scale"] = [draw(st.floats(0.3, 1.0)) for _ in range(n)]
    if draw(st.booleans()):
        job["acceleration_scale"] = draw(st.floats(0.3, 1.0))
    if draw(st.integers(0, 3)) == 0:
        job["tolerance_counts"] = draw(st.integers(1, 4))


@st.composite
def path_jobs(draw: st.DrawFn, cell: CellConfig) -> dict[str, Any]:
    """Random paths inside the position limits: free, zig-zag (sharp corners), back and forth along one
    line (180-degree reversals), one axis back and forth, waypoints on the limits; every tolerance form."""
    shape = draw(st.sampled_from(["free", "zigzag", "reversal", "one-axis", "edges"]))
    axes = _axes(draw, cell, 1 if shape == "one-axis" else 8)
    rows = draw(st.integers(2, 7))
    lo_hi = (0.0, 1.0) if shape == "edges" else (0.2, 0.8)
    if shape == "reversal":
        a = [_position(draw, cell, x, 0.2, 0.8) for x in axes]
        b = [_position(draw, cell, x, 0.2, 0.8) for x in axes]
        wp = [list(a) if k % 2 == 0 else list(b) for k in range(rows)]
    elif shape == "zigzag":
        wp = []
        for k in range(rows):
            u = draw(st.floats(0.0, 0.3)) if k % 2 == 0 else draw(st.floats(0.7, 1.0))
            wp.append([_position(draw, cell, x, *lo_hi) if j else cell.axis(x).position_min
                       + (0.2 + 0.6 * u) * (cell.axis(x).position_max - cell.axis(x).position_min)
                       for j, x in enumerate(axes)])
    elif shape == "edges":
        wp = [[_position(draw, cell, x, 0.0, 1.0) if draw(st.booleans()) else
               (cell.axis(x).position_min if draw(st.booleans()) else cell.axis(x).position_max)
               for x in axes] for _ in range(rows)]
    else:
        wp = [[_position(draw, cell, x, *lo_hi) for x in axes] for _ in range(rows)]
    if draw(st.booleans()) and rows > 2:
        wp[1] = list(wp[0])  # a duplicate consecutive waypoint
    if all(row == wp[0] for row in wp):
        ax = cell.axis(axes[0])
        wp[-1][0] = 0.5 * (wp[-1][0] + 0.5 * (ax.position_min + ax.position_max)) + 0.01  # move towards the middle
    job: dict[str, Any] = {"kind": "path", "axes": axes, "waypoints": wp}
    form = draw(st.sampled_from(["default", "one", "per-axis", "zero"]))
    if form == "one":
        job["path_tolerance"] = draw(st.floats(1e-4, 0.05))
    elif form == "per-axis":
        job["path_tolerance"] = [draw(st.sampled_from([0.0, 1e-3, 0.01, 0.05])) for _ in axes]
    elif form == "zero":
        job["path_tolerance"] = 0.0
    _scales(draw, job, len(axes))
    return job


@st.composite
def small_path_jobs(draw: st.DrawFn, cell: CellConfig) -> dict[str, Any]:
    """Fine positioning: 2-200 counts between waypoints, either way on each of 1-3 axes, up to 40 waypoints
    (moves of a few ms each, where the quantisation of positions and velocities weighs most)."""
    axes = _axes(draw, cell, 3)
    rows = draw(st.integers(3, 40))
    size = draw(st.floats(2.0, 200.0))
    cpu = np.array([cell.axis(a).counts_per_unit for a in axes])
    steps = np.array([[draw(st.sampled_from([-1.0, 1.0])) * size * draw(st.floats(0.3, 1.0)) for _ in axes]
                      for _ in range(rows - 1)]) / cpu
    start = np.array([_position(draw, cell, a, 0.4, 0.6) for a in axes])
    wp = start + np.vstack([np.zeros(len(axes)), np.cumsum(steps, axis=0)])
    job: dict[str, Any] = {"kind": "path", "axes": axes, "waypoints": wp.tolist()}
    if draw(st.integers(0, 3)) == 0:
        job["tolerance_counts"] = draw(st.integers(1, 4))
    return job


@st.composite
def move_jobs(draw: st.DrawFn, cell: CellConfig) -> dict[str, Any]:
    axes = _axes(draw, cell)
    start = [_position(draw, cell, a, 0.3, 0.7) for a in axes]
    mode = draw(st.sampled_from(["absolute", "relative"]))
    if mode == "absolute":
        target = [_position(draw, cell, a) for a in axes]
    else:
        target = [draw(st.floats(-0.25, 0.25)) for _ in axes]
    job: dict[str, Any] = {"kind": "move", "axes": axes, "start": start, "target": target, "mode": mode}
    _scales(draw, job, len(axes))
    return job


@st.composite
def timed_jobs(draw: st.DrawFn, cell: CellConfig) -> dict[str, Any]:
    axes = _axes(draw, cell)
    rows = draw(st.integers(2, 5))
    pos = [[_position(draw, cell, a, 0.4, 0.6) for a in axes] for _ in range(rows)]
    times = [0.0]
    vel = np.array([cell.axis(a).velocity for a in axes])
    acc = np.array([cell.axis(a).acceleration for a in axes])
    for k in range(1, rows):
        dq = np.abs(np.array(pos[k]) - np.array(pos[k - 1]))
        need = float(np.max(np.maximum(3.0 * dq / vel, np.sqrt(20.0 * dq / acc))))
        times.append(round(times[-1] + need + draw(st.floats(0.05, 0.6)), 4))
    return {
        "kind": "timed",
        "axes": axes,
        "times": times,
        "positions": pos,
        "tolerance_counts": draw(st.integers(1, 3)),
    }


@st.composite
def pvt_jobs(draw: st.DrawFn, cell: CellConfig) -> dict[str, Any]:
    """Rows sampled from a smooth, slowed-down move (so the rows themselves respect the limits)."""
    axes = _axes(draw, cell, max_axes=6)
    start = [_position(draw, cell, a, 0.4, 0.6) for a in axes]
    target = [_position(draw, cell, a, 0.3, 0.7) for a in axes]
    move = job_from_dict(
        {
            "kind": "move",
            "axes": axes,
            "start": start,
            "target": target,
            "velocity_scale": 0.5,
            "acceleration_scale": 0.4,
        },
        cell,
    )
    traj = plan_job(move, cell)
    step = draw(st.integers(25, 120))
    m = traj.duration_ms
    ticks = list(range(0, m, step))
    if len(ticks) > 1 and m - ticks[-1] < step // 2:
        ticks.pop()  # no short last segment: rows that close together make the quantisation the motion
    ticks.append(m)
    cpu = traj.counts_per_unit[:, None]
    pos = (traj.plan.positions[:, ticks] / cpu).T
    vel = (traj.plan.velocities[:, ticks] * 1000.0 / cpu).T
    vel[0] = 0.0
    vel[-1] = 0.0
    return {
        "kind": "pvt",
        "axes": axes,
        "times": [t / 1000.0 for t in ticks],
        "positions": pos.tolist(),
        "velocities": vel.tolist(),
    }


def _plan(cell: CellConfig, data: dict[str, Any]) -> Any:
    job = job_from_dict(data, cell)
    return job, plan_job(job, cell)


def _check_path(cell: CellConfig, jd: dict[str, Any], per_run_s: float) -> Any:
    """Plan a path job (never refused), check every promise at every ms, and its duration: within 1.02 of
    the optimum (as slowed down) plus `per_run_s` per rest-to-rest run. The acceleration-only plan (the
    jerk-limited one, the default, has its properties in tests/planner/motion/test_jerkpath.py)."""
    jd = {**jd, "jerk_limited": False}
    job, traj = _plan(cell, jd)
    wp = np.array(jd["waypoints"])
    assert_invariants(traj, cell, target_counts=_counts(cell, jd["axes"], wp[-1]))
    assert_path_within(traj, job, cell)
    assert_not_more_than_uniform(traj, job, cell)
    if "optimal_s" in traj.info:  # (a path within a count is a move)
        runs = traj.info.get("runs", 1.0)
        assert traj.duration_s <= 1.02 * traj.info["time_scale"] * traj.info["optimal_s"] + per_run_s * runs
    return traj


@SETTINGS
@given(st.data())
def test_path_jobs(cell8: CellConfig, data: st.DataObject) -> None:
    jd = data.draw(path_jobs(cell8))
    # waypoints inside the limits: never refused (a blend stays between its two segments); time-optimal up
    # to the re-timing onto whole ms and the drive-followable chain (1 ms per run), and, where the
    # quantisation needed it, a slower replay (the benchmark measures against raw toppra)
    traj = _check_path(cell8, jd, 0.001)
    assert np.array_equal(traj.positions[:, 0], _counts(cell8, jd["axes"], np.array(jd["waypoints"])[0]))
    assert np.all(traj.velocities[:, 0] == 0)
    assert traj.info["time_scale"] <= 1.25


@SETTINGS
@given(st.data())
def test_small_path_jobs(cell8: CellConfig, data: st.DataObject) -> None:
    """Never refused (before: 5.5 % of such paths, where 1.46x slower was not enough for the acceleration
    budget), and never more points than the uniform grid that keeps the same promises (before: a slowed
    replay was not compared with it).

    Each rest-to-rest run of a few ms has its phases on whole ms, and a blended run of a few tens of ms its
    chain's repairs (measured on 1200 random small paths: at most 3.0 ms per run beyond 1.02 x the optimum,
    median 1.09 x); the quantisation may need the motion slower (at most 2.4x on 2700 of them)."""
    _check_path(cell8, data.draw(small_path_jobs(cell8)), 0.004)


@SETTINGS
@given(st.data())
def test_move_jobs(cell8: CellConfig, data: st.DataObject) -> None:
    jd = data.draw(move_jobs(cell8))
    job, traj = _plan(cell8, jd)
    assert_not_more_than_uniform(traj, job, cell8)
    assert traj.info["straight_line"] == 1.0  # along the line from start to target (ruckig, phase-synchronised)
    assert traj.info["line_deviation_counts"] <= traj.tolerance_counts + 1.0
    start = np.array(jd["start"])
    end = start + np.array(jd["target"]) if jd["mode"] == "relative" else np.array(jd["target"])
    assert np.array_equal(traj.positions[:, 0], _counts(cell8, jd["axes"], start))
    assert_invariants(traj, cell8, target_counts=_counts(cell8, jd["axes"], end))


@SETTINGS
@given(st.data())
def test_timed_jobs(cell8: CellConfig, data: st.DataObject) -> None:
    jd = data.draw(timed_jobs(cell8))
    job, traj = _plan(cell8, jd)
    assert_not_more_than_uniform(traj, job, cell8)
    assert_invariants(traj, cell8, target_counts=_counts(cell8, jd["axes"], np.array(jd["positions"][-1])))
    total_ms = (jd["times"][-1] - jd["times"][0]) * 1000.0
    assert total_ms - 1e-6 <= traj.duration_ms < total_ms + 1.0  # the user's timing, to the ms


@SETTINGS
@given(st.data())
def test_pvt_jobs(cell: CellConfig, data: st.DataObject) -> None:
    jd = data.draw(pvt_jobs(cell))
    try:
        job, traj = _plan(cell, jd)
    except PlanningError as e:
        # rows whose own Hermite exceeds a limit, or whose quantisation the drive cannot reproduce within
        # the acceleration budget, are rejected with a reason (raw rows are never re-timed)
        assume(not (e.code == "INFEASIBLE" and ("needs a" in e.message or "cannot reproduce" in e.message)))
        raise
    assert_invariants(traj, cell, target_counts=_counts(cell, jd["axes"], np.array(jd["positions"][-1])))
    assert_not_more_than_uniform(traj, job, cell)


@st.composite
def states(draw: st.DrawFn, cell: CellConfig) -> tuple[list[str], list[float], list[float], list[float]]:
    axes = _axes(draw, cell)
    pos, vel, acc = [], [], []
    for a in axes:
        ax = cell.axis(a)
        pos.append(_position(draw, cell, a, 0.3, 0.7))
        vel.append(draw(st.floats(-1.0, 1.0)) * ax.velocity)
        acc.append(draw(st.floats(-1.0, 1.0)) * ax.acceleration)
    return axes, pos, vel, acc


@SETTINGS
@given(st.data())
def test_stops(cell8: CellConfig, data: st.DataObject) -> None:
    axes, pos, vel, acc = data.draw(states(cell8))
    traj = plan_stop(cell8, axes, pos, vel, acc)
    assert_invariants(traj, cell8)
    cpu = traj.counts_per_unit
    conv = traj.counts_per_rev / 60000.0
    assert np.array_equal(traj.positions[:, 0], np.round(np.array(pos) * cpu))
    assert np.array_equal(traj.velocities[:, 0], np.round(np.array(vel) * cpu / 1000.0 / conv))


@pytest.mark.parametrize("n", [1, 3, 8])
def test_axis_counts(cell8: CellConfig, n: int) -> None:
    axes = list(cell8.axis_names()[:n])
    wp = [[0.0] * n, [0.4] * n, [-0.2] * n]
    _job, traj = _plan(cell8, {"kind": "path", "axes": axes, "waypoints": wp})
    assert traj.n_axes == n
    assert_invariants(traj, cell8, target_counts=_counts(cell8, axes, np.array(wp[-1])))
