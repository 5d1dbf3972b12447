"""The Zenoh handlers of the job service: what is declared on the session and who answers it.

Theory of operation. Zenoh callbacks run on Zenoh's threads and must return at once: they only copy the
request into a queue. Submissions (query or put on `pvt/<cell>/submit`) go to the intake queue
(intake.py; when it is full the answer is BUSY at once); every other query goes to the control queue,
whose thread (`_control_loop`) answers it: the read-only ones here (job list, job status, a job's
event history, service status), the verbs in control_verbs.py. A coded error becomes the query's error
reply; anything else is logged and answered INTERNAL.
"""

from __future__ import annotations

import logging
import queue
from collections.abc import Callable
from typing import Any

import zenoh

from streamer.api import errors as E
from streamer.api import keys
from streamer.api.control_verbs import ControlVerbsMixin
from streamer.api.errors import MotionError
from streamer.api.intake import IntakeMixin
from streamer.api.journal import STOP
from streamer.api.model import JobState
from streamer.api.service_state import Submit

# every part of the service logs as `streamer.api.service`, the logger it always had (log filters name it)
log = logging.getLogger("streamer.api.service")


class ZenohHandlersMixin(IntakeMixin, ControlVerbsMixin):
    """The Zenoh side of `JobService`: declarations, callbacks, the control thread, the read-only queries."""

    def _declare(self) -> list[Any]:
        """The service's queryables and subscriber on its session (undeclared by close())."""
        s, c = self.session, self.cell
        return [
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

    # -- Zenoh callbacks (short: they only queue) -------------------------------------------------
    def _on_submit_query(self, query: zenoh.Query) -> None:
        payload = query.payload
        size = len(payload) if payload is not None else 0
        data = payload.to_bytes() if payload is not None and size <= self.options.limits.max_bytes else None
        self._queue_submit(Submit(data, size, "query", query))

    def _on_submit_put(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            return
        size = len(sample.payload)
        data = sample.payload.to_bytes() if size <= self.options.limits.max_bytes else None
        self._queue_submit(Submit(data, size, "put", None))

    def _queue_submit(self, sub: Submit) -> None:
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
            if item is STOP:
                return
            kind, query = item
            try:
                handlers[kind](query)
            except MotionError as err:
                self._reply_err(query, err)
            except Exception as exc:
                log.exception("control query %s failed", kind)
                self._reply_err(query, MotionError(E.INTERNAL, f"{type(exc).__name__}: {exc}"))

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

    def _q_service(self, query: zenoh.Query) -> None:
        self._reply(query, keys.service(self.cell), self.service_status())

