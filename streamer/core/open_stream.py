"""Open-ended streams (a velocity move, planner/motion/travel.py): no end record; the stream goes on in chunks.

When the stream ends less than `extend_ahead_ms` ahead of the fastest drive, the core asks its `extender`
for the next chunk (None: not ready yet), which must start exactly at the last knot and is appended on
every axis. `extend_need_ms` keeps the top-up rule from meeting the stream's end (every FIFO stays >= U);
no chunk by then stops the motion and fails EXTENSION_FAILED. It ends by a change, a cancel, a fault or a
closed chunk. Every SYNC `_retire` drops what is behind `_retain_ms` of the slowest drive and confirmed
(never what a splice follows), and the feedback log spills to the runtime's store, so memory stays flat.
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
