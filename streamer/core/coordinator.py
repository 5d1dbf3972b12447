"""Coordinator: the multi-axis job state machine of the PVT streamer (one object per job, no I/O).

Owns one job: the shared timing of the record streams, one `FifoFeeder` per axis, the lockstep
prefix (how many records every axis should have been sent), the per-SYNC frame budget, the
synchronous start, finish, cancel and fault handling, and the job outcome. It is fed
`bus.events` (Sync, BufferStatus, PositionFeedback, Emcy, HeartbeatLost, Bootup, Cancel, SendFailed,
AdapterError, BusLoad) through `handle(event)`, which returns a `Reaction`: the `Send` frames to put
on the bus now, in order, and the job state changes (the terminal one carries the `JobOutcome`).
Dispatch is a table keyed by (job state, event type); a pair without an entry raises
`UnexpectedEvent`.

Contract with the runtime (the adapter that calls it):
- feed `Sync(n)` after SYNC n is on the wire (or queued ahead of anything the core returns), and before
  any TPDO answering it; counts increase by exactly 1 (a jump is a lost SYNC: SYNC_LOST); `Sync.since`,
  when the runtime knows it, is when the SYNC's unbroken run began (else the core counts from its first
  Sync): an XtrapulsPac gets controlword bit 4 only once SYNC has run its `sync_lock_ms` (180 ms);
- feed TPDOs with `sync_count` set to the newest SYNC on the wire when they arrived (None = the last Sync
  fed): the core decides which SYNC each answers (Feedback attribution, below); their time stamps are not
  used for that;
- send the returned frames at once, in order; they must reach the drives before the next SYNC;
- the drives are operation enabled in mode 7 with the buffer cleared and enabled before the job
  (the core verifies it on the first TPDOs and fails DRIVE_NOT_READY otherwise; the adapter does the
  SDO setup). Optionally feed `BusLoad` (measured load, any sender) about once per SYNC.

Job life cycle (JobState):
  CONFIGURING  wait for the first TPDO1 + TPDO2 of every axis; check operation enabled, buffer enabled,
               ip mode inactive, FIFO empty, position demand == the plan's knot 0 (START_MISMATCH).
               Then controlword 0x000F (bit 4 low, so the start is a rising edge) to every axis;
               priming begins with the next SYNC.
  PRIMING      fill every FIFO to the priming level P = min(O, max(2, what the first cycle needs for
               the lead time and the repair margin)), `prime_records_per_sync` records per axis per
               cycle, each batch confirmed before the next (feeder.py).
  STARTING     on the first SYNC at which every FIFO is confirmed primed, controlword 0x001F to every
               axis in that one cycle; RPDO1 is synchronous, so all drives apply it, and enter ip mode
               active, at the next SYNC s = the recorded start SYNC. Each drive must report ip mode
               active at s (START_FAILED otherwise).
  RUNNING      every SYNC the lockstep prefix K is raised by the top-up rule (schedule.py) within the
               frame budget; every axis gets the records up to K when its TPDO1 confirms its previous
               batch, never more than its free space nor above O. All axes share one grid, so the
               records of one grid index go out in the same cycle (except an axis repairing a loss or
               missing a TPDO: it catches up one record per cycle beyond the lockstep step, from the
               budget's spare part, or faster when its fill needs it).
  FINISHING    every end record (time 0) is confirmed queued; DONE when every drive reports ip mode
               inactive and target reached (statusword bit 10) after the plan's end.
  CANCELLING / HALTING  see cancel below; then CANCELLED.
  DONE, CANCELLED, FAILED  terminal: every event is accepted and ignored, nothing is ever sent again;
               a new job needs a new Coordinator.

Frame budget: per SYNC cycle, bus_load_limit (70%) x bitrate x period minus the traffic the job
causes anyway (SYNC, TPDO1 + TPDO2 per drive, heartbeats), in worst-case frame bits (bus/budget.py).
The lockstep grows at most as many records per axis per cycle as that allows; resends and catch-up
use what this cycle's lockstep step leaves. The whole nominal schedule is dry-run at construction: if
it cannot keep every FIFO >= min(U, records left), the job is FAILED at once with BUS_OVERLOAD (the
budget is to blame) or BUFFER_UNDERFLOW (the plan is denser than the FIFO can buffer per SYNC), before
anything is sent. At run time, a FIFO reported below min(U, records left) with no record of that axis
missing, or on a bus whose measured load (BusLoad) is over the limit, fails BUS_OVERLOAD before the
drive can underflow (records could not be sent in time). While records are missing (lost, being
resent), the feeder's due-time check decides instead: resend while it can still arrive before the
record is due, else predicted BUFFER_UNDERFLOW; a resend that is lost again at the last chance lets
the drive underflow (its EMCY: BUFFER_UNDERFLOW), which is the price of repairing every loss the
timing allows rather than giving up on the first one.

Cancel: the stop follows a trajectory from the state at the end of what is already queued, K = the
most records sent to any axis: the stop planner (a callable given to the constructor) is asked for a
trajectory from knot K (positions, rpm velocities, Hermite accelerations of all axes); it is spliced
in after record K of every axis (lagging axes first catch up to K), so all axes follow one jerk-limited
stop on one grid, and nothing already in a FIFO has to be taken back (it cannot be: the FIFO has no
delete). The stop begins after what is queued: at most about lead_ms + repair_syncs periods later.
Halt (controlword 0x011F, bit 8) is the fallback, used only when no stop planner was given, the
planner raised or returned a trajectory that does not start at knot K of every axis, or the stop
cannot be streamed in time. It is not path-synchronous (each drive decelerates on its own profile
deceleration 0x6084) and not jerk-limited, but acts at the next SYNC; after every drive reports
standstill (bit 10) the core sends 0x000F (ip mode off, halt released) and the job is CANCELLED. A
cancel before the start (CONFIGURING, PRIMING) cancels at once: nothing moved, nothing is sent (the
runtime clears the buffers before the next job). A cancel when the plan's end is already queued lets
the plan finish (it ends at rest) and reports CANCELLED.

Open-ended streams (a velocity move, planner/travel.py): the plan's last knot moves and it has no end
record; the stream goes on in chunks. Every SYNC (from PRIMING on, while the job streams), when the stream
ends less than `extend_ahead_ms` after the fastest drive's interpolation time, the core asks the `extender`
(a callable given to the constructor) for the next chunk, given the chunk before it; the chunk must start
exactly at that chunk's last knot (to the count and the rpm, as a splice) and is appended after it on every
axis (FIFO records, cyclic set points sampled from it across the boundary) without an end record in
between. The margin: `extend_need_ms` = one period + max(repair_syncs periods, lead_ms) + (U + 2) records
of the longest segment (255 ms): while the stream reaches that far ahead, the top-up rule is never capped by
the stream's end, so every FIFO stays >= U as in a closed plan; the core asks from `extend_need_ms` +
EXTEND_EARLY_MS on, so an extender that plans on another thread (it answers None while it is not ready)
has that long. No chunk by `extend_need_ms` (the extender failed, returned a chunk that does not start at the
last knot, or none at all): the motion is stopped from the end of the queue (the stop planner, as cancel
does; halt without one) and the job ends FAILED EXTENSION_FAILED once at rest. An open stream never
finishes by itself: it ends by a change (a `Change`, "aborting" only: it has no end to buffer after), a
cancel, a fault, or a closed chunk (the planner's chunk brakes by itself before the position limits; the
job is then DONE at rest there). A chunk whose successor follows keeps only its records: the plan at every
ms (`StreamPlan.reference`) of chunks wholly in the past is dropped. And every SYNC of an open stream the core
retires its past (`_retire`): the segment ends, the FIFO axes' records and frames and the pieces from before
`_retain_ms` (>= 1 s, more than every SYNC a TPDO can still be attributed to: the demand prediction reads the
records around the drive's time then) behind the slowest drive's interpolation time, and never a frame not
yet confirmed in its FIFO (a resend) nor anything a stop, change or chunk is spliced after (the queue's end,
later still). Records, frames and ends are `Window`s (streamer/core/window.py): indices still count from
the stream's start, so every index keeps its meaning; reading a retired one raises instead of misreading.
The per-SYNC feedback log of an open stream keeps its old samples in the `store` the runtime gives
(streamer/core/spool.py). So an endless job's memory stays flat however long it runs (`held` counts what it
holds; benchmarks/bench_endless.py); a closed plan retires nothing and keeps its log in memory, as before.

Fault: any EMCY from a job node (except code 0x0000, "no error"), a lost heartbeat, a boot-up, a buffer
error bit or the statusword fault bit in a TPDO, TPDO1/TPDO2 missing for `tpdo_timeout_syncs` SYNCs,
SendFailed or AdapterError, and every accounting failure of a feeder -> controlword 0x000B (quick stop)
to every axis in that same reaction (unless nothing had been sent to the drives yet) and FAILED with
the code, the node and a message. Then the core is poisoned (rule 4 of STYLE.md).

Feedback attribution (streamer/core/attribution.py): a drive answers every SYNC once, in order, but may
answer up to 0.9 period late (an EPOS; a busy bus or host adds to it), so its answer can reach the master
after the next SYNC. Each TPDO is attributed to the SYNC it answers by what it contains: among the SYNCs it
can answer (after the last one its node answered, TPDO1 also after its TPDO2's, up to the newest on the wire
and at most 3 before it; TPDO2 every n-th SYNC only on SYNCs whose counter carries it) the earliest whose
predicted content it fits: TPDO2 the position demand below (`_demand_fits`; a cyclic axis: the set points
it can have reached), TPDO1 ip mode active only from the start SYNC and a fill the records sent and consumed
explain (`_status_fits`); the earliest candidate when it fits none (the check then fails). Arrival time
plays no part. The start check, the fill accounting, the demand check and the report (`JobReport.feedback`:
per node, every TPDO2 and the last ip-active SYNC as attributed) all use this one decision.

Position demand check: every TPDO2 is compared with the demand the drive must have after the ms it
interpolated, predicted from the queued records with planner.hermite (exact with counts_per_rev, at
knots only without). A difference over demand_tolerance_counts is PROTOCOL (records executed out of
order, twice or not at all: this is what catches two records of one batch swapped, which the fill
cannot see), or START_MISMATCH before the start. Off while halting (no plan to compare with).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, NamedTuple

import numpy as np

from bus.budget import (
    CONTROLWORD_FRAME_BITS,
    RECORD_FRAME_BITS,
    CycleBudget,
    cycle_budget,
    setpoint_frame_bits,
)
from bus.cob import pack_controlword, rpdo1_id, rpdo2_id
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
from planner import hermite
from planner.cyclic import Setpoints
from planner.record import PvtRecord, pack
from streamer.core import attribution
from streamer.core import outcome as oc
from streamer.core.attribution import FeedbackLog
from streamer.core.cyclic import HOLD_AFTER_ACTIVE, CyclicFeeder, pack_frame
from streamer.core.drive_time import DriveTime
from streamer.core.feeder import AxisTelemetry, FeederInput, FeederState, FifoFeeder, stream_framing
from streamer.core.outcome import JobOutcome, JobResult
from streamer.core.plan_source import (
    Change,
    ChangeResult,
    EmergencyStop,
    Extender,
    PvtTrajectoryLike,
    StopPlanner,
    StopRequest,
    StreamPlan,
)
from streamer.core.positioning import NotInTarget, PositioningChange, PositioningState, PositioningTracker
from streamer.core.schedule import (
    FillPolicy,
    consumed_at,
    dry_run,
    needed_fill,
    priming_level,
    segment_ends,
    target_prefix,
)
from streamer.core.settings import StreamerSettings
from streamer.core.spool import StoreFactory
from streamer.core.window import Window

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
_SENDING = frozenset({_J.PRIMING, _J.STARTING, _J.RUNNING, _J.CANCELLING})
_FEEDING = frozenset({FeederState.PRIMING, FeederState.STARTING, FeederState.STREAMING})
_IN_MOTION = frozenset({_J.STARTING, _J.RUNNING, _J.FINISHING, _J.CANCELLING})
_F = FeederState
_CYCLIC_SENDING = frozenset({_F.PRIMING, _F.PRIMED, _F.STARTING, _F.STREAMING, _F.DRAINING})
_ALL_PRIMED = frozenset({_F.PRIMED})
_ALL_ACTIVE = frozenset({_F.STREAMING, _F.DRAINING, _F.FINISHED})
_ALL_QUEUED = frozenset({_F.DRAINING, _F.FINISHED})
_ALL_FINISHED = frozenset({_F.FINISHED})
_EXTENDING = frozenset({_J.PRIMING, _J.STARTING, _J.RUNNING})  # job states in which an open stream is extended
RETAIN_MIN_MS = 1000  # an endless job keeps at least this much of its past records (see `_retire`)
EXTEND_EARLY_MS = 500  # ask the extender this long before the chunk is needed (it may plan on another thread)
MAX_EXTENSIONS_PER_SYNC = 4  # short chunks: several may be needed at once; bounded so one SYNC stays short
LONGEST_SEGMENT_MS = 255  # the PVT time field

_JOB_TRANSITIONS: dict[JobState, frozenset[JobState]] = {
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
_EVENT_TYPES: dict[str, type] = {
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


def _stream_ends(plan: StreamPlan) -> list[int]:
    """ends[i] of a plan's records (schedule.segment_ends), without the end record when it is open-ended."""
    ends = segment_ends(plan.segment_ms)
    return ends[:-1] if plan.open_end else ends


def dispatch_table() -> dict[tuple[JobState, type], str]:
    table: dict[tuple[JobState, type], str] = {}
    for state in JobState:
        for name, etype in _EVENT_TYPES.items():
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


_DISPATCH = dispatch_table()


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


_NOTHING = Reaction((), ())


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


class Coordinator:
    """One streaming job over all axes. `handle(event) -> Reaction`; see the module docstring."""

    def __init__(
        self,
        plan: StreamPlan | PvtTrajectoryLike,
        settings: StreamerSettings,
        stop_planner: StopPlanner | None = None,
        extender: Extender | None = None,
        store: StoreFactory | None = None,
    ) -> None:
        self._wire_sync: int | None = None
        self._plan = plan if isinstance(plan, StreamPlan) else StreamPlan.from_trajectory(plan)
        self._extender = extender
        # the open stream's last chunk as given (what the extender extends) and as streamed; None: closed
        self._open_source: PvtTrajectoryLike | None = None
        self._open_plan: StreamPlan | None = None
        if self._plan.open_end:
            self._open_plan = self._plan
            self._open_source = None if isinstance(plan, StreamPlan) else plan
        self._extensions = 0
        self._extend_failure: tuple[str, str] | None = None  # (code, message) once the stream could not go on
        self._settings = s = settings
        self._stop_planner = stop_planner
        self._period = s.sync_period_ms
        self._fifo = s.fifo_size
        self._u = s.underflow_watermark
        self._o = s.overflow_watermark
        readings = {node: s.reading(node) for node in self._plan.node_ids}
        cyclic_nodes = [node for node in self._plan.node_ids if node in s.cyclic]
        fifo_nodes = [node for node in self._plan.node_ids if node not in s.cyclic]
        # a drive that counts the record it interpolates towards out of its FIFO reports one record less
        # while it moves: keep one more queued, so that its own count stays above the watermark too
        hide = any(readings[n].fifo_count == "until_segment_start" for n in fifo_nodes)
        self._policy = FillPolicy(
            s.sync_period_ms, s.underflow_watermark + (1 if hide else 0), s.overflow_watermark, s.lead_ms,
            s.repair_syncs
        )
        self._ends: Window[int] = Window(_stream_ends(self._plan))  # by record index; an endless job drops its past
        self._t_end = self._ends[-1]
        self.extend_need_ms = s.sync_period_ms + max(s.repair_syncs * s.sync_period_ms, s.lead_ms) + (
            self._policy.underflow_watermark + 2) * LONGEST_SEGMENT_MS
        self.extend_ahead_ms = self.extend_need_ms + EXTEND_EARLY_MS
        self._prime_level = priming_level(self._ends, self._policy)
        n = self._plan.n_axes
        self._feedback = s.feedback
        self._feedback_every = s.feedback.every if s.feedback is not None else 1
        # the cyclic axes' frames: one per axis or multiplexed group, every SYNC (members in frame order)
        self._groups: dict[int, tuple[int, ...]] = {}
        for node in cyclic_nodes:
            slot = s.cyclic[node].slot
            self._groups[slot.cob_id] = slot.members
        self._budget: CycleBudget = cycle_budget(
            n, s.sync_period_ms, s.bitrate, s.bus_load_limit, s.heartbeat_ms,
            feedback_every=self._feedback_every, time_stamp=s.time_stamp, cyclic_nodes=len(cyclic_nodes),
            setpoint_bits=setpoint_frame_bits(s.cyclic[m[0]].slot.frame_bytes for m in self._groups.values()
                                              if m[0] in s.cyclic),
        )
        self._step = self._budget.record_frames_per_axis(len(fifo_nodes)) if fifo_nodes else 0
        self._feeders: list[FifoFeeder] = []  # the FIFO axes
        self._cyclic: list[CyclicFeeder] = []  # the axes fed one set point per SYNC
        self._axes: list[FifoFeeder | CyclicFeeder] = []  # every axis, in the plan's order
        self._by_node: dict[int, FifoFeeder | CyclicFeeder] = {}
        self._cw: dict[int, dict[int, Send]] = {}
        self._clocks: dict[int, DriveTime] = {}
        self._sampling: dict[int, str | None] = {}
        # what every drive reported, per SYNC as attributed (the report's deviation is measured from it)
        # (an endless job's go to `store` block by block, when the runtime gives one: streamer/core/spool.py)
        log_store = store if self._plan.open_end else None
        self._feedback_log: dict[int, FeedbackLog] = {node: FeedbackLog(log_store) for node in self._plan.node_ids}
        self._memo_progress: tuple[tuple[int, int, bool], tuple[bool, bool, int, int]] | None = None
        self._memo_demand: tuple[tuple[int, int], tuple[int, ...]] | None = None
        self._memo_match: tuple[tuple[int, int, int], tuple[list[int], int]] | None = None
        for axis, node in enumerate(self._plan.node_ids):
            r = readings[node]
            start = self._plan.start_positions[axis]
            feeder: FifoFeeder | CyclicFeeder
            if node in s.cyclic:
                pos, vel, _ = self._reference(self._plan, axis)
                feeder = CyclicFeeder(axis, node, start, s.cyclic[node], s.sync_period_ms, pos, vel)
                self._cyclic.append(feeder)
            else:
                rid = rpdo2_id(node)
                last = self._plan.records[axis][-1]
                end = PvtRecord(last.position, 0, 0) if self._plan.open_end else last
                lead, tail = stream_framing(start, end, r.first_record, r.fifo_count)
                feeder = FifoFeeder(
                    axis,
                    node,
                    start,
                    list(self._plan.records[axis]),
                    [Send(rid, frame) for frame in self._plan.frames[axis]],
                    sync_period_ms=s.sync_period_ms,
                    loss_confirm_syncs=s.loss_confirm_syncs,
                    repair_margin_ms=s.margin_ms,
                    counts_per_rev=s.counts_per_rev.get(node),
                    lead=Send(rid, pack(lead)) if lead is not None else None,
                    tail=Send(rid, pack(tail)) if tail is not None else None,
                    hides_target=r.fifo_count == "until_segment_start",
                    rounding=r.rounding,
                    open_end=self._plan.open_end,
                    echoed=s.records_echoed,
                )
                self._feeders.append(feeder)
            self._clocks[node] = DriveTime.of_reading(r, s.sync_period_ms, cyclic=node in s.cyclic,
                                                      time_stamped=s.time_stamp)
            self._sampling[node] = r.tpdo_sampling
            self._axes.append(feeder)
            self._by_node[node] = feeder
            cid = rpdo1_id(node)
            self._cw[node] = {
                cw: Send(cid, pack_controlword(cw))
                for cw in (CW_ENABLE_OPERATION, CW_START_IP, CW_HALT, CW_QUICK_STOP)
            }
        self._job_end_ms = max([self._t_end] + [f.end_ms for f in self._cyclic])
        self._points = sum(len(f.sends) for f in self._feeders) + sum(f.n + 1 for f in self._cyclic)
        self._dispatch: dict[tuple[JobState, type], Callable[[Any], None]] = {
            key: getattr(self, name) for key, name in _DISPATCH.items()
        }
        self._state = JobState.CONFIGURING
        self._outcome: JobOutcome | None = None
        self._out: list[Send] = []
        self._changes: list[StateChange] = []
        self._sync: int | None = None
        self._first_sync: int | None = None
        self._sync_since: float | None = None  # when the SYNC's current run began (Sync.since, or our first)
        self._sync_times: dict[int, float] = {}  # recent SYNC count -> time sent
        self._wire_times: dict[int, float] = {}  # fed ahead (`ahead_syncs`): recent SYNC count -> time on the wire
        self._sync_counters: dict[int, int | None] = {}  # recent SYNC count -> its counter byte
        self._t = 0.0
        self._last_sync_t: float | None = None
        self._start_sync: int | None = None
        self._halt_sync: int | None = None
        self._lockstep = 0
        self._lock_prev = 0
        self._safe_prefix = 0  # records an axis needs now to keep its fill >= U for repair_syncs SYNCs
        self._extra_bits = 0.0
        self._cycle_used_bits = 0.0
        self._bus_load_peak = 0.0
        self._measured_peak: float | None = None
        self._congested = False
        self._emitted_any = False
        self._frames_sent = 0
        self._record_frames = 0
        self._control_frames = 0
        self._cancel_info: dict[str, Any] = {}
        # the stream as (start ms, plan) pieces: the job's plan, then every change spliced in (a cyclic axis'
        # state at a time comes from the piece that covers it)
        self._pieces: list[tuple[int, StreamPlan]] = [(0, self._plan)]
        self._pieces_dropped = 0  # pieces of an endless job wholly in the past, forgotten (`_retire`)
        self._retired = 0  # records, frames and segment ends forgotten so far (`_retire`)
        # how far behind the slowest drive an endless job keeps its records: every SYNC a TPDO can still be
        # attributed to (attribution.REACH, the TPDO2 schedule's 2n - 1), with room to spare, and at least 1 s
        self._retain_ms = max(RETAIN_MIN_MS, (attribution.REACH + 2 * self._feedback_every + 2) * self._period)
        self._change_results: list[ChangeResult] = []
        self._emergency: dict[str, Any] | None = None  # what an EmergencyStop did (see `emergency`)
        self._positioning = PositioningTracker(self._plan, s.target_window_counts, s.in_target_timeout_ms)
        self._check_feasible()

    # ---- public surface ---------------------------------------------------------------------------
    def handle(self, event: object, *, wire_sync: int | None = None) -> Reaction:
        """Feed one event; returns the frames to send now and the state changes it caused.

        `wire_sync`: the newest SYNC already on the wire when the returned frames will go out. A
        real-time runtime that lags behind the bus (its queue already holds a later SYNC than the one
        the core last saw) passes it, so records sent now are counted in the drive's fill from the SYNC
        after that one, not from the SYNC after the core's; otherwise a late batch looks lost.
        """
        fn = self._dispatch.get((self._state, type(event)))
        if fn is None:
            raise UnexpectedEvent(f"no transition for {type(event).__name__} in state {self._state.name}")
        self._wire_sync = wire_sync
        # what the attribution worked out for a TPDO, kept for the checks of that same TPDO only
        self._memo_progress = self._memo_demand = self._memo_match = None
        fn(event)
        if not self._out and not self._changes:
            return _NOTHING
        reaction = Reaction(self._out, self._changes)
        self._out = []
        self._changes = []
        return reaction

    @property
    def state(self) -> JobState:
        return self._state

    @property
    def outcome(self) -> JobOutcome | None:
        return self._outcome

    @property
    def start_sync(self) -> int | None:
        return self._start_sync

    @property
    def priming_level(self) -> int:
        return self._prime_level

    @property
    def node_ids(self) -> tuple[int, ...]:
        return self._plan.node_ids

    @property
    def progress(self) -> float:
        """Fraction of the (current, possibly stop-spliced) stream's duration interpolated so far."""
        if self._state is JobState.DONE:
            return 1.0
        if self._start_sync is None or self._sync is None:
            return 0.0
        return min(1.0, max(0.0, self._elapsed(self._sync) / self._job_end_ms))

    @property
    def stream_duration_ms(self) -> int:
        """How long the stream runs from the start SYNC: the plan's duration, or longer/shorter after a splice."""
        return self._job_end_ms

    @property
    def change_results(self) -> tuple[ChangeResult, ...]:
        """Every `Change` fed so far and what became of it, in order."""
        return tuple(self._change_results)

    @property
    def open_ended(self) -> bool:
        """The stream goes on (an open-ended plan being extended chunk by chunk)."""
        return self._open_plan is not None

    @property
    def extensions(self) -> int:
        """Chunks appended to an open-ended stream so far."""
        return self._extensions

    @property
    def pieces_dropped(self) -> int:
        """Pieces before `pieces[0]` that an endless job forgot (wholly interpolated long ago)."""
        return self._pieces_dropped

    @property
    def held(self) -> dict[str, int]:
        """What the core holds of the stream now (what grows with a job's length unless it is retired):
        segment ends, the FIFO axes' records and frames, the pieces and their records; and `retired`, how
        many records, frames and ends it has forgotten."""
        return {
            "ends": self._ends.held,
            "records": sum(f.records.held for f in self._feeders),
            "frames": sum(f.sends.held for f in self._feeders),
            "pieces": len(self._pieces),
            "piece_records": sum(len(r) for _, p in self._pieces for r in p.records),
            "retired": self._retired,
            "feedback_samples": sum(log.held for log in self._feedback_log.values()),
        }

    @property
    def pieces(self) -> tuple[tuple[int, StreamPlan], ...]:
        """The stream as (start ms from the job's start, plan): the job's plan, then each change."""
        return tuple(self._pieces)

    def positioning(self) -> dict[int, PositioningState]:
        """Each axis' positioning state now (seed 002's 9020:03; streamer/core/positioning.py), by node id."""
        return self._positioning.states()

    @property
    def positioning_changes(self) -> tuple[PositioningChange, ...]:
        """Every positioning state change of the job so far, in order (node, state, ms from the start SYNC)."""
        return tuple(self._positioning.changes)

    @property
    def emergency(self) -> dict[str, Any] | None:
        """What an `EmergencyStop` did: None (none fed), {"method": "emergency_trajectory", "knot", "time_ms",
        "stop_duration_ms"} (spliced after what is queued), or {"method": "quick_stop", "reason"}."""
        return None if self._emergency is None else dict(self._emergency)

    @property
    def positioning_change_count(self) -> int:
        """How many positioning changes so far (cheap: a runtime polls it to publish the states when they move)."""
        return len(self._positioning.changes)

    @property
    def warnings(self) -> tuple[NotInTarget, ...]:
        """Warnings of the job so far (`not_in_target`: an axis outside its window after its in-target timeout)."""
        return tuple(self._positioning.warnings)

    def fifo_fills(self) -> dict[int, int | None]:
        """Last reported fill per node (for live displays; None for a cyclic axis: it has no FIFO)."""
        return {f.node_id: f.last_fill if isinstance(f, FifoFeeder) else None for f in self._axes}

    def telemetry(self) -> tuple[AxisTelemetry, ...]:
        return tuple(f.telemetry() for f in self._axes)

    def setpoints(self, node: int) -> Setpoints | None:
        """The set points a cyclic axis is sent (its stop spliced in after a cancel); None for a FIFO axis."""
        f = self._by_node[node]
        return f.setpoints if isinstance(f, CyclicFeeder) else None

    def report(self) -> JobReport:
        ends = [f.end_sync for f in self._axes if f.end_sync is not None]
        syncs = 0 if self._sync is None or self._first_sync is None else self._sync - self._first_sync + 1
        return JobReport(
            state=self._state.value,
            outcome=self._outcome,
            progress=self.progress,
            sync_period_ms=self._period,
            priming_level=self._prime_level,
            start_sync=self._start_sync,
            end_sync=max(ends) if len(ends) == len(self._axes) else None,
            syncs=syncs,
            frames_sent=self._frames_sent,
            record_frames=self._record_frames,
            control_frames=self._control_frames,
            points=self._points,
            frames_per_point=self._frames_sent / self._points if self._points else 0.0,
            bus_load_peak=self._bus_load_peak,
            measured_bus_load_peak=self._measured_peak,
            duration_ms=self._job_end_ms,
            cancel=dict(self._cancel_info),
            axes=self.telemetry(),
            positioning={n: st.name for n, st in self._positioning.states().items()},
            warnings=tuple(self._positioning.warnings),
            feedback=dict(self._feedback_log),
        )

    # ---- construction-time feasibility --------------------------------------------------------------
    def _check_feasible(self) -> None:
        for f in self._cyclic:
            problem = self._cyclic_problem(f)
            if problem is not None:
                self._fail(oc.SETPOINT_RANGE, problem[0], f.node_id, problem[1])
                return
        if self._budget.streamer_bits < 0:
            self._fail(
                oc.BUS_OVERLOAD,
                f"{len(self._axes)} axes at {self._settings.bitrate} bit/s and {self._period} ms SYNC: the SYNC, the "
                f"feedback and the set point frames alone exceed {self._settings.bus_load_limit:.0%} bus load",
                None,
                {"budget_bits": self._budget.streamer_bits},
            )
            return
        if not self._feeders:
            return
        n = len(self._feeders)
        if self._step < 1:
            self._fail(
                oc.BUS_OVERLOAD,
                f"{n} axes at {self._settings.bitrate} bit/s and {self._period} ms SYNC leave no room for "
                f"one record per axis per SYNC under {self._settings.bus_load_limit:.0%} bus load",
                None,
                {"budget_bits": self._budget.streamer_bits},
            )
            return
        short = dry_run(self._ends, self._policy, self._step, self._prime_level, 0)
        if short is None:
            return
        unlimited = dry_run(self._ends, self._policy, self._fifo, self._prime_level, 0)
        code = oc.BUS_OVERLOAD if unlimited is None else oc.BUFFER_UNDERFLOW
        why = (
            f"the bus budget ({self._step} records per axis per SYNC)"
            if unlimited is None
            else f"the FIFO (overflow watermark {self._o}) at a {self._period} ms SYNC"
        )
        self._fail(
            code,
            f"the plan cannot be streamed: {why} would leave {short.fill} records (< {short.needed}) at "
            f"{short.elapsed_ms} ms",
            None,
            {"predicted": True, "elapsed_ms": short.elapsed_ms, "fill": short.fill},
        )

    def _cyclic_problem(self, f: CyclicFeeder) -> tuple[str, dict[str, Any]] | None:
        """Why a cyclic axis' set points cannot go on the wire: a multiplexed frame whose other members are
        not in the job (their part of the frame would be garbage), or a 16-bit step / velocity too large."""
        slot = f.spec.slot
        missing = [m for m in slot.members if m not in self._by_node]
        if missing:
            return (f"node {f.node_id} shares its multiplexed frame 0x{slot.cob_id:03X} with node(s) {missing}, "
                    f"which are not in the job: a job must include every axis of the group",
                    {"cob_id": slot.cob_id, "missing": missing})
        sp = f.setpoints
        if slot.position_bits == 16:
            steps = np.abs(np.diff(sp.positions))
            if steps.size and int(steps.max()) > 32767:
                j = int(steps.argmax())
                return (f"node {f.node_id}: set point {j + 1} moves {int(steps[j])} counts in one SYNC period; a "
                        "multiplexed 16-bit set point carries at most 32767", {"step_counts": int(steps[j])})
        if slot.velocity_bits == 16 and sp.velocities.size and int(np.abs(sp.velocities).max()) > 32767:
            return (f"node {f.node_id}: a velocity of {int(np.abs(sp.velocities).max())} counts/s does not fit "
                    "the 16-bit velocity of its multiplexed frame", {})
        return None

    def _reference(self, plan: StreamPlan, axis: int) -> tuple[Any, Any, Any]:
        """(positions, velocities per ms, accelerations per ms^2) of one axis at every ms: the plan's, or the
        records' own Hermite curve when the trajectory does not carry the plan."""
        if plan.reference is not None:
            pos, vel, acc = plan.reference
            return np.asarray(pos[axis], dtype=np.float64), np.asarray(vel[axis], dtype=np.float64), \
                np.asarray(acc[axis], dtype=np.float64)
        node = plan.node_ids[axis]
        cpr = self._settings.counts_per_rev.get(node)
        if cpr is None:
            raise ValueError(f"node {node} is a cyclic axis: the core needs its counts_per_rev (settings) to "
                             "sample set points from records")
        recs = plan.records[axis][:-1]
        knots = np.array([plan.start_positions[axis]] + [r.position for r in recs], dtype=np.float64)
        vels = np.array([0.0] + [hermite.rpm_to_counts_per_ms(r.velocity, cpr) for r in recs])
        return hermite.reconstruct(knots, vels, np.array(plan.segment_ms, dtype=np.int64))

    # ---- helpers -----------------------------------------------------------------------------------
    def _elapsed(self, sync: int) -> int:
        """Nominal interpolation time at SYNC `sync` (ms since the start SYNC, by the SYNC count)."""
        s = self._start_sync
        if s is None or sync <= s:
            return 0
        return (sync - s) * self._period

    def _elapsed_bounds(self, sync: int, t: float) -> tuple[int, int]:
        """[least, most] interpolation time over every drive at SYNC `sync` (sent at t), whole ms: what
        the slowest drive surely consumed, and what the fastest may have."""
        s = self._start_sync
        if s is None or sync <= s:
            return 0, 0
        lo = hi = self._elapsed(sync)
        for clock in self._clocks.values():
            if clock.exact:
                continue
            k_lo, k_hi = clock.ticks(sync, t)
            lo, hi = min(lo, k_lo), max(hi, k_hi)
        return lo, hi

    def _sync_time(self, sync: int) -> float:
        return self._sync_times.get(sync, self._t)

    def _slack_ms(self, f: FifoFeeder, index: int) -> float:
        """Time from the current SYNC until stream record `index` of `f` becomes the interpolation target
        (pessimistic: as seen by the fastest clock the drive may have)."""
        s = self._start_sync
        if s is None or self._sync is None:
            return float("inf")
        plan_index = index - f.lead
        due = self._ends[plan_index - 1] if plan_index > 0 else 0
        if self._sync <= s:
            return float(due + (s - self._sync) * self._period)
        _, now_hi = self._clocks[f.node_id].ticks(self._sync, self._sync_time(self._sync))
        return float(due - now_hi)

    def _attribute(self, f: FifoFeeder | CyclicFeeder, pdo: int, sync_count: int | None,
                   fits: attribution.Fits) -> int | None:
        """The SYNC a TPDO of `f`'s node answers, by what it contains (streamer/core/attribution.py: one
        rule for every check and the report). `sync_count` is the runtime's tag: the newest SYNC on the
        wire before the TPDO arrived, so the TPDO answers it or an older one; `fits(m)` tests the TPDO's
        content against SYNC m. TPDO2 every n-th SYNC answers a SYNC whose counter carries it."""
        cur = self._sync
        if cur is None:
            return None  # no SYNC seen yet in this job: an answer to an earlier one, not ours
        upper = cur
        if sync_count is not None:
            if sync_count > cur:
                raise ValueError(
                    f"TPDO answering SYNC {sync_count} fed before Sync({sync_count}) (last Sync {cur})"
                )
            upper = sync_count
        fb = self._feedback
        if pdo == 2:
            if fb is not None and fb.every > 1:
                counters, node = self._sync_counters, f.node_id
                return attribution.attribute(
                    upper, f.last_tpdo2, fits,
                    scheduled=lambda m: m in counters and fb.carries(node, counters[m]),
                    schedule_reach=2 * fb.every - 1)
            return attribution.attribute(upper, f.last_tpdo2, fits)
        # a SYNC's TPDO1 goes out before its TPDO2: a TPDO1 answers a SYNC after the one TPDO2 last answered
        return attribution.attribute(upper, max(f.last_tpdo1, f.last_tpdo2), fits)

    def _progress_at(self, f: FifoFeeder, m: int, active: bool) -> tuple[bool, bool, int, int]:
        """(started, activated, least ms, most ms interpolated) of `f`'s drive at SYNC m, given whether it
        reports ip mode active there (the start SYNC's TPDO may be sampled before its controlword)."""
        memo = self._memo_progress
        if memo is not None and memo[0] == (f.node_id, m, active):
            return memo[1]  # the attribution just worked it out for this TPDO
        s = self._start_sync
        started = s is not None and m >= s
        activated = started and (m != s or active)
        if not activated:
            out = started, False, 0, 0
        else:
            lo_ms, hi_ms = self._clocks[f.node_id].ticks(m, self._sync_time(m))
            out = started, True, lo_ms, hi_ms
        self._memo_progress = ((f.node_id, m, active), out)
        return out

    def _status_fits(self, f: FifoFeeder, m: int, sw: int, bs: int, fill: int) -> bool | None:
        """Could a FIFO drive report (statusword, buffer status, fill) at SYNC m? No when ip mode is active
        before the start, inactive while the stream is running (the start SYNC's sampling reading aside), or
        the fill is not one the records sent and consumed by then explain (above: a duplicate there; below
        by more than the unconfirmed batch: consumed records the plan does not explain); None when the state
        checks nothing."""
        fs = f.state
        if (self._state in (JobState.CONFIGURING, JobState.HALTING) or bs & BS_ERRORS or sw & SW_FAULT
                or fs in (FeederState.WAITING, FeederState.FINISHED, FeederState.FAULTED, FeederState.HALTING)):
            return None
        active = bool(bs & BS_IP_ACTIVE or sw & SW_IP_ACTIVE)
        started, activated, lo_ms, hi_ms = self._progress_at(f, m, active)
        if active and not started:
            return False
        if started and not active:
            sampled_before = m == self._start_sync and self._sampling[f.node_id] != "after_rpdo"
            if not sampled_before and (fs is FeederState.STARTING or hi_ms < self._t_end):
                return False
        least, most = f.possible_fill(m, f.stream_consumed(consumed_at(self._ends, lo_ms), activated),
                                      f.stream_consumed(consumed_at(self._ends, hi_ms), activated),
                                      1 if f.hides_target and active else 0)
        return least <= fill <= most

    def _demand_fits(self, f: FifoFeeder, m: int, demand: int) -> bool | None:
        """Is the position demand a FIFO drive reports the plan's at SYNC m (within the demand tolerance, at
        any tick its clock allows)? None when there is nothing to compare with (configuring, halting)."""
        if self._state in (JobState.CONFIGURING, JobState.HALTING) or f.state is FeederState.FAULTED:
            return None
        tol = self._settings.demand_tolerance_counts
        s, clock = self._start_sync, self._clocks[f.node_id]
        if s is None or m <= s or clock.exact:
            options = self._demand_options(f, self._elapsed(m))
            return min(abs(demand - c) for c in options) <= tol if options else None
        _, err = self._clock_match(f, m, demand)
        return err <= tol

    def _demand_options(self, f: FifoFeeder, elapsed_ms: int) -> tuple[int, ...]:
        """`f.demand_candidates(elapsed_ms)`, worked out once per TPDO2 (the attribution, then the check)."""
        memo = self._memo_demand
        if memo is not None and memo[0] == (f.node_id, elapsed_ms):
            return memo[1]
        out = f.demand_candidates(elapsed_ms, self._ends)
        self._memo_demand = ((f.node_id, elapsed_ms), out)
        return out

    def _clock_match(self, f: FifoFeeder, m: int, demand: int) -> tuple[list[int], int]:
        """The own clock's ticks at SYNC m that `demand` matches, and the error (`DriveTime.matching`),
        worked out once per TPDO2."""
        memo = self._memo_match
        if memo is not None and memo[0] == (f.node_id, m, demand):
            return memo[1]
        out = self._clocks[f.node_id].matching(m, self._sync_time(m), lambda k: f.demand_candidates(k, self._ends),
                                               demand, self._settings.demand_tolerance_counts)
        self._memo_match = ((f.node_id, m, demand), out)
        return out

    def _setpoint_fits(self, f: CyclicFeeder, m: int, demand: int) -> bool | None:
        """Is a cyclic drive's reported demand between the set points it can have reached at SYNC m?"""
        if self._state is JobState.CONFIGURING or f.state in (FeederState.HALTING, FeederState.FAULTED,
                                                                FeederState.FINISHED):
            return None
        lo, hi = f.expected_demand(m, self._start_sync)
        return max(0, lo - demand, demand - hi) <= self._settings.demand_tolerance_counts

    def _set_state(self, new: JobState, outcome: JobOutcome | None = None) -> None:
        if new not in _JOB_TRANSITIONS[self._state]:
            raise UnexpectedEvent(f"job state {self._state.name} cannot go to {new.name}")
        self._state = new
        if outcome is not None:
            self._outcome = outcome
        self._changes.append(StateChange(new, self._sync, self._t, outcome))

    def _emit_cw(self, feeder: FifoFeeder | CyclicFeeder, controlword: int) -> None:
        self._out.append(self._cw[feeder.node_id][controlword])
        feeder.frames_sent += 1
        self._cycle_used_bits += CONTROLWORD_FRAME_BITS
        self._extra_bits -= CONTROLWORD_FRAME_BITS
        self._frames_sent += 1
        self._control_frames += 1
        self._emitted_any = True

    def _all_feeders(self, states: frozenset[FeederState]) -> bool:
        return all(f.state in states for f in self._axes)

    def _finish(self, result: JobResult, message: str, detail: dict[str, Any] | None = None) -> None:
        state = JobState.DONE if result is JobResult.DONE else JobState.CANCELLED
        if state is JobState.CANCELLED:
            self._positioning.stopped(self._elapsed_now())
        self._set_state(state, JobOutcome(result, None, None, message, self._sync, self._t, detail or {}))

    def _fail(self, code: str, message: str, node: int | None, detail: dict[str, Any] | None = None) -> None:
        if self._state in TERMINAL:
            return
        if self._emitted_any:
            for f in self._axes:
                self._emit_cw(f, CW_QUICK_STOP)
        for f in self._axes:
            if f.state is not FeederState.FAULTED:
                f.fire(FeederInput.FAULT)
        if node is not None and node in self._by_node:
            self._by_node[node].errors.append(code)
        self._positioning.failed(self._elapsed_now())
        self._set_state(
            JobState.FAILED,
            JobOutcome(JobResult.FAILED, code, node, message, self._sync, self._t, detail or {}),
        )

    # ---- event handlers ----------------------------------------------------------------------------
    def _ignore(self, event: object) -> None:
        return None

    def _on_sync(self, ev: Sync) -> None:
        m = ev.count
        self._t = ev.t
        prev = self._sync
        self._sync_times[m] = ev.t
        self._sync_counters[m] = ev.counter
        if ev.since is not None:
            self._sync_since = ev.since
        elif self._sync_since is None:
            self._sync_since = ev.t  # the runtime does not say: SYNC has run at least since our first
        self._sync_times.pop(m - 64, None)
        self._sync_counters.pop(m - 64, None)
        if prev is None:
            self._first_sync = m
            for f in self._axes:
                f.last_tpdo1 = f.last_tpdo2 = m - 1
        else:
            if m <= prev:
                raise ValueError(f"Sync count {m} after {prev}: counts must increase by one")
            self._close_cycle()
            if m != prev + 1:
                self._sync = m
                self._fail(
                    oc.SYNC_LOST,
                    f"SYNC count jumped from {prev} to {m}: {m - prev - 1} SYNC(s) missing",
                    None,
                    {"previous": prev, "count": m},
                )
                return
            gap = self._settings.sync_gap_factor
            if (
                gap is not None
                and self._last_sync_t is not None
                and ev.t - self._last_sync_t > gap * self._period / 1000.0
            ):
                self._sync = m
                self._fail(
                    oc.SYNC_LOST,
                    f"SYNC {m} came {1000.0 * (ev.t - self._last_sync_t):.1f} ms after the "
                    f"previous one (period {self._period} ms)",
                    None,
                    {"gap_s": ev.t - self._last_sync_t},
                )
                return
        self._sync = m
        self._last_sync_t = ev.t
        self._cycle_used_bits = 0.0
        self._extra_bits = self._budget.streamer_bits
        if not self._settings.ahead_syncs and self._tpdo_overdue(m):
            return
        if m == self._start_sync:
            for clock in self._clocks.values():
                clock.start(m, ev.t)
        if self._open_plan is not None and self._state in _EXTENDING:
            self._keep_open(m, ev.t)
            self._retire(m, ev.t)
        st = self._state
        if st is JobState.PRIMING:
            for cf in self._cyclic:
                self._prime_cyclic(cf, m)
                if self._state in TERMINAL:
                    return
            if self._all_feeders(_ALL_PRIMED):
                self._start(m)
            elif self._feeders:
                self._advance_lockstep(
                    self._prime_level, min(self._step, self._settings.prime_records_per_sync)
                )
        elif st in _SENDING and self._feeders:
            now_lo, _ = self._elapsed_bounds(m, ev.t)
            _, next_hi = self._elapsed_bounds(m + 1, ev.t + self._period / 1000.0)
            self._advance_lockstep(
                target_prefix(self._ends, now_lo, next_hi, self._policy), self._step
            )
            self._update_safe_prefix(m)
        if self._cyclic and self._state not in TERMINAL:
            self._send_setpoints(m)
        self._track_time(m)
        if (st in _IN_MOTION and self._elapsed(m) > self._job_end_ms + self._settings.finish_timeout_ms
                and not self._all_feeders(_ALL_FINISHED)):  # all finished: the in-target timeout bounds the wait
            late = next(f for f in self._axes if f.state is not FeederState.FINISHED)
            self._fail(
                oc.FINISH_TIMEOUT,
                f"node {late.node_id}: no ip mode inactive + target reached (or, for a cyclic axis, its "
                f"last set point) {self._settings.finish_timeout_ms} ms after the plan's end",
                late.node_id,
            )
        elif (
            st is JobState.HALTING
            and self._halt_sync is not None
            and (m - self._halt_sync) * self._period > self._settings.finish_timeout_ms
        ):
            late = next(f for f in self._axes if f.state is not FeederState.FINISHED)
            self._fail(
                oc.FINISH_TIMEOUT,
                f"node {late.node_id}: no standstill {self._settings.finish_timeout_ms} ms after the halt",
                late.node_id,
            )

    def _on_sync_on_wire(self, ev: SyncOnWire) -> None:
        """Fed ahead of the wire (`ahead_syncs`): the answers overdue are judged when SYNC n is on the wire."""
        if self._sync is not None and self._settings.ahead_syncs:
            self._wire_times[ev.count] = ev.t
            self._wire_times.pop(ev.count - 64, None)
            if ev.count in self._sync_times:
                # the answers to SYNC n are judged at its time on the wire, not the nominal time it was fed with:
                # a drive that times its interpolation by the clock or by the SYNCs ran the true time
                self._sync_times[ev.count] = ev.t
                if ev.count == self._start_sync:
                    for clock in self._clocks.values():
                        clock.start(ev.count, ev.t)
            self._tpdo_overdue(min(ev.count, self._sync), ev.t)

    def _on_record_on_wire(self, ev: RecordOnWire) -> None:
        """One of our PVT records received back from the bus (`records_echoed`): the batch it completes counts
        in its drive's fill from the SYNC after the one it followed on the wire (FifoFeeder.on_wire)."""
        f = self._by_node.get(ev.node)
        if isinstance(f, FifoFeeder):
            f.on_wire(ev.sync_count)

    def _tpdo_overdue(self, m: int, t_wire: float | None = None) -> bool:
        """TPDO_TIMEOUT when a node has not answered for `tpdo_timeout_syncs` SYNCs up to SYNC m (every frame
        the bus carried before SYNC m has been fed). With the SYNCs' times on the wire (`t_wire`, SYNC m's),
        those SYNCs must also span that many periods less half of one: SYNCs a stalled sender put on the wire
        back to back leave a drive no time to answer, and its silence is no loss yet."""
        timeout = self._settings.tpdo_timeout_syncs
        limit = m - timeout - 1
        limit2 = m - timeout * self._feedback_every - 1

        def silent(last: int, syncs: int) -> bool:
            if t_wire is None:
                return True
            t_first = self._wire_times.get(last + 1)  # the first SYNC left unanswered
            return t_first is None or (t_wire - t_first) * 1000.0 >= (syncs - 0.5) * self._period

        for f in self._axes:
            late1 = f.last_tpdo1 <= limit and silent(f.last_tpdo1, timeout)
            late2 = f.last_tpdo2 <= limit2 and silent(f.last_tpdo2, timeout * self._feedback_every)
            if late1 or late2:
                which = "TPDO1" if late1 else "TPDO2"
                self._fail(
                    oc.TPDO_TIMEOUT,
                    f"node {f.node_id}: no {which} for "
                    f"{timeout if which == 'TPDO1' else timeout * self._feedback_every} "
                    f"SYNCs (last answered SYNC {min(f.last_tpdo1, f.last_tpdo2)})",
                    f.node_id,
                )
                return True
        return False

    def _close_cycle(self) -> None:
        load = (self._budget.fixed_bits + self._cycle_used_bits) / self._budget.cycle_bits
        if load > self._bus_load_peak:
            self._bus_load_peak = load

    def _advance_lockstep(self, want: int, step: int) -> None:
        old = self._lockstep
        new = min(want, old + step) if want > old else old
        self._lock_prev = old
        self._lockstep = new
        if new > old:
            feeding = sum(1 for f in self._feeders if f.state in _FEEDING)
            self._extra_bits -= feeding * (new - old) * RECORD_FRAME_BITS

    def _start(self, m: int) -> None:
        for f in self._feeders:
            f.fire(FeederInput.START)
            self._emit_cw(f, CW_START_IP)
        for cf in self._cyclic:  # already interpolating the hold: the first set point that moves starts it
            cf.fire(FeederInput.START)
        self._start_sync = m + 1
        self._set_state(JobState.STARTING)
        if self._feeders:
            self._advance_lockstep(target_prefix(self._ends, 0, 0, self._policy), self._step)
            self._update_safe_prefix(m)

    def _update_safe_prefix(self, m: int) -> None:
        if self._start_sync is not None:
            _, next_hi = self._elapsed_bounds(m + 1, self._sync_time(m) + self._period / 1000.0)
            # fed ahead, a batch's confirmation (and so the next batch) comes `ahead_syncs` SYNCs later too
            horizon = next_hi + (self._policy.repair_syncs + self._settings.ahead_syncs) * self._period
            self._safe_prefix = consumed_at(self._ends, horizon) + self._policy.underflow_watermark

    def _feed(self, f: FifoFeeder, fill: int, free: int) -> None:
        if f.pending:
            return
        lo = f.confirmed
        hi = f.stream_prefix(self._lockstep)
        n = min(hi - lo, free, self._o - fill)
        if n <= 0:
            return
        # keep batches as small as this cycle's lockstep step (>= 1): an axis behind the others (after a
        # repair or a missed TPDO) catches up one record per cycle, not in one large batch whose partial
        # loss could not be repaired, unless its fill needs more to stay >= U for repair_syncs SYNCs
        cap = max(1, self._lockstep - self._lock_prev, f.stream_prefix(self._safe_prefix) - lo)
        if n > cap:
            n = cap
        catch = min(n, f.stream_prefix(self._lock_prev) - lo)
        if catch > 0:
            afford = int(self._extra_bits // RECORD_FRAME_BITS)
            if afford < catch:
                n = afford  # only what the spare budget allows; the regular part must wait (order)
            self._extra_bits -= min(catch, n) * RECORD_FRAME_BITS
            if n <= 0:
                return
        newest = max(s for s in (self._sync, self._wire_sync) if s is not None) if (
            self._sync is not None or self._wire_sync is not None) else -1
        sends = f.take(n, newest + 1)
        self._out.extend(sends)
        self._cycle_used_bits += n * RECORD_FRAME_BITS
        self._frames_sent += n
        self._record_frames += n
        self._emitted_any = True

    # ---- cyclic axes --------------------------------------------------------------------------------
    def _prime_cyclic(self, f: CyclicFeeder, m: int) -> None:
        """PRIMING: PRIMED once ip mode was seen active at SYNC a and m >= a + HOLD_AFTER_ACTIVE (the holds
        after a are latched); START_FAILED when it never comes."""
        if f.state is not FeederState.PRIMING:
            return
        if f.spec.starts_with_bit4 and f.bit4_sync is None:
            self._request_ip(f, m)
            return
        if f.active_sync is not None:
            if m >= f.active_sync + HOLD_AFTER_ACTIVE:
                f.fire(FeederInput.PRIMED)
            return
        asked = f.bit4_sync if f.spec.starts_with_bit4 else f.ready_sync
        if asked is not None and (m - asked) * self._period > self._settings.activate_timeout_ms:
            what = "ip mode active (statusword bit 12)" if f.spec.starts_with_bit4 else \
                "following the set point (statusword bit 12)"
            why = (f"; SYNC had run {f.bit4_sync_ran_ms} ms at the SYNC that applied bit 4, the drive needs "
                   f"{f.spec.sync_lock_ms} ms of it" if f.spec.starts_with_bit4 else "")
            self._fail(
                oc.START_FAILED,
                f"node {f.node_id}: not {what} {self._settings.activate_timeout_ms} ms after "
                f"{'controlword bit 4' if f.spec.starts_with_bit4 else 'operation enabled'} (statusword "
                f"0x{f.last_statusword or 0:04X}{why})",
                f.node_id,
                {"statusword": f.last_statusword, "sync_ran_ms": f.bit4_sync_ran_ms},
            )

    def _sync_ran_ms(self, m: int) -> float:
        """How long SYNC had run at SYNC m (since the producer's run began, as far as the core knows)."""
        t = self._sync_times.get(m)
        if t is None or self._sync_since is None:
            return 0.0
        return 1000.0 * (t - self._sync_since)

    def _request_ip(self, f: CyclicFeeder, m: int) -> None:
        """Controlword bit 4 to an XtrapulsPac after SYNC m, once SYNC has run long enough at the SYNC that
        applies it (m + 1) for the drive's PLL to have locked: `sync_lock_ms` before SYNC m, one period to
        spare (a drive refuses bit 4 before that, seed 003: "At least 180 ms are necessary for the
        servo-drive to start the synchronisation"; the manual gives no synchronisation state to read, so
        statusword bit 12 after bit 4 is the check)."""
        ran = self._sync_ran_ms(m)
        if ran + 1e-6 < f.spec.sync_lock_ms:
            return
        self._emit_cw(f, CW_START_IP)
        f.bit4_sync = m
        f.bit4_sync_ran_ms = round(ran + self._period)

    def _send_setpoints(self, m: int) -> None:
        """After SYNC m: every cyclic frame whose axes are being fed, each axis' set point for SYNC m + 1;
        an XtrapulsPac that has reached its last set point gets bit 4 cleared (ip mode off)."""
        s = self._start_sync
        values: dict[int, tuple[int, int]] = {}
        sending: set[int] = set()
        for f in self._cyclic:
            j = f.index_after(m, s) if f.state is not FeederState.FINISHED else f.n
            values[f.node_id] = f.value(j)
            if f.state in _CYCLIC_SENDING:
                sending.add(f.node_id)
                f.sent(j)
                if f.state is FeederState.STREAMING and j >= f.n and self._open_plan is None:
                    f.fire(FeederInput.END_QUEUED)
            if (f.state is FeederState.DRAINING and f.spec.starts_with_bit4 and f.bit4_off_sync is None
                    and s is not None and m >= s + f.n):
                self._emit_cw(f, CW_ENABLE_OPERATION)  # the drive is at its last set point: ip mode off
                f.bit4_off_sync = m + 1
        if self._state is JobState.HALTING:
            return  # the cyclic axes were quick-stopped: they take no set points
        for members in self._groups.values():
            if not any(node in sending for node in members):
                continue
            frame = pack_frame({n: self._settings.cyclic[n].slot for n in members}, members, values)
            self._out.append(frame)
            self._cycle_used_bits += float(setpoint_frame_bits((len(frame.data),)))
            self._frames_sent += 1
            self._record_frames += 1
            self._emitted_any = True

    def _on_status(self, ev: StatusWord) -> None:
        f = self._by_node.get(ev.node)
        if not isinstance(f, CyclicFeeder):
            return
        m = self._attribute(f, 1, ev.sync_count, lambda _m: None)
        if m is None or m <= f.last_tpdo1:
            return
        f.last_tpdo1 = m
        self._t = ev.t
        sw, node = ev.statusword, f.node_id
        if sw & SW_IP_ACTIVE:
            self._feedback_log[node].active(m)
        f.last_statusword = sw
        if sw & SW_FAULT:
            self._fail(oc.DRIVE_FAULT, f"node {node}: statusword 0x{sw:04X} reports a fault at SYNC {m}", node,
                       {"statusword": sw})
            return
        if self._state is JobState.CONFIGURING:
            f.first_status = sw
            self._try_configure()
            return
        fs = f.state
        if fs in (FeederState.FINISHED, FeederState.FAULTED, FeederState.WAITING):
            return
        active = bool(sw & SW_IP_ACTIVE)
        if fs is FeederState.HALTING:
            state = sw & SW_STATE_MASK
            if state not in (SW_OPERATION_ENABLED, SW_QUICK_STOP_ACTIVE) or (
                    state == SW_QUICK_STOP_ACTIVE and sw & SW_TARGET_REACHED):
                f.fire(FeederInput.STOPPED)
                f.end_sync = m
                self._progress_job()
            return
        if fs is FeederState.PRIMING:
            asked = f.bit4_sync if f.spec.starts_with_bit4 else f.ready_sync
            if active and f.active_sync is None and asked is not None and m > asked:
                f.active_sync = m
            return
        s = self._start_sync
        if not active:
            if fs is FeederState.DRAINING and f.bit4_off_sync is not None and m >= f.bit4_off_sync:
                f.fire(FeederInput.STOPPED)
                f.end_sync = m
                self._progress_job()
                return
            self._fail(oc.PROTOCOL, f"node {node}: ip mode inactive (statusword 0x{sw:04X}) at SYNC {m} while "
                       "it is being fed set points", node, {"statusword": sw})
            return
        if fs is FeederState.STARTING and s is not None and m >= s:
            f.fire(FeederInput.ACTIVE)
            f.start_sync = s
            self._progress_job()

    def _on_buffer_status(self, ev: BufferStatus) -> None:
        f = self._by_node.get(ev.node)
        if not isinstance(f, FifoFeeder):
            return
        sw, bs, node = ev.statusword, ev.buffer_status, f.node_id
        fill = self._fifo - ev.free_size
        m = self._attribute(f, 1, ev.sync_count, lambda k: self._status_fits(f, k, sw, bs, fill))
        if m is None or m <= f.last_tpdo1:
            return
        f.last_tpdo1 = m
        self._t = ev.t
        if bs & BS_IP_ACTIVE or sw & SW_IP_ACTIVE:
            self._feedback_log[node].active(m)
        if bs & BS_ERRORS:
            if bs & BS_UNDERFLOW_ERROR:
                code, what = oc.BUFFER_UNDERFLOW, "IP buffer underflow error"
            elif bs & BS_OVERFLOW_ERROR:
                code, what = oc.BUFFER_OVERFLOW, "IP buffer overflow error"
            elif bs & BS_VELOCITY_ERROR:
                code, what = oc.DRIVE_FAULT, "IP velocity error (0x607F exceeded)"
            else:
                code, what = oc.DRIVE_FAULT, "IP acceleration error (0x60C5 exceeded)"
            self._fail(
                code,
                f"node {node}: {what} (buffer status 0x{bs:04X}) at SYNC {m}",
                node,
                {"buffer_status": bs, "statusword": sw},
            )
            return
        if sw & SW_FAULT:
            self._fail(
                oc.DRIVE_FAULT,
                f"node {node}: statusword 0x{sw:04X} reports a fault at SYNC {m}",
                node,
                {"statusword": sw},
            )
            return
        if not 0 <= fill <= self._fifo:
            self._fail(oc.PROTOCOL, f"node {node}: free size {ev.free_size} is outside 0..{self._fifo}", node)
            return
        if self._state is JobState.CONFIGURING:
            f.first_status = (sw, bs, fill)
            self._try_configure()
            return
        fs = f.state
        if fs is FeederState.FINISHED or fs is FeederState.FAULTED:
            return
        if fs is FeederState.HALTING:
            if self._halt_sync is not None and m > self._halt_sync and sw & SW_TARGET_REACHED:
                f.fire(FeederInput.STOPPED)
                f.end_sync = m
                self._progress_job()
            return
        active = bool(bs & BS_IP_ACTIVE or sw & SW_IP_ACTIVE)
        s = self._start_sync
        # the TPDO of the start SYNC itself may be sampled before or after that SYNC's controlword
        # applies (reading `tpdo_sampling`): it may still show ip mode inactive
        sampling = self._sampling[node]
        started, activated, lo_ms, hi_ms = self._progress_at(f, m, active)
        if not started:
            if active:
                self._fail(oc.PROTOCOL, f"node {node}: ip mode active at SYNC {m}, before the start", node)
                return
        else:
            assert s is not None
            if not active:
                sampled_before = m == s and sampling != "after_rpdo"
                if fs is FeederState.STARTING and not sampled_before:
                    self._fail(
                        oc.START_FAILED,
                        f"node {node}: ip mode not active at the start SYNC {s} (reported "
                        f"at SYNC {m}, statusword 0x{sw:04X}, buffer status 0x{bs:04X})",
                        node,
                        {"start_sync": s},
                    )
                    return
                if hi_ms < self._t_end and not sampled_before:
                    self._fail(
                        oc.PROTOCOL,
                        f"node {node}: ip mode inactive at SYNC {m}, {self._t_end - hi_ms} ms "
                        f"before the stream ends",
                        node,
                    )
                    return
            if fs is FeederState.STARTING and active:
                f.fire(FeederInput.ACTIVE)
                f.start_sync = s
                fs = FeederState.STREAMING
        plan_lo = consumed_at(self._ends, lo_ms) if activated else 0
        plan_hi = consumed_at(self._ends, hi_ms) if activated else 0
        hidden = 1 if f.hides_target and active else 0
        failure = f.account(m, f.stream_consumed(plan_lo, activated), fill, lambda i: self._slack_ms(f, i),
                            self._congested, consumed_hi=f.stream_consumed(plan_hi, activated), hidden=hidden)
        if failure is not None:
            self._fail(failure.code, failure.message, node, failure.detail)
            return
        if started:
            remaining = len(self._ends) - plan_hi  # plan records not yet consumed (the tail never is)
            # what the drive holds of the plan: its count, plus the target it leaves out, minus the tail
            tail_in_fifo = max(0, f.confirmed - f.lead - f.plan_len)
            fill_plan = fill + hidden - tail_in_fifo
            f.observe_fill(fill, self._u, self._o, remaining >= self._u)
            needed = needed_fill(self._u, remaining)
            missing = f.repair_pending > 0 or f.suspect_sync is not None
            # with records missing, the feeder's due-time check decides (resend in time, or predicted
            # BUFFER_UNDERFLOW). Otherwise a fill below U means records could not be sent in time: on a
            # congested bus that is BUS_OVERLOAD at once (before any drive underflows); on a quiet bus
            # it is a late master (a real-time runtime that lagged a cycle), which the next top-up
            # repairs, so it fails only when what the FIFO holds runs out within two SYNC periods (a
            # top-up sent now still arrives in time for one more, with a period to spare).
            covered_ms = (self._ends[min(plan_lo + fill_plan, len(self._ends)) - 1] - hi_ms
                          if fill_plan > 0 else 0)
            danger = covered_ms < 2 * self._period and plan_lo + fill_plan < len(self._ends)
            if fill_plan < needed and (self._congested or (not missing and danger)):
                self._fail(
                    oc.BUS_OVERLOAD,
                    f"node {node}: FIFO down to {fill} records (< {needed}) at SYNC {m}: records could not "
                    f"be delivered in time",
                    node,
                    {"fill": fill, "needed": needed, "congested": self._congested,
                     "covered_ms": covered_ms},
                )
                return
        if fs is FeederState.PRIMING:
            if not f.pending and f.confirmed >= f.stream_prefix(self._prime_level):
                f.fire(FeederInput.PRIMED)
                fs = FeederState.PRIMED
        elif fs is FeederState.STREAMING and not f.pending and f.confirmed >= len(f.sends) and not f.open_end:
            f.fire(FeederInput.END_QUEUED)
            fs = FeederState.DRAINING
        if fs is FeederState.DRAINING:
            if started and hi_ms >= self._t_end and not active and sw & SW_TARGET_REACHED:
                f.fire(FeederInput.STOPPED)
                f.end_sync = m
        elif fs in _FEEDING and self._state in _SENDING:
            self._feed(f, fill, ev.free_size)
        self._progress_job()

    def _try_configure(self) -> None:
        for f in self._axes:
            if f.first_status is None or f.first_demand is None:
                return
        tol = self._settings.start_tolerance_counts
        for f in self._axes:
            assert f.first_status is not None and f.first_demand is not None
            node = f.node_id
            why = ""
            if isinstance(f, FifoFeeder):
                sw, bs, fill = f.first_status
                if sw & SW_STATE_MASK != SW_OPERATION_ENABLED:
                    why = f"not operation enabled (statusword 0x{sw:04X})"
                elif bs & BS_IP_ACTIVE or sw & SW_IP_ACTIVE:
                    why = "ip mode already active"
                elif fill != 0:
                    why = f"FIFO holds {fill} records (clear the buffer before a job)"
                detail: dict[str, Any] = {"statusword": sw, "buffer_status": bs}
            else:
                sw = f.first_status
                if sw & SW_STATE_MASK != SW_OPERATION_ENABLED:
                    why = f"not operation enabled (statusword 0x{sw:04X})"
                elif f.spec.starts_with_bit4 and sw & SW_IP_ACTIVE:
                    why = "ip mode already active"
                detail = {"statusword": sw}
            if why:
                self._fail(oc.DRIVE_NOT_READY, f"node {node}: {why}", node, detail)
                return
            if abs(f.first_demand - f.start_position) > tol:
                self._fail(
                    oc.START_MISMATCH,
                    f"node {node}: position demand {f.first_demand} counts is not the "
                    f"plan's start {f.start_position} (off by {f.first_demand - f.start_position})",
                    node,
                    {"position_demand": f.first_demand, "plan_start": f.start_position},
                )
                return
        for f in self._axes:
            f.fire(FeederInput.READY)
            if isinstance(f, FifoFeeder):
                self._emit_cw(f, CW_ENABLE_OPERATION)
            else:
                # the hold set point from now on (sent with the next SYNC's reaction, and this one now, so the
                # SYNC that applies bit 4 finds one); an XtrapulsPac gets bit 4 (a rising edge: enable left it
                # low) once SYNC has run long enough for its PLL, a CSP drive already follows its target
                f.ready_sync = self._sync
                if f.spec.starts_with_bit4 and self._sync is not None:
                    self._request_ip(f, self._sync)
        self._set_state(JobState.PRIMING)
        self._positioning.start()
        if self._cyclic and self._sync is not None:
            self._send_setpoints(self._sync)
        # priming starts with the next SYNC, whose lockstep step reserves the budget for every axis
        self._lock_prev = self._lockstep = 0

    def _progress_job(self) -> None:
        st = self._state
        if st is JobState.STARTING and self._all_feeders(_ALL_ACTIVE):
            self._set_state(JobState.RUNNING)
            st = JobState.RUNNING
        if st is JobState.RUNNING and self._all_feeders(_ALL_QUEUED):
            self._set_state(JobState.FINISHING)
            st = JobState.FINISHING
        if st in (JobState.FINISHING, JobState.CANCELLING, JobState.HALTING) and self._all_feeders(
            _ALL_FINISHED
        ):
            if st is JobState.FINISHING:
                if not self._positioning.settled():
                    return  # PRE_TARGET: waiting for the target windows (or their in-target timeouts)
                self._finish_done()
            elif self._extend_failure is not None:
                if st is JobState.HALTING:
                    for f in self._feeders:  # halt released
                        self._emit_cw(f, CW_ENABLE_OPERATION)
                code, message = self._extend_failure  # stopped at rest, then failed
                self._set_state(JobState.FAILED, JobOutcome(JobResult.FAILED, code, None, message, self._sync,
                                                            self._t, dict(self._cancel_info)))
            elif st is JobState.CANCELLING:
                self._finish(
                    JobResult.CANCELLED,
                    "cancelled: " + str(self._cancel_info.get("summary", "")),
                    dict(self._cancel_info),
                )
            else:
                for f in self._feeders:  # halt released (the cyclic axes were quick-stopped instead)
                    self._emit_cw(f, CW_ENABLE_OPERATION)
                self._finish(
                    JobResult.CANCELLED,
                    "cancelled: " + str(self._cancel_info.get("summary", "")),
                    dict(self._cancel_info),
                )

    def _on_position(self, ev: PositionFeedback) -> None:
        f = self._by_node.get(ev.node)
        if f is None:
            return
        if isinstance(f, CyclicFeeder):
            self._on_cyclic_position(f, ev)
            return
        m = self._attribute(f, 2, ev.sync_count, lambda k: self._demand_fits(f, k, ev.position_demand))
        if m is None or m <= f.last_tpdo2:
            return
        f.last_tpdo2 = m
        self._t = ev.t
        self._feedback_log[f.node_id].position(m, ev.position_demand, ev.position_actual)
        if self._state is JobState.CONFIGURING:
            f.first_demand = ev.position_demand
            self._try_configure()
            return
        self._track_actual(f.node_id, ev.position_actual, m)
        if self._state is JobState.HALTING or f.state is FeederState.FAULTED:
            return  # under halt each drive ramps down on its own: there is no plan to check against
        s = self._start_sync
        demand = ev.position_demand
        clock = self._clocks[f.node_id]
        if s is None or m <= s or clock.exact:
            candidates = self._demand_options(f, self._elapsed(m))
            if not candidates:
                return
            err = min(abs(demand - c) for c in candidates)
            expected = min(candidates, key=lambda c: abs(demand - c))
        else:
            # a drive with its own clock: the ticks its demand matches pin its clock down
            t_m = self._sync_time(m)
            ticks, err = self._clock_match(f, m, demand)
            clock.observe(m, t_m, ticks)
            lo, _ = clock.ticks(m, t_m)
            expected = (f.demand_candidates(lo, self._ends) or (demand,))[0]
        if err > f.max_demand_error:
            f.max_demand_error = err
        if err > self._settings.demand_tolerance_counts:
            if s is None or m <= s:
                self._fail(
                    oc.START_MISMATCH,
                    f"node {f.node_id}: position demand moved to {demand} "
                    f"before the start (plan start {expected})",
                    f.node_id,
                    {"position_demand": demand, "expected": expected},
                )
            else:
                self._fail(
                    oc.PROTOCOL,
                    f"node {f.node_id}: position demand {demand} at SYNC {m} is "
                    f"{err} counts from the plan's {expected}: records executed out of order, twice or "
                    f"not at all",
                    f.node_id,
                    {"position_demand": demand, "expected": expected, "sync": m},
                )

    def _on_cyclic_position(self, f: CyclicFeeder, ev: PositionFeedback) -> None:
        m = self._attribute(f, 2, ev.sync_count, lambda k: self._setpoint_fits(f, k, ev.position_demand))
        if m is None or m <= f.last_tpdo2:
            return
        f.last_tpdo2 = m
        self._t = ev.t
        self._feedback_log[f.node_id].position(m, ev.position_demand, ev.position_actual)
        if self._state is JobState.CONFIGURING:
            f.first_demand = ev.position_demand
            self._try_configure()
            return
        self._track_actual(f.node_id, ev.position_actual, m)
        if f.state in (FeederState.HALTING, FeederState.FAULTED, FeederState.FINISHED):
            return
        s = self._start_sync
        demand = ev.position_demand
        lo, hi = f.expected_demand(m, s)
        err = max(0, lo - demand, demand - hi)
        f.max_demand_error = max(f.max_demand_error, err)
        if err > self._settings.demand_tolerance_counts:
            before = s is None or m <= s
            self._fail(
                oc.START_MISMATCH if before else oc.PROTOCOL,
                f"node {f.node_id}: position demand {demand} at SYNC {m} is {err} counts from the set point "
                f"{'it holds before the start' if before else 'it reached at that SYNC'} ({lo}..{hi})",
                f.node_id,
                {"position_demand": demand, "expected": [lo, hi], "sync": m},
            )
            return
        # a CSP drive has no ip mode to switch off: it is done when it reports its last set point
        if (f.state is FeederState.DRAINING and not f.spec.starts_with_bit4 and s is not None
                and m >= s + f.n and demand == f.value(f.n)[0]):
            f.fire(FeederInput.STOPPED)
            f.end_sync = m
            self._progress_job()

    def _on_emcy(self, ev: Emcy) -> None:
        if ev.node not in self._by_node or ev.code == oc.EMCY_NO_ERROR:
            return
        self._t = ev.t
        code, what = oc.classify_emcy(ev.code, ev.data, cyclic=isinstance(self._by_node[ev.node], CyclicFeeder))
        self._fail(
            code,
            f"node {ev.node}: EMCY 0x{ev.code:04X} ({what})",
            ev.node,
            {"emcy_code": ev.code, "error_register": ev.register, "data": ev.data.hex()},
        )

    def _on_heartbeat_lost(self, ev: HeartbeatLost) -> None:
        if ev.node in self._by_node:
            self._t = ev.t
            self._fail(oc.NODE_LOST, f"node {ev.node}: heartbeat lost", ev.node)

    def _on_bootup(self, ev: Bootup) -> None:
        if ev.node in self._by_node:
            self._t = ev.t
            self._fail(oc.NODE_REBOOT, f"node {ev.node}: boot-up message (the drive rebooted)", ev.node)

    def _on_send_failed(self, ev: SendFailed) -> None:
        self._t = ev.t
        self._fail(oc.BUS_ERROR, f"the bus refused a frame: {ev.reason}", None, {"reason": ev.reason})

    def _on_adapter_error(self, ev: AdapterError) -> None:
        self._t = ev.t
        self._fail(
            oc.BUS_ERROR,
            f"bus adapter error in {ev.where}: {ev.reason}",
            None,
            {"where": ev.where, "reason": ev.reason},
        )

    def _on_bus_load(self, ev: BusLoad) -> None:
        self._congested = ev.load > self._settings.bus_load_limit
        if self._measured_peak is None or ev.load > self._measured_peak:
            self._measured_peak = ev.load

    # ---- cancel ------------------------------------------------------------------------------------
    def _cancel_before_start(self, ev: Cancel) -> None:
        self._t = ev.t
        for cf in self._cyclic:  # an XtrapulsPac may already interpolate the hold: ip mode off, one last hold
            if cf.state is not FeederState.WAITING and cf.spec.starts_with_bit4:
                self._emit_cw(cf, CW_ENABLE_OPERATION)
        if self._cyclic and self._sync is not None and any(
                f.state is not FeederState.WAITING for f in self._cyclic):
            self._send_setpoints(self._sync)
        for f in self._axes:
            f.fire(FeederInput.ABANDON)
        self._cancel_info = {"stop": "before_start", "summary": "before the start; nothing moved"}
        self._finish(
            JobResult.CANCELLED, "cancelled before the start; nothing moved", dict(self._cancel_info)
        )

    def _cancel_after_end(self, ev: Cancel) -> None:
        self._t = ev.t
        self._cancel_info = {
            "stop": "plan_end",
            "summary": "the plan's end was already queued; it ends at rest",
        }
        self._set_state(JobState.CANCELLING)

    def _queue_end(self, at_plan_end: bool = False) -> tuple[int, int, bool]:
        """(k, t0, done): the plan records every axis has queued (k), the time of knot k from the job's start
        (t0), and whether the stream's last segment is already queued (nothing can follow it any more).
        `at_plan_end`: the knot before the end record instead (a buffered change is appended there)."""
        open_stream = self._open_plan is not None  # no end record: nothing is "the last segment" yet
        n_segments = len(self._ends) - (0 if open_stream else 1)
        if self._feeders:
            k = max(min(len(self._ends), f.max_sent - f.lead) for f in self._feeders)  # plan records queued
            if at_plan_end:  # done once the end record (time 0) went out: interpolation stops there
                done = k > n_segments or any(f.sent_index >= f.n for f in self._cyclic)
                k = n_segments
            else:
                done = k >= n_segments and not open_stream
            t0 = self._ends[k - 1] if k > 0 else 0
        elif at_plan_end:  # after the last set point: done once it was sent (the holds that follow stay put)
            k = 0
            t0 = max(f.end_ms for f in self._cyclic)
            done = any(f.sent_index >= f.n for f in self._cyclic)
        else:  # one set point per SYNC: the stop starts after the last set point sent
            k = 0
            sent = max(f.sent_index for f in self._cyclic)
            done = all(f.sent_index >= f.n for f in self._cyclic) and not open_stream
            t0 = max(0, sent) * self._period
        return k, t0, done

    def _state_request(self, k: int, t0: int) -> StopRequest:
        """The state of every axis at knot k / time t0: what a stop or a change must start from."""
        positions: list[int] = []
        velocities: list[int] = []
        accs: list[float | None] = []
        for f in self._axes:
            if isinstance(f, FifoFeeder):
                positions.append(f.records[k - 1].position if k > 0 else f.start_position)
                velocities.append(f.records[k - 1].velocity if k > 0 else 0)
                accs.append(f.end_acceleration(k - 1))
            else:  # the stream's planned state at t0 (the cyclic axis follows the plan, not the records)
                start, piece = next((o, pl) for o, pl in reversed(self._pieces) if o <= t0)
                pos, vel, acc = self._reference(piece, f.axis)
                i = min(t0 - start, pos.size - 1)
                cpr = self._settings.counts_per_rev.get(f.node_id)
                positions.append(hermite.round_counts(float(pos[i])))
                velocities.append(round(hermite.counts_per_ms_to_rpm(float(vel[i]), cpr)) if cpr else 0)
                accs.append(float(acc[i]) if cpr else None)
        return StopRequest(
            knot_index=k,
            time_ms=t0,
            node_ids=self._plan.node_ids,
            positions_counts=tuple(positions),
            velocities_rpm=tuple(velocities),
            accelerations_counts_per_ms2=None
            if any(a is None for a in accs)
            else tuple(float(a or 0.0) for a in accs),
        )

    def _splice_problem(self, request: StopRequest, planned: PvtTrajectoryLike) -> tuple[StreamPlan | None, str]:
        """(the plan to splice, "") or (None, why it cannot be): it must start at the request's state and be
        streamable in time from there (the dry run of the fill)."""
        k, t0 = request.knot_index, request.time_ms
        try:
            plan = StreamPlan.from_trajectory(planned)
        except Exception as exc:
            return None, f"the trajectory cannot be streamed: {type(exc).__name__}: {exc}"
        if plan.node_ids != self._plan.node_ids or plan.start_positions != request.positions_counts:
            return None, (
                f"the trajectory does not start at knot {k} of every axis "
                f"(starts {list(plan.start_positions)}, queued {list(request.positions_counts)})"
            )
        if self._feeders:
            new_ends = self._ends.spliced(k, [t0 + e for e in _stream_ends(plan)])
            assert self._sync is not None
            _, now_hi = self._elapsed_bounds(self._sync, self._sync_time(self._sync))
            short = dry_run(new_ends, self._policy, self._step, k, now_hi)
            if short is not None:
                return None, (f"the trajectory cannot be streamed in time ({short.fill} records left at "
                              f"{short.elapsed_ms} ms)")
        return plan, ""

    def _splice(self, k: int, t0: int, plan: StreamPlan, kind: str = "change",
                start_rpm: Sequence[int] | None = None, source: PvtTrajectoryLike | None = None) -> None:
        """Put `plan` after knot k (time t0) of every axis: FIFO axes get its records after record k, cyclic
        axes its set points from t0 on; nothing already sent is taken back. `kind` ("change", "stop",
        "emergency") and `start_rpm` (the velocities it starts from) are for the positioning state;
        `source`: the trajectory `plan` was made from (an open-ended one is what the next extension
        extends)."""
        for f in self._axes:
            if isinstance(f, FifoFeeder):
                rid = rpdo2_id(f.node_id)
                f.splice(k, list(plan.records[f.axis]), [Send(rid, frame) for frame in plan.frames[f.axis]],
                         open_end=plan.open_end)
            else:
                pos, vel, _ = self._reference(plan, f.axis)
                f.splice(t0, pos, vel)
                if f.state is FeederState.DRAINING:  # it had sent its last set point: the new part has more
                    f.state = FeederState.STREAMING
        if k < self._ends.base:  # no FIFO axis: k is 0, the cyclic axes' part from t0 on is the whole timing
            self._ends = Window()
        else:
            self._ends.truncate(k)
        self._ends.extend(t0 + e for e in _stream_ends(plan))
        self._t_end = self._ends[-1]
        self._job_end_ms = max([self._t_end] + [f.end_ms for f in self._cyclic])
        self._lockstep = min(self._lockstep, k)
        self._lock_prev = min(self._lock_prev, k)
        self._points = sum(len(f.sends) for f in self._feeders) + sum(f.n + 1 for f in self._cyclic)
        self._pieces = [(o, pl) for o, pl in self._pieces if o < t0] + [(t0, plan)]
        self._positioning.splice(t0, plan, kind, start_rpm if start_rpm is not None else [0] * plan.n_axes)
        self._open_plan = plan if plan.open_end else None
        self._open_source = source if plan.open_end else None

    def _cancel_in_motion(self, ev: Cancel) -> None:
        self._t = ev.t
        k, t0, done = self._queue_end()
        if done:
            self._cancel_info = {
                "stop": "plan_end",
                "knot": k,
                "summary": "the plan's last segment was already queued; it ends at rest",
            }
            self._set_state(JobState.CANCELLING)
            return
        if self._stop_planner is None:
            self._halt("no stop planner was given")
            return
        request = self._state_request(k, t0)
        try:
            planned = self._stop_planner(request)
        except Exception as exc:  # the planner's failure is recorded in the outcome, and halt takes over
            self._halt(f"the stop planner failed: {type(exc).__name__}: {exc}")
            return
        stop, why = self._splice_problem(request, planned)
        if stop is None:
            self._halt(why.replace("the trajectory", "the stop trajectory", 1))
            return
        self._splice(k, t0, stop, "stop", request.velocities_rpm)
        self._cancel_info = {
            "stop": "trajectory",
            "knot": k,
            "time_ms": t0,
            "stop_duration_ms": stop.duration_ms,
            "summary": f"stop trajectory from {'knot ' + str(k) + ' ' if self._feeders else ''}{t0} ms, "
                       f"{stop.duration_ms} ms long",
        }
        self._set_state(JobState.CANCELLING)

    # ---- positioning state (seed 002's 9020:03; streamer/core/positioning.py) ----------------------------
    def _elapsed_now(self) -> int | None:
        """Interpolation time at the last SYNC (None before the start SYNC: nothing moved yet)."""
        s = self._start_sync
        if s is None or self._sync is None or self._sync < s:
            return None
        return self._elapsed(self._sync)

    def _track_time(self, m: int) -> None:
        s = self._start_sync
        if s is None or m < s or self._state in TERMINAL:
            return
        self._positioning.on_time(self._elapsed(m))
        if self._state is JobState.FINISHING:
            self._progress_job()

    def _track_actual(self, node: int, actual: int, m: int) -> None:
        s = self._start_sync
        if s is None or m < s or self._state in TERMINAL:
            return
        self._positioning.on_actual(node, actual, self._elapsed(m))
        if self._state is JobState.FINISHING:
            self._progress_job()

    def _finish_done(self) -> None:
        warnings = self._positioning.warnings
        message = f"all {len(self._axes)} axes finished the plan"
        detail: dict[str, Any] = {}
        if warnings:
            message += "; " + "; ".join(
                f"node {w.node} not in its target window ({w.window_counts} counts) {w.timeout_ms} ms after the "
                f"plan's end: {w.error_counts:+d} counts from the target" for w in warnings)
            detail["warnings"] = [
                {"code": w.code, "node": w.node, "error_counts": w.error_counts, "window_counts": w.window_counts,
                 "timeout_ms": w.timeout_ms} for w in warnings]
        self._finish(JobResult.DONE, message, detail)

    # ---- open-ended streams (see the module docstring) ------------------------------------------------
    def _keep_open(self, m: int, t: float) -> None:
        """SYNC m: append the next chunk(s) while the stream ends less than `extend_ahead_ms` ahead of the
        fastest drive; stop the motion when none comes by `extend_need_ms`."""
        now_lo, now_hi = self._elapsed_bounds(m, t)
        for _ in range(MAX_EXTENSIONS_PER_SYNC):
            last, source = self._open_plan, self._open_source
            if last is None:
                return
            ahead = self._t_end - now_hi
            if ahead > self.extend_ahead_ms:
                return
            chunk: PvtTrajectoryLike | None = None
            why = ""
            if source is None or self._extender is None:
                why = "no extender was given" if self._extender is None else "the stream's plan is not a trajectory"
            else:
                try:
                    chunk = self._extender(source)
                except Exception as exc:  # the planner's error is the job's; the motion stops from the queue's end
                    why = f"the extender failed: {type(exc).__name__}: {exc}"
            plan: StreamPlan | None = None
            if chunk is not None:
                plan, why = self._extension_problem(chunk, last, now_hi)
            if plan is None:
                if why or ahead <= self.extend_need_ms:
                    self._end_open(why or f"no next chunk {ahead} ms before the stream's end (it must reach "
                                          f"{self.extend_need_ms} ms ahead)")
                return
            start_rpm = [r[-1].velocity if r else 0 for r in last.records]  # the chunk goes on from there
            self._splice(len(self._ends), self._t_end, plan, "change", start_rpm, source=chunk)
            self._extensions += 1
            self._drop_past_references(now_lo)

    def _extension_problem(self, chunk: PvtTrajectoryLike, last: StreamPlan, now_hi: int) -> tuple[StreamPlan | None,
                                                                                                  str]:
        """(the chunk to append, "") or (None, why not): it starts exactly at the last knot (position and rpm)
        and can be streamed in time after the stream (the dry run of the fill)."""
        try:
            plan = StreamPlan.from_trajectory(chunk)
        except Exception as exc:
            return None, f"the next chunk cannot be streamed: {type(exc).__name__}: {exc}"
        knots = tuple(recs[-1] for recs in last.records)
        positions = tuple(r.position for r in knots)
        velocities = getattr(chunk, "velocities", None)
        start_rpm = tuple(int(v[0]) for v in velocities) if velocities is not None else None
        if (plan.node_ids != self._plan.node_ids or plan.start_positions != positions
                or (start_rpm is not None and start_rpm != tuple(r.velocity for r in knots))):
            return None, (f"the next chunk does not start at the last knot (starts {list(plan.start_positions)} "
                          f"counts, {list(start_rpm or ())} rpm; the stream ends at {list(positions)} counts, "
                          f"{[r.velocity for r in knots]} rpm)")
        if self._feeders:
            ends = self._ends.spliced(len(self._ends), [self._t_end + e for e in _stream_ends(plan)])
            short = dry_run(ends, self._policy, self._step, self._lockstep, now_hi)
            if short is not None:
                return None, (f"the next chunk cannot be streamed in time ({short.fill} records left at "
                              f"{short.elapsed_ms} ms)")
        return plan, ""

    def _end_open(self, why: str) -> None:
        """The open stream cannot go on: stop from the end of the queue (as a cancel does) and fail the job
        EXTENSION_FAILED once the axes are at rest."""
        self._extend_failure = (oc.EXTENSION_FAILED, f"the open-ended motion could not be extended: {why}; it was "
                                "stopped from the end of what was queued")
        if self._state is JobState.PRIMING:  # nothing moved yet
            self._fail(*self._extend_failure, None)
            return
        self._cancel_in_motion(Cancel(self._t))
        self._cancel_info["reason"] = why
        self._open_plan = None
        self._open_source = None

    def _retire(self, m: int, t: float) -> None:
        """SYNC m of an open stream: forget what no one can read again, so that an endless job's memory stays
        flat. Kept: `_retain_ms` behind the slowest drive's interpolation time (every SYNC a TPDO may still be
        attributed to, whose demand is predicted from the records around it), every frame not yet confirmed
        in its FIFO (a resend), and everything after (a stop, change or chunk is spliced after what is
        queued, which is later still). Indices keep counting from the stream's start (`Window`)."""
        if self._start_sync is None or m <= self._start_sync:
            return
        now_lo, _ = self._elapsed_bounds(m, t)
        keep_ms = now_lo - self._retain_ms
        if keep_ms <= 0:
            return
        k = consumed_at(self._ends, keep_ms) - 2  # record k - 1 stays: the segment before k starts there
        if self._feeders:
            k = min([k] + [f.confirmed - f.lead - 1 for f in self._feeders])
        if k > self._ends.base:
            self._retired += self._ends.drop_before(k)
            for f in self._feeders:
                self._retired += f.retire(k)
        while len(self._pieces) > 1 and self._pieces[1][0] <= keep_ms:
            del self._pieces[0]
            self._pieces_dropped += 1

    def _drop_past_references(self, now_ms: int) -> None:
        """The plan at every ms of the pieces wholly interpolated already is not needed any more (an endless
        job would otherwise keep every chunk's): their records stay."""
        for i in range(len(self._pieces) - 1):
            o, pl = self._pieces[i]
            if self._pieces[i + 1][0] <= now_ms and pl.reference is not None:
                self._pieces[i] = (o, dataclasses.replace(pl, reference=None))

    # ---- change ------------------------------------------------------------------------------------
    def _change_refused(self, ev: Change) -> None:
        st = self._state
        why = {
            _J.CONFIGURING: "the job has not started moving yet",
            _J.PRIMING: "the job has not started moving yet",
            _J.CANCELLING: "the job is stopping",
            _J.HALTING: "the job is halting",
            _J.FINISHING: "the running plan's end is already queued: the axes come to rest at its target (submit "
                          "the move as a new job)",
        }.get(st, f"the job has ended ({st.value})")
        self._change_results.append(ChangeResult(ev.tag, ev.mode, False, why, sync=self._sync))

    def _change_in_motion(self, ev: Change) -> None:
        """Splice another trajectory after what is queued (aborting) or after the plan's end (buffered); the
        job goes on RUNNING. Refused (nothing changes) when it cannot be planned, does not start where the
        axes will be, or cannot be streamed in time: the caller learns it from `change_results`."""
        self._t = ev.t
        buffered = ev.mode == "buffered"
        if ev.mode not in ("aborting", "buffered"):
            self._change_results.append(ChangeResult(ev.tag, ev.mode, False, f"unknown mode {ev.mode!r}",
                                                     sync=self._sync))
            return
        if buffered and self._open_plan is not None:
            self._change_results.append(ChangeResult(ev.tag, ev.mode, False, "a velocity move has no end to buffer "
                                                     "after: change it with buffer aborting", sync=self._sync))
            return
        k, t0, done = self._queue_end(at_plan_end=buffered)
        if done:
            self._change_results.append(ChangeResult(
                ev.tag, ev.mode, False, "the running plan's end is already queued: the axes come to rest at its "
                "target (submit the move as a new job)", knot=k, time_ms=t0, sync=self._sync))
            return
        request = self._state_request(k, t0)
        try:
            planned = ev.planner(request)
        except Exception as exc:
            self._change_results.append(ChangeResult(ev.tag, ev.mode, False, str(exc) or type(exc).__name__,
                                                     knot=k, time_ms=t0, sync=self._sync))
            return
        plan, why = self._splice_problem(request, planned)
        if plan is None:
            self._change_results.append(ChangeResult(ev.tag, ev.mode, False, why, knot=k, time_ms=t0,
                                                     sync=self._sync))
            return
        self._splice(k, t0, plan, "change", request.velocities_rpm, source=planned)
        self._change_results.append(ChangeResult(ev.tag, ev.mode, True, "", knot=k, time_ms=t0,
                                                 duration_ms=plan.duration_ms, sync=self._sync))

    # ---- emergency stop ----------------------------------------------------------------------------
    def _emergency_before_start(self, ev: EmergencyStop) -> None:
        self._emergency = {"method": "before_start", "reason": "the job had not started moving"}
        self._cancel_before_start(Cancel(ev.t))
        self._cancel_info["emergency"] = True

    def _emergency_in_motion(self, ev: EmergencyStop) -> None:
        """Splice the emergency stop (the emergency deceleration) after what is queued, as the cancel's stop;
        the drives' quick stop only when no plan is possible in time. A second emergency stop while the first
        one's trajectory runs plans again from the end of the queue (its end may already be queued: that one
        stands)."""
        self._t = ev.t
        if (self._emergency is not None and self._emergency.get("method") == "emergency_trajectory"
                and self._queue_end()[2]):
            return
        why = self._emergency_splice(ev)
        if why:
            self._emergency_quick_stop(why)

    def _emergency_splice(self, ev: EmergencyStop) -> str:
        """Splice the planned emergency stop; "" when done, else why it could not be."""
        if self._state is JobState.HALTING:
            return "the job is halting (no plan to append to)"
        if ev.planner is None:
            return "no emergency stop planner was given"
        k, t0, done = self._queue_end()
        if done:
            return "the plan's end is already queued (nothing can follow it)"
        request = self._state_request(k, t0)
        try:
            planned = ev.planner(request)
        except Exception as exc:
            return f"the emergency stop planner failed: {type(exc).__name__}: {exc}"
        stop, why = self._splice_problem(request, planned)
        if stop is None:
            return why.replace("the trajectory", "the emergency stop trajectory", 1)
        self._splice(k, t0, stop, "emergency", request.velocities_rpm)
        self._emergency = {"method": "emergency_trajectory", "knot": k, "time_ms": t0,
                           "stop_duration_ms": stop.duration_ms, "sync": self._sync}
        self._cancel_info = {
            "stop": "emergency_trajectory", "knot": k, "time_ms": t0, "stop_duration_ms": stop.duration_ms,
            "emergency": True,
            "summary": f"emergency stop trajectory from {'knot ' + str(k) + ' ' if self._feeders else ''}{t0} ms, "
                       f"{stop.duration_ms} ms long",
        }
        if self._state is not JobState.CANCELLING:
            self._set_state(JobState.CANCELLING)
        return ""

    def _emergency_quick_stop(self, reason: str) -> None:
        """No plan possible in time: quick stop (0x000B) on every axis now, and the job fails EMERGENCY_STOP."""
        self._emergency = {"method": "quick_stop", "reason": reason, "sync": self._sync}
        self._positioning.emergency(self._elapsed_now())
        self._fail(oc.EMERGENCY_STOP, f"emergency stop: quick stop (controlword 0x000B) to every axis: {reason}",
                   None, {"method": "quick_stop", "reason": reason})

    def _halt(self, reason: str) -> None:
        """Halt (bit 8) on the FIFO axes; a cyclic axis has no halt in its mode (XtrapulsPac: "only in PV,
        PT, AS, AT"), so it is quick-stopped (its quick stop option 0x605A, written at configuration)."""
        for f in self._feeders:
            if f.state in (FeederState.STARTING, FeederState.STREAMING):
                f.fire(FeederInput.HALT)
            self._emit_cw(f, CW_HALT)
        for cf in self._cyclic:
            if cf.state in (FeederState.STARTING, FeederState.STREAMING, FeederState.DRAINING):
                if cf.state is FeederState.DRAINING:
                    cf.state = FeederState.STREAMING
                cf.fire(FeederInput.HALT)
                self._emit_cw(cf, CW_QUICK_STOP)
        self._halt_sync = (self._sync if self._sync is not None else 0) + 1
        self._positioning.halted(self._elapsed_now())
        self._cancel_info = {"stop": "halt", "reason": reason, "summary": f"halt (bit 8): {reason}"}
        self._set_state(JobState.HALTING)
