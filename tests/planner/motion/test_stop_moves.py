"""Jerk-limited moves from waypoint to waypoint with their corner stops cut short (planner/motion/stop_moves.py):
the limits and the tolerance at every ms, never slower than stopping, and what plan_job takes."""

from __future__ import annotations

import itertools
import os
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planner import plan_job
from planner.config import CellConfig
from planner.job import effective_limits, job_from_dict, path_tolerance
from planner.motion.geometry import point_to_path, polyline_deviation
from planner.motion.reference import Reference
from planner.motion.stop_moves import stop_moves
from planner.plan import axis_configs

SETTINGS = settings(max_examples=int(os.environ.get("JERK_EXAMPLES", "12")), deadline=None)
AXES = ["j4", "j1"]
WAYPOINTS = [[-1.888, 0.54], [-1.217, -0.86], [-1.938, -0.612], [1.358, 0.32]]  # a random path of the benchmark


def _setup(cell: CellConfig, axes: list[str]) -> tuple[Any, np.ndarray]:
    job = job_from_dict({"kind": "path", "axes": axes, "waypoints": [[0.0] * len(axes), [0.1] * len(axes)]}, cell)
    cpu = np.array([c.counts_per_unit for c in axis_configs(job.axes, cell)])
    return effective_limits(job, cell), cpu


def _check(ref: Reference, wp: np.ndarray, lim: Any, cpu: np.ndarray, tol: np.ndarray | None) -> None:
    """At every ms: velocity, acceleration and jerk (the change of acceleration over the ms) within the limits,
    no acceleration step, rest at both ends on the end waypoints; within `tol` of the polyline and passing
    every waypoint within it (exactly on the polyline without `tol`)."""
    c = cpu[:, None]
    assert np.all(np.abs(ref.velocities) * 1000.0 / c <= lim.velocity[:, None] * (1 + 1e-9))
    assert np.all(np.abs(ref.acc_right) * 1.0e6 / c <= lim.acceleration[:, None] * (1 + 1e-9))
    assert np.all(np.abs(np.diff(ref.acc_right, axis=1)) * 1.0e9 / c <= lim.jerk[:, None] * (1 + 1e-6))
    step = np.abs(ref.acc_right - ref.acc_left).max(axis=1) * 1.0e9 / cpu  # as a jerk over the ms
    assert np.all(step <= lim.jerk * 1e-6), step / lim.jerk
    assert np.allclose(ref.positions[:, 0], wp[0] * cpu) and np.allclose(ref.positions[:, -1], wp[-1] * cpu)
    assert np.abs(ref.velocities[:, [0, -1]]).max() == 0.0
    floor = 1e-3 / cpu  # a thousandth of a count: the arithmetic's noise
    scale = floor if tol is None else np.maximum(tol, floor)
    drive = (ref.positions / c).T
    assert polyline_deviation(drive, wp, scale * (1 + 1e-9)).max() <= 1.0 + 1e-6
    assert point_to_path(wp, drive, scale * (1 + 1e-9)).max() <= 1.0 + 1e-6


def test_the_stops_are_cut_short_within_the_tolerance(cell: CellConfig) -> None:
    lim, cpu = _setup(cell, AXES)
    wp = np.array(WAYPOINTS)
    tol = np.array([0.1, 0.1])
    stops = stop_moves(wp, cpu, lim.velocity, lim.acceleration, lim.jerk)
    info: dict[str, float] = {}
    cut = stop_moves(wp, cpu, lim.velocity, lim.acceleration, lim.jerk, tolerance=tol, info=info)
    _check(stops, wp, lim, cpu, None)
    _check(cut, wp, lim, cpu, tol)
    assert info["jerk_transitions"] == 2  # both corners (with ruckig's transitions at half the jerk: the first)
    assert cut.duration_ms < stops.duration_ms, (cut.duration_ms, stops.duration_ms)
    # the axes stop at one corner only (they did at both)
    speed = np.abs(cut.velocities).max(axis=0)
    assert np.count_nonzero(speed[1:-1] == 0.0) < np.count_nonzero(np.abs(stops.velocities).max(axis=0)[1:-1] == 0.0)


def test_no_tolerance_no_transition(cell: CellConfig) -> None:
    lim, cpu = _setup(cell, AXES)
    wp = np.array(WAYPOINTS)
    stops = stop_moves(wp, cpu, lim.velocity, lim.acceleration, lim.jerk)
    info: dict[str, float] = {}
    zero = stop_moves(wp, cpu, lim.velocity, lim.acceleration, lim.jerk, tolerance=np.zeros(2), info=info)
    assert info["jerk_transitions"] == 0
    assert np.array_equal(zero.positions, stops.positions)


def test_a_corner_that_reverses_passes_its_waypoint(cell: CellConfig) -> None:
    """Nearly back along the same line: a transition could keep near both segments and turn back early; it
    must come within the tolerance of the waypoint."""
    lim, cpu = _setup(cell, ["j1", "j2"])
    wp = np.array([[0.0, 0.0], [0.8, 0.0], [0.0, 0.01]])
    tol = np.array([0.02, 0.02])
    cut = stop_moves(wp, cpu, lim.velocity, lim.acceleration, lim.jerk, tolerance=tol)
    _check(cut, wp, lim, cpu, tol)


def test_an_exact_reversal_keeps_every_bound(cell: CellConfig) -> None:
    """Back along the same segment: the two moves are mirror images. A transition between their constant-
    acceleration phases, (p, v, -A) -> (p, -v, -A), made ruckig 0.19.4 end the process (a segmentation fault)
    when ruckig planned the transitions; the shared phases solve it like any other joint."""
    lim, cpu = _setup(cell, ["j1", "j2"])
    wp = np.array([[0.0, 0.0], [0.8, 0.5], [0.0, 0.0]])
    tol = np.array([0.06, 0.04])
    cut = stop_moves(wp, cpu, lim.velocity, lim.acceleration, lim.jerk, tolerance=tol)
    _check(cut, wp, lim, cpu, tol)
    assert cut.duration_ms <= stop_moves(wp, cpu, lim.velocity, lim.acceleration, lim.jerk).duration_ms


def test_a_transition_is_three_phases_every_axis_shares(cell: CellConfig) -> None:
    """Each transition is three constant-jerk phases with the same ends on every axis, each at least 35 ms
    where that fits: between the plan's phase ends (its hints, where the encoder may put knots) every axis'
    acceleration is a straight line, so the drive's cubic reproduces it exactly on knots that far apart. With
    ruckig's transitions each axis had seven phases of its own: hints 1-40 ms apart."""
    from planner.motion.stop_moves import MIN_PHASE_MS, PHASES

    lim, cpu = _setup(cell, AXES)
    wp = np.array(WAYPOINTS)
    stops = stop_moves(wp, cpu, lim.velocity, lim.acceleration, lim.jerk)
    info: dict[str, float] = {}
    cut = stop_moves(wp, cpu, lim.velocity, lim.acceleration, lim.jerk, tolerance=np.array([0.1, 0.1]), info=info)
    edges = np.concatenate([[0], cut.hints, [cut.duration_ms]])
    for lo, hi in itertools.pairwise(edges):
        jerk = np.diff(cut.acc_right[:, lo:hi + 1], axis=1)[:, 1:-1]  # per ms, inside one phase (a move's phase
        if jerk.shape[1] > 1:  # may end between two ms: the ms either side of each end are left out)
            assert np.allclose(jerk, jerk[:, :1], rtol=1e-6, atol=1e-12 * cpu.max()), (lo, hi)
    # the first transition starts where the plan leaves the stopping one: three phases of equal length (on
    # whole ms), here at least 35 ms each
    m = cut.positions.shape[1]
    start = int(np.argmax(np.any(cut.positions != stops.positions[:, :m], axis=0))) - 1
    k = int(np.searchsorted(edges, start))
    assert edges[k] == start, (start, edges)
    lengths = np.diff(edges[k:k + PHASES + 1])
    assert np.ptp(lengths) <= 1 and lengths.min() >= MIN_PHASE_MS[0], lengths


def test_plan_job_takes_the_cut_moves_where_faster_and_keeps_the_drive_within_the_tolerance(cell: CellConfig) -> None:
    from planner_checks import assert_path_within

    job = job_from_dict({"kind": "path", "axes": AXES, "waypoints": WAYPOINTS, "jerk_limited": True}, cell)
    traj = plan_job(job, cell)
    assert traj.info["jerk_stops"] == 1.0 and traj.info["jerk_transitions"] == 2.0
    lim, cpu = _setup(cell, AXES)
    stops = stop_moves(np.array(WAYPOINTS), cpu, lim.velocity, lim.acceleration, lim.jerk)
    assert traj.duration_ms < stops.duration_ms  # 2939 ms against 3100 (ruckig's transitions: 2971)
    # the drive's acceleration continuous across the knots within the jerk bound (issue 26): 0.32 and 0.85 here
    assert max(s.knot_acceleration_step * 1000.0 / s.jerk_limit for s in traj.stats) <= 1.0
    assert_path_within(traj, job, cell)
    assert path_tolerance(job, cell) == pytest.approx([0.062, 0.06])  # the default: 1 % of the travel
    assert max(s.peak_jerk / s.jerk_limit for s in traj.stats) <= 1.05  # the drive's, inside its segments


@st.composite
def _paths(draw: st.DrawFn, cell: CellConfig) -> tuple[list[str], np.ndarray, np.ndarray]:
    n = draw(st.integers(1, 4))
    axes = [a.name for a in cell.axes[:n]]
    k = draw(st.integers(3, 6))
    wp = np.array([[draw(st.floats(0.3 * cell.axis(a).position_min, 0.3 * cell.axis(a).position_max,
                                   allow_nan=False)) for a in axes] for _ in range(k)])
    tol = np.array([draw(st.floats(0.0, 0.05)) for _ in axes])
    return axes, wp, tol


@SETTINGS
@given(st.data())
def test_random_paths_keep_every_bound_and_are_never_slower_than_stopping(cell8: CellConfig,
                                                                           data: st.DataObject) -> None:
    axes, wp, tol = data.draw(_paths(cell8))
    lim, cpu = _setup(cell8, axes)
    wp = np.round(wp * cpu) / cpu  # on whole counts (plan_job snaps the ends)
    stops = stop_moves(wp, cpu, lim.velocity, lim.acceleration, lim.jerk)
    cut = stop_moves(wp, cpu, lim.velocity, lim.acceleration, lim.jerk, tolerance=tol)
    _check(cut, wp, lim, cpu, tol)
    assert cut.duration_ms <= stops.duration_ms
