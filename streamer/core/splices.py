"""Splices: one place for cancel, change and emergency stop (and, through `_splice`, an open stream's next chunk).

One sequence serves the three verbs (`_plan_splice`): take the state at the end of what is queued
(`_queue_end`, `_state_request`: knot K = the most records sent to any axis), ask the verb's planner for a
trajectory from there, check it starts there and can be streamed in time (`_splice_problem`), and splice
it after knot K of every axis (`_splice`); nothing sent is taken back (a FIFO has no delete), so the
verb acts after what is queued. Where it falls short it says so in a `SpliceAttempt`, and each verb
reacts its own way: a cancel halts (controlword bit 8, each drive on its own 0x6084, at the next SYNC;
then 0x000F and CANCELLED), a change is refused (`change_results`), an emergency stop quick-stops
(FAILED EMERGENCY_STOP). A cancel before the start ends at once; one after the plan's end is queued lets
it finish. A change is "aborting" (after what is queued) or "buffered" (after the plan's end).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from bus.cob import rpdo2_id
from bus.events import Cancel, Send
from planner.encoding import hermite
from streamer.core import outcome as oc
from streamer.core.axis_state import FeederInput, FeederState
from streamer.core.fifo_feeder import FifoFeeder
from streamer.core.job_state import CW_ENABLE_OPERATION, CW_HALT, CW_QUICK_STOP, JobState, stream_ends
from streamer.core.outcome import JobResult
from streamer.core.plan_source import Change, ChangeResult, EmergencyStop, PvtTrajectoryLike, StopRequest, StreamPlan
from streamer.core.schedule import dry_run
from streamer.core.sending import Sending
from streamer.core.window import Window


@dataclass(frozen=True)
class SpliceAttempt:
    """What `_plan_splice` did: spliced `plan` after knot `k` (time `t0`), or stopped short. `failed`: "" (spliced),
    "end_queued" (the plan's end is already queued: nothing can follow it), "no_planner", "planner" (it raised
    `error`) or "unfit" (the trajectory does not start at the request's state or cannot be streamed in time:
    `why`)."""

    k: int
    t0: int
    failed: str = ""
    plan: StreamPlan | None = None
    why: str = ""
    error: Exception | None = None


class Splices(Sending):
    """Cancel, change, emergency stop and halt: one splice after what is queued."""

    def _cancel_before_start(self, ev: Cancel) -> None:
        """Nothing moved yet: ip mode off where an XtrapulsPac already interpolates the hold, and the job ends
        CANCELLED. Where set points flow, that last hold goes out in the next SYNC's reaction, as every set
        point does (a cancel comes at any time in the cycle; a set point must precede its SYNC by 100 us)."""
        self._t = ev.t
        if self._sync is not None and any(f.state is not FeederState.WAITING for f in self._cyclic):
            self._cancel_pending = True
            return
        self._release_before_start()

    def _release_before_start(self) -> None:
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
            new_ends = self._ends.spliced(k, [t0 + e for e in stream_ends(plan)])
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
                    f.fire(FeederInput.EXTENDED)
        if k < self._ends.base:  # no FIFO axis: k is 0, the cyclic axes' part from t0 on is the whole timing
            self._ends = Window()
        else:
            self._ends.truncate(k)
        self._ends.extend(t0 + e for e in stream_ends(plan))
        self._t_end = self._ends[-1]
        self._job_end_ms = max([self._t_end] + [f.end_ms for f in self._cyclic])
        self._lockstep = min(self._lockstep, k)
        self._lock_prev = min(self._lock_prev, k)
        self._points = sum(len(f.sends) for f in self._feeders) + sum(f.n + 1 for f in self._cyclic)
        self._pieces = [(o, pl) for o, pl in self._pieces if o < t0] + [(t0, plan)]
        self._positioning.splice(t0, plan, kind, start_rpm if start_rpm is not None else [0] * plan.n_axes)
        self._open_plan = plan if plan.open_end else None
        self._open_source = source if plan.open_end else None

    def _plan_splice(self, planner: Callable[[StopRequest], PvtTrajectoryLike] | None, kind: str, *,
                     at_plan_end: bool = False, keep_source: bool = False) -> SpliceAttempt:
        """The one splice sequence of cancel, change and emergency stop (see the module docstring): from the end
        of what is queued (`at_plan_end`: after the plan's end), `planner`'s trajectory, spliced as `kind`
        (`keep_source`: an open-ended one is what the next extension extends)."""
        k, t0, done = self._queue_end(at_plan_end=at_plan_end)
        if done:
            return SpliceAttempt(k, t0, "end_queued")
        if planner is None:
            return SpliceAttempt(k, t0, "no_planner")
        request = self._state_request(k, t0)
        try:
            planned = planner(request)
        except Exception as exc:  # the planner's failure is the verb's to report
            return SpliceAttempt(k, t0, "planner", error=exc)
        plan, why = self._splice_problem(request, planned)
        if plan is None:
            return SpliceAttempt(k, t0, "unfit", why=why)
        self._splice(k, t0, plan, kind, request.velocities_rpm, source=planned if keep_source else None)
        return SpliceAttempt(k, t0, plan=plan)

    def _cancel_in_motion(self, ev: Cancel) -> None:
        self._t = ev.t
        done = self._plan_splice(self._stop_planner, "stop")
        k, t0, stop = done.k, done.t0, done.plan
        if done.failed == "end_queued":
            self._cancel_info = {
                "stop": "plan_end",
                "knot": k,
                "summary": "the plan's last segment was already queued; it ends at rest",
            }
            self._set_state(JobState.CANCELLING)
            return
        if stop is None:
            exc = done.error
            self._halt("no stop planner was given" if done.failed == "no_planner"
                       else f"the stop planner failed: {type(exc).__name__}: {exc}" if done.failed == "planner"
                       else done.why.replace("the trajectory", "the stop trajectory", 1))
            return
        self._cancel_info = {
            "stop": "trajectory",
            "knot": k,
            "time_ms": t0,
            "stop_duration_ms": stop.duration_ms,
            "summary": f"stop trajectory from {'knot ' + str(k) + ' ' if self._feeders else ''}{t0} ms, "
                       f"{stop.duration_ms} ms long",
        }
        self._set_state(JobState.CANCELLING)

    def _halt(self, reason: str) -> None:
        """Halt (bit 8) on the FIFO axes; a cyclic axis has no halt in its mode (XtrapulsPac: "only in PV,
        PT, AS, AT"), so it is quick-stopped (its quick stop option 0x605A, written at configuration)."""
        for f in self._feeders:
            if f.state in (FeederState.STARTING, FeederState.STREAMING):
                f.fire(FeederInput.HALT)
            self._emit_cw(f, CW_HALT)
        for cf in self._cyclic:
            if cf.state in (FeederState.STARTING, FeederState.STREAMING, FeederState.DRAINING):
                cf.fire(FeederInput.HALT)
                self._emit_cw(cf, CW_QUICK_STOP)
        self._halt_sync = (self._sync if self._sync is not None else 0) + 1
        self._positioning.halted(self._elapsed_now())
        self._cancel_info = {"stop": "halt", "reason": reason, "summary": f"halt (bit 8): {reason}"}
        self._set_state(JobState.HALTING)

    def _change_refused(self, ev: Change) -> None:
        st = self._state
        why = {
            JobState.CONFIGURING: "the job has not started moving yet",
            JobState.PRIMING: "the job has not started moving yet",
            JobState.CANCELLING: "the job is stopping",
            JobState.HALTING: "the job is halting",
            JobState.FINISHING: "the running plan's end is already queued: the axes come to rest at its target (submit "
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
        done = self._plan_splice(ev.planner, "change", at_plan_end=buffered, keep_source=True)
        k, t0, plan = done.k, done.t0, done.plan
        if plan is None:
            exc = done.error
            why = ("the running plan's end is already queued: the axes come to rest at its target (submit the "
                   "move as a new job)" if done.failed == "end_queued"
                   else (str(exc) or type(exc).__name__) if done.failed == "planner" else done.why)
            self._change_results.append(ChangeResult(ev.tag, ev.mode, False, why, knot=k, time_ms=t0,
                                                     sync=self._sync))
            return
        self._change_results.append(ChangeResult(ev.tag, ev.mode, True, "", knot=k, time_ms=t0,
                                                 duration_ms=plan.duration_ms, sync=self._sync))

    def _emergency_before_start(self, ev: EmergencyStop) -> None:
        self._emergency = {"method": "before_start", "reason": "the job had not started moving"}
        self._t = ev.t
        self._release_before_start()  # at once (an emergency does not wait for the next SYNC)
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
        done = self._plan_splice(ev.planner, "emergency")
        k, t0, stop = done.k, done.t0, done.plan
        if stop is None:
            exc = done.error
            return ("the plan's end is already queued (nothing can follow it)" if done.failed == "end_queued"
                    else f"the emergency stop planner failed: {type(exc).__name__}: {exc}" if done.failed == "planner"
                    else done.why.replace("the trajectory", "the emergency stop trajectory", 1))
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
