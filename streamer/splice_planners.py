"""The streamer core's stop, emergency stop and change planners, backed by the planner's ruckig motions.

The core asks for a trajectory from the state at the end of what is queued, in wire units (`StopRequest`);
`planner.motion.stop.plan_stop_from_wire`, `plan_emergency_stop_from_wire` (`make_emergency_planner`) and
`plan_change_from_wire` (`ChangePlanner`, which keeps what it planned for the job that asked) plan from
exactly those values, so knot 0 is the queued knot to the count and the rpm. Planning runs on the thread
that handles the verb (a few ms for 6 axes, against a SYNC period of margin per queued record).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

from planner.config import CellConfig
from planner.motion.stop import ChangePlan, plan_change_from_wire, plan_emergency_stop_from_wire, plan_stop_from_wire
from planner.trajectory import PvtTrajectory
from streamer.core.plan_source import StopPlanner, StopRequest


def _wire_planner(cell: CellConfig, traj: PvtTrajectory, plan_from_wire: Callable[..., PvtTrajectory]) -> StopPlanner:
    """A core StopPlanner calling `plan_from_wire` (planner/motion/stop.py) with the request's state in drive units."""
    names_by_node = dict(zip(traj.node_ids, traj.axis_names, strict=True))

    def plan(request: StopRequest) -> PvtTrajectory:
        names = [names_by_node[n] for n in request.node_ids]
        return plan_from_wire(
            cell,
            names,
            request.positions_counts,
            request.velocities_rpm,
            request.accelerations_counts_per_ms2,
            tolerance_counts=traj.tolerance_counts,
        )

    return plan


def make_stop_planner(cell: CellConfig, traj: PvtTrajectory) -> StopPlanner:
    """The planner of a cancel's stop: jerk-limited, at each axis' acceleration limit."""
    return _wire_planner(cell, traj, plan_stop_from_wire)


def make_emergency_planner(cell: CellConfig, traj: PvtTrajectory) -> StopPlanner:
    """The planner of a `streamer.core.EmergencyStop`: the stop at each axis' emergency deceleration (cell config
    `emergency_deceleration`), from the same state as the cancel's stop."""
    return _wire_planner(cell, traj, plan_emergency_stop_from_wire)


class ChangePlanner:
    """The `planner` of a `Change` to absolute targets (user units, by axis name): called by the core with
    the state at the end of the queue; `planned` is what it returned (None until then, or when it raised),
    `error` the exception it raised, `planning_s` the wall time it took."""

    def __init__(self, cell: CellConfig, traj: PvtTrajectory, target: dict[str, float], *,
                 tolerance_counts: int | None = None, velocity_limit: Sequence[float] | None = None,
                 acceleration_limit: Sequence[float] | None = None, jerk_limit: Sequence[float] | None = None):
        names = tuple(str(n) for n in traj.axis_names)
        missing = [n for n in names if n not in target]
        extra = [n for n in target if n not in names]
        if missing or extra:
            raise ValueError(f"a change must give a target for every axis of the running job {list(names)}"
                             f" (missing {missing}, not in the job {extra})")
        self._cell = cell
        self._names_by_node = dict(zip(traj.node_ids, names, strict=True))
        self._target = dict(target)
        self._tol = traj.tolerance_counts if tolerance_counts is None else tolerance_counts
        self._limits = (velocity_limit, acceleration_limit, jerk_limit)
        self.planned: ChangePlan | None = None
        self.error: BaseException | None = None
        self.planning_s = 0.0

    def __call__(self, request: StopRequest) -> PvtTrajectory:
        names = [self._names_by_node[n] for n in request.node_ids]
        t0 = time.perf_counter()
        try:
            self.planned = plan_change_from_wire(
                self._cell, names, request.positions_counts, request.velocities_rpm,
                request.accelerations_counts_per_ms2, [self._target[n] for n in names],
                tolerance_counts=self._tol, velocity_limit=self._limits[0], acceleration_limit=self._limits[1],
                jerk_limit=self._limits[2],
            )
        except BaseException as exc:
            self.error = exc
            raise
        finally:
            self.planning_s = time.perf_counter() - t0
        return self.planned.trajectory
