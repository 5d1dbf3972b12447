"""Coordinator: the multi-axis job state machine of the PVT streamer (one object per job, no I/O).

Owns one job: one feeder per axis (fifo_feeder.py, cyclic_feeder.py), the shared timing and lockstep, the
per-SYNC frame budget, the synchronous start, finish, cancel and fault handling, and the outcome.
`handle(event)` takes `bus.events` and returns a `Reaction` (frames to send now, in order, and state
changes), dispatched by a table of (job state, event type); a missing pair raises `UnexpectedEvent`.

Contract with the runtime: feed `Sync(n)` once SYNC n is on the wire, before TPDOs answering it, counts
rising by 1; tag TPDOs with the newest SYNC on the wire (the core attributes them: attribution.py); send
the returned frames at once; hand over drives enabled with the buffer cleared (else DRIVE_NOT_READY).
States (job_state.JobState): CONFIGURING -> PRIMING -> STARTING (0x001F to every axis in one cycle) ->
RUNNING -> FINISHING -> DONE; CANCELLING / HALTING (splices.py); CANCELLED, FAILED. Any fault sends quick
stop 0x000B to every axis in that reaction, fails the job, and nothing is sent again (STYLE.md rule 4).
The parts each build on the one before; docs/streamer.md ("One job") walks through them.
"""

from __future__ import annotations

from typing import Any

from bus.events import AdapterError, Bootup, BusLoad, Emcy, HeartbeatLost, SendFailed
from planner.encoding.cyclic import Setpoints
from streamer.core import outcome as oc
from streamer.core.cyclic_feeder import CyclicFeeder
from streamer.core.feedback import Feedback
from streamer.core.fifo_feeder import AxisTelemetry, FifoFeeder
from streamer.core.job_state import CW_ENABLE_OPERATION as CW_ENABLE_OPERATION
from streamer.core.job_state import CW_HALT as CW_HALT
from streamer.core.job_state import CW_QUICK_STOP as CW_QUICK_STOP
from streamer.core.job_state import CW_START_IP as CW_START_IP

# re-exported: the job's states, tables and control words are read from here by the runtime and the tests
from streamer.core.job_state import DISPATCH as DISPATCH
from streamer.core.job_state import EVENT_TYPES as EVENT_TYPES
from streamer.core.job_state import JOB_TRANSITIONS as JOB_TRANSITIONS
from streamer.core.job_state import NOTHING
from streamer.core.job_state import TERMINAL as TERMINAL
from streamer.core.job_state import JobReport as JobReport
from streamer.core.job_state import JobState as JobState
from streamer.core.job_state import Reaction as Reaction
from streamer.core.job_state import StateChange as StateChange
from streamer.core.job_state import UnexpectedEvent as UnexpectedEvent
from streamer.core.job_state import dispatch_table as dispatch_table
from streamer.core.outcome import JobOutcome
from streamer.core.plan_source import ChangeResult, Extender, PvtTrajectoryLike, StopPlanner, StreamPlan
from streamer.core.positioning import NotInTarget, PositioningChange, PositioningState
from streamer.core.scheduling import Scheduler
from streamer.core.settings import StreamerSettings
from streamer.core.spool import StoreFactory


class Coordinator(Scheduler, Feedback):
    """One streaming job over all axes. `handle(event) -> Reaction`; see the module docstring (and its parts')."""

    def __init__(
        self,
        plan: StreamPlan | PvtTrajectoryLike,
        settings: StreamerSettings,
        stop_planner: StopPlanner | None = None,
        extender: Extender | None = None,
        store: StoreFactory | None = None,
    ) -> None:
        super().__init__(plan, settings, stop_planner, extender, store)
        self._check_feasible()

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
        self._answered = None
        fn(event)
        if not self._out and not self._changes:
            return NOTHING
        reaction = Reaction(self._out, self._changes)
        self._out = []
        self._changes = []
        return reaction

    @property
    def state(self) -> JobState:
        return self._state

    @property
    def answered_sync(self) -> int | None:
        """The SYNC the event just handled answers, as attributed (streamer/core/attribution.py), when it was a
        drive's TPDO the core attributed; None otherwise. A trace or a live view that keys the drives' answers
        by SYNC takes it from here, not from the arrival tag (a late answer arrives after the next SYNC)."""
        return self._answered

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

    def _ignore(self, event: object) -> None:
        return None

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
