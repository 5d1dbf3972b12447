"""Pure math, no I/O: cell configs and jobs -> time-optimal trajectories -> PVT points.

Public API (imported lazily, so `import planner.encoding.record` stays cheap for the bus layer):

    planner.plan_job(job, cell, *, start=None) -> PvtTrajectory
    planner.PvtTrajectory, planner.AxisStats
    planner.Job, planner.job_from_dict, planner.job_to_dict, planner.load_job
    planner.plan_stop (also planner.motion.stop.plan_stop), planner.plan_stop_from_wire
    planner.warm_up() (load the compiled kernels and the solvers ahead of the first job)
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from planner.job import Job, job_from_dict, job_to_dict, load_job
    from planner.motion.stop import plan_stop, plan_stop_from_wire
    from planner.plan import plan_job, warm_up
    from planner.trajectory import AxisStats, PvtTrajectory

_EXPORTS = {
    "plan_job": "planner.plan",
    "warm_up": "planner.plan",
    "PvtTrajectory": "planner.trajectory",
    "AxisStats": "planner.trajectory",
    "Job": "planner.job",
    "job_from_dict": "planner.job",
    "job_to_dict": "planner.job",
    "load_job": "planner.job",
    "plan_stop": "planner.motion.stop",
    "plan_stop_from_wire": "planner.motion.stop",
}

__all__ = [
    "AxisStats",
    "Job",
    "PvtTrajectory",
    "job_from_dict",
    "job_to_dict",
    "load_job",
    "plan_job",
    "plan_stop",
    "plan_stop_from_wire",
    "warm_up",
]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'planner' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(module), name)
