"""The job service of one cell: Zenoh in, motion backend out, everything journalled.

Theory of operation. Five threads, each owning one concern; Zenoh callbacks only copy the request
into a queue (they run on Zenoh's threads and must return at once):

- intake: decodes a submission (payload.py), answers idempotent resubmits and CONFLICT from the
  journal, validates and plans through the backend (so INFEASIBLE/ENCODING_RANGE are known before
  the answer), applies NOT_READY and BUSY (bounded queue), has the job journalled (`accepted` +
  `planned`, one transaction) and only then replies (query) or publishes (put). Planning happens
  here, never on the motion runtime's SYNC thread.
- executor: takes queued jobs one at a time, emits `priming`, calls `backend.execute` (blocking) with
  an `emit` for progress and a `CancelToken`, writes the job's recording (below), then journals the
  result (`done`/`failed`/`cancelled`).
- control: status, list, event history, cancel, service status and reset queries (cheap, separate
  from intake so a long planning job does not stall them).
- events: the only writer of the journal. Every event gets the job's next sequence number, passes
  the transition table (model.py), is committed, and is then published on the job's events key, in
  order. Backends may emit from any thread; emitting never blocks (progress is throttled).
- telemetry: publishes the backend's per-axis snapshot at `telemetry_hz`.

Recordings: a backend that has `take_recording()` (the real one does) hands over each job's recording
(a `JobRecording`, or the `RecordingInputs` to build it from) after `execute`; the executor has it
built and written to `<recordings dir>/<job_id>.mcap` (default: beside the journal, `<journal
stem>.recordings/`) by a low-priority worker process (streamer/recording/writer.py: this process keeps
its GIL for SYNC and the drives) and applies the retention (`ServiceOptions`), after the motion ended
and before the final event, so a `done` job's recording is already on disk and the next job starts
after the write, never during it. The report gets `recording: {file, bytes, messages}` (or `{error}`:
a recording that cannot be written does not fail a job that moved).

On start, jobs the journal shows queued or running (the previous process died) are failed with
SERVICE_RESTART and those events published before the service answers anything. A liveliness token
on `pvt/<cell>/alive` tells clients the service is up.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import logging
import math
import queue
import threading
import time
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import zenoh

from streamer.api import errors as E
from streamer.api import keys
from streamer.api.backend import CancelToken, MotionBackend, Planned
from streamer.api.errors import MotionError, error_from_exception
from streamer.api.model import Event, EventType, InvalidTransition, JobRecord, JobState, transition
from streamer.api.payload import DEFAULT_LIMITS, PayloadLimits, Submission, decode_submission, pack, plain
from streamer.api.store import JobStore
from streamer.recording.files import RecordingFiles, RecordingRetention, default_recordings_dir
from streamer.recording.writer import RecordingWriter

log = logging.getLogger(__name__)

API_VERSION = 1
ENCODING = "application/msgpack"


@dataclass(frozen=True)
class ServiceOptions:
    """Tunables of one job service (defaults are the documented ones)."""

    queue_limit: int = 16  # queued jobs (not counting the running one); more -> BUSY
    telemetry_hz: float | None = None  # None: the cell config's zenoh.telemetry_hz (default 20)
    progress_hz: float = 10.0  # most `running` progress events per second per job
    limits: PayloadLimits = DEFAULT_LIMITS
    intake_limit: int = 256  # submissions waiting to be decoded; more -> BUSY at once
    shutdown_timeout_s: float = 10.0  # how long close() waits for a cancelled job to stop
    list_limit_max: int = 10_000
    record_jobs: bool = True  # write each job's recording (when the backend has take_recording)
    recordings_dir: str | None = None  # None: beside the journal, <journal stem>.recordings/
    recordings: RecordingRetention = field(default_factory=RecordingRetention)  # 200 files, 1 GiB

    def __post_init__(self) -> None:
        if self.queue_limit < 1:
            raise ValueError(f"queue_limit must be >= 1, got {self.queue_limit}")
        if self.telemetry_hz is not None and not (0.0 < self.telemetry_hz <= 1000.0):
            raise ValueError(f"telemetry_hz must be in (0, 1000], got {self.telemetry_hz}")
        if not (0.0 < self.progress_hz <= 1000.0):
            raise ValueError(f"progress_hz must be in (0, 1000], got {self.progress_hz}")
        if self.intake_limit < 1:
            raise ValueError(f"intake_limit must be >= 1, got {self.intake_limit}")


@dataclass
class _Queued:
    """A job accepted and waiting for (or in) execution; the plan lives only in memory."""

    job_id: str
    planned: Planned
    token: CancelToken = field(default_factory=CancelToken)


@dataclass
class _Submit:
    data: bytes | None
    size: int
    via: str  # "query" | "put"
    query: zenoh.Query | None


@dataclass
class _Post:
    """A batch of events for one job, written in one transaction, then published in order."""

    job_id: str
    events: list[tuple[EventType, dict[str, Any], dict[str, Any]]]  # (type, wire fields, row updates)
    new_job: dict[str, Any] | None = None  # the jobs row to insert with the first event
    done: threading.Event = field(default_factory=threading.Event)
    result: list[Event] = field(default_factory=list)
    error: BaseException | None = None

    def wait(self, timeout: float | None = None) -> list[Event]:
        if not self.done.wait(timeout):
            raise MotionError(E.INTERNAL, f"journal did not answer within {timeout} s")
        if self.error is not None:
            raise self.error
        return self.result


_STOP = object()


class _Emitter:
    """The `emit` handed to `backend.execute`: thread-safe, non-blocking, throttled, inert after use."""

    def __init__(self, service: JobService, job_id: str, min_interval_s: float):
        self._service = service
        self._job_id = job_id
        self._min_interval_s = min_interval_s
        self._lock = threading.Lock()
        self._last_sent = -math.inf
        self._held: dict[str, Any] | None = None
        self._closed = False

    def __call__(self, event_type: str, fields: Mapping[str, Any] | None = None) -> None:
        if event_type == EventType.PRIMING.value:
            return  # the service emitted it before execute()
        if event_type != EventType.RUNNING.value:
            log.warning("backend emitted %r for job %s; only 'running' is accepted", event_type, self._job_id)
            return
        data = plain(dict(fields or {}))
        try:
            progress = float(data.get("progress", 0.0))
        except (TypeError, ValueError):
            progress = 0.0
        data["progress"] = min(1.0, max(0.0, progress)) if math.isfinite(progress) else 0.0
        now = time.monotonic()
        with self._lock:
            if self._closed:
                return
            if now - self._last_sent < self._min_interval_s and data["progress"] < 1.0:
                self._held = data  # the latest update is sent at the end if nothing newer goes out
                return
            self._last_sent = now
            self._held = None
            self._service._post_running(self._job_id, data)

    def close(self) -> None:
        """Stop accepting; send the last held-back progress update so the final progress is seen."""
        with self._lock:
            self._closed = True
            held, self._held = self._held, None
            if held is not None:
                self._service._post_running(self._job_id, held)



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

class JobService:
    """Serves one cell on an open Zenoh session. Several services may share one session (one per cell).

    The caller owns the session, the backend and the store; `close()` stops the service's own threads
    and declarations only.
    """

    def __init__(
        self,
        session: zenoh.Session,
        backend: MotionBackend,
        store: JobStore,
        options: ServiceOptions | None = None,
        *,
        clock: Callable[[], float] = time.time,
    ):
        self.session = session
        self.backend = backend
        self.store = store
        self.options = options or ServiceOptions()
        self.cell = keys.check_cell(backend.cell.name)
        hz = (
            self.options.telemetry_hz
            if self.options.telemetry_hz is not None
            else backend.cell.zenoh.telemetry_hz
        )
        self.telemetry_hz = float(hz)
        self._clock = clock
        self._started_t = 0.0
        self._intake_q: queue.Queue[Any] = queue.Queue(maxsize=self.options.intake_limit)
        self._control_q: queue.Queue[Any] = queue.Queue()
        self._events_q: queue.Queue[Any] = queue.Queue()
        self._cv = threading.Condition()
        self._pending: collections.OrderedDict[str, _Queued] = collections.OrderedDict()
        self._current: _Queued | None = None
        # where the axes moved by queued/running jobs stand when the queue has run (the next plan's start)
        self._queue_end: dict[str, float] = {}
        self._stopping = False
        self._stop_telemetry = threading.Event()
        self._threads: list[threading.Thread] = []
        self._declared: list[Any] = []
        self._token: Any = None
        self._job_cache: dict[str, tuple[JobState, int]] = {}
        self._telemetry_seq = 0
        self._started = False
        self._closed = False
        self.counters: collections.Counter[str] = collections.Counter()
        self.recordings: RecordingFiles | None = None
        self._writer: RecordingWriter | None = None
        if self.options.record_jobs:
            folder = self.options.recordings_dir or default_recordings_dir(store.path)
            self.recordings = RecordingFiles(folder, self.options.recordings)
            self._writer = RecordingWriter(self.recordings)

    # -- lifecycle -----------------------------------------------------------------------------
    def start(self) -> JobService:
        if self._started:
            raise RuntimeError("service already started")
        self._started = True
        self._started_t = self._clock()
        if self._writer is not None:
            self._writer.start()
        self._spawn("events", self._events_loop)
        self._recover()
        self._spawn("intake", self._intake_loop)
        self._spawn("control", self._control_loop)
        self._spawn("executor", self._executor_loop)
        self._spawn("telemetry", self._telemetry_loop)
        s, c = self.session, self.cell
        self._declared = [
            s.declare_queryable(keys.submit(c), self._on_submit_query),
            s.declare_subscriber(keys.submit(c), self._on_submit_put),
            s.declare_queryable(keys.jobs(c), lambda q: self._control_q.put(("list", q))),
            s.declare_queryable(keys.job_any(c), lambda q: self._control_q.put(("status", q))),
            s.declare_queryable(keys.job_events_any(c), lambda q: self._control_q.put(("events", q))),
            s.declare_queryable(keys.job_cancel_any(c), lambda q: self._control_q.put(("cancel", q))),
            s.declare_queryable(keys.service(c), lambda q: self._control_q.put(("service", q))),
            s.declare_queryable(keys.reset(c), lambda q: self._control_q.put(("reset", q))),
        ]
        self._token = s.liveliness().declare_token(keys.alive(c))
        log.info("job service for cell %r started (store %s)", c, self.store.path)
        return self

    def _spawn(self, name: str, target: Callable[[], None]) -> None:
        t = threading.Thread(target=target, name=f"pvt-{self.cell}-{name}", daemon=True)
        t.start()
        self._threads.append(t)

    def close(self) -> None:
        """Stop: no new input; queued jobs fail SERVICE_STOPPED; the running job is cancelled and awaited."""
        if self._closed or not self._started:
            self._closed = True
            return
        self._closed = True
        for obj in [self._token, *self._declared]:
            try:
                if obj is not None:
                    obj.undeclare()
            except Exception:  # the session may already be closed
                pass
        self._token = None
        self._declared = []
        threads = dict((t.name.rsplit("-", 1)[-1], t) for t in self._threads)
        self._intake_q.put(_STOP)
        threads["intake"].join(timeout=30.0)
        with self._cv:
            self._stopping = True
            stopped = list(self._pending.values())
            self._pending.clear()
            current = self._current
            self._cv.notify_all()
        posts = [
            self._post_final_queued(
                q.job_id,
                EventType.FAILED,
                E.SERVICE_STOPPED,
                "the service was shut down before the job started",
            )
            for q in stopped
        ]
        if current is not None:
            current.token.cancel()
        threads["executor"].join(timeout=self.options.shutdown_timeout_s)
        if self._writer is not None:
            self._writer.close()
        self._control_q.put(_STOP)
        threads["control"].join(timeout=10.0)
        self._stop_telemetry.set()
        threads["telemetry"].join(timeout=10.0)
        for p in posts:
            with contextlib.suppress(Exception):
                p.wait(timeout=10.0)
        self._events_q.put(_STOP)
        threads["events"].join(timeout=30.0)
        log.info("job service for cell %r stopped", self.cell)

    def __enter__(self) -> JobService:
        return self.start() if not self._started else self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- status helpers (also used by tests) ------------------------------------------------------
    @property
    def queue_length(self) -> int:
        with self._cv:
            return len(self._pending)

    @property
    def running_job(self) -> str | None:
        with self._cv:
            return self._current.job_id if self._current is not None else None

    def service_status(self) -> dict[str, Any]:
        ready, reason = self._ready()
        with self._cv:
            running = self._current.job_id if self._current is not None else None
            queued = list(self._pending)
        return {
            "cell": self.cell,
            "api_version": API_VERSION,
            "ready": ready,
            "reason": reason,
            "running_job": running,
            "queued_jobs": queued,
            "queue_length": len(queued),
            "queue_limit": self.options.queue_limit,
            "axes": [a.name for a in self.backend.cell.axes],
            "telemetry_hz": self.telemetry_hz,
            "started_t": self._started_t,
            "store": str(self.store.path),
            "recordings": str(self.recordings.directory) if self.recordings is not None else None,
        }

    def _ready(self) -> tuple[bool, str]:
        try:
            ready, reason = self.backend.ready()
            return bool(ready), str(reason or "")
        except Exception as exc:
            return False, f"backend.ready() raised {type(exc).__name__}: {exc}"

    # -- Zenoh callbacks (short: they only queue) -------------------------------------------------
    def _on_submit_query(self, query: zenoh.Query) -> None:
        payload = query.payload
        size = len(payload) if payload is not None else 0
        data = payload.to_bytes() if payload is not None and size <= self.options.limits.max_bytes else None
        self._queue_submit(_Submit(data, size, "query", query))

    def _on_submit_put(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            return
        size = len(sample.payload)
        data = sample.payload.to_bytes() if size <= self.options.limits.max_bytes else None
        self._queue_submit(_Submit(data, size, "put", None))

    def _queue_submit(self, sub: _Submit) -> None:
        try:
            self._intake_q.put_nowait(sub)
        except queue.Full:
            self.counters["intake_full"] += 1
            err = MotionError(
                E.BUSY,
                f"the service has {self.options.intake_limit} submissions waiting to be "
                "decoded; try again later",
            )
            self._answer_rejection(sub, None, err)

    # -- intake ------------------------------------------------------------------------------------
    def _intake_loop(self) -> None:
        while True:
            item = self._intake_q.get()
            if item is _STOP:
                return
            try:
                self._handle_submit(item)
            except Exception:  # a bug: keep serving, but say so
                log.exception("intake failed on a submission")

    def _handle_submit(self, sub: _Submit) -> None:
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
            "planned_duration_s": record.planned_duration_s,
            "points": record.points,
            "existing": existing,
        }
        if not existing:
            reply["queue_position"] = self._queue_position(record.job_id)
            reply["planning_s"] = planning_s
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
        job_body, record = _split_record(sub.body)
        job = self.backend.validate(job_body)
        ready, reason = self._ready()
        if not ready:
            raise MotionError(
                E.NOT_READY,
                f"cell {self.cell!r} is not ready: {reason or 'faulted'}; reset it "
                f"(get {keys.reset(self.cell)}) and resubmit",
            )
        if self.queue_length >= self.options.queue_limit:
            raise MotionError(
                E.BUSY,
                f"the queue of cell {self.cell!r} is full ({self.options.queue_limit} jobs); try again later",
            )
        with self._cv:
            start = dict(self._queue_end) if (self._pending or self._current is not None) else None
        planned = self.backend.plan(job, start)
        if not isinstance(planned, Planned):
            raise MotionError(E.INTERNAL, f"backend.plan returned {type(planned).__name__}, not Planned")
        if record is not None:
            planned = dataclasses.replace(planned, record=record)
        planning_s = time.perf_counter() - t0
        post = _Post(
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
        self._events_q.put(post)
        post.wait(timeout=60.0)  # journalled (and published) before the answer
        with self._cv:
            if not self._pending and self._current is None:
                self._queue_end.clear()
            self._queue_end.update(planned.end_positions)
            self._pending[job_id] = _Queued(job_id, planned)
            self._cv.notify_all()
        record = self.store.get(job_id)
        if record is None:
            raise MotionError(E.INTERNAL, f"job {job_id!r} was journalled but cannot be read back")
        self.counters["accepted"] += 1
        return record, False, planning_s

    def _answer_rejection(self, sub: _Submit, job_id: str | None, err: MotionError) -> None:
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

    # -- executor ----------------------------------------------------------------------------------
    def _executor_loop(self) -> None:
        min_interval = 1.0 / self.options.progress_hz
        while True:
            with self._cv:
                while not self._pending and not self._stopping:
                    self._cv.wait()
                if self._stopping:
                    return
                _, item = self._pending.popitem(last=False)
                self._current = item
            try:
                self._run_one(item, min_interval)
            except Exception:
                log.exception("executor failed on job %s", item.job_id)
            finally:
                with self._cv:
                    self._current = None
                    self._cv.notify_all()

    def _run_one(self, item: _Queued, min_interval: float) -> None:
        if item.token.cancelled:
            self._post_final_queued(
                item.job_id, EventType.CANCELLED, None, "cancelled before it started"
            ).wait(60)
            return
        ready, reason = self._ready()
        if not ready:
            self._post_final_queued(
                item.job_id,
                EventType.FAILED,
                E.NOT_READY,
                f"cell {self.cell!r} became not ready before the job started: {reason or 'faulted'}",
            ).wait(60)
            return
        self._post(item.job_id, [(EventType.PRIMING, {}, {"started_t": self._clock()})]).wait(60)
        emitter = _Emitter(self, item.job_id, min_interval)
        try:
            report: Any = self.backend.execute(item.planned, emitter, item.token)
        except Exception as exc:
            log.exception("backend.execute raised for job %s", item.job_id)
            report = {
                "result": "failed",
                "error": {
                    "code": E.INTERNAL,
                    "node": None,
                    "message": f"backend.execute raised {type(exc).__name__}: {exc}",
                },
            }
        finally:
            emitter.close()
        report = self._record(item.job_id, report)
        etype, data, updates = self._final_from_report(report)
        self._post(item.job_id, [(etype, data, updates)]).wait(60)

    def _record(self, job_id: str, report: Any) -> Any:
        """Write the job's recording (if the backend made one); the report says where, or why not."""
        take = getattr(self.backend, "take_recording", None)
        if self._writer is None or not callable(take):
            return report
        try:
            rec = take()
            if rec is None:
                return report
            saved = self._writer.save(job_id, rec, cell=self.cell)
            info: dict[str, Any] = saved.info()
            self.counters["recordings"] += 1
            self.counters["recordings_deleted"] += len(saved.deleted)
        except Exception as exc:
            log.exception("could not write the recording of job %s", job_id)
            info = {"error": f"{type(exc).__name__}: {exc}"[:500]}
        return {**report, "recording": info} if isinstance(report, Mapping) else report

    def _final_from_report(self, report: Any) -> tuple[EventType, dict[str, Any], dict[str, Any]]:
        rep = plain(report) if isinstance(report, Mapping) else {"result": "failed", "raw": plain(report)}
        result = rep.get("result")
        now = self._clock()
        if result == "done":
            return EventType.DONE, {"report": rep}, {"report": rep, "progress": 1.0, "finished_t": now}
        if result == "cancelled":
            return EventType.CANCELLED, {"report": rep}, {"report": rep, "finished_t": now}
        raw_err = rep.get("error")
        if result == "failed" and isinstance(raw_err, Mapping) and isinstance(raw_err.get("code"), str):
            err = {
                **raw_err,  # extras such as `detail` (emcy_code, ...) and `sync` pass through
                "code": raw_err["code"],
                "path": str(raw_err.get("path", "") or ""),
                "node": raw_err.get("node"),
                "message": str(raw_err.get("message", "")),
            }
        elif result == "failed":
            err = {
                "code": E.INTERNAL,
                "path": "",
                "node": None,
                "message": f"backend reported failure without an error code: {raw_err!r}"[:500],
            }
        else:
            err = {
                "code": E.INTERNAL,
                "path": "",
                "node": None,
                "message": f"backend returned result {result!r}, expected done, cancelled or failed"[:500],
            }
        return (
            EventType.FAILED,
            {"error": err, "report": rep},
            {"error": err, "report": rep, "finished_t": now},
        )

    # -- events (the only journal writer) ------------------------------------------------------------
    def _post(
        self,
        job_id: str,
        events: list[tuple[EventType, dict[str, Any], dict[str, Any]]],
        new_job: dict[str, Any] | None = None,
    ) -> _Post:
        post = _Post(job_id, events, new_job)
        self._events_q.put(post)
        return post

    def _post_running(self, job_id: str, data: dict[str, Any]) -> None:
        self._events_q.put(_Post(job_id, [(EventType.RUNNING, data, {"progress": data["progress"]})]))

    def _post_final_queued(self, job_id: str, etype: EventType, code: str | None, message: str) -> _Post:
        if etype == EventType.FAILED:
            err = {"code": code or E.INTERNAL, "path": "", "node": None, "message": message}
            return self._post(
                job_id, [(etype, {"error": err, "report": None}, {"error": err, "finished_t": self._clock()})]
            )
        return self._post(
            job_id, [(etype, {"report": None, "message": message}, {"finished_t": self._clock()})]
        )

    def _events_loop(self) -> None:
        while True:
            post = self._events_q.get()
            if post is _STOP:
                return
            try:
                post.result = self._journal(post)
            except BaseException as exc:
                post.error = exc
                if isinstance(exc, InvalidTransition):
                    log.warning("dropped event(s) for job %s: %s", post.job_id, exc)
                else:
                    log.exception("could not journal events of job %s", post.job_id)
            finally:
                post.done.set()
            for ev in post.result:
                self._put(keys.job_events(self.cell, ev.job_id), ev.to_wire(self.cell), reliable=True)

    def _journal(self, post: _Post) -> list[Event]:
        if post.new_job is not None:
            state: JobState | None = None
            seq = 0
        else:
            cached = self._job_cache.get(post.job_id)
            if cached is None:
                rec = self.store.get(post.job_id)
                if rec is None:
                    raise InvalidTransition(f"job {post.job_id!r} is unknown")
                cached = (rec.state, rec.last_seq)
            state, seq = cached
        built: list[tuple[Event, dict[str, Any]]] = []
        now = self._clock()
        for etype, data, updates in post.events:
            state = transition(state, etype)
            seq += 1
            built.append((Event(post.job_id, seq, etype, now, state, plain(data)), updates))
        if post.new_job is not None:
            nj = post.new_job
            self.store.insert(
                job_id=post.job_id,
                cell=self.cell,
                kind=nj["kind"],
                via=nj["via"],
                body_hash=nj["body_hash"],
                body=nj["body"],
                events=[e for e, _ in built],
                planned_duration_s=nj["planned_duration_s"],
                points=nj["points"],
            )
        else:
            for ev, updates in built:
                self.store.append(ev, updates)
        assert state is not None
        if state.final:
            self._job_cache.pop(post.job_id, None)
        else:
            self._job_cache[post.job_id] = (state, seq)
        return [e for e, _ in built]

    def _recover(self) -> None:
        """Fail every job the journal shows queued or running: the previous service died with it."""
        posts = []
        for rec in self.store.unfinished():
            message = (
                f"the service stopped while the job was {rec.state.value}; it did not complete "
                "(the motion, if any, was stopped when the bus master went away)"
            )
            posts.append(self._post_final_queued(rec.job_id, EventType.FAILED, E.SERVICE_RESTART, message))
        for p in posts:
            p.wait(timeout=60.0)
        if posts:
            log.warning("marked %d unfinished job(s) FAILED with SERVICE_RESTART", len(posts))
        self.counters["recovered"] += len(posts)

    # -- control queries ---------------------------------------------------------------------------
    def _control_loop(self) -> None:
        handlers: dict[str, Callable[[zenoh.Query], None]] = {
            "list": self._q_list,
            "status": self._q_status,
            "events": self._q_events,
            "cancel": self._q_cancel,
            "service": self._q_service,
            "reset": self._q_reset,
        }
        while True:
            item = self._control_q.get()
            if item is _STOP:
                return
            kind, query = item
            try:
                handlers[kind](query)
            except MotionError as err:
                self._reply_err(query, err)
            except Exception as exc:
                log.exception("control query %s failed", kind)
                self._reply_err(query, MotionError(E.INTERNAL, f"{type(exc).__name__}: {exc}"))

    def _query_job_id(self, query: zenoh.Query) -> str:
        key = str(query.key_expr)
        job_id = keys.job_id_from_key(key, self.cell)
        if job_id is None or any(ch in key for ch in "*$?#"):
            raise MotionError(E.BAD_REQUEST, f"{key!r} does not name one job (no wildcards in the job id)")
        return job_id

    def _q_list(self, query: zenoh.Query) -> None:
        params = query.parameters
        limit_text = params.get("limit") or "100"
        try:
            limit = int(limit_text)
        except ValueError:
            raise MotionError(E.BAD_REQUEST, f"limit={limit_text!r} is not an integer") from None
        if not 1 <= limit <= self.options.list_limit_max:
            raise MotionError(E.BAD_REQUEST, f"limit={limit} must be 1..{self.options.list_limit_max}")
        states = None
        state_text = params.get("state")
        if state_text:
            try:
                states = [JobState(s.strip()) for s in state_text.split(",") if s.strip()]
            except ValueError:
                raise MotionError(
                    E.BAD_REQUEST, f"state={state_text!r}: states are {[s.value for s in JobState]}"
                ) from None
        records = self.store.list_jobs(states=states, limit=limit)
        jobs = []
        for r in records:
            st = r.to_status()
            st.pop("report", None)
            jobs.append(st)
        self._reply(query, keys.jobs(self.cell), {"cell": self.cell, "jobs": jobs})

    def _q_status(self, query: zenoh.Query) -> None:
        job_id = self._query_job_id(query)
        rec = self.store.get(job_id)
        if rec is None:
            raise MotionError(E.NOT_FOUND, f"no job {job_id!r} in cell {self.cell!r}", path="job_id")
        self._reply(query, keys.job(self.cell, job_id), rec.to_status())

    def _q_events(self, query: zenoh.Query) -> None:
        job_id = self._query_job_id(query)
        after_text = query.parameters.get("after") or "0"
        try:
            after = int(after_text)
        except ValueError:
            raise MotionError(E.BAD_REQUEST, f"after={after_text!r} is not an integer") from None
        if self.store.get(job_id) is None:
            raise MotionError(E.NOT_FOUND, f"no job {job_id!r} in cell {self.cell!r}", path="job_id")
        events = [e.to_wire(self.cell) for e in self.store.events(job_id, after)]
        self._reply(
            query, keys.job_events(self.cell, job_id), {"job_id": job_id, "cell": self.cell, "events": events}
        )

    def _q_cancel(self, query: zenoh.Query) -> None:
        job_id = self._query_job_id(query)
        post: _Post | None = None
        requested = False
        with self._cv:
            if job_id in self._pending:
                del self._pending[job_id]
                post = self._post_final_queued(job_id, EventType.CANCELLED, None, "cancelled while queued")
            elif self._current is not None and self._current.job_id == job_id:
                self._current.token.cancel()
                requested = True
        if post is not None:
            post.wait(timeout=60.0)
        rec = self.store.get(job_id)
        if rec is None:
            raise MotionError(E.NOT_FOUND, f"no job {job_id!r} in cell {self.cell!r}", path="job_id")
        status = rec.to_status()
        status["cancel_requested"] = requested or post is not None
        self.counters["cancel"] += 1
        self._reply(query, keys.job_cancel(self.cell, job_id), status)

    def _q_service(self, query: zenoh.Query) -> None:
        self._reply(query, keys.service(self.cell), self.service_status())

    def _q_reset(self, query: zenoh.Query) -> None:
        if self.running_job is not None:
            raise MotionError(E.BUSY, f"job {self.running_job!r} is running; cancel it before a reset")
        try:
            ready, reason = self.backend.reset()
        except Exception as exc:
            raise MotionError(E.INTERNAL, f"backend.reset() raised {type(exc).__name__}: {exc}") from None
        self._reply(
            query,
            keys.reset(self.cell),
            {"cell": self.cell, "ready": bool(ready), "reason": str(reason or "")},
        )

    # -- telemetry ---------------------------------------------------------------------------------
    def _telemetry_loop(self) -> None:
        period = 1.0 / self.telemetry_hz
        next_t = time.monotonic()
        while True:
            next_t += period
            delay = next_t - time.monotonic()
            if delay < -period:  # fell behind (stalled process): skip, do not burst
                next_t = time.monotonic()
                delay = 0.0
            if self._stop_telemetry.wait(max(0.0, delay)):
                return
            try:
                axes = plain(list(self.backend.telemetry()))
                error = None
            except Exception as exc:
                axes, error = [], f"backend.telemetry() raised {type(exc).__name__}: {exc}"
            ready, reason = self._ready()
            with self._cv:
                current = self._current.job_id if self._current is not None else None
            self._telemetry_seq += 1
            msg: dict[str, Any] = {
                "cell": self.cell,
                "t": self._clock(),
                "seq": self._telemetry_seq,
                "ready": ready,
                "reason": reason,
                "job_id": current,
                "axes": axes,
            }
            if error:
                msg["error"] = error
            self._put(keys.telemetry(self.cell), msg, reliable=False)

    # -- zenoh output ------------------------------------------------------------------------------
    def _put(self, key: str, obj: Any, *, reliable: bool) -> None:
        try:
            self.session.put(
                key,
                pack(obj),
                encoding=ENCODING,
                congestion_control=zenoh.CongestionControl.BLOCK
                if reliable
                else zenoh.CongestionControl.DROP,
            )
        except Exception as exc:
            log.warning("could not publish on %s: %s", key, exc)

    def _reply(self, query: zenoh.Query, key: str, obj: Any) -> None:
        try:
            query.reply(key, pack(obj), encoding=ENCODING)
        except Exception as exc:
            log.warning("could not reply on %s: %s", key, exc)
        finally:
            self._drop(query)

    def _reply_err(self, query: zenoh.Query, err: MotionError) -> None:
        try:
            query.reply_err(pack(err.to_dict()), encoding=ENCODING)
        except Exception as exc:
            log.warning("could not send error reply %s: %s", err.code, exc)
        finally:
            self._drop(query)

    @staticmethod
    def _drop(query: Any) -> None:
        with contextlib.suppress(Exception):
            query.drop()
