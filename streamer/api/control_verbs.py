"""The control verbs of the job service: cancel, stop, emergency stop, halt, hold, resume, reset.

Theory of operation. Each verb is a query on its own key (keys.py), answered on the control thread
(handlers.py) so planning at intake does not stall it, acting on the cell's queue under its lock. cancel:
a queued job ends at once; the running one is `cancelling` at once, stops on its jerk-limited stop, and
the queue is held. stop: holds and stops like a cancel; with `emergency=true` the backend's
`emergency_stop()` when it has one. halt: stops like a cancel without holding. hold: holds, stops nothing.
resume: lifts the hold (resetting the backend first with `reset=true` or after an emergency stop).
reset: the backend's fault reset, refused while a job runs.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

import zenoh

from streamer.api import errors as E
from streamer.api import keys
from streamer.api.cell_queue import CellQueueMixin
from streamer.api.errors import MotionError
from streamer.api.journal import Post
from streamer.api.model import EventType
from streamer.api.service_state import Queued
from streamer.api.telemetry import TelemetryMixin

# every part of the service logs as `streamer.api.service`, the logger it always had (log filters name it)
log = logging.getLogger("streamer.api.service")


class ControlVerbsMixin(CellQueueMixin, TelemetryMixin):
    """The control verbs of `JobService` (see the module's docstring)."""

    def _query_job_id(self, query: zenoh.Query) -> str:
        key = str(query.key_expr)
        job_id = keys.job_id_from_key(key, self.cell)
        if job_id is None or any(ch in key for ch in "*$?#"):
            raise MotionError(E.BAD_REQUEST, f"{key!r} does not name one job (no wildcards in the job id)")
        return job_id

    def _q_cancel(self, query: zenoh.Query) -> None:
        job_id = self._query_job_id(query)
        post: Post | None = None
        running: Queued | None = None
        with self._cv:
            if job_id in self._pending:
                del self._pending[job_id]
                post = self._journal.post_final_queued(job_id, EventType.CANCELLED, None, "cancelled while queued")
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

