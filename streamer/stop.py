"""The streamer core's stop planner, backed by the planner's jerk-limited stop (ruckig).

The core asks for a stop from the state at the end of what is queued, in drive units (counts, rpm,
counts/ms^2, see `StopRequest`); `planner.stop.plan_stop_from_wire` plans it from exactly those wire
values, so knot 0 of the stop is the queued knot to the count and the rpm. Planning runs on whatever
thread handles the cancel (a stop for 6 axes plans in a few ms; the core has a SYNC period of margin
per queued record).
"""

from __future__ import annotations

from planner.config import CellConfig
from planner.stop import plan_stop_from_wire
from planner.trajectory import PvtTrajectory
from streamer.core.plan_source import StopPlanner, StopRequest


def make_stop_planner(cell: CellConfig, traj: PvtTrajectory) -> StopPlanner:
    names_by_node = dict(zip(traj.node_ids, traj.axis_names, strict=True))

    def plan(request: StopRequest) -> PvtTrajectory:
        names = [names_by_node[n] for n in request.node_ids]
        return plan_stop_from_wire(
            cell,
            names,
            request.positions_counts,
            request.velocities_rpm,
            request.accelerations_counts_per_ms2,
            tolerance_counts=traj.tolerance_counts,
        )

    return plan
