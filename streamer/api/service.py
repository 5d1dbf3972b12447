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
- control: status, list, event history, cancel, service status, reset, stop, hold and resume queries
  (cheap, separate from intake so a long planning job does not stall them).
- events: the only writer of the journal. Every event gets the job's next sequence number, passes
  the transition table (model.py), is committed, and is then published on the job's events key, in
  order. Backends may emit from any thread; emitting never blocks (progress is throttled).
- telemetry: publishes the backend's per-axis snapshot at `telemetry_hz`.

Recordings: a backend whose `take_recording()` returns one (the real one's does) hands over each job's recording
(a `JobRecording`, or the `RecordingInputs` to build it from) after `execute`; the executor has it
built and written to `<recordings dir>/<job_id>.mcap` (default: beside the journal, `<journal
stem>.recordings/`) by a low-priority worker process (streamer/recording/writer.py: this process keeps
its GIL for SYNC and the drives) and applies the retention (`ServiceOptions`), after the motion ended
and before the final event, so a `done` job's recording is already on disk and the next job starts
after the write, never during it. The report gets `recording: {file, bytes, messages}` (or `{error}`:
a recording that cannot be written does not fail a job that moved).

Hold: a cancel of the running job, and every stop, holds the queue: the executor starts no further job
until `resume` (a `hold` request holds it without stopping anything). Before a queued job starts, the
executor checks that it still starts where the axes stand (`current_positions()` of the backend): the
job before it may have been cancelled or stopped elsewhere. A move is re-planned from there; a path,
timed or pvt job fails INFEASIBLE naming the axis, where it stands and where the job starts, unless the
job said `start = "current"` (a path is then planned from where the axes stand through its waypoints).
Stop with `emergency=true` calls the backend's `emergency_stop()` when it has one (`can_emergency_stop`; the
real backend: the running job's planned emergency stop at the emergency deceleration, or the quick stop on
every drive when no plan is possible; the reply's `method` says which); `resume` then re-enables the drives.

Travel memory (planner/travel.py's `last_target` contract): per axis the service keeps the last commanded
target (a move's resolved target, a path/timed/pvt job's last row, None after a velocity move; also for a
job later stopped, cancelled or replaced) and the sign of the last commanded motion, from every job it
accepts (`Planned.commanded_target` / `commanded_direction`), and passes them to `backend.plan` and
`backend.change`, so `additive` and `modulo_current` moves work through the
service; a queued job re-planned at its start keeps those it was accepted with.

A cancel of the running job is journalled at once as a `cancelling` event (state CANCELLING); the
backend's later progress updates are published as `cancelling` events too, with the progress of the
job's own plan. A second cancel answers `cancel_requested: false`.

On start, jobs the journal shows queued, running or cancelling (the previous process died) are failed
with SERVICE_RESTART and those events published before the service answers anything. A liveliness
token on `pvt/<cell>/alive` tells clients the service is up. Every job's acceptance, start and end is
logged (logger `streamer.api.service`, INFO).
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

from planner.errors import POSITION_LIMIT
from streamer.api import errors as E
from streamer.api import keys
from streamer.api.backend import CancelToken, MotionBackend, Planned
from streamer.api.errors import MotionError, error_from_exception
from streamer.api.model import Event, EventType, InvalidTransition, JobRecord, JobState, transition
from streamer.api.payload import DEFAULT_LIMITS, PayloadLimits, Submission, decode_submission, pack, plain
from streamer.api.store import JobStore
from streamer.core.settings import StreamerSettings
from streamer.recording.files import RecordingFiles, RecordingRetention, default_recordings_dir
from streamer.recording.writer import RecordingWriter

log = logging.getLogger(__name__)

API_VERSION = 1
REPAIR_SYNCS = StreamerSettings.repair_syncs  # the feeders' repair horizon (the floor of a job's lead_ms)
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
    body: dict[str, Any] = field(default_factory=dict)  # the job as submitted (for a re-plan)
    start_current: bool = False  # `start = "current"`: plan from where the axes stand
    started: bool = False  # its `priming` event is posted (under the service's lock)
    cancel_requested: bool = False
    emergency: bool = False  # an emergency stop hit it
    emitter: _Emitter | None = None
    replaced_by: _Queued | None = None  # a change took the running motion over (this job ended aborted)
    travel: dict[str, Any] = field(default_factory=dict)  # the last target/direction it was planned with

    @property
    def kind(self) -> str:
        kind = self.body.get("kind")
        return kind if isinstance(kind, str) else ""


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
    """The `emit` handed to `backend.execute`: thread-safe, non-blocking, throttled, inert after use.

    After `mark_cancelling()` every update is published as a `cancelling` event (the job's state is then
    CANCELLING), in order with the ones before: both go through this object's lock."""

    def __init__(self, service: JobService, job_id: str, min_interval_s: float, *, paused: bool = False):
        self._service = service
        self._job_id = job_id
        self._min_interval_s = min_interval_s
        self._lock = threading.Lock()
        self._last_sent = -math.inf
        self._held: dict[str, Any] | None = None
        self._closed = False
        self._cancelling = False
        # a change's emitter is handed to the backend before the job is journalled running: it keeps the
        # latest update until `unpause()`, so no progress event can come before the job's `priming`
        self._paused = paused
        self.progress = 0.0  # the latest progress the backend reported (status, telemetry)
        self._positioning: Any = None  # the latest `positioning` the backend reported (the cancelling event's)
        self._timer: threading.Timer | None = None  # sends a held update once the interval is over

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
        with self._lock:
            now = time.monotonic()  # under the lock: a post another thread makes meanwhile is counted
            if self._closed:
                return
            self.progress = data["progress"]
            if "positioning" in data:
                self._positioning = data["positioning"]
            # at most one per min_interval, also after the plan's end (progress 1.0, positioning changes): the
            # latest update waits and goes out with the next one allowed, or at the end (close)
            if self._paused or now - self._last_sent < self._min_interval_s:
                self._held = data
                if not self._paused and self._timer is None:
                    self._timer = threading.Timer(self._last_sent + self._min_interval_s - now, self._flush)
                    self._timer.daemon = True
                    self._timer.start()
                return
            self._held = None
            self._service._post_progress(self._job_id, self._type(), data)
            self._last_sent = time.monotonic()  # after the event's time stamp: the next one is an interval later

    def _flush(self) -> None:
        """The timer: the held update goes out (latest wins) unless something newer already went."""
        with self._lock:
            self._timer = None
            held, self._held = self._held, None
            if held is None or self._closed or self._paused:
                self._held = held
                return
            self._service._post_progress(self._job_id, self._type(), held)
            self._last_sent = time.monotonic()

    def unpause(self) -> None:
        with self._lock:
            self._paused = False
            held, self._held = self._held, None
            if held is not None and not self._closed:
                self._last_sent = time.monotonic()
                self._service._post_progress(self._job_id, self._type(), held)

    def _type(self) -> EventType:
        return EventType.CANCELLING if self._cancelling else EventType.RUNNING

    def mark_cancelling(self, reason: str) -> _Post | None:
        """Publish the `cancelling` event now (state CANCELLING); None if the job already ended."""
        with self._lock:
            if self._closed:
                return None
            held, self._held = self._held, None
            if held is not None:  # what the backend said before the cancel goes out first, in order
                self._service._post_progress(self._job_id, EventType.RUNNING, held)
            self._cancelling = True
            self._last_sent = time.monotonic()
            fields: dict[str, Any] = {"progress": self.progress, "reason": reason}
            if self._positioning is not None:  # the cancelling events carry it, the first one too
                fields["positioning"] = self._positioning
            return self._service._post_progress(self._job_id, EventType.CANCELLING, fields)

    def close(self) -> None:
        """Stop accepting; send the last held-back progress update so the final progress is seen: once the
        interval since the previous one is over (at most progress_hz per second, the last one too), before the
        job's final event (the caller posts it after this returns)."""
        with self._lock:
            self._closed = True
            if self._timer is not None:
                self._timer.cancel()
                self._timer = None
            held, self._held = self._held, None
            if held is None or self._paused:
                return
            kind = self._type()
            wait_s = self._last_sent + self._min_interval_s - time.monotonic()
        if wait_s > 0.0:
            time.sleep(wait_s)  # nothing else posts for this job now: it is closed
        self._service._post_progress(self._job_id, kind, held)



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
        # per axis the last commanded target (None: none, or a velocity move's) and the sign of the last commanded
        # motion, from every job accepted (planner/travel.py's contract): the additive and modulo modes plan from
        # them, so an additive move after a stop at an arbitrary position still counts from the last target
        self._last_target: dict[str, float | None] = {}
        self._last_direction: dict[str, int] = {}
        # the hold: no further job starts until resume (after a cancel of the running job, a stop, a hold)
        self._held = False
        self._hold_reason = ""
        self._hold_t: float | None = None
        self._emergency_pending = False  # an emergency stop disabled the drives; resume re-enables them
        self._accepted_kind: dict[str, str] = {}  # events thread only: the kind, for the acceptance log line
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
            s.declare_queryable(keys.stop(c), lambda q: self._control_q.put(("stop", q))),
            s.declare_queryable(keys.hold(c), lambda q: self._control_q.put(("hold", q))),
            s.declare_queryable(keys.halt(c), lambda q: self._control_q.put(("halt", q))),
            s.declare_queryable(keys.resume(c), lambda q: self._control_q.put(("resume", q))),
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
            self._cancel_running(current, "the service is shutting down")
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

    @property
    def held(self) -> bool:
        with self._cv:
            return self._held

    def service_status(self) -> dict[str, Any]:
        ready, reason = self._ready()
        with self._cv:
            current = self._current
            pending = list(self._pending.values())
            held, hold_reason, hold_t = self._held, self._hold_reason, self._hold_t
        running = None
        if current is not None:
            emitter = current.emitter
            running = {
                "job_id": current.job_id,
                "kind": current.kind,
                "state": "cancelling" if current.cancel_requested else ("running" if current.started else "starting"),
                "progress": emitter.progress if emitter is not None else 0.0,
                "planned_duration_s": current.planned.duration_s,
            }
        return {
            "cell": self.cell,
            "api_version": API_VERSION,
            "ready": ready,
            "reason": reason,
            "held": held,
            "hold_reason": hold_reason,
            "hold_t": hold_t,
            "running_job": current.job_id if current is not None else None,
            "running": running,
            "queued_jobs": [q.job_id for q in pending],
            "queue": [
                {"job_id": q.job_id, "kind": q.kind, "planned_duration_s": q.planned.duration_s}
                for q in pending
            ],
            "queue_length": len(pending),
            "queue_limit": self.options.queue_limit,
            "axes": [a.name for a in self.backend.cell.axes],
            "units": {a.name: a.unit for a in self.backend.cell.axes},
            "velocity_limits": {a.name: a.velocity for a in self.backend.cell.axes},  # unit/s (pvt jog's default)
            "drives": self._drives(),
            "telemetry_hz": self.telemetry_hz,
            "started_t": self._started_t,
            "store": str(self.store.path),
            "recordings": str(self.recordings.directory) if self.recordings is not None else None,
        }

    def _drives(self) -> list[dict[str, Any]]:
        """The backend's telemetry snapshot, each axis with its unit (the status and telemetry's `axes`)."""
        units = {a.name: a.unit for a in self.backend.cell.axes}
        try:
            axes = plain(list(self.backend.telemetry()))
        except Exception as exc:
            log.warning("backend.telemetry() raised %s: %s", type(exc).__name__, exc)
            return []
        for a in axes:
            if isinstance(a, dict) and isinstance(a.get("name"), str):
                a.setdefault("unit", units.get(a["name"], ""))
        return [a for a in axes if isinstance(a, dict)]

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
        record = self.store.get(job_id)  # read before the executor can take it: the reply says "queued"
        with self._cv:
            if not self._pending and self._current is None:
                self._queue_end.clear()
            self._queue_end.update(planned.end_positions)
            self._remember(planned)
            self._pending[job_id] = _Queued(job_id, planned, body=sub.body, start_current=sub.start_current,
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

    def _admit_change(self, sub: Submission, via: str, job_id: str, job: Any, current: _Queued, t0: float,
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
        emitter = _Emitter(self, job_id, 1.0 / self.options.progress_hz, paused=True)
        planned, info = self.backend.change(job, "aborting", emitter, **self._travel())
        if not isinstance(planned, Planned):
            raise MotionError(E.INTERNAL, f"backend.change returned {type(planned).__name__}, not Planned")
        planning_s = time.perf_counter() - t0
        item = _Queued(job_id, planned, token=current.token, body=sub.body, started=True, emitter=emitter)
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
        aborted = self._post(current.job_id, [(EventType.ABORTED, {
            "replaced_by": job_id, "message": f"replaced by job {job_id!r} (buffer aborting) at "
            f"{info.get('time_ms')} ms of the running stream", "progress": old.progress if old else None,
        }, {"finished_t": now})])
        post = _Post(
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
        self._events_q.put(post)
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

    def _travel(self) -> dict[str, Any]:
        """The last commanded target and direction per axis, as keyword arguments of the backend's plan or
        change."""
        with self._cv:
            return {"last_target": dict(self._last_target), "last_direction": dict(self._last_direction)}

    def _remember(self, planned: Planned) -> None:
        """(under the lock) The accepted job's target becomes the axes' last commanded target; a velocity move
        leaves none, and where the queue ends is unknown for its axes until it is stopped."""
        target = planned.commanded_target or planned.end_positions
        for axis, x in target.items():
            self._last_target[axis] = None if x is None else float(x)
            if x is None:
                self._queue_end.pop(axis, None)
        for axis, d in planned.commanded_direction.items():
            if d:
                self._last_direction[axis] = 1 if d > 0 else -1

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
                while (not self._pending or self._held) and not self._stopping:
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
        try:
            planned = self._check_start(item)
        except Exception as exc:
            err = error_from_exception(exc)
            if err.code == E.INTERNAL:
                log.exception("checking the start of job %s failed", item.job_id)
            self._post_failed_queued(item.job_id, err).wait(60)
            return
        emitter = _Emitter(self, item.job_id, min_interval)
        priming: _Post | None = None
        with self._cv:  # `started`, the emitter and the priming event together: a cancel sees all or none
            if not item.token.cancelled:
                item.started = True
                item.emitter = emitter
                priming = self._post(item.job_id, [(EventType.PRIMING, {}, {"started_t": self._clock()})])
        if priming is None:
            self._post_final_queued(
                item.job_id, EventType.CANCELLED, None, "cancelled before it started"
            ).wait(60)
            return
        priming.wait(60)
        try:
            report: Any = self.backend.execute(planned, emitter, item.token)
        except Exception as exc:
            err = error_from_exception(exc)
            if err.code == E.INTERNAL:
                log.exception("backend.execute raised for job %s", item.job_id)
                message = f"backend.execute raised {type(exc).__name__}: {exc}"
            else:  # a coded error (e.g. the backend's own re-plan): an ordinary failure, not a crash
                log.warning("job %s: backend.execute raised %s", item.job_id, err)
                message = err.message
            report = {
                "result": "failed",
                "error": {"code": err.code, "path": err.path, "node": None, "message": message,
                          **({"detail": err.detail} if err.detail else {})},
            }
        finally:
            with self._cv:  # a change may have handed the motion on: the report is the last owner's
                last = item
                while last.replaced_by is not None:
                    last = last.replaced_by
            (last.emitter or emitter).close()
        report = self._record(last.job_id, report)
        etype, data, updates = self._final_from_report(report)
        self._post(last.job_id, [(etype, data, updates)]).wait(60)

    # -- the start of a queued job -------------------------------------------------------------------
    def _positions(self) -> dict[str, float] | None:
        """Where every axis' position demand stands (backend.current_positions()), or None if unknown."""
        try:
            got = self.backend.current_positions()
            if got is None:
                return None
            return {str(k): float(v) for k, v in dict(got).items()}
        except Exception as exc:
            log.warning("backend.current_positions() raised %s: %s", type(exc).__name__, exc)
            return None

    @staticmethod
    def _rows_field(kind: str) -> str:
        return "waypoints" if kind == "path" else "positions"

    def _with_start(self, body: Mapping[str, Any], at: Mapping[str, float]) -> dict[str, Any] | None:
        """A path body that begins where the axes stand (`at`): that position prepended to its waypoints, or
        None when its first waypoint is already there (within half a count on every axis)."""
        axes = body.get("axes")
        rows = body.get("waypoints")
        if not isinstance(axes, list) or not isinstance(rows, list) or not rows or not isinstance(rows[0], list):
            return None
        if any(a not in at for a in axes):
            return None
        here = [float(at[a]) for a in axes]
        cpu = {a.name: a.counts_per_unit for a in self.backend.cell.axes}
        try:
            if all(abs(float(v) - h) * cpu.get(a, 1.0) <= 0.5 for a, v, h in zip(axes, rows[0], here, strict=True)):
                return None
        except (TypeError, ValueError):
            return None
        return {**body, "waypoints": [here, *rows]}

    def _check_start(self, item: _Queued) -> Planned:
        """The plan to run: `item.planned` when its start is where the axes stand; else a move re-planned from
        there, a `start = "current"` path re-planned through a waypoint there, anything else INFEASIBLE."""
        here = self._positions()
        planned = item.planned
        if here is None or not planned.start_positions:
            return planned
        cpu = {a.name: a.counts_per_unit for a in self.backend.cell.axes}
        off = [
            (name, here[name], start)
            for name, start in planned.start_positions.items()
            if name in here and abs(here[name] - start) * cpu.get(name, 1.0) > 0.5
        ]
        if not off:
            return planned
        kind = item.kind
        if kind == "move" or (item.start_current and kind == "path"):
            job = planned.job
            if kind == "path":
                moved = self._with_start(item.body, here)
                if moved is not None:
                    job = self.backend.validate(moved)
            replanned = self.backend.plan(job, None, **item.travel)  # from where the axes stand, same last target
            if not isinstance(replanned, Planned):
                raise MotionError(E.INTERNAL, f"backend.plan returned {type(replanned).__name__}, not Planned")
            log.info("job %s re-planned from where the axes stand (%s)", item.job_id,
                     ", ".join(f"{n} at {h:.6g}, planned from {p:.6g}" for n, h, p in off))
            return replanned
        name, at, start = off[0]
        axes = item.body.get("axes")
        j = axes.index(name) if isinstance(axes, list) and name in axes else 0
        unit = next((a.unit for a in self.backend.cell.axes if a.name == name), "")
        field_path = f"{self._rows_field(kind)}[0][{j}]"
        raise MotionError(
            E.INFEASIBLE,
            f"{field_path}: axis {name!r} stands at {at:.6g} {unit} but the job starts at {start:.6g} {unit} "
            "(it was planned from where the jobs before it would end, and the axes stopped elsewhere: a "
            "cancel or a stop); submit it again from here, or give it start = \"current\" to have a path "
            "planned from where the axes stand",
            path=field_path,
            detail={"axis": name, "position": at, "job_start": start,
                    "axes": [{"axis": n, "position": h, "job_start": p} for n, h, p in off]},
        )

    def _record(self, job_id: str, report: Any) -> Any:
        """Write the job's recording (if the backend made one); the report says where, or why not."""
        if self._writer is None:
            return report
        try:
            rec = self.backend.take_recording()
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

    def _post_progress(self, job_id: str, etype: EventType, data: dict[str, Any]) -> _Post:
        post = _Post(job_id, [(etype, data, {"progress": data["progress"]})])
        self._events_q.put(post)
        return post

    def _post_failed_queued(self, job_id: str, err: MotionError) -> _Post:
        """A queued job that fails before it starts, with the whole error (code, path, detail)."""
        error = {"code": err.code, "path": err.path, "node": None, "message": err.message,
                 **({"detail": err.detail} if err.detail else {})}
        updates = {"error": error, "finished_t": self._clock()}
        return self._post(job_id, [(EventType.FAILED, {"error": error, "report": None}, updates)])

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
                # logged before it is published: whoever sees the event (a client's wait) finds its line logged
                self._log_event(ev)
                self._put(keys.job_events(self.cell, ev.job_id), ev.to_wire(self.cell), reliable=True)

    def _log_event(self, ev: Event) -> None:
        """One log line per job milestone: accepted, started, cancelling, done, failed, cancelled."""
        d = ev.data
        if ev.type == EventType.ACCEPTED:
            self._accepted_kind[ev.job_id] = str(d.get("kind", "?"))  # logged with the plan, next event
        elif ev.type == EventType.PLANNED:
            log.info("job %s accepted: %s job, planned %.3f s, %s points", ev.job_id,
                     self._accepted_kind.pop(ev.job_id, "?"), float(d.get("planned_duration_s") or 0.0),
                     d.get("points"))
        elif ev.type == EventType.PRIMING:
            log.info("job %s started", ev.job_id)
        elif ev.type == EventType.CANCELLING and "reason" in d:
            log.info("job %s cancelling at %.0f%% (%s)", ev.job_id, 100.0 * float(d.get("progress") or 0.0),
                     d.get("reason"))
        elif ev.type == EventType.DONE:
            rep: Mapping[str, Any] = d["report"] if isinstance(d.get("report"), Mapping) else {}
            log.info("job %s done (%.3f s)", ev.job_id, float(rep.get("duration_s") or 0.0))
        elif ev.type == EventType.FAILED:
            err: Mapping[str, Any] = d["error"] if isinstance(d.get("error"), Mapping) else {}
            log.warning("job %s failed %s: %s", ev.job_id, err.get("code"), err.get("message"))
        elif ev.type == EventType.CANCELLED:
            log.info("job %s cancelled%s", ev.job_id, f": {d['message']}" if d.get("message") else "")

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
            "stop": self._q_stop,
            "hold": self._q_hold,
            "halt": self._q_halt,
            "resume": self._q_resume,
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
        running: _Queued | None = None
        with self._cv:
            if job_id in self._pending:
                del self._pending[job_id]
                post = self._post_final_queued(job_id, EventType.CANCELLED, None, "cancelled while queued")
            elif self._current is not None and self._current.job_id == job_id:
                running = self._current
        requested = post is not None
        message = "cancelled while queued" if post is not None else ""
        if post is not None:
            post.wait(timeout=60.0)
        if running is not None:
            started = running.started
            requested = self._cancel_running(running, "cancel requested", hold=f"job {job_id} was cancelled")
            if requested:
                message = (
                    "the job stops on its jerk-limited stop trajectory; the queue is held until resume"
                    if started
                    else "the job was about to start: it ends cancelled without moving; the queue is held until "
                    "resume"
                )
            else:
                message = "a cancel of this job was already requested; it is stopping"
        rec = self.store.get(job_id)
        if rec is None:
            raise MotionError(E.NOT_FOUND, f"no job {job_id!r} in cell {self.cell!r}", path="job_id")
        status = rec.to_status()
        if not requested and not message:
            message = f"the job is {rec.state.value}: nothing to cancel"
        status["cancel_requested"] = requested
        status["message"] = message
        status["held"] = self.held
        self.counters["cancel"] += 1
        self._reply(query, keys.job_cancel(self.cell, job_id), status)

    def _cancel_running(self, item: _Queued, reason: str, hold: str | None = None) -> bool:
        """Cancel the job the executor holds; True if this request had an effect (the first one does).
        `hold`: also hold the queue, for this reason, in the same step (a job that ends at once must not let
        the executor start the next one before the hold is in place)."""
        with self._cv:
            if item.cancel_requested:
                return False
            item.cancel_requested = True
            if hold is not None and not self._held:
                self._held, self._hold_reason, self._hold_t = True, hold, self._clock()
                log.info("queue of cell %r held: %s", self.cell, hold)
            emitter = item.emitter if item.started else None
        posted = emitter.mark_cancelling(reason) if emitter is not None else None
        if emitter is not None and posted is None:
            return False  # it ended meanwhile
        item.token.cancel()
        if posted is not None:
            with contextlib.suppress(Exception):
                posted.wait(timeout=10.0)  # journalled: the answer's status says `cancelling`
        return True

    def _hold(self, reason: str) -> None:
        with self._cv:
            if not self._held:
                self._held, self._hold_reason, self._hold_t = True, reason, self._clock()
                log.info("queue of cell %r held: %s", self.cell, reason)
            self._cv.notify_all()

    @staticmethod
    def _flag(query: zenoh.Query, name: str) -> bool:
        text = (query.parameters.get(name) or "false").strip().lower()
        if text in ("true", "1", "yes", "on"):
            return True
        if text in ("false", "0", "no", "off", ""):
            return False
        raise MotionError(E.BAD_REQUEST, f"{name}={text!r} must be true or false")

    def _q_stop(self, query: zenoh.Query) -> None:
        emergency = self._flag(query, "emergency")
        self._hold("emergency stop" if emergency else "stop requested")
        with self._cv:
            current = self._current
        method = "none"
        what = ""
        if emergency and self.backend.can_emergency_stop:
            if current is not None:
                current.emergency = True
                if not current.started:
                    current.token.cancel()  # it had not started: it never will
            try:
                did = self.backend.emergency_stop()
            except Exception as exc:
                log.exception("backend.emergency_stop() raised")
                raise MotionError(E.INTERNAL, f"backend.emergency_stop() raised {type(exc).__name__}: {exc}") from None
            self._emergency_pending = True
            # a backend says what it did: a message (the quick stop), or {"method", "message", ...} (the planned
            # emergency stop, "emergency_trajectory", or its fallback "quick_stop")
            if isinstance(did, Mapping):
                method = str(did.get("method", "quick_stop"))
                what = str(did.get("message", ""))
            else:
                method, what = "quick_stop", str(did)
            log.warning("EMERGENCY STOP of cell %r%s: %s", self.cell,
                        f" (job {current.job_id} running)" if current is not None else "", what)
        elif current is not None:
            if self._cancel_running(current, "emergency stop" if emergency else "stop requested"):
                method = "stop_trajectory"
                what = "the running job stops on its jerk-limited stop trajectory"
            else:
                method = "stop_trajectory"
                what = "the running job was already stopping"
            if emergency:
                what += " (this backend has no emergency stop: the jerk-limited stop is the fastest it has)"
        else:
            what = "nothing was moving"
        self.counters["stop"] += 1
        self._reply(query, keys.stop(self.cell), {
            "cell": self.cell,
            "held": True,
            "emergency": emergency,
            "method": method,
            "job_id": current.job_id if current is not None else None,
            "message": what,
            "queued_jobs": self.service_status()["queued_jobs"],
        })

    def _q_halt(self, query: zenoh.Query) -> None:
        """Halt: the running job stops on its jerk-limited stop (ends cancelled); unlike stop, the queue is not
        held, so the next job starts from where the axes came to rest."""
        with self._cv:
            current = self._current
        if current is None:
            method, what = "none", "nothing was moving"
        elif self._cancel_running(current, "halt requested"):
            method, what = "stop_trajectory", "the running job stops on its jerk-limited stop trajectory"
        else:
            method, what = "stop_trajectory", "the running job was already stopping"
        self.counters["halt"] += 1
        self._reply(query, keys.halt(self.cell), {
            "cell": self.cell, "held": self.held, "job_id": current.job_id if current is not None else None,
            "method": method, "message": what,
        })

    def _q_hold(self, query: zenoh.Query) -> None:
        self._hold("hold requested")
        with self._cv:
            running = self._current.job_id if self._current is not None else None
            queued = list(self._pending)
        self._reply(query, keys.hold(self.cell), {
            "cell": self.cell, "held": True, "hold_reason": self._hold_reason, "running_job": running,
            "queued_jobs": queued,
        })

    def _q_resume(self, query: zenoh.Query) -> None:
        reset = self._flag(query, "reset")
        ready, reason = self._ready()
        did_reset = False
        if not ready:
            if not (reset or self._emergency_pending):
                raise MotionError(
                    E.NOT_READY,
                    f"cell {self.cell!r} is not ready: {reason or 'faulted'}; resume with reset "
                    f"(`pvt resume --reset`, get {keys.resume(self.cell)}?reset=true) to clear it first",
                )
            if self.running_job is not None:
                raise MotionError(E.BUSY, f"job {self.running_job!r} is still stopping; resume when it has ended")
            try:
                ready, reason = self.backend.reset()
            except MotionError:
                raise  # a coded refusal (BUSY: the emergency stop is still stopping the drives)
            except Exception as exc:
                raise MotionError(E.INTERNAL, f"backend.reset() raised {type(exc).__name__}: {exc}") from None
            did_reset = True
            if not ready:
                raise MotionError(E.NOT_READY, f"cell {self.cell!r} is still not ready after a reset: {reason}")
            self._emergency_pending = False
        with self._cv:
            was_held, self._held, self._hold_reason, self._hold_t = self._held, False, "", None
            queued = list(self._pending)
            self._cv.notify_all()
        log.info("queue of cell %r resumed%s (%d queued)", self.cell, " after a reset" if did_reset else "",
                 len(queued))
        self._reply(query, keys.resume(self.cell), {
            "cell": self.cell, "held": False, "was_held": was_held, "reset": did_reset, "ready": bool(ready),
            "reason": str(reason or ""), "queued_jobs": queued,
        })

    def _q_service(self, query: zenoh.Query) -> None:
        self._reply(query, keys.service(self.cell), self.service_status())

    def _q_reset(self, query: zenoh.Query) -> None:
        if self.running_job is not None:
            raise MotionError(E.BUSY, f"job {self.running_job!r} is running; cancel it before a reset")
        try:
            ready, reason = self.backend.reset()
        except MotionError:
            raise
        except Exception as exc:
            raise MotionError(E.INTERNAL, f"backend.reset() raised {type(exc).__name__}: {exc}") from None
        if ready:
            self._emergency_pending = False
        self._reply(
            query,
            keys.reset(self.cell),
            {"cell": self.cell, "ready": bool(ready), "reason": str(reason or "")},
        )

    # -- telemetry ---------------------------------------------------------------------------------
    def _telemetry_loop(self) -> None:
        period = 1.0 / self.telemetry_hz
        units = {a.name: a.unit for a in self.backend.cell.axes}
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
            for a in axes:
                if isinstance(a, dict) and isinstance(a.get("name"), str):
                    a.setdefault("unit", units.get(a["name"], ""))
            ready, reason = self._ready()
            with self._cv:
                item = self._current
                held = self._held
            emitter = item.emitter if item is not None else None
            self._telemetry_seq += 1
            msg: dict[str, Any] = {
                "cell": self.cell,
                "t": self._clock(),
                "seq": self._telemetry_seq,
                "ready": ready,
                "reason": reason,
                "held": held,
                "job_id": item.job_id if item is not None else None,
                "job_state": None if item is None else (
                    "cancelling" if item.cancel_requested else "running" if item.started else "starting"),
                "progress": emitter.progress if emitter is not None else None,
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
