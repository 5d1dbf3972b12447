"""The job's states and tables: `JobState` and its transition table, the two tables that move it (data, so
they are inspectable and testable), the CiA 402 control words and status bits the core uses, and what the
core hands back (`Reaction`, `StateChange`, `JobReport`). No behaviour.

- Event-triggered: `DISPATCH`, (job state, event type) -> the handler that takes the event.
- State-triggered: `STATE_TRIGGERED`, (job state, the states every axis must be in, an extra guard) -> the
  move that takes the job on ("all axes active -> RUNNING"). After anything that may change an axis' state,
  `JobCore._progress_job` applies the entries to a fixed point: the first entry of the current state whose
  conditions hold makes its move (every move leaves the state), until none holds.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, NamedTuple

from bus.events import (
    AdapterError,
    Bootup,
    BufferStatus,
    BusLoad,
    Cancel,
    Emcy,
    HeartbeatLost,
    PositionFeedback,
    RecordOnWire,
    Send,
    SendFailed,
    StatusWord,
    Sync,
    SyncOnWire,
)
from streamer.core.attribution import FeedbackLog
from streamer.core.axis_state import FeederState
from streamer.core.fifo_feeder import AxisTelemetry
from streamer.core.outcome import JobOutcome
from streamer.core.plan_source import Change, EmergencyStop, StreamPlan
from streamer.core.positioning import NotInTarget
from streamer.core.schedule import segment_ends

# controlwords (CiA 402, seed 000 4.3.4)
CW_ENABLE_OPERATION = 0x000F  # operation enabled, ip mode bit 4 low
CW_START_IP = 0x001F  # + bit 4: enable ip mode (rising edge starts interpolation)
CW_HALT = 0x011F  # + bit 8: halt with profile deceleration
CW_QUICK_STOP = 0x000B  # bit 2 low: quick stop

# statusword / buffer status bits
SW_FAULT = 0x0008
SW_TARGET_REACHED = 0x0400
SW_IP_ACTIVE = 0x1000
SW_STATE_MASK, SW_OPERATION_ENABLED, SW_QUICK_STOP_ACTIVE = 0x006F, 0x0027, 0x0007
BS_UNDERFLOW_ERROR, BS_OVERFLOW_ERROR = 0x0100, 0x0200
BS_VELOCITY_ERROR, BS_ACCELERATION_ERROR = 0x0400, 0x0800
BS_ERRORS = 0x0F00
BS_BUFFER_ENABLED = 0x4000
BS_IP_ACTIVE = 0x8000


class UnexpectedEvent(RuntimeError):
    """The event has no entry in the dispatch table for the current state."""


class JobState(Enum):
    CONFIGURING = "configuring"
    PRIMING = "priming"
    STARTING = "starting"
    RUNNING = "running"
    FINISHING = "finishing"
    CANCELLING = "cancelling"
    HALTING = "halting"
    DONE = "done"
    CANCELLED = "cancelled"
    FAILED = "failed"


_J = JobState
TERMINAL = frozenset({_J.DONE, _J.CANCELLED, _J.FAILED})
SENDING = frozenset({_J.PRIMING, _J.STARTING, _J.RUNNING, _J.CANCELLING})
FEEDING = frozenset({FeederState.PRIMING, FeederState.STARTING, FeederState.STREAMING})
IN_MOTION = frozenset({_J.STARTING, _J.RUNNING, _J.FINISHING, _J.CANCELLING})
_F = FeederState
CYCLIC_SENDING = frozenset({_F.PRIMING, _F.PRIMED, _F.STARTING, _F.STREAMING, _F.DRAINING})
ALL_PRIMED = frozenset({_F.PRIMED})
_ALL_ACTIVE = frozenset({_F.STREAMING, _F.DRAINING, _F.FINISHED})
_ALL_QUEUED = frozenset({_F.DRAINING, _F.FINISHED})
ALL_FINISHED = frozenset({_F.FINISHED})
EXTENDING = frozenset({_J.PRIMING, _J.STARTING, _J.RUNNING})  # job states in which an open stream is extended
RETAIN_MIN_MS = 1000  # an endless job keeps at least this much of its past records (see `_retire`)
EXTEND_EARLY_MS = 500  # ask the extender this long before the chunk is needed (it may plan on another thread)
MAX_EXTENSIONS_PER_SYNC = 4  # short chunks: several may be needed at once; bounded so one SYNC stays short
LONGEST_SEGMENT_MS = 255  # the PVT time field

JOB_TRANSITIONS: dict[JobState, frozenset[JobState]] = {
    _J.CONFIGURING: frozenset({_J.PRIMING, _J.CANCELLED, _J.FAILED}),
    _J.PRIMING: frozenset({_J.STARTING, _J.CANCELLED, _J.FAILED}),
    _J.STARTING: frozenset({_J.RUNNING, _J.CANCELLING, _J.HALTING, _J.FAILED}),
    _J.RUNNING: frozenset({_J.FINISHING, _J.CANCELLING, _J.HALTING, _J.FAILED}),
    _J.FINISHING: frozenset({_J.DONE, _J.CANCELLING, _J.FAILED}),
    _J.CANCELLING: frozenset({_J.CANCELLED, _J.FAILED}),
    _J.HALTING: frozenset({_J.CANCELLED, _J.FAILED}),
    _J.DONE: frozenset(),
    _J.CANCELLED: frozenset(),
    _J.FAILED: frozenset(),
}

# (state, event type) -> handler name. Built as data so the table is inspectable and testable.
_EVENT_HANDLERS: dict[str, str] = {
    "Sync": "_on_sync",
    "SyncOnWire": "_on_sync_on_wire",
    "RecordOnWire": "_on_record_on_wire",
    "BufferStatus": "_on_buffer_status",
    "StatusWord": "_on_status",
    "PositionFeedback": "_on_position",
    "Emcy": "_on_emcy",
    "HeartbeatLost": "_on_heartbeat_lost",
    "Bootup": "_on_bootup",
    "SendFailed": "_on_send_failed",
    "AdapterError": "_on_adapter_error",
    "BusLoad": "_on_bus_load",
}
_CANCEL_HANDLERS: dict[JobState, str] = {
    _J.CONFIGURING: "_cancel_before_start",
    _J.PRIMING: "_cancel_before_start",
    _J.STARTING: "_cancel_in_motion",
    _J.RUNNING: "_cancel_in_motion",
    _J.FINISHING: "_cancel_after_end",
    _J.CANCELLING: "_ignore",
    _J.HALTING: "_ignore",
}
EVENT_TYPES: dict[str, type] = {
    "Sync": Sync,
    "SyncOnWire": SyncOnWire,
    "RecordOnWire": RecordOnWire,
    "BufferStatus": BufferStatus,
    "StatusWord": StatusWord,
    "PositionFeedback": PositionFeedback,
    "Emcy": Emcy,
    "HeartbeatLost": HeartbeatLost,
    "Bootup": Bootup,
    "SendFailed": SendFailed,
    "AdapterError": AdapterError,
    "BusLoad": BusLoad,
    "Cancel": Cancel,
    "Change": Change,
    "EmergencyStop": EmergencyStop,
}
# a change is answered in every state (a refusal names why), so that whoever asked always learns the result
_CHANGE_HANDLERS: dict[JobState, str] = {
    **{st: "_change_refused" for st in JobState},
    _J.STARTING: "_change_in_motion",
    _J.RUNNING: "_change_in_motion",
}


_EMERGENCY_HANDLERS: dict[JobState, str] = {
    _J.CONFIGURING: "_emergency_before_start",
    _J.PRIMING: "_emergency_before_start",
    _J.STARTING: "_emergency_in_motion",
    _J.RUNNING: "_emergency_in_motion",
    _J.FINISHING: "_emergency_in_motion",
    _J.CANCELLING: "_emergency_in_motion",
    _J.HALTING: "_emergency_in_motion",
}


def stream_ends(plan: StreamPlan) -> list[int]:
    """ends[i] of a plan's records (schedule.segment_ends), without the end record when it is open-ended."""
    ends = segment_ends(plan.segment_ms)
    return ends[:-1] if plan.open_end else ends


def dispatch_table() -> dict[tuple[JobState, type], str]:
    table: dict[tuple[JobState, type], str] = {}
    for state in JobState:
        for name, etype in EVENT_TYPES.items():
            if name == "Change":
                table[(state, etype)] = _CHANGE_HANDLERS[state]
            elif state in TERMINAL:
                table[(state, etype)] = "_ignore"
            elif name == "Cancel":
                table[(state, etype)] = _CANCEL_HANDLERS[state]
            elif name == "EmergencyStop":
                table[(state, etype)] = _EMERGENCY_HANDLERS[state]
            else:
                table[(state, etype)] = _EVENT_HANDLERS[name]
    return table


DISPATCH = dispatch_table()


class StateTrigger(NamedTuple):
    """In job state `state`, once every axis is in one of `axes_in` and the guard method (if any) says so,
    the job core calls `move` (a method that changes the job state)."""

    state: JobState
    axes_in: frozenset[FeederState]
    guard: str | None
    move: str


STATE_TRIGGERED: tuple[StateTrigger, ...] = (
    StateTrigger(_J.STARTING, _ALL_ACTIVE, None, "_to_running"),
    StateTrigger(_J.RUNNING, _ALL_QUEUED, None, "_to_finishing"),
    # PRE_TARGET: the plan is done but an axis is not yet in its target window (nor timed out there)
    StateTrigger(_J.FINISHING, ALL_FINISHED, "_settled", "_finish_done"),
    StateTrigger(_J.CANCELLING, ALL_FINISHED, None, "_cancel_done"),
    StateTrigger(_J.HALTING, ALL_FINISHED, None, "_halt_done"),
)
TRIGGERS_BY_STATE: dict[JobState, tuple[StateTrigger, ...]] = {
    st: tuple(t for t in STATE_TRIGGERED if t.state is st) for st in dict.fromkeys(t.state for t in STATE_TRIGGERED)}


@dataclass(frozen=True)
class StateChange:
    state: JobState
    sync: int | None
    t: float
    outcome: JobOutcome | None = None


class Reaction(NamedTuple):
    """What one event produced: frames to send now (in order) and job state changes."""

    sends: Sequence[Send]
    changes: Sequence[StateChange]


NOTHING = Reaction((), ())


@dataclass(frozen=True)
class JobReport:
    """The job's report hooks (the runtime adds what only the bus and the drives know)."""

    state: str
    outcome: JobOutcome | None
    progress: float
    sync_period_ms: int
    priming_level: int
    start_sync: int | None
    end_sync: int | None
    syncs: int
    frames_sent: int
    record_frames: int
    control_frames: int
    points: int  # records in the streams (all axes, end records included)
    frames_per_point: float
    bus_load_peak: float  # predicted from the budget's accounting (this job's traffic + SYNC/TPDOs)
    measured_bus_load_peak: float | None  # from BusLoad events, when the runtime feeds them
    duration_ms: int
    cancel: dict[str, Any] = field(default_factory=dict)
    axes: tuple[AxisTelemetry, ...] = ()
    positioning: dict[int, str] = field(default_factory=dict)  # node -> PositioningState name, at the end
    warnings: tuple[NotInTarget, ...] = ()
    # per node, what its drive reported at each SYNC as the core attributed it (the report's deviation and
    # end SYNC come from it, never from arrival order); the core's own logs, read-only
    feedback: dict[int, FeedbackLog] = field(default_factory=dict)
