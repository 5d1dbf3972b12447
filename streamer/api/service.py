"""The job service of one cell: Zenoh in, motion backend out, everything journalled.

Five threads, each a concern of its own module; Zenoh callbacks only queue the request. Intake
(intake.py: decode, validate, plan, journal, answer), executor (cell_queue.py: queue, hold, execute),
control (handlers.py, control_verbs.py: queries and verbs, apart so planning never stalls them), events
(journal.py: the journal's only writer, in order) and telemetry (telemetry.py). service_state.py holds
what they share; this module starts and stops them. On start, jobs left unfinished fail SERVICE_RESTART
before anything is answered; `pvt/<cell>/alive` says the service is up.
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

