"""Shared checks for the planner tests, imported by name (`from planner_checks import ...`) from tests/planner and
its motion/ and encoding/ folders: these are rootless test directories (no __init__.py; pytest's default
`prepend` import mode), and loading tests/planner/conftest.py puts tests/planner on sys.path for all of them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from planner.config import CellConfig
from planner.encoding import hermite
from planner.encoding.encoder import ACC_EXCESS_LIMIT, VELOCITY_SLACK, Knots, planned_demand
from planner.encoding.record import PvtRecord, pack, unpack
from planner.encoding.uniform import meets
from planner.job import Job, PathData, effective_limits, path_tolerance
from planner.motion.geometry import point_to_path, polyline_deviation
from planner.plan import axis_configs, axis_scales
from planner.trajectory import PvtTrajectory

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def assert_invariants(
    traj: PvtTrajectory, cell: CellConfig, *, target_counts: np.ndarray | None = None
) -> None:
    """Everything the encoder promises, checked from the outside (through planner.encoding.hermite)."""
    n = traj.n_axes
    dt = np.asarray(traj.dt_ms)
    # shared grid of whole ms in 1..255
    assert dt.dtype.kind == "i" and dt.size >= 1
    assert dt.min() >= 1 and dt.max() <= 255
    assert traj.positions.shape == (n, dt.size + 1) == traj.velocities.shape
    for i in range(n):
        recs = traj.records(i)
        assert [r.time_ms for r in recs[:-1]] == dt.tolist()  # every axis on the same grid
        assert recs[-1] == PvtRecord(int(traj.positions[i, -1]), 0, 0)  # end record
        for r in recs:
            assert unpack(pack(r)) == r  # every record fits the wire
    # exact end at rest
    assert np.all(traj.velocities[:, -1] == 0)
    if target_counts is not None:
        assert np.array_equal(traj.positions[:, -1], target_counts)
    # the drive's reconstruction, rounded as the drive rounds, within tolerance of the planned demand
    pos, vel, acc = traj.drive_profile()
    assert np.all(np.isfinite(pos)) and np.all(np.isfinite(vel)) and np.all(np.isfinite(acc))
    assert np.all(np.isfinite(traj.plan.positions))
    demand = hermite.round_counts_array(pos)
    dev = np.abs(demand - hermite.round_counts_array(traj.plan.positions))
    assert dev.max() <= traj.tolerance_counts
    assert np.array_equal(demand, traj.demand())
    assert demand[:, -1].tolist() == traj.positions[:, -1].tolist()
    # C1 at the knots: the velocity arriving at a knot equals the one leaving it (the knot's own value)
    conv = traj.counts_per_rev / 60000.0
    kt = traj.knot_times_ms
    for i in range(n):
        np.testing.assert_allclose(vel[i, kt], traj.velocities[i] * conv[i], atol=1e-6)
        for k in range(1, dt.size):  # leaving knot k: the next segment's velocity at tau = -T
            a, b, c, _d = hermite.coefficients(
                traj.positions[i, k],
                traj.velocities[i, k] * conv[i],
                traj.positions[i, k + 1],
                traj.velocities[i, k + 1] * conv[i],
                int(dt[k]),
            )
            _p, v0, _a = hermite.evaluate((a, b, c, _d), -float(dt[k]))
            assert abs(v0 - traj.velocities[i, k] * conv[i]) < 1e-6
    # limits: velocity (axis limit + 0.5 % or one rpm, and 0x607F), acceleration (0x60C5 and 5 % excess)
    for i, s in enumerate(traj.stats):
        ax = cell.axis(traj.axis_names[i])
        cpu = traj.counts_per_unit[i]
        vmax = np.abs(vel[i]).max() * 1000.0 / cpu
        lim = max(s.velocity_limit * (1 + VELOCITY_SLACK), s.velocity_limit + conv[i] * 1000.0 / cpu)
        if traj.kind != "stop":
            assert vmax <= lim + 1e-9, (traj.axis_names[i], vmax, lim)
        assert np.abs(vel[i]).max() / conv[i] <= ax.max_profile_velocity_rpm + 1e-9
        assert s.peak_acceleration <= ax.max_acceleration + 1e-9
        assert s.acceleration_excess_share <= ACC_EXCESS_LIMIT + 1e-12
        assert s.max_deviation_counts <= traj.tolerance_counts


def assert_path_within(traj: PvtTrajectory, job: Job, cell: CellConfig) -> None:
    """A path job along straight segments: at every ms of the drive's demand, every axis within its
    path tolerance of the polyline through the job's waypoints, and of every waypoint at some ms (an
    axis whose tolerance is below what the encoding may add, tolerance_counts + 1 count, within that)."""
    assert isinstance(job.data, PathData) and job.data.geometry == "lines"
    cpu = traj.counts_per_unit
    scale = np.maximum(path_tolerance(job, cell), (traj.tolerance_counts + 1.0) / cpu) * (1 + 1e-9)
    drive = (traj.demand() / cpu[:, None]).T  # (M+1, n) user units, what the drive commands
    wp = np.asarray(job.data.waypoints)
    dev = polyline_deviation(drive, wp, scale)
    assert dev.max() <= 1.0, (float(dev.max()), int(np.argmax(dev)))
    # the drive moves continuously between two ms: the waypoint against the motion, not its samples
    near = point_to_path(wp, drive, scale)
    assert near.max() <= 1.0, (int(np.argmax(near)), float(near.max()))


def assert_not_more_than_uniform(traj: PvtTrajectory, job: Job, cell: CellConfig) -> None:
    """No uniform grid with fewer points than the encoding meets the tolerance on the same plan and
    keeps the planner's margins (the encoding never needs more records than the coarsest uniform
    grid that is a valid encoding, planner/encoding/uniform.py; the benchmark also counts against grids that
    only meet the tolerance)."""
    scales = axis_scales(axis_configs(job.axes, cell), effective_limits(job, cell))
    first = Knots(np.array([0]), traj.positions[:, :1], traj.velocities[:, :1])
    want = planned_demand(traj.plan)
    m = traj.duration_ms
    for dt in range(min(255, m), 0, -1):
        points = -(-m // dt) + 1
        if points >= traj.n_points:
            break
        assert not meets(traj.plan, scales, traj.tolerance_counts, dt, first, want, margins=True), (
            dt,
            points,
            traj.n_points,
        )
