"""Open-ended streams (a velocity move, planner/motion/travel.py): the plan's last knot moves and it has no end
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
"""

from __future__ import annotations

import dataclasses

from bus.events import Cancel
from streamer.core import outcome as oc
from streamer.core.job_state import MAX_EXTENSIONS_PER_SYNC, JobState, stream_ends
from streamer.core.plan_source import PvtTrajectoryLike, StreamPlan
from streamer.core.schedule import consumed_at, dry_run
from streamer.core.splices import Splices


class OpenStream(Splices):
    """Extending an open-ended stream and retiring its past."""

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
            ends = self._ends.spliced(len(self._ends), [self._t_end + e for e in stream_ends(plan)])
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
