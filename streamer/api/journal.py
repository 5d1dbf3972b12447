"""The journal calls of the job service: the events thread, the only writer of the job journal.

Every part with something to say about a job builds a `Post` (a batch of one job's events and row updates)
and hands it to `Journal.submit`. The events thread (`Journal.run`) takes posts in order: each event gets
the job's next sequence number and passes the transition table (model.py), the batch is committed in one
transaction, then logged and published. A caller that must not answer first waits (`Post.wait`).
`recover()` fails the jobs a previous process left unfinished (SERVICE_RESTART).
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from streamer.api import errors as E
from streamer.api import keys
from streamer.api.errors import MotionError
from streamer.api.model import Event, EventType, InvalidTransition, JobState, transition
from streamer.api.payload import plain
from streamer.api.store import JobStore

# every part of the service logs as `streamer.api.service`, the logger it always had (log filters name it)
log = logging.getLogger("streamer.api.service")

@dataclass
class Post:
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


STOP = object()


class Journal:
    """The events thread's side of the journal: posts in, committed and published events out."""

    def __init__(self, store: JobStore, cell: str, clock: Callable[[], float],
                 publish: Callable[[str, Any], None]):
        self.store = store
        self.cell = cell
        self._clock = clock
        self._publish = publish  # (key, message): reliably on the session
        self.queue: queue.Queue[Any] = queue.Queue()
        self._accepted_kind: dict[str, str] = {}  # events thread only: the kind, for the acceptance log line
        self._job_cache: dict[str, tuple[JobState, int]] = {}

    def submit(self, post: Post) -> Post:
        self.queue.put(post)
        return post

    def stop(self) -> None:
        """The events thread ends after the posts submitted before this."""
        self.queue.put(STOP)

    def post(
        self,
        job_id: str,
        events: list[tuple[EventType, dict[str, Any], dict[str, Any]]],
        new_job: dict[str, Any] | None = None,
    ) -> Post:
        return self.submit(Post(job_id, events, new_job))

    def post_progress(self, job_id: str, etype: EventType, data: dict[str, Any]) -> Post:
        return self.submit(Post(job_id, [(etype, data, {"progress": data["progress"]})]))

    def post_failed_queued(self, job_id: str, err: MotionError) -> Post:
        """A queued job that fails before it starts, with the whole error (code, path, detail)."""
        error = {"code": err.code, "path": err.path, "node": None, "message": err.message,
                 **({"detail": err.detail} if err.detail else {})}
        updates = {"error": error, "finished_t": self._clock()}
        return self.post(job_id, [(EventType.FAILED, {"error": error, "report": None}, updates)])

    def post_final_queued(self, job_id: str, etype: EventType, code: str | None, message: str) -> Post:
        if etype == EventType.FAILED:
            err = {"code": code or E.INTERNAL, "path": "", "node": None, "message": message}
            return self.post(
                job_id, [(etype, {"error": err, "report": None}, {"error": err, "finished_t": self._clock()})]
            )
        return self.post(
            job_id, [(etype, {"report": None, "message": message}, {"finished_t": self._clock()})]
        )

    def run(self) -> None:
        """The events thread: until `stop()`."""
        while True:
            post = self.queue.get()
            if post is STOP:
                return
            try:
                post.result = self._write(post)
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
                self._publish(keys.job_events(self.cell, ev.job_id), ev.to_wire(self.cell))

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

    def _write(self, post: Post) -> list[Event]:
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

    def recover(self) -> int:
        """Fail every job the journal shows queued or running: the previous service died with it. Returns how
        many."""
        posts = []
        for rec in self.store.unfinished():
            message = (
                f"the service stopped while the job was {rec.state.value}; it did not complete "
                "(the motion, if any, was stopped when the bus master went away)"
            )
            posts.append(self.post_final_queued(rec.job_id, EventType.FAILED, E.SERVICE_RESTART, message))
        for p in posts:
            p.wait(timeout=60.0)
        if posts:
            log.warning("marked %d unfinished job(s) FAILED with SERVICE_RESTART", len(posts))
        return len(posts)
