"""The per-SYNC cycle: SYNC and TPDO checks, extension, priming and the synchronous start, the lockstep top-up.

Every `Sync`: close the last cycle's bus load, check the SYNC count and gap (SYNC_LOST) and the TPDO
timeouts, extend and retire an open stream, then by job state: prime and start every axis in one cycle
(`_start`), or grow the lockstep prefix by the top-up rule (schedule.py) within the frame budget
(`_advance_lockstep`), then set points, positioning and the finish timeouts. Frame budget: bus_load_limit
x bitrate x period minus the traffic the job causes anyway, in worst-case bits (bus/budget.py). The
nominal schedule is dry-run at construction: a plan that cannot keep every FIFO >= min(U, records left)
fails at once, BUS_OVERLOAD or BUFFER_UNDERFLOW, before anything is sent. At run time a low FIFO with
nothing missing, or a measured load over the limit, fails BUS_OVERLOAD before the drive underflows;
while records are missing the feeder's due-time check decides.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from bus.budget import RECORD_FRAME_BITS
from bus.events import RecordOnWire, Sync, SyncOnWire
from streamer.core import outcome as oc
from streamer.core.axis_state import FeederInput, FeederState
from streamer.core.cyclic_feeder import HOLD_AFTER_ACTIVE, CyclicFeeder
from streamer.core.fifo_feeder import FifoFeeder
from streamer.core.job_state import (
    ALL_FINISHED,
    ALL_PRIMED,
    CW_ENABLE_OPERATION,
    CW_START_IP,
    EXTENDING,
    FEEDING,
    IN_MOTION,
    SENDING,
    TERMINAL,
    JobState,
)
from streamer.core.open_stream import OpenStream
from streamer.core.schedule import consumed_at, dry_run, target_prefix

BIT4_RETRY_MIN_MS = 50.0  # a bit 4 request stands at least this long before it is dropped and raised again


class Scheduler(OpenStream):
    """The per-SYNC cycle: feasibility, lockstep and budget, priming and start, timeouts."""

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
                f.answers_from(m)
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
        if not self._settings.ahead_syncs:
            # fed as it goes out: its time is its time on the wire (SYNCs a stalled sender bunched are no
            # silence of the drives)
            self._wire_times[m] = ev.t
            self._wire_times.pop(m - 64, None)
            if self._tpdo_overdue(m, ev.t):
                return
        if self._cancel_pending and self._state in (JobState.CONFIGURING, JobState.PRIMING):
            self._cancel_pending = False
            self._release_before_start()  # the last hold and bit 4 off, right after this SYNC
            return
        if m == self._start_sync:
            for clock in self._clocks.values():
                clock.start(m, ev.t)
        if self._open_plan is not None and self._state in EXTENDING:
            self._keep_open(m, ev.t)
            self._retire(m, ev.t)
        st = self._state
        if st is JobState.PRIMING:
            for cf in self._cyclic:
                self._prime_cyclic(cf, m)
                if self._state in TERMINAL:
                    return
            if self._all_feeders(ALL_PRIMED):
                self._start(m)
            elif self._feeders:
                self._advance_lockstep(
                    self._prime_level, min(self._step, self._settings.prime_records_per_sync)
                )
        elif st in SENDING and self._feeders:
            now_lo, _ = self._elapsed_bounds(m, ev.t)
            _, next_hi = self._elapsed_bounds(m + 1, ev.t + self._period / 1000.0)
            self._advance_lockstep(
                target_prefix(self._ends, now_lo, next_hi, self._policy), self._step
            )
            self._update_safe_prefix(m)
        if self._cyclic and self._state not in TERMINAL:
            self._send_setpoints(m)
        self._track_time(m)
        if (st in IN_MOTION and self._elapsed(m) > self._job_end_ms + self._settings.finish_timeout_ms
                and not self._all_feeders(ALL_FINISHED)):  # all finished: the in-target timeout bounds the wait
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
            feeding = sum(1 for f in self._feeders if f.state in FEEDING)
            self._extra_bits -= feeding * (new - old) * RECORD_FRAME_BITS

    def _start(self, m: int) -> None:
        for f in self._feeders:
            f.fire(FeederInput.START)
            self._emit_cw(f, CW_START_IP)
        for cf in self._cyclic:  # already interpolating the hold: the first set point that moves starts it
            cf.fire(FeederInput.START)
        # the controlword applies at the SYNC after it is on the wire: after SYNC m, or after a later one already
        # out when a lagging real-time master (no cycle engine) gets here (`wire_sync`)
        self._start_sync = max(m, self._wire_sync if self._wire_sync is not None else m) + 1
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

    def _prime_cyclic(self, f: CyclicFeeder, m: int) -> None:
        """PRIMING: PRIMED once ip mode was seen active at SYNC a and m >= a + HOLD_AFTER_ACTIVE (the holds
        after a are latched); START_FAILED when it never comes.

        An XtrapulsPac that does not take bit 4 within `_bit4_retry_ms` of it gets it dropped for one SYNC and
        raised again, up to `activate_timeout_ms` after the first request. The manual (seed 003 3.1.1.4) says
        the drive needs 180 ms of SYNC to synchronise and not what it does with bit 4 before: take it when
        locked, or refuse it until it falls and rises again (the simulated drive). A host stall restarts the
        drive's lock count where the master cannot see it; the new edge serves every reading."""
        if f.state is not FeederState.PRIMING:
            return
        bit4 = f.spec.starts_with_bit4
        if bit4 and f.bit4_sync is None and (f.bit4_low_sync is None or m > f.bit4_low_sync):
            self._request_ip(f, m)
            return
        if f.active_sync is not None:
            if m >= f.active_sync + HOLD_AFTER_ACTIVE:
                f.fire(FeederInput.PRIMED)
            return
        asked = f.bit4_first_sync if bit4 else f.ready_sync
        if asked is not None and (m - asked) * self._period > self._settings.activate_timeout_ms:
            what = "ip mode active (statusword bit 12)" if bit4 else "following the set point (statusword bit 12)"
            times = f"{f.bit4_requests} time{'s' if f.bit4_requests != 1 else ''}"
            why = (f"; bit 4 raised {times}, SYNC had run {f.bit4_sync_ran_ms} ms at the SYNC "
                   f"that applied the last, the drive needs {f.spec.sync_lock_ms} ms of it" if bit4 else "")
            self._fail(
                oc.START_FAILED,
                f"node {f.node_id}: not {what} {self._settings.activate_timeout_ms} ms after "
                f"{'controlword bit 4' if bit4 else 'operation enabled'} (statusword "
                f"0x{f.last_statusword or 0:04X}{why})",
                f.node_id,
                {"statusword": f.last_statusword, "sync_ran_ms": f.bit4_sync_ran_ms, "bit4_requests": f.bit4_requests},
            )
            return
        if bit4 and f.bit4_sync is not None and (m - f.bit4_sync) * self._period >= self._bit4_retry_ms(f):
            self._emit_cw(f, CW_ENABLE_OPERATION)  # not taken: low for the next SYNC, raised again after it
            f.ip_dropped(m)

    def _bit4_retry_ms(self, f: CyclicFeeder) -> float:
        """How long a bit 4 request is left standing: the drive's lock time (a drive that takes bit 4 once
        locked has then taken it) and three periods for its statusword to come back (TPDO latency up to 0.9
        period), at least BIT4_RETRY_MIN_MS."""
        return max(float(f.spec.sync_lock_ms), BIT4_RETRY_MIN_MS) + 3 * self._period
