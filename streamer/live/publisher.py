"""Live channels: the job recording's channels, published while the job runs, over foxglove-sdk's WebSocket
server (protocol `foxglove.sdk.v1`).

The streaming thread already appends everything to the job's `JobTrace`; `LivePublisher` wakes every
`period_s` on its own thread and a `TraceFollower` turns what was appended into messages of the recording's
schemas (one layout for recordings and live cells); between jobs, the cell's telemetry. The streaming
thread never waits for it: a publisher that fell behind skips to `max_batch` samples (`dropped`), and a
slow client loses its oldest. Binds to 127.0.0.1 unless told.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from streamer.live import DEFAULT_HOST, DEFAULT_PORT
from streamer.recording.mcap_io import (
    AXIS_SAMPLE_SCHEMA,
    AXIS_TOPIC_PREFIX,
    EVENTS_TOPIC,
    JOB_EVENT_SCHEMA,
    event_message,
    sample_message,
)
from streamer.recording.model import START, RecordedEvent, change_events, noted_event, plan_index

TELEMETRY_TOPIC = "/cell/telemetry"
# a held sample waits for its SYNC's TPDO1 (FIFO fill) at most this many SYNCs
FILL_WAIT_SYNCS = 3

_NUM = {"type": ["number", "null"]}
TELEMETRY_SCHEMA: dict[str, Any] = {
    "title": "pvt.Telemetry",
    "description": "The cell's drives as the service last saw them (published between and during jobs).",
    "type": "object",
    "properties": {
        "t": {"type": "number", "description": "wall-clock time, seconds since the Unix epoch"},
        "axes": {"type": "array", "items": {
            "type": "object",
            "properties": {
                "name": {"type": "string"}, "node_id": {"type": "integer"},
                "position": _NUM, "position_demand": _NUM, "velocity": _NUM,
                "fifo_fill": {"type": ["integer", "null"]}, "state": {"type": "string"},
                "positioning": {"type": "string", "description": "positioning state (seed 002's 9020:03)"},
                "referenced": {"type": "boolean"},
            },
        }},
    },
    "required": ["t", "axes"],
}

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LiveJob:
    """The running job as the live view reads it: its plan (a `PvtTrajectory`), its streamer core (read:
    `start_sync`) and its trace (read: the append-only lists)."""

    plan: Any
    core: Any
    trace: Any
    sync_period_ms: int
    # wall clock = epoch_s + the trace's time: 0 for the real-time runtime (python-can timestamps are Unix
    # time, as the recording's log times), the run's start for virtual time
    epoch_s: float = 0.0


class TraceFollower:
    """What one job's trace gained since the last `poll`, as messages (no I/O, no clock)."""

    def __init__(self, job: LiveJob, *, max_batch: int = 5000):
        self.job = job
        self.max_batch = max_batch
        self.dropped = 0
        plan = job.plan
        self._planned = plan.planned_demand()
        self._duration_ms = int(plan.duration_ms)
        self._row = {int(n): i for i, n in enumerate(plan.node_ids)}
        self._names = {int(n): str(name) for name, n in zip(plan.axis_names, plan.node_ids, strict=True)}
        self._pos_k: dict[int, int] = dict.fromkeys(self._row, 0)
        self._fill_k: dict[int, int] = dict.fromkeys(self._row, 0)
        self._fills: dict[int, dict[int, tuple[int, int | None, int | None]]] = {n: {} for n in self._row}
        self._changes_k = 0
        self._noted_k = 0
        self._start_sent = False
        self._t0: float | None = None
        self._first_sync = 0

    def _first_time(self) -> float | None:
        if self._t0 is None:
            try:  # the first SYNC the trace saw (dicts keep insertion order); the streaming thread may insert
                self._first_sync, self._t0 = next(iter(self.job.trace.sync_times.items()))
            except (StopIteration, RuntimeError):
                return None
        return self._t0

    def _t(self, sync: int) -> float:
        t = self.job.trace.sync_times.get(sync)
        t0 = self._t0 if self._t0 is not None else 0.0
        if t is None:
            return round((sync - self._first_sync) * self.job.sync_period_ms / 1000.0, 6)
        return round(float(t) - t0, 6)

    def log_time_ns(self, t: float) -> int:
        """The wall-clock time of `t` (seconds since the job's first SYNC), ns since the epoch (the MCAP log time
        the recording gives the same message)."""
        t0 = self._t0 if self._t0 is not None else 0.0
        return max(0, round((self.job.epoch_s + t0 + t) * 1e9))

    def poll(self, *, final: bool = False) -> tuple[dict[str, list[dict[str, Any]]], list[dict[str, Any]]]:
        """(per axis name its new `pvt.AxisSample` messages, new `pvt.JobEvent` messages). `final`: the job
        ended, publish what was held back waiting for its FIFO fill."""
        samples: dict[str, list[dict[str, Any]]] = {}
        if self._first_time() is None:
            return samples, []
        trace = self.job.trace
        start_sync = self.job.core.start_sync
        for node, i in self._row.items():
            ax = trace.axes.get(node)
            if ax is None:
                continue
            samples[self._names[node]] = self._axis(ax, node, i, start_sync, final)
        return samples, self._events(start_sync)

    def _axis(self, ax: Any, node: int, i: int, start_sync: int | None, final: bool) -> list[dict[str, Any]]:
        fills = self._fills[node]
        nf = min(len(ax.fill_sync), len(ax.fill))
        with_status = len(ax.statusword) >= nf and len(ax.buffer_status) >= nf
        for k in range(self._fill_k[node], nf):
            fills[ax.fill_sync[k]] = (ax.fill[k], ax.statusword[k] if with_status else None,
                                      ax.buffer_status[k] if with_status else None)
        self._fill_k[node] = nf
        last_fill = ax.fill_sync[nf - 1] if nf else None
        n = min(len(ax.pos_sync), len(ax.actual), len(ax.demand))
        k = self._pos_k[node]
        if n - k > self.max_batch:  # fell behind: the newest samples, not a growing delay
            self.dropped += n - k - self.max_batch
            k = n - self.max_batch
        out: list[dict[str, Any]] = []
        newest = ax.pos_sync[n - 1] if n else 0
        while k < n:
            s = ax.pos_sync[k]
            if (not final and nf and s not in fills and (last_fill is None or s > last_fill)
                    and newest - s < FILL_WAIT_SYNCS):
                break  # its TPDO1 (FIFO fill) is still on its way
            actual, demand = ax.actual[k], ax.demand[k]
            row: dict[str, int | None] = {"actual": actual, "demand": demand, "following_error": actual - demand,
                                          "planned": int(self._planned[i, plan_index(s, start_sync,
                                                                                     self.job.sync_period_ms,
                                                                                     self._duration_ms)])}
            f = fills.pop(s, None)
            if f is not None:
                row["fifo_fill"], row["statusword"], row["buffer_status"] = f
            out.append(sample_message(self._t(s), s, node, row))
            k += 1
        self._pos_k[node] = k
        if out and len(fills) > 64:  # fills no sample will claim (a TPDO2 lost)
            oldest = out[-1]["sync"] - FILL_WAIT_SYNCS
            for s in [s for s in fills if s < oldest]:
                del fills[s]
        return out

    def _events(self, start_sync: int | None) -> list[dict[str, Any]]:
        trace = self.job.trace
        t0 = self._t0 if self._t0 is not None else 0.0
        events: list[RecordedEvent] = []
        n = len(trace.changes)
        for c in trace.changes[self._changes_k:n]:
            events += change_events(c, round(c.t - t0, 6) if c.t else self._t(c.sync or 0))
        self._changes_k = n
        n = len(trace.noted)
        for noted in trace.noted[self._noted_k:n]:
            events.append(noted_event(noted, round(float(noted.event.t) - t0, 6)))
        self._noted_k = n
        if start_sync is not None and not self._start_sent:
            self._start_sent = True
            events.append(RecordedEvent(self._t(start_sync), start_sync, START,
                                        message=f"every axis in ip mode from SYNC {start_sync}"))
        events.sort(key=lambda e: e.t)
        return [event_message(e) for e in events]


class LivePublisher:
    """foxglove-sdk's WebSocket server and the publishing thread (see the module docstring).

    `axes`: (name, node id) of every axis of the cell (one channel each, advertised from the start);
    `source()`: the running job or None; `telemetry()`: the cell's telemetry rows (the job service's
    `telemetry()`), or None for no telemetry channel."""

    def __init__(self, axes: Sequence[tuple[str, int]], *, source: Callable[[], LiveJob | None],
                 telemetry: Callable[[], Sequence[Mapping[str, Any]]] | None = None,
                 host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, period_s: float = 0.02,
                 telemetry_period_s: float = 0.1, max_batch: int = 5000, backlog: int = 4096,
                 name: str = "pvt"):
        self.axes = tuple((str(a), int(n)) for a, n in axes)
        self.source = source
        self.telemetry = telemetry
        self.host = host
        self.requested_port = port
        self.period_s = period_s
        self.telemetry_period_s = telemetry_period_s
        self.max_batch = max_batch
        self.backlog = backlog
        self.name = name
        self.dropped = 0
        self.published = 0
        self.error: BaseException | None = None
        self._server: Any = None
        self._context: Any = None
        self._channels: dict[str, Any] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._follower: TraceFollower | None = None
        self._next_telemetry = 0.0

    # ---- life
    def start(self) -> LivePublisher:
        import foxglove
        from foxglove.channel import Channel

        # our own context (two publishers in one process do not share channels), kept: a context no one holds is
        # dropped, and its channels with it (the server then advertises nothing)
        self._context = context = foxglove.Context()
        self._server = foxglove.start_server(name=self.name, host=self.host, port=self.requested_port,
                                             context=context, message_backlog_size=self.backlog)
        for axis, node in self.axes:
            self._channels[AXIS_TOPIC_PREFIX + axis] = Channel(
                AXIS_TOPIC_PREFIX + axis, schema=AXIS_SAMPLE_SCHEMA, context=context,
                metadata={"node_id": str(node)})
        self._channels[EVENTS_TOPIC] = Channel(EVENTS_TOPIC, schema=JOB_EVENT_SCHEMA, context=context)
        if self.telemetry is not None:
            self._channels[TELEMETRY_TOPIC] = Channel(TELEMETRY_TOPIC, schema=TELEMETRY_SCHEMA, context=context)
        self._thread = threading.Thread(target=self._run, name="pvt-live", daemon=True)
        self._thread.start()
        return self

    @property
    def port(self) -> int:
        if self._server is None:
            raise RuntimeError("the live server is not started")
        port: int = self._server.port
        return port

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def subscribed(self, topics: Sequence[str] | None = None) -> bool:
        """Whether a client subscribed to every one of `topics` (default: every axis channel)."""
        wanted = topics if topics is not None else [AXIS_TOPIC_PREFIX + a for a, _ in self.axes]
        return all(self._channels[t].has_sinks() for t in wanted)

    def wait_subscribed(self, timeout_s: float, topics: Sequence[str] | None = None) -> bool:
        end = time.monotonic() + timeout_s
        while not self.subscribed(topics):
            if time.monotonic() >= end or self._stop.is_set():
                return False
            time.sleep(0.02)
        return True

    def stop(self, *, linger_s: float = 0.5) -> None:
        """Publish what is left of the running job, give the server `linger_s` to send it, stop."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            self._thread = None
        if self._server is not None:
            if linger_s > 0:
                time.sleep(linger_s)
            self._server.stop()
            self._server = None
        for ch in self._channels.values():
            ch.close()
        self._channels.clear()
        self._context = None

    def __enter__(self) -> LivePublisher:
        return self.start() if self._server is None else self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ---- the publishing thread
    def _run(self) -> None:
        try:
            while not self._stop.wait(self.period_s):
                self.tick()
            self.tick(final=True)
        except Exception as e:  # the live view stops; the job goes on (its recording has everything)
            self.error = e
            log.exception("live view stopped publishing")

    def tick(self, *, final: bool = False) -> None:
        job = self.source()
        follower = self._follower
        if follower is not None and (job is None or job.trace is not follower.job.trace):
            self._publish(follower, final=True)  # that job ended: what was held back
            self.dropped += follower.dropped
            self._follower = follower = None
        if job is not None and follower is None:
            self._follower = follower = TraceFollower(job, max_batch=self.max_batch)
        if follower is not None:
            self._publish(follower, final=final)
            if final:
                self.dropped += follower.dropped
                self._follower = None
        if self.telemetry is not None:
            now = time.monotonic()
            if now >= self._next_telemetry or final:
                self._next_telemetry = now + self.telemetry_period_s
                rows = [dict(r) for r in self.telemetry()]
                self._log(TELEMETRY_TOPIC, {"t": round(time.time(), 6), "axes": rows})

    def _publish(self, follower: TraceFollower, *, final: bool) -> None:
        samples, events = follower.poll(final=final)
        for axis, msgs in samples.items():
            topic = AXIS_TOPIC_PREFIX + axis
            for m in msgs:
                self._log(topic, m, follower.log_time_ns(m["t"]))
        for e in events:
            self._log(EVENTS_TOPIC, e, follower.log_time_ns(e["t"]))

    def _log(self, topic: str, msg: Mapping[str, Any], log_time_ns: int | None = None) -> None:
        ch = self._channels.get(topic)
        if ch is not None:
            ch.log(dict(msg), log_time=log_time_ns)
            self.published += 1
