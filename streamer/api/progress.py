"""Progress publishing of the job service: the `emit` handed to `backend.execute` and `backend.change`.

Theory of operation. A backend reports a running job's progress from any thread, as often as it likes;
the `Emitter` turns that into `running` events on the job's events key (through the journal, in
order), at most `progress_hz` per second: an update that comes too soon is held and goes out with the
next one allowed (a timer, latest wins) or when the job ends (`close`), so the final progress is seen.
After a cancel (`mark_cancelling`) every update is a `cancelling` event instead. Emitting never blocks
the backend; after `close` the emitter is inert. The per-axis telemetry snapshot is telemetry.py's.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Mapping
from typing import Any

from streamer.api.journal import Journal, Post
from streamer.api.model import EventType
from streamer.api.payload import plain

# every part of the service logs as `streamer.api.service`, the logger it always had (log filters name it)
log = logging.getLogger("streamer.api.service")


class Emitter:
    """The `emit` handed to `backend.execute`: thread-safe, non-blocking, throttled, inert after use.

    After `mark_cancelling()` every update is published as a `cancelling` event (the job's state is then
    CANCELLING), in order with the ones before: both go through this object's lock."""

    def __init__(self, journal: Journal, job_id: str, min_interval_s: float, *, paused: bool = False):
        self._journal = journal
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
            self._journal.post_progress(self._job_id, self._type(), data)
            self._last_sent = time.monotonic()  # after the event's time stamp: the next one is an interval later

    def _flush(self) -> None:
        """The timer: the held update goes out (latest wins) unless something newer already went."""
        with self._lock:
            self._timer = None
            held, self._held = self._held, None
            if held is None or self._closed or self._paused:
                self._held = held
                return
            self._journal.post_progress(self._job_id, self._type(), held)
            self._last_sent = time.monotonic()

    def unpause(self) -> None:
        with self._lock:
            self._paused = False
            held, self._held = self._held, None
            if held is not None and not self._closed:
                self._last_sent = time.monotonic()
                self._journal.post_progress(self._job_id, self._type(), held)

    def _type(self) -> EventType:
        return EventType.CANCELLING if self._cancelling else EventType.RUNNING

    def mark_cancelling(self, reason: str) -> Post | None:
        """Publish the `cancelling` event now (state CANCELLING); None if the job already ended."""
        with self._lock:
            if self._closed:
                return None
            held, self._held = self._held, None
            if held is not None:  # what the backend said before the cancel goes out first, in order
                self._journal.post_progress(self._job_id, EventType.RUNNING, held)
            self._cancelling = True
            self._last_sent = time.monotonic()
            fields: dict[str, Any] = {"progress": self.progress, "reason": reason}
            if self._positioning is not None:  # the cancelling events carry it, the first one too
                fields["positioning"] = self._positioning
            return self._journal.post_progress(self._job_id, EventType.CANCELLING, fields)

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
        self._journal.post_progress(self._job_id, kind, held)


