"""planner/motion/stop.py: stops from a plan's knot states (the stream continues seamlessly from the queued
knot), at rest, time-synchronised, from above the limits, and refused inputs."""

from __future__ import annotations

import numpy as np
import pytest
from planner_checks import CONFIGS, assert_invariants

from planner import plan_job
from planner.config import CellConfig
from planner.job import load_job
from planner.motion.stop import plan_stop, plan_stop_from_wire
from planner.trajectory import PvtTrajectory


@pytest.fixture(scope="module")
def demo(cell: CellConfig) -> PvtTrajectory:
    return plan_job(load_job(CONFIGS / "jobs" / "demo-path.toml", cell), cell)


def test_stop_from_the_middle_of_a_job(cell: CellConfig, demo: PvtTrajectory) -> None:
    for k in (1, demo.n_segments // 3, demo.n_segments // 2, demo.n_segments - 1):
        p, v, a = demo.knot_state(k)
        stop = plan_stop(cell, demo.axis_names, p, v, a)
        assert_invariants(stop, cell)
        # knot 0 of the stop is exactly the queued knot (the stream continues seamlessly)
        assert np.array_equal(stop.positions[:, 0], demo.positions[:, k])
        assert np.array_equal(stop.velocities[:, 0], demo.velocities[:, k])
        assert np.all(stop.velocities[:, -1] == 0)
        # the wire-unit variant gives the same stop
        acc_counts = a * demo.counts_per_unit / 1.0e6
        same = plan_stop_from_wire(
            cell, demo.axis_names, demo.positions[:, k], demo.velocities[:, k], acc_counts
        )
        assert np.array_equal(same.positions, stop.positions) and np.array_equal(same.dt_ms, stop.dt_ms)


def test_stop_at_rest_is_a_no_op(cell: CellConfig) -> None:
    stop = plan_stop(cell, ["j1", "j2"], [0.1, -0.2], [0.0, 0.0], [0.0, 0.0])
    assert stop.n_segments == 1 and stop.duration_ms == 1
    assert np.all(stop.positions == stop.positions[:, :1]) and np.all(stop.velocities == 0)


def test_stop_time_synchronised(cell: CellConfig) -> None:
    # a fast axis and a slow one come to rest together (the slow one sets the stopping time)
    stop = plan_stop(cell, ["j1", "j4"], [0.0, 0.0], [2.0, 0.3], [0.0, 0.0])
    vel = stop.drive_profile()[1]
    moving = np.abs(vel) > 1e-3
    assert moving[0].nonzero()[0].max() >= stop.duration_ms - 30
    assert moving[1].nonzero()[0].max() >= stop.duration_ms - 30


def test_stop_from_above_the_limits(cell: CellConfig) -> None:
    ax = cell.axis("j1")
    stop = plan_stop(cell, ["j1"], [0.0], [ax.velocity], [ax.acceleration * 1.2])
    assert_invariants(stop, cell)
    assert stop.stats[0].peak_velocity > ax.velocity  # it must first bring the acceleration to zero


def test_stop_errors(cell: CellConfig) -> None:
    from planner.errors import PlanningError

    with pytest.raises(PlanningError) as e:
        plan_stop(cell, ["j1", "j2"], [0.0], [0.0, 0.0], [0.0, 0.0])
    assert e.value.code == "AXIS_COUNT"
    with pytest.raises(PlanningError) as e:
        plan_stop(cell, ["j1"], [0.0], [float("nan")], [0.0])
    assert e.value.code == "NONFINITE"
    with pytest.raises(PlanningError) as e:
        plan_stop(cell, ["j7"], [0.0], [0.0], [0.0])
    assert e.value.code == "AXIS_ID"
