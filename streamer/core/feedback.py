"""Feedback: the TPDO handlers, every check of what a drive reports, and attribution's inputs.

Each TPDO is attributed by attribution.py to the SYNC it answers, by content: TPDO2 by the position
demand it can have (`_demand_fits`; a cyclic axis: the set points it can have reached), TPDO1 by ip mode
and a fill the records sent and consumed explain (`_status_fits`); `_reach` measures how far back answers
can still be on their way. The start check, the fill accounting, the demand check and the report
(`JobReport.feedback`) all use that one decision. Demand check: every TPDO2 against the demand predicted
from the queued records with planner.encoding.hermite; beyond demand_tolerance_counts it is PROTOCOL
(records executed out of order, twice or not at all: what catches two swapped records) or START_MISMATCH
before the start; off while halting. Also here: the configuration check on the first TPDOs
(`_try_configure`) and the slack a missing record still has (`_slack_ms`).
"""

from __future__ import annotations

from typing import Any, NamedTuple

from bus.events import BufferStatus, PositionFeedback, StatusWord
from streamer.core import attribution
from streamer.core import outcome as oc
from streamer.core.axis_state import FeederInput, FeederState
from streamer.core.cyclic_feeder import CyclicFeeder
from streamer.core.fifo_feeder import FifoFeeder
from streamer.core.job_state import (
    BS_ERRORS,
    BS_IP_ACTIVE,
    BS_OVERFLOW_ERROR,
    BS_UNDERFLOW_ERROR,
    BS_VELOCITY_ERROR,
    CW_ENABLE_OPERATION,
    FEEDING,
    SENDING,
    SW_FAULT,
    SW_IP_ACTIVE,
    SW_OPERATION_ENABLED,
    SW_QUICK_STOP_ACTIVE,
    SW_STATE_MASK,
    SW_TARGET_REACHED,
    JobState,
)
from streamer.core.schedule import consumed_at, needed_fill
from streamer.core.sending import Sending


class Feedback(Sending):
    """TPDO attribution and the checks of what every drive reports."""

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
        timeout = self._settings.tpdo_timeout_syncs
        if pdo == 2:
            if fb is not None and fb.every > 1:
                counters, node = self._sync_counters, f.node_id
                return attribution.attribute(
                    upper, f.last_tpdo2, fits, reach=self._reach(upper, timeout * fb.every),
                    scheduled=lambda m: m in counters and fb.carries(node, counters[m]),
                    schedule_reach=2 * fb.every - 1)
            return attribution.attribute(upper, f.last_tpdo2, fits, reach=self._reach(upper, timeout))
        # a SYNC's TPDO1 goes out before its TPDO2: a TPDO1 answers a SYNC after the one TPDO2 last answered
        return attribution.attribute(upper, max(f.last_tpdo1, f.last_tpdo2), fits,
                                     reach=self._reach(upper, timeout))

    def _reach(self, upper: int, syncs: int) -> int:
        """How many SYNCs before `upper` an answer arriving after it may answer: those on the wire within
        `syncs` periods (the TPDO timeout: an answer not in by then is lost) before it, by their times on
        the wire: SYNCs a stalled sender put out back to back all count, as the timeout does not count them
        as silence either (attribution.REACH at least; the SYNCs the core still remembers at most)."""
        times = self._wire_times
        t_up = times.get(upper)
        reach = attribution.REACH
        if t_up is None:
            return reach
        window_s = (syncs + 0.5) * self._period / 1000.0
        while (t := times.get(upper - reach - 1)) is not None and t_up - t <= window_s:
            reach += 1
        return reach

    def _answering(self, t: float) -> None:
        """A TPDO that left at `t` is being handled: what it shows was sampled by then (the memos of the last
        one were worked out for another time)."""
        self._answer_t = t
        self._memo_progress = self._memo_match = None

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
            lo_ms, hi_ms = self._clocks[f.node_id].ticks(m, self._sync_time(m), self._answer_t)
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
                                               demand, self._settings.demand_tolerance_counts, self._answer_t)
        self._memo_match = ((f.node_id, m, demand), out)
        return out

    def _setpoint_fits(self, f: CyclicFeeder, m: int, demand: int) -> bool | None:
        """Is a cyclic drive's reported demand between the set points it can have reached at SYNC m?"""
        if self._state is JobState.CONFIGURING or f.state in (FeederState.HALTING, FeederState.FAULTED,
                                                                FeederState.FINISHED):
            return None
        lo, hi = f.expected_demand(m, self._start_sync)
        return max(0, lo - demand, demand - hi) <= self._settings.demand_tolerance_counts

    def _on_status(self, ev: StatusWord) -> None:
        f = self._by_node.get(ev.node)
        if not isinstance(f, CyclicFeeder):
            return
        m = self._attribute(f, 1, ev.sync_count, lambda _m: None)
        if m is None or m <= f.last_tpdo1:
            return
        self._answered = m
        f.answered(1, m)
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
            f.first_status, f.status_heard = sw, self._heard(ev.sync_count)
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
                f.stopped(m)
                self._progress_job()
            return
        if fs is FeederState.PRIMING:
            asked = f.bit4_sync if f.spec.starts_with_bit4 else f.ready_sync
            if active and f.active_sync is None and asked is not None and m > asked:
                f.seen_active(m)
            return
        s = self._start_sync
        if not active:
            if fs is FeederState.DRAINING and f.bit4_off_sync is not None and m >= f.bit4_off_sync:
                f.stopped(m)
                self._progress_job()
                return
            self._fail(oc.PROTOCOL, f"node {node}: ip mode inactive (statusword 0x{sw:04X}) at SYNC {m} while "
                       "it is being fed set points", node, {"statusword": sw})
            return
        if fs is FeederState.STARTING and s is not None and m >= s:
            f.activated(s)
            self._progress_job()

    def _on_buffer_status(self, ev: BufferStatus) -> None:
        f = self._by_node.get(ev.node)
        if not isinstance(f, FifoFeeder):
            return
        sw, bs, node = ev.statusword, ev.buffer_status, f.node_id
        fill = self._fifo - ev.free_size
        self._answering(ev.t)
        m = self._attribute(f, 1, ev.sync_count, lambda k: self._status_fits(f, k, sw, bs, fill))
        if m is None or m <= f.last_tpdo1:
            return
        self._answered = m
        f.answered(1, m)
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
            f.first_status, f.status_heard = (sw, bs, fill), self._heard(ev.sync_count)
            self._try_configure()
            return
        fs = f.state
        if fs is FeederState.FINISHED or fs is FeederState.FAULTED:
            return
        if fs is FeederState.HALTING:
            if self._halt_sync is not None and m > self._halt_sync and sw & SW_TARGET_REACHED:
                f.stopped(m)
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
                f.activated(s)
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
                f.stopped(m)
        elif fs in FEEDING and self._state in SENDING:
            self._feed(f, fill, ev.free_size)
        self._progress_job()

    def _heard(self, sync_count: int | None) -> int:
        """The newest SYNC on the wire when an answer arrived (the runtime's tag, else the last Sync fed)."""
        return sync_count if sync_count is not None else (self._sync if self._sync is not None else -1)

    def _fresh(self, heard: int) -> bool:
        """Was an answer heard late enough that it cannot answer a SYNC before the job? An answer to one of
        those (a drive within its stated latency, or a late one) comes at most the TPDO timeout after it; before
        that, what it says of the drive may be what the drive was (its FIFO before the buffer clear)."""
        first = self._first_sync
        return first is None or heard >= first + self._settings.tpdo_timeout_syncs

    def _try_configure(self) -> None:
        """The start checks on each axis' newest answers. A check that fails on an answer that may be stale
        waits for a fresh one; one that passes does not wait (the job's own checks follow at once)."""
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
                if self._fresh(f.status_heard):
                    self._fail(oc.DRIVE_NOT_READY, f"node {node}: {why}", node, detail)
                return
            if abs(f.first_demand - f.start_position) > tol:
                if not self._fresh(f.demand_heard):
                    return
                self._fail(
                    oc.START_MISMATCH,
                    f"node {node}: position demand {f.first_demand} counts is not the "
                    f"plan's start {f.start_position} (off by {f.first_demand - f.start_position})",
                    node,
                    {"position_demand": f.first_demand, "plan_start": f.start_position},
                )
                return
        for f in self._axes:
            if isinstance(f, FifoFeeder):
                f.fire(FeederInput.READY)
                self._emit_cw(f, CW_ENABLE_OPERATION)
            else:
                # the hold set point from the next SYNC's reaction on, and bit 4 for an XtrapulsPac (a rising
                # edge: enable left it low) in that reaction once SYNC has run long enough for its PLL; a CSP
                # drive already follows its target. Nothing cyclic goes out now: this answer may come late
                # in the cycle, and a set point must precede its SYNC by 100 us (seed 003, error 50)
                f.ready(self._sync)
        self._set_state(JobState.PRIMING)
        self._positioning.start()
        # priming starts with the next SYNC, whose lockstep step reserves the budget for every axis
        self._lock_prev = self._lockstep = 0

    # ---- TPDO2: one attribution path for both axis kinds ---------------------------------------------
    # The steps are the same for a FIFO and a cyclic axis; what differs per kind sits in the five
    # `_demand_*` methods below it: which SYNCs the demand fits (the attribution), whether a demand is
    # checked in the axis' state, how far it is from the plan, how a mismatch is reported, and whether the
    # demand ends the axis (a CSP drive has no ip mode to switch off).

    def _on_position(self, ev: PositionFeedback) -> None:
        f = self._by_node.get(ev.node)
        if f is None:
            return
        demand = ev.position_demand
        self._answering(ev.t)
        m = self._attribute(f, 2, ev.sync_count, lambda k: self._demand_fits_at(f, k, demand))
        if m is None or m <= f.last_tpdo2:
            return
        self._answered = m
        f.answered(2, m)
        self._t = ev.t
        late_us = max(0, round((ev.t - self._sync_time(m)) * 1e6))
        self._feedback_log[f.node_id].position(m, demand, ev.position_actual, late_us)
        if self._state is JobState.CONFIGURING:
            f.first_demand, f.demand_heard = demand, self._heard(ev.sync_count)
            self._try_configure()
            return
        self._track_actual(f.node_id, ev.position_actual, m)
        if not self._demand_checked(f):
            return
        miss = self._demand_error(f, m, demand)
        if miss is None:
            return
        f.demand_checked(miss.err)
        if miss.err > self._settings.demand_tolerance_counts:
            code, message, detail = self._demand_mismatch(f, m, demand, miss)
            self._fail(code, message, f.node_id, detail)
            return
        self._demand_reached(f, m, demand)

    def _demand_fits_at(self, f: FifoFeeder | CyclicFeeder, m: int, demand: int) -> bool | None:
        """The attribution's test: could `f`'s drive report this position demand at SYNC m?"""
        if isinstance(f, CyclicFeeder):
            return self._setpoint_fits(f, m, demand)
        return self._demand_fits(f, m, demand)

    def _demand_checked(self, f: FifoFeeder | CyclicFeeder) -> bool:
        """Is there a plan to check `f`'s demand against? Not under halt (each drive ramps down on its own),
        not once faulted, and for a cyclic axis not once finished either."""
        if isinstance(f, CyclicFeeder):
            return f.state not in (FeederState.HALTING, FeederState.FAULTED, FeederState.FINISHED)
        return not (self._state is JobState.HALTING or f.state is FeederState.FAULTED)

    def _demand_error(self, f: FifoFeeder | CyclicFeeder, m: int, demand: int) -> _DemandMiss | None:
        """How far `demand` at SYNC m is from what the plan allows (None: nothing to compare with). A FIFO
        drive with its own clock: the ticks its demand matches pin that clock down (`DriveTime.observe`)."""
        if isinstance(f, CyclicFeeder):
            lo, hi = f.expected_demand(m, self._start_sync)
            return _DemandMiss(max(0, lo - demand, demand - hi), lo, hi)
        s, clock = self._start_sync, self._clocks[f.node_id]
        if s is None or m <= s or clock.exact:
            candidates = self._demand_options(f, self._elapsed(m))
            if not candidates:
                return None
            expected = min(candidates, key=lambda c: abs(demand - c))
            return _DemandMiss(min(abs(demand - c) for c in candidates), expected, expected)
        t_m = self._sync_time(m)
        ticks, err = self._clock_match(f, m, demand)
        clock.observe(m, t_m, ticks, self._answer_t)
        lo_ms, _ = clock.ticks(m, t_m)
        expected = (f.demand_candidates(lo_ms, self._ends) or (demand,))[0]
        return _DemandMiss(err, expected, expected)

    def _demand_mismatch(self, f: FifoFeeder | CyclicFeeder, m: int, demand: int,
                         miss: _DemandMiss) -> tuple[str, str, dict[str, Any]]:
        """(code, message, detail) of a demand off the plan: START_MISMATCH up to the start, then PROTOCOL."""
        s, node, err = self._start_sync, f.node_id, miss.err
        before = s is None or m <= s
        if isinstance(f, CyclicFeeder):
            lo, hi = miss.lo, miss.hi
            return (oc.START_MISMATCH if before else oc.PROTOCOL,
                    f"node {node}: position demand {demand} at SYNC {m} is {err} counts from the set point "
                    f"{'it holds before the start' if before else 'it reached at that SYNC'} ({lo}..{hi})",
                    {"position_demand": demand, "expected": [lo, hi], "sync": m})
        expected = miss.lo
        if before:
            return (oc.START_MISMATCH,
                    f"node {node}: position demand moved to {demand} before the start (plan start {expected})",
                    {"position_demand": demand, "expected": expected})
        return (oc.PROTOCOL,
                f"node {node}: position demand {demand} at SYNC {m} is {err} counts from the plan's {expected}: "
                "records executed out of order, twice or not at all",
                {"position_demand": demand, "expected": expected, "sync": m})

    def _demand_reached(self, f: FifoFeeder | CyclicFeeder, m: int, demand: int) -> None:
        """A CSP drive has no ip mode to switch off: it is done when it reports its last set point. (A FIFO
        drive and an XtrapulsPac end on their TPDO1: ip mode off.)"""
        s = self._start_sync
        if (isinstance(f, CyclicFeeder) and f.state is FeederState.DRAINING and not f.spec.starts_with_bit4
                and s is not None and m >= s + f.n and demand == f.value(f.n)[0]):
            f.stopped(m)
            self._progress_job()


class _DemandMiss(NamedTuple):
    """A TPDO2's distance from the plan: `err` counts outside [lo, hi] (a FIFO axis: lo == hi, the plan's
    demand nearest the reported one)."""

    err: int
    lo: int
    hi: int
