"""The job's state and the moves every part of the coordinator makes (streamer/core/coordinator.py).

`JobCore` holds one job's plan, feeders, clocks, lockstep, budget, pieces and outcome, all set up in
`__init__`; the parts built on it add behaviour, not state. Here: the job's SYNC time (`_elapsed`,
`_elapsed_bounds`), state changes by the table, `_fail` (quick stop once anything was sent, then FAILED:
STYLE.md rule 4), control words, and `_progress_job`, the state-triggered transitions applied to a fixed point.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from bus.budget import CONTROLWORD_FRAME_BITS, CycleBudget, cycle_budget, setpoint_frame_bits
from bus.cob import pack_controlword, rpdo1_id, rpdo2_id
from bus.events import Send
from planner.encoding import hermite
from planner.encoding.record import PvtRecord, pack
from streamer.core import attribution
from streamer.core.attribution import FeedbackLog
from streamer.core.axis_state import FeederInput, FeederState
from streamer.core.cyclic_feeder import CyclicFeeder
from streamer.core.drive_time import DriveTime
from streamer.core.fifo_feeder import FifoFeeder, stream_framing
from streamer.core.job_state import (
    CW_ENABLE_OPERATION,
    CW_HALT,
    CW_QUICK_STOP,
    CW_START_IP,
    DISPATCH,
    EXTEND_EARLY_MS,
    JOB_TRANSITIONS,
    LONGEST_SEGMENT_MS,
    RETAIN_MIN_MS,
    TERMINAL,
    TRIGGERS_BY_STATE,
    JobState,
    StateChange,
    UnexpectedEvent,
    stream_ends,
)
from streamer.core.outcome import JobOutcome, JobResult
from streamer.core.plan_source import ChangeResult, Extender, PvtTrajectoryLike, StopPlanner, StreamPlan
from streamer.core.positioning import PositioningTracker
from streamer.core.schedule import FillPolicy, priming_level
from streamer.core.settings import StreamerSettings
from streamer.core.spool import StoreFactory
from streamer.core.window import Window


class JobCore:
    """The job's state (set up once, in `__init__`) and the primitives every part uses."""

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
        self._ends: Window[int] = Window(stream_ends(self._plan))  # by record index; an endless job drops its past
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
        self._answered: int | None = None  # the SYNC the TPDO just handled answers (`answered_sync`)
        self._memo_match: tuple[tuple[int, int, int], tuple[list[int], int]] | None = None
        # the time on the wire of the TPDO being handled: a drive with its own clock (or timed by the SYNCs)
        # sampled what it shows at that time at the latest (streamer/core/drive_time.py)
        self._answer_t: float | None = None
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
            key: getattr(self, name) for key, name in DISPATCH.items()
        }
        self._state = JobState.CONFIGURING
        self._outcome: JobOutcome | None = None
        self._out: list[Send] = []
        self._changes: list[StateChange] = []
        self._sync: int | None = None
        self._first_sync: int | None = None
        self._sync_since: float | None = None  # when the SYNC's current run began (Sync.since, or our first)
        self._sync_times: dict[int, float] = {}  # recent SYNC count -> time sent
        self._wire_times: dict[int, float] = {}  # recent SYNC count -> time on the wire
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
        self._cancel_pending = False  # a cancel before the start, carried out in the next SYNC's reaction
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

    def _elapsed_now(self) -> int | None:
        """Interpolation time at the last SYNC (None before the start SYNC: nothing moved yet)."""
        s = self._start_sync
        if s is None or self._sync is None or self._sync < s:
            return None
        return self._elapsed(self._sync)

    def _set_state(self, new: JobState, outcome: JobOutcome | None = None) -> None:
        if new not in JOB_TRANSITIONS[self._state]:
            raise UnexpectedEvent(f"job state {self._state.name} cannot go to {new.name}")
        self._state = new
        if outcome is not None:
            self._outcome = outcome
        self._changes.append(StateChange(new, self._sync, self._t, outcome))

    def _emit_cw(self, feeder: FifoFeeder | CyclicFeeder, controlword: int) -> None:
        self._out.append(self._cw[feeder.node_id][controlword])
        feeder.controlword_sent()
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
            self._by_node[node].failed(code)
        self._positioning.failed(self._elapsed_now())
        self._set_state(
            JobState.FAILED,
            JobOutcome(JobResult.FAILED, code, node, message, self._sync, self._t, detail or {}),
        )

    def _progress_job(self) -> None:
        """The state-triggered transitions to a fixed point: the first entry of `STATE_TRIGGERED` for the
        current state whose conditions hold makes its move; again from the new state, until none holds."""
        while True:
            st = self._state
            for trigger in TRIGGERS_BY_STATE.get(st, ()):
                if self._all_feeders(trigger.axes_in) and (trigger.guard is None or getattr(self, trigger.guard)()):
                    getattr(self, trigger.move)()
                    break
            else:
                return
            if self._state is st:
                raise RuntimeError(f"state-triggered move {trigger.move} left the job in {st.name}")

    # ---- the state-triggered moves (job_state.STATE_TRIGGERED) -------------------------------------------
    def _to_running(self) -> None:
        self._set_state(JobState.RUNNING)

    def _to_finishing(self) -> None:
        self._set_state(JobState.FINISHING)

    def _settled(self) -> bool:
        """Every axis in its target window (or stopped, or timed out there): FINISHING may end."""
        return self._positioning.settled()

    def _cancel_done(self) -> None:
        """CANCELLING, every axis stopped on its stop trajectory: CANCELLED."""
        self._stopped_done()

    def _halt_done(self) -> None:
        """HALTING, every axis at standstill: the halt released (the FIFO axes; the cyclic axes were quick-stopped
        instead), CANCELLED."""
        for f in self._feeders:
            self._emit_cw(f, CW_ENABLE_OPERATION)
        self._stopped_done()

    def _stopped_done(self) -> None:
        """The end of a cancel or halt: CANCELLED, or FAILED with the extension failure that made the stop (an
        open-ended stream whose next chunk could not be planned stops at rest, then fails)."""
        if self._extend_failure is not None:
            code, message = self._extend_failure
            self._set_state(JobState.FAILED, JobOutcome(JobResult.FAILED, code, None, message, self._sync,
                                                        self._t, dict(self._cancel_info)))
            return
        self._finish(
            JobResult.CANCELLED,
            "cancelled: " + str(self._cancel_info.get("summary", "")),
            dict(self._cancel_info),
        )

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
