"""The job service of one cell: Zenoh in, motion backend out, everything journalled.

Theory of operation. Five threads, each owning one concern; Zenoh callbacks only copy the request
into a queue (they run on Zenoh's threads and must return at once). Each concern is a module of its
own, and `JobService` is put together from them:

- intake (intake.py): decodes a submission, answers idempotent resubmits and CONFLICT from the
  journal, validates and plans through the backend, applies NOT_READY and BUSY, has the job journalled
  and only then answers; `buffer = "aborting"` while a job moves is a change of the running motion.
- executor (cell_queue.py): the cell's queue and hold policy: takes queued jobs one at a time unless
  the queue is held, checks each still starts where the axes stand, calls `backend.execute` (blocking)
  with a progress emitter (progress.py) and a `CancelToken`, writes the job's recording, journals the
  result; the travel memory (last target and direction per axis) for the backend's plans.
- control (handlers.py, control_verbs.py): status, list, event history and service status queries, and
  the verbs cancel, stop (emergency too), halt, hold, resume and reset, separate from intake so a long
  planning job does not stall them.
- events (journal.py): the only writer of the journal: every event gets the job's next sequence number,
  passes the transition table (model.py), is committed, and is then published on the job's events key,
  in order. Backends may emit from any thread; emitting never blocks (progress is throttled).
- telemetry (telemetry.py): publishes the backend's per-axis snapshot at `telemetry_hz`.

service_state.py holds what the parts share (the queue under one lock, the hold, the options) and the
Zenoh output. This module starts and stops the threads.

On start, jobs the journal shows queued, running or cancelling (the previous process died) are failed
with SERVICE_RESTART and those events published before the service answers anything. A liveliness
token on `pvt/<cell>/alive` tells clients the service is up. Every job's acceptance, start and end is
logged (logger `streamer.api.service`, INFO, for every part).
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable

from streamer.api import errors as E
from streamer.api import keys
from streamer.api.handlers import ZenohHandlersMixin
from streamer.api.intake import BUFFER_MODES, LEAD_MS_MAX
from streamer.api.journal import STOP
from streamer.api.model import EventType
from streamer.api.service_state import API_VERSION, ENCODING, REPAIR_SYNCS, ServiceOptions

# every part of the service logs as `streamer.api.service`, the logger it always had (log filters name it)
log = logging.getLogger("streamer.api.service")

__all__ = ["API_VERSION", "BUFFER_MODES", "ENCODING", "LEAD_MS_MAX", "REPAIR_SYNCS", "JobService", "ServiceOptions"]


class JobService(ZenohHandlersMixin):
    """Serves one cell on an open Zenoh session. Several services may share one session (one per cell).

    The caller owns the session, the backend and the store; `close()` stops the service's own threads
    and declarations only.
    """

    # -- lifecycle -----------------------------------------------------------------------------
    def start(self) -> JobService:
        if self._started:
            raise RuntimeError("service already started")
        self._started = True
        self._started_t = self._clock()
        if self._writer is not None:
            self._writer.start()
        self._spawn("events", self._journal.run)
        self.counters["recovered"] += self._journal.recover()
        self._spawn("intake", self._intake_loop)
        self._spawn("control", self._control_loop)
        self._spawn("executor", self._executor_loop)
        self._spawn("telemetry", self._telemetry_loop)
        s, c = self.session, self.cell
        self._declared = self._declare()
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
        self._intake_q.put(STOP)
        threads["intake"].join(timeout=30.0)
        with self._cv:
            self._stopping = True
            stopped = list(self._pending.values())
            self._pending.clear()
            current = self._current
            self._cv.notify_all()
        posts = [
            self._journal.post_final_queued(
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
        self._control_q.put(STOP)
        threads["control"].join(timeout=10.0)
        self._stop_telemetry.set()
        threads["telemetry"].join(timeout=10.0)
        for p in posts:
            with contextlib.suppress(Exception):
                p.wait(timeout=10.0)
        self._journal.stop()
        threads["events"].join(timeout=30.0)
        log.info("job service for cell %r stopped", self.cell)

    def __enter__(self) -> JobService:
        return self.start() if not self._started else self

    def __exit__(self, *exc: object) -> None:
        self.close()

