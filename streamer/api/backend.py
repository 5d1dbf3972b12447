"""The seam between the job service and the motion runtime: the `MotionBackend` base class.

The service owns the network side (decoding, admission, queue, journal, events, telemetry); everything
that touches the planner or the bus is behind this class, so the service is tested with a fake
(tests/api/fakes.py). Required methods are abstract; optional capabilities have defaults (python-can's
`BusABC` way) and the two the service must know before acting are declared (`can_change`,
`can_emergency_stop`). Each method's docstring is its contract. `load_backend` imports a factory by
"module:function" (`pvt serve --backend`).
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
    """What the job service needs from the motion runtime (each method's docstring is its contract). A
    backend subclasses it: the required methods are abstract, the optional capabilities are methods with
    defaults (python-can's `BusABC` way), and the two capabilities the service must know of before it acts
    are declared (`can_change`, `can_emergency_stop`), so the service never probes a backend."""

    cell: CellConfig
    can_change: ClassVar[bool] = False  # `change` splices a job into the running motion (else it rejects)
    can_emergency_stop: ClassVar[bool] = False  # `emergency_stop` has a stop of its own (else the cancel's)

    @abc.abstractmethod
    def validate(self, body: Mapping[str, Any]) -> Any:
        """The job body as decoded from msgpack (a job file's fields, `job_id` removed; payload.py already
        rejected malformed input) -> the planner's `Job` (`planner.job.job_from_dict(body, cell)`). Raises
        `PlanningError` for every bad job. Intake thread."""
        ...

    @abc.abstractmethod
    def plan(self, job: Any, start: Mapping[str, float] | None, *,
             last_target: Mapping[str, float | None] | None = None,
             last_direction: Mapping[str, int] | None = None, lead_ms: int | None = None) -> Planned:
        """Plan and encode; return `Planned` (`planned_from_trajectory` also records where the job ends). Raises
        `PlanningError` (INFEASIBLE, ENCODING_RANGE, ...). Intake thread, never the SYNC thread, one call at a
        time. Jobs are planned when accepted, possibly behind queued ones: `start` maps axis name -> where the
        service expects the axis to stand when this job starts; other axes use the drives' current positions.
        `last_target` / `last_direction`: the last commanded target (None: none) and the sign of the last
        commanded motion, kept by the service from every accepted job, for the additive and modulo_current
        modes (planner/motion/travel.py). `lead_ms` (only when the job set it): segments bounded so that a
        change or stop acts within about that lead. A backend ignores what it has no use for."""

    @abc.abstractmethod
    def execute(self, planned: Planned, emit: Emit, cancel: CancelToken) -> Mapping[str, Any]:
        """Run the motion and block until it has ended. Executor thread, one job at a time, only after
        `ready()` said True. Progress: `emit("running", {"progress": p, ...})`, p in 0..1, at any rate, from
        any thread (`emit` never blocks; the service throttles and emits `priming` itself). Cancel: poll
        `cancel.cancelled` or register `cancel.add_callback(fn)` (once, on the cancelling thread: keep it
        short), stop all axes with the jerk-limited stop and return "cancelled" (at once if cancelled on
        entry); `progress` then stays the share of the job's own plan executed.

        Returns the report (`result` "done", "cancelled" or "failed", `sync_period_ms`, `duration_s`, `syncs`,
        `frames`, `bus_load_peak`, `faults`, `axes`; for "failed" an `error` {"code", "node", "message", ...}).
        It should not raise; if it does, the job fails with the exception's `code`, else INTERNAL. If the
        drives do not stand at knot 0: with `current_positions()` the service has already re-planned the
        start with the travel memory, so fail START_MISMATCH and never re-plan (a second re-plan without that
        memory could take an additive or modulo move elsewhere); without it, re-plan from the current
        positions or fail START_MISMATCH. `planned.record` (a `RecordRequest` or None): arm the drives' data
        recorder on those axes before the motion and read it after (docs/api.md), or ignore it."""
        ...

    @abc.abstractmethod
    def telemetry(self) -> Sequence[Mapping[str, Any]]:
        """One mapping per axis, at least `name`, `position` (user units), `velocity` (user units/s),
        `fifo_fill` (records), `state` (a short string). Telemetry thread, concurrently with `execute`:
        cheap and thread-safe."""
        ...

    @abc.abstractmethod
    def ready(self) -> tuple[bool, str]:
        """(True, "") when a job may start; (False, reason) while the cell is faulted and not reset (new and
        queued jobs then fail NOT_READY: nothing moves unexpectedly after a reset). Any thread."""
        ...

    @abc.abstractmethod
    def reset(self) -> tuple[bool, str]:
        """Clear a fault (fault reset on the drives) and return `ready()`. Control thread, no job running."""
        ...

    @abc.abstractmethod
    def close(self) -> None:
        """Release the bus. Called once, after the executor has stopped."""
        ...

    def change(self, job: Any, mode: str, emit: Emit, *, last_target: Mapping[str, float | None] | None = None,
               last_direction: Mapping[str, int] | None = None) -> tuple[Planned, dict[str, Any]]:
        """Splice `job` into the running motion (a backend with `can_change`); by default it cannot.

        A move submitted with `buffer = "aborting"` while a job runs replaces the running job's remainder
        without stopping, planned from the state at the end of what is queued (streamer.core.Change); the new
        job's progress then goes to `emit`. Returns its `Planned` and what was done (`time_ms`, `reaction_ms`,
        `overrun_axes`, ...). Raises `MotionError(COMMAND_REJECTED)` naming the reason when it cannot be made;
        the running job then goes on untouched. Intake thread; waits a period or two for the SYNC thread."""
        raise MotionError(E.COMMAND_REJECTED, "this backend cannot change a running motion", path="buffer")

    def current_positions(self) -> Mapping[str, float] | None:
        """Where each axis' position demand stands now, user units; None (the default): not known. Any
        thread, cheap. With it the service checks before `execute` that a queued job still starts where the
        axes stand: a move is re-planned, a path/timed/pvt job fails INFEASIBLE unless `start = "current"`."""
        return None

    def emergency_stop(self) -> str | Mapping[str, Any]:
        """The fastest stop the runtime has (a backend with `can_emergency_stop`); by default none: the service
        stops with the cancel's stop and does not call this.

        The real backend splices the running job's planned emergency stop after what is queued, or quick-stops
        every drive (controlword 0x000B, ramping on 0x6085) when no plan is possible or nothing runs. A running
        `execute` then returns "failed" with EMERGENCY_STOP and `ready()` stays False until `reset()`. Any
        thread; returns a message (method `quick_stop`) or {"method": "emergency_trajectory" | "quick_stop",
        "message": ...}."""
        raise NotImplementedError(f"{type(self).__name__} has no emergency stop of its own")

    def take_recording(self) -> Any:
        """The recording of the job the last `execute` ran, once; None (the default): none. A
        `streamer.recording.JobRecording` or the `RecordingInputs` to build it from; executor thread, right
        after `execute`; the service writes it beside its journal (docs/recording.md)."""
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
