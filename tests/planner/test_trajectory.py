"""PvtTrajectory: records, plan and reconstruction at any time, knot states, CSV; plan_job from a start.
(The stops planned from its knot states: motion/test_stop.py.)"""

from __future__ import annotations

import numpy as np
import pytest
from planner_checks import CONFIGS

from planner import plan_job
from planner.config import CellConfig
from planner.encoding import hermite
from planner.encoding.record import PvtRecord
from planner.job import load_job
from planner.trajectory import CSV_COLUMNS, PvtTrajectory


@pytest.fixture(scope="module")
def demo(cell: CellConfig) -> PvtTrajectory:
    return plan_job(load_job(CONFIGS / "jobs" / "demo-path.toml", cell), cell)


def test_shape_and_records(demo: PvtTrajectory) -> None:
    assert demo.axis_names == ("j1", "j2", "j3", "j4", "j5", "j6")
    assert demo.node_ids == (1, 2, 3, 4, 5, 6)
    assert demo.n_points == demo.n_segments + 1 == demo.positions.shape[1]
    assert demo.duration_ms == int(demo.dt_ms.sum()) and demo.duration_s == demo.duration_ms / 1000
    assert demo.knot_times_s[-1] == pytest.approx(demo.duration_s)
    recs = demo.records(2)
    assert len(recs) == demo.n_segments + 1
    assert recs[0] == PvtRecord(int(demo.positions[2, 1]), int(demo.velocities[2, 1]), int(demo.dt_ms[0]))
    assert recs[-1].is_end and recs[-1].position == recs[-2].position
    assert all(len(b) == 8 for b in demo.packed(2))
    for name in ("dt_ms", "positions", "velocities"):
        assert not getattr(demo, name).flags.writeable


def test_reference_and_reconstruction(demo: PvtTrajectory) -> None:
    t = demo.knot_times_s
    # at the knots the drive's polynomial passes through the knot positions exactly
    np.testing.assert_allclose(demo.reconstruction(t), demo.positions, atol=1e-6)
    # the plan at any time: the plan's own samples at whole ms, smooth in between
    ms = np.arange(0, demo.duration_ms + 1, 37)
    np.testing.assert_allclose(demo.reference(ms / 1000.0), demo.plan.positions[:, ms], atol=1e-9)
    tt = np.linspace(0, demo.duration_s, 1001)
    assert np.abs(demo.reconstruction(tt) - demo.reference(tt)).max() <= demo.tolerance_counts + 1.0
    # per-ms: the drive's demand is the reconstruction rounded as the drive rounds
    pos, _vel, _acc = demo.drive_profile()
    np.testing.assert_allclose(demo.reconstruction(np.arange(demo.duration_ms + 1) / 1000.0), pos, atol=1e-6)
    assert np.array_equal(demo.demand(), hermite.round_counts_array(pos))
    assert np.abs(demo.deviation()).max() <= demo.tolerance_counts
    # outside the motion the axes rest where it starts and ends
    assert np.array_equal(
        np.round(demo.reconstruction([-1.0, demo.duration_s + 1.0])), demo.positions[:, [0, -1]]
    )


def test_stats(demo: PvtTrajectory) -> None:
    s = demo.summary()
    assert s["points"] == demo.n_points and s["duration_s"] == demo.duration_s
    assert len(s["axes"]) == 6
    for a in s["axes"]:
        assert a["max_deviation_counts"] <= demo.tolerance_counts
        assert a["peak_velocity"] <= a["velocity_limit"] * 1.005
        assert a["peak_acceleration"] <= a["drive_acceleration_limit"]
        assert a["acceleration_excess_share"] <= 0.05
    assert demo.info["optimal_s"] > 0


def test_csv(demo: PvtTrajectory) -> None:
    lines = demo.to_csv().splitlines()
    assert lines[0] == ",".join(CSV_COLUMNS)
    assert len(lines) == 1 + demo.n_axes * demo.n_points
    first = lines[1].split(",")
    assert first[0] == "j1" and first[1] == "1" and first[2] == "0" and first[4] == "0"  # start, dt 0
    second = lines[2].split(",")
    assert int(second[4]) == int(demo.dt_ms[0]) and int(second[5]) == int(demo.positions[0, 1])


def test_plan_job_start(cell: CellConfig) -> None:
    from planner.errors import PlanningError
    from planner.job import job_from_dict

    move = job_from_dict({"kind": "move", "axes": ["j1"], "target": [0.1], "mode": "relative"}, cell)
    traj = plan_job(move, cell, start=[0.5])
    assert traj.positions[0, 0] == round(0.5 * traj.counts_per_unit[0])
    assert traj.positions[0, -1] == round(0.6 * traj.counts_per_unit[0])
    path = job_from_dict({"kind": "path", "axes": ["j1"], "waypoints": [[0.0], [0.2]]}, cell)
    near = plan_job(path, cell, start=[0.5 / traj.counts_per_unit[0]])  # half a count away: fine
    assert near.positions[0, 0] == 0
    with pytest.raises(PlanningError) as e:
        plan_job(path, cell, start=[0.01])
    assert e.value.code == "INFEASIBLE" and e.value.path == "waypoints[0][0]"
