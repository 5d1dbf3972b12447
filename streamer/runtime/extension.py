"""Open-ended (velocity) motion on a runtime: the next chunk planned off the SYNC thread, and a change into
velocity mode.

Theory of operation. The core asks its `Extender` for the next chunk on the thread that feeds it, the SYNC
loop in real time, which must answer every SYNC within a period; planning a chunk takes too large a share
of one (docs/streamer.md, velocity jobs). `PrefetchExtender` plans each chunk on a worker thread as soon
as the chunk before it is known, so the SYNC thread normally only takes it; until it is ready it answers
None and the core asks again (until `extend_need_ms`: EXTENSION_FAILED). A chunk extends the
`CruiseState` it carries; after a change the extender starts on the new trajectory when first asked (the
core asks early enough to cover that). `VelocityChangePlanner` is the `Change` planner of a velocity move
replacing a running motion: `plan_velocity` from the queue's end state, open-ended.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

from planner.config import CellConfig
from planner.job import Job
from planner.motion.travel import MotionState, extend_velocity, plan_velocity
from planner.trajectory import PvtTrajectory
from streamer.core.plan_source import PvtTrajectoryLike, StopRequest


class PrefetchExtender:
    """The core's `Extender`, planning each next chunk on a worker thread ahead of the core's request.

    `prefetch(traj)` starts planning the chunk after `traj`; calling the extender with `traj` returns that
    chunk when it is planned (and starts the one after it), None while it is not, and raises what the
    planner raised. `close()` stops the worker (chunks not taken are dropped)."""

    def __init__(self, extend: Callable[[PvtTrajectory], PvtTrajectory] = extend_velocity):
        self._extend = extend
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="pvt-extend")
        self._lock = threading.Lock()
        # id(traj) -> (traj, its next chunk): the trajectory is kept so its id is not reused meanwhile
        self._ahead: dict[int, tuple[Any, Future[tuple[PvtTrajectory, float]]]] = {}
        self.planning_s: list[float] = []  # wall time of every chunk planned (the worker's)
        self.not_ready = 0  # requests answered None (the chunk was still being planned)

    def _timed(self, traj: PvtTrajectory) -> tuple[PvtTrajectory, float]:
        t0 = time.perf_counter()
        chunk = self._extend(traj)
        return chunk, time.perf_counter() - t0

    def prefetch(self, traj: Any) -> None:
        """Start planning the chunk after `traj` (nothing for a trajectory that ends at rest)."""
        if not getattr(traj, "open_ended", False):
            return
        with self._lock:
            if id(traj) not in self._ahead:
                self._ahead[id(traj)] = (traj, self._pool.submit(self._timed, traj))

    def __call__(self, traj: PvtTrajectoryLike) -> PvtTrajectoryLike | None:
        with self._lock:
            entry = self._ahead.get(id(traj))
        if entry is None:
            self.prefetch(traj)
            self.not_ready += 1
            return None
        future = entry[1]
        if not future.done():
            self.not_ready += 1
            return None
        with self._lock:
            self._ahead.pop(id(traj), None)
        chunk, seconds = future.result()  # raises the planner's error: the core stops the motion
        self.planning_s.append(seconds)
        self.prefetch(chunk)
        return chunk

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
        with self._lock:
            self._ahead.clear()


@dataclass(frozen=True)
class VelocityPlan:
    """What a `VelocityChangePlanner` planned (the shape of planner.motion.stop.ChangePlan: a velocity has no target
    to pass, so no overrun)."""

    trajectory: PvtTrajectory
    overrun_axes: tuple[str, ...] = ()
    overrun_counts: tuple[int, ...] = ()


class VelocityChangePlanner:
    """The `planner` of a `Change` into velocity mode: the velocity move `job` from the state at the end of the
    queue (open-ended). `planned` is what it returned (None until then, or when it raised), `error` the
    exception, `planning_s` the wall time."""

    def __init__(self, cell: CellConfig, job: Job, node_ids: tuple[int, ...]):
        self._cell = cell
        self._job = job
        self._node_ids = node_ids
        self.planned: VelocityPlan | None = None
        self.error: BaseException | None = None
        self.planning_s = 0.0

    def __call__(self, request: StopRequest) -> PvtTrajectory:
        if tuple(request.node_ids) != self._node_ids:
            raise ValueError(f"the running job's nodes {list(request.node_ids)} are not the change's "
                             f"{list(self._node_ids)}")
        state = MotionState(tuple(request.positions_counts), tuple(request.velocities_rpm),
                            tuple(request.accelerations_counts_per_ms2 or ()))
        t0 = time.perf_counter()
        try:
            self.planned = VelocityPlan(plan_velocity(self._job, self._cell, state))
        except BaseException as exc:
            self.error = exc
            raise
        finally:
            self.planning_s = time.perf_counter() - t0
        return self.planned.trajectory
