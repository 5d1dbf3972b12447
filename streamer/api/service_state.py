"""The state the job service's parts share, and how the service speaks on its Zenoh session.

`JobService` (service.py) is a class over this one per part (intake, cell_queue, control_verbs,
telemetry, handlers). This class owns what they share: options, backend and store, one condition
variable `_cv` guarding the queue (`_pending`, `_current`, `_queue_end`), the travel memory, the hold and
the counters; it starts no thread. Answers go out through `_put`, `_reply`, `_reply_err` (msgpack); a
failure to send is logged, never raised (the peer may have gone).
"""

from __future__ import annotations

import collections
import contextlib
import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from streamer.api import keys
from streamer.api.backend import CancelToken, MotionBackend, Planned
from streamer.api.errors import MotionError
from streamer.api.journal import Journal
from streamer.api.payload import DEFAULT_LIMITS, PayloadLimits, pack
from streamer.api.progress import Emitter
from streamer.api.store import JobStore
from streamer.core.settings import StreamerSettings
from streamer.recording.files import RecordingFiles, RecordingRetention, default_recordings_dir
from streamer.recording.writer import RecordingWriter

# every part of the service logs as `streamer.api.service`, the logger it always had (log filters name it)
log = logging.getLogger("streamer.api.service")

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
class Queued:
    """A job accepted and waiting for (or in) execution; the plan lives only in memory."""

    job_id: str
    planned: Planned
    token: CancelToken = field(default_factory=CancelToken)
    body: dict[str, Any] = field(default_factory=dict)  # the job as submitted (for a re-plan)
    start_current: bool = False  # `start = "current"`: plan from where the axes stand
    started: bool = False  # its `priming` event is posted (under the service's lock)
    cancel_requested: bool = False
    emergency: bool = False  # an emergency stop hit it
    emitter: Emitter | None = None
    replaced_by: Queued | None = None  # a change took the running motion over (this job ended aborted)
    travel: dict[str, Any] = field(default_factory=dict)  # the last target/direction it was planned with

    @property
    def kind(self) -> str:
        kind = self.body.get("kind")
        return kind if isinstance(kind, str) else ""


@dataclass
class Submit:
    data: bytes | None
    size: int
    via: str  # "query" | "put"
    query: zenoh.Query | None



class ServiceState:
    """What the parts of `JobService` share (see the module's docstring); not a service on its own."""

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
        # the only journal writer (the events thread): every event of every job goes through it
        self._journal = Journal(store, self.cell, clock, lambda key, obj: self._put(key, obj, reliable=True))
        self._cv = threading.Condition()
        self._pending: collections.OrderedDict[str, Queued] = collections.OrderedDict()
        self._current: Queued | None = None
        # where the axes moved by queued/running jobs stand when the queue has run (the next plan's start)
        self._queue_end: dict[str, float] = {}
        # per axis the last commanded target (None: none, or a velocity move's) and the sign of the last commanded
        # motion, from every job accepted (planner/motion/travel.py's contract): the additive and modulo modes plan from
        # them, so an additive move after a stop at an arbitrary position still counts from the last target
        self._last_target: dict[str, float | None] = {}
        self._last_direction: dict[str, int] = {}
        # the hold: no further job starts until resume (after a cancel of the running job, a stop, a hold)
        self._held = False
        self._hold_reason = ""
        self._hold_t: float | None = None
        self._emergency_pending = False  # an emergency stop disabled the drives; resume re-enables them
        self._stopping = False
        self._stop_telemetry = threading.Event()
        self._threads: list[threading.Thread] = []
        self._declared: list[Any] = []
        self._token: Any = None
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

    def _ready(self) -> tuple[bool, str]:
        try:
            ready, reason = self.backend.ready()
            return bool(ready), str(reason or "")
        except Exception as exc:
            return False, f"backend.ready() raised {type(exc).__name__}: {exc}"

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
