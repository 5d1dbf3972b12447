"""The seam between the job service and the motion runtime: the `MotionBackend` base class.

The job service (streamer/api/service.py and its parts: intake.py, cell_queue.py, control_verbs.py,
journal.py, progress.py, telemetry.py, handlers.py) owns the network side: decoding, admission, the queue,
the journal, events and telemetry. Everything that touches the planner or the bus is behind this
protocol, so the service is tested with a fake (tests/api/fakes.py) and the motion runtime plugs in
without the service knowing about CAN.

    class MotionBackend(abc.ABC):
        cell: CellConfig
        can_change: ClassVar[bool] = False
        can_emergency_stop: ClassVar[bool] = False
        def validate(self, body: Mapping[str, Any]) -> Any                                   # abstract
        def plan(self, job: Any, start: Mapping[str, float] | None, *,
                 last_target: Mapping[str, float | None] | None = None,
                 last_direction: Mapping[str, int] | None = None,
                 lead_ms: int | None = None) -> Planned                                      # abstract
        def execute(self, planned: Planned, emit: Emit, cancel: CancelToken) -> Mapping[str, Any]  # abstract
        def telemetry(self) -> Sequence[Mapping[str, Any]]                                   # abstract
        def ready(self) -> tuple[bool, str]                                                  # abstract
        def reset(self) -> tuple[bool, str]                                                  # abstract
        def close(self) -> None                                                              # abstract
        def change(self, job, mode, emit, *, last_target=None, last_direction=None)          # rejects
        def current_positions(self) -> Mapping[str, float] | None                            # None
        def emergency_stop(self) -> str | Mapping[str, Any]                                  # none
        def take_recording(self) -> Any                                                      # None

A backend subclasses it; the optional capabilities have defaults (python-can's `BusABC` way), so the service
calls every method as declared and never probes a backend for what it takes or has.

Contract, method by method (which service thread calls it, what it may raise):

- `validate(body)`: the job body as decoded from msgpack (a dict with a job file's fields, `job_id`
  removed; payload.py already rejected malformed/oversized input, non-string or duplicate keys, bools,
  huge ints, NaN/inf). Returns the planner's `Job` (`planner.job.job_from_dict(body, cell)`). Raises
  `PlanningError` (code/path/message) for every bad job. Called on the service's intake thread.
- `plan(job, start)`: plans and encodes, returns `Planned` (use `planned_from_trajectory`, which also
  records where the job ends). Raises `PlanningError` (INFEASIBLE, ENCODING_RANGE, ...). Intake thread,
  never the SYNC thread; one call at a time. Jobs are planned when they are accepted, which may be
  while other jobs are still queued: `start` maps axis name -> user-unit position where the service
  expects that axis to stand when this job starts (the end of the last queued or running job that
  moves it); for axes not in `start` use the drives' current positions. So:
  `plan_job(job, cell, start=[start.get(a, current[a]) for a in job.axes])`. `last_target` and
  `last_direction` (axis name -> the last commanded target, None for none, and the sign of the last
  commanded motion; the service keeps them from every job it accepted: `Planned.commanded_target` /
  `commanded_direction`) serve the additive and modulo_current modes (planner/motion/travel.py); a backend that has
  no use for them ignores them (additive then counts from the start position). `lead_ms` (given only when
  the job set its own lead): segments bounded so that a change or stop acts within about that lead.
- `execute(planned, emit, cancel)`: runs the motion and blocks until it has ended. Called on the
  service's executor thread, one job at a time, only when `ready()` said True just before. While it
  runs it calls `emit("running", {"progress": p, ...})` (p in 0..1, at any rate: the service
  throttles to `progress_hz` and keeps the first and the last) from any thread; `emit` never blocks
  and is thread-safe, so the SYNC thread may call it. The service itself emits `priming` before it
  calls `execute` (a backend `priming` is ignored). `cancel` is a `CancelToken`: poll
  `cancel.cancelled` each SYNC or register `cancel.add_callback(fn)` (called once, on the cancelling
  thread: keep it short, e.g. queue a `Cancel()` event for the core); on cancel, stop all axes with the
  jerk-limited stop and return result "cancelled" (if it is already cancelled on entry, return
  "cancelled" without moving). Returns the report (the demo's report.json shape:
  `result`, `sync_period_ms`, `duration_s`, `syncs`, `frames`, `bus_load_peak`, `faults`, `axes`),
  where `result` is "done", "cancelled" or "failed", and for "failed" an `error` mapping
  `{"code": str, "node": int | None, "message": str}` (extra keys such as `detail`, `sync` are kept).
  It should not raise; if it does, the job fails with the exception's `code` when it has one (a
  `PlanningError`), else INTERNAL, with the exception text. If the drives do not stand at the plan's knot
  0 when execute is called (a job before it was cancelled or failed): with `current_positions()` the
  service has checked (and re-planned) the start itself before `execute` (below), with the travel memory
  the job's target was reported with, so the backend fails START_MISMATCH and never re-plans on its own
  (a second re-plan, without that memory, could take an additive or modulo move elsewhere); a backend
  without `current_positions()` re-plans from the current positions (`self.plan(planned.job, None)`) or
  fails START_MISMATCH. After a cancel, `progress` stays the share of the *job's* plan
  that was executed (it does not run on to 1.0 through the stop trajectory): the service publishes those
  updates as `cancelling` events with the true progress.
  `planned.record` is the job's `record` section (a `RecordRequest`, checked by the service) or None:
  a backend whose drives have a data recorder configures and arms it on the recorded axes before the
  motion and reads it after (docs/api.md, "The record section"); one without ignores it.
- `telemetry()`: a snapshot, one mapping per axis, at least `name`, `position` (user units),
  `velocity` (user units/s), `fifo_fill` (records), `state` (drive state, a short string). Called on
  the telemetry thread at `telemetry_hz`, concurrently with `execute`: must be cheap and thread-safe.
- `ready()`: (True, "") when a job may start; (False, reason) while the cell is faulted and not
  reset. Any thread. A new submission gets NOT_READY, and a queued job that comes up while not ready
  fails with NOT_READY (it is not kept to move unexpectedly after a reset).
- `reset()`: clear a fault (fault reset on the drives); returns `ready()` afterwards. Called by the
  control thread only while no job runs.
- `close()`: release the bus. Called once, after the executor has stopped.
- optional `current_positions() -> Mapping[str, float] | None`: where each axis' position demand stands now,
  user units (any thread, cheap); the default None: not known. With it, the service checks before `execute`
  that a queued job still starts where the axes stand (the job before it may have been cancelled or stopped): a move is
  re-planned from there, a path/timed/pvt job fails INFEASIBLE naming the axis and both positions, unless it said
  `start = "current"` (a path is then planned from where the axes stand through all its waypoints).
- optional `emergency_stop() -> str | Mapping`, with `can_emergency_stop = True`: the fastest stop the
  motion runtime has, on every axis (the
  real backend: the running job's planned emergency stop at each axis' emergency deceleration, spliced
  after what is queued; the quick stop, controlword 0x000B, each drive ramping down on its quick stop
  deceleration 0x6085, when no plan is possible or nothing runs); a running `execute` then returns
  "failed" with code EMERGENCY_STOP, and `ready()` stays False until `reset()`. Any thread; returns what
  it did for the reply: a message (method `quick_stop`) or `{"method": "emergency_trajectory" |
  "quick_stop", "message": ...}`. Without it (the default) the service's emergency stop falls back to the
  jerk-limited stop of a cancel.
- optional `change(job, mode, emit, *, last_target, last_direction) -> (Planned, info)`, with
  `can_change = True`: a move submitted with `buffer = "aborting"` while a
  job runs: replace the running job's remainder with it, without stopping, planned from the state at the
  end of what is queued (streamer.core.Change); from then on the new job's progress goes to `emit`.
  Returns the new job's `Planned` and what was done (`time_ms`: where it begins in the running stream,
  `reaction_ms`: from the request to that point, `overrun_axes`: axes that pass the new target, ...).
  Raises `MotionError(COMMAND_REJECTED)` naming the reason when it cannot be made (out of reach within the
  limits and position limits, cannot be streamed in time, the running plan's end already queued); the
  running job then goes on untouched. Intake thread; it waits for the SYNC thread's answer (a period or two).
  Without it (the default), `aborting` is rejected while a job runs.
- optional `take_recording()`: the recording of the job the last `execute` ran (a
  `streamer.recording.JobRecording`, or `streamer.recording.writer.RecordingInputs` to build it from),
  or None; each once. Called on the executor thread right after `execute`; the service writes it
  beside its journal (docs/recording.md). The default: None, no recordings.

`load_backend(spec, cell, ...)` imports a backend factory by "module:function" name; `pvt serve`
uses `DEFAULT_BACKEND` unless `--backend` names another (tests use this to run the fake).
"""

from __future__ import annotations

import abc
import importlib
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

from planner.config import CellConfig
from streamer.api import errors as E
from streamer.api.errors import MotionError

# The motion runtime's factory: open_backend(cell, *, sim, interface, channel, bitrate) -> MotionBackend
DEFAULT_BACKEND = "streamer.runtime.bus_backend:open_backend"

Emit = Callable[[str, Mapping[str, Any]], None]
"""emit(event_type, fields): report progress of the running job ("running" with "progress" 0..1)."""

REQUIRED_METHODS = ("validate", "plan", "execute", "telemetry", "ready", "reset", "close")


@dataclass(frozen=True)
class Planned:
    """A planned job: what `execute` needs, plus the two numbers the acceptance reply carries."""

    job: Any  # planner.job.Job
    trajectory: Any  # planner PvtTrajectory
    duration_s: float
    points: int  # PVT points per axis (knots, including the start point)
    planning_s: float = 0.0  # wall time spent planning (for the benchmark's planner share)
    end_positions: Mapping[str, float] = field(default_factory=dict)  # axis -> user units at the end
    start_positions: Mapping[str, float] = field(default_factory=dict)  # axis -> user units at knot 0
    record: Any = None  # the job's `record` section (a streamer.recording.drive.RecordRequest), or None
    lead_ms: int | None = None  # the job's own lead (`lead_ms`, checked by the service), None: the cell's
    # what the job leaves as each axis' last commanded target and direction (planner/motion/travel.py's contract: a
    # move's resolved target, a path/timed/pvt job's last row, None after a velocity move; the sign of the
    # last commanded motion, 0 none): the service keeps them for the next job's additive and modulo modes
    commanded_target: Mapping[str, float | None] = field(default_factory=dict)
    commanded_direction: Mapping[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.duration_s >= 0.0:
            raise ValueError(f"Planned.duration_s must be >= 0, got {self.duration_s}")
        if self.points < 0:
            raise ValueError(f"Planned.points must be >= 0, got {self.points}")


def planned_from_trajectory(job: Any, trajectory: Any, planning_s: float = 0.0) -> Planned:
    """Wrap a planner `PvtTrajectory` (`.duration_s`, `.dt_ms`: points = len(dt_ms) + 1; the start and end
    positions from the first and last knot of `.positions` (counts) / `.counts_per_unit`)."""
    end: dict[str, float] = {}
    begin: dict[str, float] = {}
    target: dict[str, float | None] = {}
    direction: dict[str, int] = {}
    names = getattr(trajectory, "axis_names", None)
    positions = getattr(trajectory, "positions", None)
    velocities = getattr(trajectory, "velocities", None)
    cpu = getattr(trajectory, "counts_per_unit", None)
    endless = bool(getattr(trajectory, "open_ended", False))
    if names is not None and positions is not None and cpu is not None:
        for i, name in enumerate(names):
            begin[str(name)] = float(positions[i][0]) / float(cpu[i])
            if not endless:  # an open-ended (velocity) move has no end: nothing may be planned from it
                end[str(name)] = float(positions[i][-1]) / float(cpu[i])
            target[str(name)] = None if endless else end[str(name)]
            moving = [int(v) for v in velocities[i] if v] if velocities is not None else []
            direction[str(name)] = (1 if moving[-1] > 0 else -1) if moving else 0
    return Planned(
        job=job,
        trajectory=trajectory,
        duration_s=float(trajectory.duration_s),
        points=len(trajectory.dt_ms) + 1,
        planning_s=planning_s,
        end_positions=end,
        start_positions=begin,
        commanded_target=target,
        commanded_direction=direction,
    )


class CancelToken:
    """A one-shot, thread-safe cancel flag with callbacks (the service cancels, the backend reacts)."""

    def __init__(self) -> None:
        self._event = threading.Event()
        self._lock = threading.Lock()
        self._callbacks: list[Callable[[], None]] = []

    @property
    def cancelled(self) -> bool:
        return self._event.is_set()

    def cancel(self) -> None:
        with self._lock:
            if self._event.is_set():
                return
            self._event.set()
            callbacks, self._callbacks = self._callbacks, []
        for fn in callbacks:
            fn()

    def add_callback(self, fn: Callable[[], None]) -> None:
        """Call `fn()` once when cancelled (now, on this thread, if already cancelled)."""
        with self._lock:
            if not self._event.is_set():
                self._callbacks.append(fn)
                return
        fn()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until cancelled or `timeout` s passed; True if cancelled (a cancellable sleep)."""
        return self._event.wait(timeout)


class MotionBackend(abc.ABC):
    """What the job service needs from the motion runtime (see the module docstring for the contract). A
    backend subclasses it: the required methods are abstract, the optional capabilities are methods with
    defaults (python-can's `BusABC` way), and the two capabilities the service must know of before it acts
    are declared (`can_change`, `can_emergency_stop`), so the service never probes a backend."""

    cell: CellConfig
    can_change: ClassVar[bool] = False  # `change` splices a job into the running motion (else it rejects)
    can_emergency_stop: ClassVar[bool] = False  # `emergency_stop` has a stop of its own (else the cancel's)

    @abc.abstractmethod
    def validate(self, body: Mapping[str, Any]) -> Any: ...

    @abc.abstractmethod
    def plan(self, job: Any, start: Mapping[str, float] | None, *,
             last_target: Mapping[str, float | None] | None = None,
             last_direction: Mapping[str, int] | None = None, lead_ms: int | None = None) -> Planned:
        """`last_target` / `last_direction`: what the service keeps of the accepted jobs (None: nothing known);
        `lead_ms`: the job's own lead (None: the cell's). A backend ignores what it has no use for."""

    @abc.abstractmethod
    def execute(self, planned: Planned, emit: Emit, cancel: CancelToken) -> Mapping[str, Any]: ...

    @abc.abstractmethod
    def telemetry(self) -> Sequence[Mapping[str, Any]]: ...

    @abc.abstractmethod
    def ready(self) -> tuple[bool, str]: ...

    @abc.abstractmethod
    def reset(self) -> tuple[bool, str]: ...

    @abc.abstractmethod
    def close(self) -> None: ...

    def change(self, job: Any, mode: str, emit: Emit, *, last_target: Mapping[str, float | None] | None = None,
               last_direction: Mapping[str, int] | None = None) -> tuple[Planned, dict[str, Any]]:
        """Splice `job` into the running motion (a backend with `can_change`); by default it cannot."""
        raise MotionError(E.COMMAND_REJECTED, "this backend cannot change a running motion", path="buffer")

    def current_positions(self) -> Mapping[str, float] | None:
        """Where each axis' position demand stands now, user units; None (the default): not known."""
        return None

    def emergency_stop(self) -> str | Mapping[str, Any]:
        """The fastest stop the runtime has (a backend with `can_emergency_stop`); by default none: the service
        stops with the cancel's stop and does not call this."""
        raise NotImplementedError(f"{type(self).__name__} has no emergency stop of its own")

    def take_recording(self) -> Any:
        """The recording of the job the last `execute` ran, once; None (the default): none."""
        return None


def check_backend(obj: object) -> None:
    """Raise TypeError naming what is missing if `obj` does not look like a MotionBackend."""
    if not isinstance(obj, MotionBackend):
        raise TypeError(f"{type(obj).__name__} is not a MotionBackend: subclass streamer.api.backend.MotionBackend")
    missing = [m for m in REQUIRED_METHODS if not callable(getattr(obj, m, None))]
    if not isinstance(getattr(obj, "cell", None), CellConfig):
        missing.append("cell (a CellConfig)")
    if missing:
        raise TypeError(f"{type(obj).__name__} is not a MotionBackend: missing {', '.join(missing)}")


class BackendUnavailable(RuntimeError):
    """The backend factory named by a spec cannot be imported."""


def load_factory(spec: str) -> Callable[..., MotionBackend]:
    """Import "package.module:function" and return the function."""
    module_name, sep, attr = spec.partition(":")
    if not sep or not module_name or not attr:
        raise BackendUnavailable(f"backend spec {spec!r} must look like 'package.module:function'")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise BackendUnavailable(f"cannot import backend module {module_name!r}: {exc}") from exc
    factory = getattr(module, attr, None)
    if not callable(factory):
        raise BackendUnavailable(f"{module_name!r} has no callable {attr!r}")
    result: Callable[..., MotionBackend] = factory
    return result


def load_backend(
    spec: str,
    cell: CellConfig,
    *,
    sim: bool = False,
    interface: str | None = None,
    channel: str | None = None,
    bitrate: int | None = None,
) -> MotionBackend:
    """Build the backend `spec` names for `cell` and check it has the protocol's methods."""
    factory = load_factory(spec)
    backend = factory(cell, sim=sim, interface=interface, channel=channel, bitrate=bitrate)
    check_backend(backend)
    return backend
