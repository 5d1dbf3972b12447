"""Intake of the job service: a submission decoded, validated, planned and admitted, or refused.

Theory of operation. Zenoh callbacks only queue a submission; the intake thread decodes it (payload.py),
answers an idempotent resubmit from the journal (a different body: CONFLICT), splits off the service's
sections (`buffer`, `lead_ms`, `record`), validates and plans through the backend (never on the SYNC
thread), applies NOT_READY and BUSY, journals `accepted` + `planned` in one transaction and only then
replies or publishes, and queues the job. `buffer = "aborting"` while a job moves is a change
(`_admit_change`): the backend splices it in or refuses (COMMAND_REJECTED); the running job ends
`aborted` and the new one owns the motion from there on.
"""

from __future__ import annotations

import dataclasses
import logging
import time
import uuid
from collections.abc import Mapping
from typing import Any

from planner.errors import POSITION_LIMIT
from streamer.api import errors as E
from streamer.api import keys
from streamer.api.backend import Planned
from streamer.api.cell_queue import CellQueueMixin
from streamer.api.errors import MotionError, error_from_exception
from streamer.api.journal import STOP, Post
from streamer.api.model import EventType, JobRecord, JobState
from streamer.api.payload import Submission, decode_submission
from streamer.api.progress import Emitter
from streamer.api.service_state import REPAIR_SYNCS, Queued, Submit

# every part of the service logs as `streamer.api.service`, the logger it always had (log filters name it)
log = logging.getLogger("streamer.api.service")


def _split_record(body: dict[str, Any]) -> tuple[dict[str, Any], Any]:
    """The job body without its `record` section, and that section checked (a `RecordRequest`, or None).
    The planner owns the job schema; the record section is the drive recorder's (docs/api.md)."""
    if "record" not in body:
        return body, None
    from streamer.recording.drive import BAD_RECORD, RecordRequest

    rest = {k: v for k, v in body.items() if k != "record"}
    request = RecordRequest.from_mapping(body["record"])
    axes = rest.get("axes")
    if isinstance(axes, list):
        for i, name in enumerate(request.axes):
            if name not in axes:
                raise MotionError(BAD_RECORD, f"record.axes[{i}]: {name!r} is not an axis of the job ({axes})",
                                  path=f"record.axes[{i}]")
    return rest, request

BUFFER_MODES = ("queued", "aborting", "buffered")
LEAD_MS_MAX = 5000


def _split_buffer(
    body: dict[str, Any], sync_period_ms: int, repair_syncs: int
) -> tuple[dict[str, Any], str, int | None]:
    """The job body without `buffer` and `lead_ms` (the service's, not the planner's), and both checked.
    A lead shorter than the repair horizon ((repair_syncs + 1) SYNC periods) would not shorten anything: the
    feeders keep that much queued anyway to see and resend a lost batch."""
    rest = {k: v for k, v in body.items() if k not in ("buffer", "lead_ms")}
    buffer = body.get("buffer", "queued")
    if not isinstance(buffer, str):
        raise MotionError(E.TYPE, f"buffer must be a string, got {buffer!r}", path="buffer")
    if buffer not in BUFFER_MODES:
        raise MotionError(E.SCHEMA, f"buffer must be one of {list(BUFFER_MODES)}, got {buffer!r}", path="buffer")
    lead = body.get("lead_ms")
    if lead is not None:
        if isinstance(lead, bool) or not isinstance(lead, int):
            raise MotionError(E.TYPE, f"lead_ms must be an integer (ms), got {lead!r}", path="lead_ms")
        least = (repair_syncs + 1) * sync_period_ms
        if not least <= lead <= LEAD_MS_MAX:
            raise MotionError(
                E.SCHEMA,
                f"lead_ms = {lead} is outside {least}..{LEAD_MS_MAX} ms: the minimum is {repair_syncs + 1} SYNC "
                f"periods of {sync_period_ms} ms (records in flight and the time to see and resend a lost batch)",
                path="lead_ms", detail={"lead_ms": lead, "minimum_ms": least, "maximum_ms": LEAD_MS_MAX},
            )
    return rest, buffer, lead


class IntakeMixin(CellQueueMixin):
    """The intake thread of `JobService`: from a queued submission to a queued job or a refusal."""

    # -- intake ------------------------------------------------------------------------------------
    def _intake_loop(self) -> None:
        while True:
            item = self._intake_q.get()
            if item is STOP:
                return
            try:
                self._handle_submit(item)
            except Exception:  # a bug: keep serving, but say so
                log.exception("intake failed on a submission")

    def _handle_submit(self, sub: Submit) -> None:
        t0 = time.perf_counter()
        job_id: str | None = None
        try:
            if sub.data is None:
                raise MotionError(
                    E.TOO_LARGE,
                    f"payload is {sub.size} bytes, more than the limit {self.options.limits.max_bytes}",
                )
            decoded = decode_submission(sub.data, self.options.limits)
            job_id = decoded.job_id
            if sub.via == "put" and job_id is None:
                raise MotionError(
                    E.SCHEMA,
                    "job_id is required when submitting by put (the outcome is "
                    "published on pvt/<cell>/jobs/<job_id>/events)",
                    path="job_id",
                )
            record, existing, planning_s = self._admit(decoded, sub.via, t0, sub.data)
        except Exception as exc:
            err = error_from_exception(exc)
            job_id = job_id or err.job_id
            self.counters[f"rejected_{err.code}"] += 1
            if err.code == E.INTERNAL:
                log.error("submission failed with an internal error: %s", err.message)
            self._answer_rejection(sub, job_id, err)
            return
        reply = {
            "job_id": record.job_id,
            "cell": self.cell,
            "state": record.state.value,
            "kind": record.kind,
            "planned_duration_s": record.planned_duration_s,
            "points": record.points,
            "existing": existing,
        }
        if not existing:
            reply["queue_position"] = self._queue_position(record.job_id)
            reply["planning_s"] = planning_s
        if self.held and record.state == JobState.QUEUED:
            reply["held"] = True  # it waits for `resume`
        if sub.query is not None:
            self._reply(sub.query, keys.submit(self.cell), reply)

    def _queue_position(self, job_id: str) -> int:
        with self._cv:
            for i, jid in enumerate(self._pending, start=1):
                if jid == job_id:
                    return i
        return 0

    def _admit(self, sub: Submission, via: str, t0: float, body: bytes) -> tuple[JobRecord, bool, float]:
        """Admit one decoded submission: (record, existing, decode+validate+plan seconds) or MotionError."""
        job_id = sub.job_id or uuid.uuid4().hex
        existing = self.store.get(job_id)
        if existing is not None:
            if existing.body_hash == sub.body_hash:
                self.counters["idempotent"] += 1
                return existing, True, 0.0
            raise MotionError(
                E.CONFLICT,
                f"job_id {job_id!r} already names a different job (state "
                f"{existing.state.value}); use a new job_id",
                path="job_id",
            )
        job_body, buffer, lead_ms = _split_buffer(sub.body, self.backend.cell.sync_period_ms, REPAIR_SYNCS)
        job_body, record = _split_record(job_body)
        job = self._validate(job_body, buffer)
        ready, reason = self._ready()
        if not ready:
            raise MotionError(
                E.NOT_READY,
                f"cell {self.cell!r} is not ready: {reason or 'faulted'}; `pvt resume --reset` (get "
                f"{keys.resume(self.cell)}?reset=true) clears it, then resubmit",
            )
        if self.queue_length >= self.options.queue_limit:
            raise MotionError(
                E.BUSY,
                f"the queue of cell {self.cell!r} is full ({self.options.queue_limit} jobs); try again later",
            )
        if buffer == "aborting":
            with self._cv:
                current, queued = self._current, list(self._pending)
            if current is not None:
                if queued:
                    raise MotionError(E.COMMAND_REJECTED, f"jobs {queued} are queued after the running job "
                                      f"{current.job_id!r}: an aborting change would skip them (cancel them first)",
                                      path="buffer")
                return self._admit_change(sub, via, job_id, job, current, t0, body)
        with self._cv:
            start = dict(self._queue_end) if (self._pending or self._current is not None) else None
        if sub.start_current and sub.kind == "path":
            # where the axes will stand when this job starts: the end of the queue, else where they are now
            here = self._positions() or {}
            moved = self._with_start(sub.body, {**here, **(start or {})})
            if moved is not None:
                job = self.backend.validate(moved)
        travel: dict[str, Any] = self._travel()
        if lead_ms is not None:
            travel["lead_ms"] = lead_ms  # a short lead bounds the plan's segments (so a change acts within it)
        planned = self.backend.plan(job, start, **travel)
        if not isinstance(planned, Planned):
            raise MotionError(E.INTERNAL, f"backend.plan returned {type(planned).__name__}, not Planned")
        if record is not None:
            planned = dataclasses.replace(planned, record=record)
        if lead_ms is not None:
            planned = dataclasses.replace(planned, lead_ms=lead_ms)
        planning_s = time.perf_counter() - t0
        post = Post(
            job_id=job_id,
            events=[
                (EventType.ACCEPTED, {"via": via, "kind": sub.kind}, {}),
                (
                    EventType.PLANNED,
                    {"planned_duration_s": planned.duration_s, "points": planned.points},
                    {"planned_duration_s": planned.duration_s, "points": planned.points},
                ),
            ],
            new_job={
                "kind": sub.kind,
                "via": via,
                "body_hash": sub.body_hash,
                "body": body,
                "planned_duration_s": planned.duration_s,
                "points": planned.points,
            },
        )
        self._journal.submit(post)
        post.wait(timeout=60.0)  # journalled (and published) before the answer
        record = self.store.get(job_id)  # read before the executor can take it: the reply says "queued"
        with self._cv:
            if not self._pending and self._current is None:
                self._queue_end.clear()
            self._queue_end.update(planned.end_positions)
            self._remember(planned)
            self._pending[job_id] = Queued(job_id, planned, body=sub.body, start_current=sub.start_current,
                                            travel=travel)
            self._cv.notify_all()
        if record is None:
            raise MotionError(E.INTERNAL, f"job {job_id!r} was journalled but cannot be read back")
        self.counters["accepted"] += 1
        return record, False, planning_s

    def _validate(self, body: Mapping[str, Any], buffer: str | None) -> Any:
        """The backend's validation. An aborting move while a job runs is a change: a target outside the
        software position limits is then the change's refusal, COMMAND_REJECTED with `detail.planner_code`
        POSITION_LIMIT, as the backend answers a relative or additive change whose target lands there (one
        code for "this change cannot be made", whatever stage found it); other bad input keeps its code."""
        try:
            return self.backend.validate(body)
        except Exception as exc:
            code = getattr(exc, "code", None)
            if buffer != "aborting" or code != POSITION_LIMIT:
                raise
            with self._cv:
                running = self._current is not None
            if not running:
                raise
            err = error_from_exception(exc)
            raise MotionError(E.COMMAND_REJECTED, f"the change's target cannot be reached: {err.message}",
                              path=err.path or "target", detail={"planner_code": code}) from None

    def _admit_change(self, sub: Submission, via: str, job_id: str, job: Any, current: Queued, t0: float,
                      body: bytes) -> tuple[JobRecord, bool, float]:
        """`buffer = "aborting"` while `current` moves: the backend splices the job in after what is queued
        (or refuses, COMMAND_REJECTED, and nothing changes); the running job ends `aborted` naming this one,
        which is journalled running at once and owns the motion (and its cancel token) from here on."""
        if not self.backend.can_change:
            raise MotionError(E.COMMAND_REJECTED, "this backend cannot change a running motion", path="buffer")
        with self._cv:
            moving = current.started and not current.cancel_requested and current.emitter is not None
        if not moving:
            raise MotionError(E.COMMAND_REJECTED, f"the running job {current.job_id!r} is "
                              f"{'stopping' if current.cancel_requested else 'not moving yet'}: nothing to change",
                              path="buffer")
        emitter = Emitter(self._journal, job_id, 1.0 / self.options.progress_hz, paused=True)
        planned, info = self.backend.change(job, "aborting", emitter, **self._travel())
        if not isinstance(planned, Planned):
            raise MotionError(E.INTERNAL, f"backend.change returned {type(planned).__name__}, not Planned")
        planning_s = time.perf_counter() - t0
        item = Queued(job_id, planned, token=current.token, body=sub.body, started=True, emitter=emitter)
        old = current.emitter
        with self._cv:
            current.replaced_by = item
            self._current = item
            self._queue_end.clear()
            self._queue_end.update(planned.end_positions)
            self._remember(planned)
        if old is not None:
            old.close()
        now = self._clock()
        aborted = self._journal.post(current.job_id, [(EventType.ABORTED, {
            "replaced_by": job_id, "message": f"replaced by job {job_id!r} (buffer aborting) at "
            f"{info.get('time_ms')} ms of the running stream", "progress": old.progress if old else None,
        }, {"finished_t": now})])
        post = Post(
            job_id=job_id,
            events=[
                (EventType.ACCEPTED, {"via": via, "kind": sub.kind, "buffer": "aborting"}, {}),
                (EventType.PLANNED, {"planned_duration_s": planned.duration_s, "points": planned.points},
                 {"planned_duration_s": planned.duration_s, "points": planned.points}),
                (EventType.PRIMING, {"replaces": current.job_id, "change": info}, {"started_t": now}),
                *([(EventType.RUNNING, {"progress": 0.0, "warning": "TARGET_OVERRUN",
                                        "overrun_axes": info["overrun_axes"],
                                        "message": f"axes {info['overrun_axes']} pass their new target and come back"},
                    {"progress": 0.0})] if info.get("overrun_axes") else []),
            ],
            new_job={"kind": sub.kind, "via": via, "body_hash": sub.body_hash, "body": body,
                     "planned_duration_s": planned.duration_s, "points": planned.points},
        )
        self._journal.submit(post)
        aborted.wait(timeout=60.0)
        post.wait(timeout=60.0)
        emitter.unpause()
        record = self.store.get(job_id)
        if record is None:
            raise MotionError(E.INTERNAL, f"job {job_id!r} was journalled but cannot be read back")
        self.counters["changes"] += 1
        log.info("job %s replaces job %s (aborting) at %s ms of the stream, reaction %s ms", job_id,
                 current.job_id, info.get("time_ms"), info.get("reaction_ms"))
        return record, False, planning_s

    def _answer_rejection(self, sub: Submit, job_id: str | None, err: MotionError) -> None:
        if sub.query is not None:
            self._reply_err(sub.query, err)
            return
        msg = {
            "job_id": job_id,
            "cell": self.cell,
            "seq": 0,
            "type": "rejected",
            "t": self._clock(),
            "state": "rejected",
            "error": err.to_dict(),
        }
        self._put(keys.rejected(self.cell), msg, reliable=True)
        if job_id is not None and err.code != E.CONFLICT:
            try:
                known = self.store.get(job_id) is not None
            except Exception:
                known = True
            if not known:
                self._put(keys.job_events(self.cell, job_id), msg, reliable=True)

