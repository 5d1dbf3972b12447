"""`MotionClient`: submit motion jobs to a cell's job service over Zenoh, watch them, cancel them.

    with MotionClient(connect="tcp/127.0.0.1:7447", cell="demo") as client:
        job = client.submit({"kind": "move", "axes": ["j1"], "target": [0.5], "mode": "absolute"})
        status = job.wait(timeout=60)        # JobFailedError if the job failed

Errors are `MotionError` with the service's code (plus TIMEOUT, NO_SERVICE, SERVICE_GONE). Each `submit`
runs a job as `<job_id>-<8 hex digits>`; `job_id="exact"` is idempotent. `submit` subscribes to the job's
events before sending it, and `events()` fills gaps from the journalled history.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import threading
import time
import tomllib
import uuid
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from planner.config import NAME_MAX, check_name
from planner.errors import PlanningError
from streamer.api import errors as E
from streamer.api import keys
from streamer.api.errors import JobFailedError, MotionError
from streamer.api.model import JobState
from streamer.api.payload import encode_submission, unpack
from streamer.api.security import ClientSecurity
from streamer.api.zenoh_config import DEFAULT_CONNECT, client_config

FINAL_EVENTS = frozenset({"done", "failed", "cancelled", "aborted"})
RUN_SUFFIX_LEN = 9  # "-" and 8 hex digits


def checked_job_id(job_id: str, what: str = "job_id") -> str:
    """`job_id` if it follows the rule of names (docs/formats.md "Names"), else MotionError SCHEMA."""
    try:
        return check_name(job_id, what, path="job_id")
    except PlanningError as exc:
        raise MotionError(exc.code, exc.message, path=exc.path) from None


def run_job_id(name: object) -> str:
    """The id of one run of a job whose own `job_id` is `name`: `<name>-<8 hex digits>` (a uuid without a
    name). So submitting the same file or dict twice runs it twice; `submit(..., job_id=)` is exact."""
    if name is None or name == "":
        return uuid.uuid4().hex
    if not isinstance(name, str):
        raise MotionError(E.TYPE, f"job_id must be a string, got {name!r}"[:200], path="job_id")
    checked_job_id(name)
    if len(name) > NAME_MAX - RUN_SUFFIX_LEN:
        raise MotionError(
            E.SCHEMA,
            f"job_id {name!r} is {len(name)} characters: as a name for runs (<job_id>-<8 hex digits>) it may "
            f"have {NAME_MAX - RUN_SUFFIX_LEN}; shorten it, or give the exact id (--job-id, job_id=)",
            path="job_id",
        )
    return f"{name}-{uuid.uuid4().hex[:8]}"


@dataclass(frozen=True)
class JobEvent:
    """One event of a job (see docs/api.md "Events"); `data` is the whole message."""

    job_id: str
    seq: int
    type: str  # accepted, planned, priming, running, done, failed, cancelled (rejected: seq 0)
    t: float  # service wall clock, Unix seconds
    state: str  # the job's state after the event
    data: Mapping[str, Any] = field(default_factory=dict)

    @property
    def final(self) -> bool:
        return self.type in FINAL_EVENTS

    @property
    def progress(self) -> float | None:
        p = self.data.get("progress")
        return float(p) if isinstance(p, int | float) and not isinstance(p, bool) else None

    @property
    def error(self) -> Mapping[str, Any] | None:
        err = self.data.get("error")
        return err if isinstance(err, Mapping) else None

    @classmethod
    def from_wire(cls, msg: Any) -> JobEvent:
        if not isinstance(msg, Mapping):
            raise MotionError(E.MALFORMED_PAYLOAD, f"event is not a map: {msg!r}"[:200])
        try:
            return cls(
                job_id=str(msg["job_id"]) if msg.get("job_id") is not None else "",
                seq=int(msg["seq"]),
                type=str(msg["type"]),
                t=float(msg["t"]),
                state=str(msg["state"]),
                data=dict(msg),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise MotionError(E.MALFORMED_PAYLOAD, f"event lacks {exc}: {msg!r}"[:300]) from None


@dataclass(frozen=True)
class JobStatus:
    """A job's journalled status (`pvt/<cell>/jobs/<job_id>`)."""

    job_id: str
    cell: str
    state: JobState
    kind: str
    planned_duration_s: float | None
    points: int | None
    progress: float
    error: Mapping[str, Any] | None
    report: Mapping[str, Any] | None
    number: int
    submitted_t: float
    finished_t: float | None
    raw: Mapping[str, Any] = field(default_factory=dict)

    @property
    def final(self) -> bool:
        return self.state.final

    @classmethod
    def from_wire(cls, msg: Any) -> JobStatus:
        if not isinstance(msg, Mapping):
            raise MotionError(E.MALFORMED_PAYLOAD, f"status is not a map: {msg!r}"[:200])
        try:
            return cls(
                job_id=str(msg["job_id"]),
                cell=str(msg.get("cell", "")),
                state=JobState(msg["state"]),
                kind=str(msg.get("kind", "")),
                planned_duration_s=msg.get("planned_duration_s"),
                points=msg.get("points"),
                progress=float(msg.get("progress") or 0.0),
                error=msg.get("error"),
                report=msg.get("report"),
                number=int(msg.get("number") or 0),
                submitted_t=float(msg.get("submitted_t") or 0.0),
                finished_t=msg.get("finished_t"),
                raw=dict(msg),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise MotionError(E.MALFORMED_PAYLOAD, f"status lacks {exc}: {msg!r}"[:300]) from None


def load_job_file(path: str | os.PathLike[str]) -> dict[str, Any]:
    """A job file (TOML or JSON, the planner's job format) as the dict the service expects."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise MotionError(E.SCHEMA, f"cannot read job file {str(p)!r}: {exc}", path="job") from None
    try:
        data = json.loads(text) if p.suffix.lower() == ".json" else tomllib.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as exc:
        raise MotionError(
            E.MALFORMED_PAYLOAD,
            f"job file {str(p)!r} is not valid {'JSON' if p.suffix.lower() == '.json' else 'TOML'}: {exc}",
        ) from None
    if not isinstance(data, dict):
        raise MotionError(E.SCHEMA, f"job file {str(p)!r} must hold a table/object", path="job")
    return data


def _reply_error(raw: bytes, key: str, timeout: float) -> MotionError:
    """An error reply as MotionError: the service's msgpack {code, path, message}, or Zenoh's own
    error replies (plain text, e.g. "Timeout" when a service matched but did not answer in time)."""
    try:
        data = unpack(raw)
    except MotionError:
        data = None
    if isinstance(data, Mapping) and "code" in data:
        return MotionError.from_dict(data)
    text = raw[:200].decode("utf-8", "replace")
    if text.strip().lower() == "timeout":
        return MotionError(E.TIMEOUT, f"no answer to {key!r} within {timeout} s")
    return MotionError(E.INTERNAL, f"error reply to {key!r}: {text!r}")


class Job:
    """A handle on one job: its events, status, cancellation. Made by `MotionClient.submit` / `.job`."""

    def __init__(self, client: MotionClient, job_id: str, accepted: Mapping[str, Any] | None = None):
        self.client = client
        self.job_id = job_id
        self.cell = client.cell
        self.accepted: dict[str, Any] = dict(accepted or {})
        self.body: dict[str, Any] | None = None  # the job as submitted through this client (change() reads axes)
        self._inbox: queue.Queue[bytes | None] = queue.Queue()  # None: the service's token vanished
        self._lock = threading.RLock()
        self._seen: list[JobEvent] = []
        self._buffer: dict[int, JobEvent] = {}
        self._history_checked = False
        self._gone = threading.Event()
        self._sub: Any = client.session.declare_subscriber(
            keys.job_events(self.cell, job_id), lambda s: self._inbox.put(s.payload.to_bytes())
        )
        # the service's liveliness token: its DELETE (the process died, or left the network) ends a wait
        # for events at once with SERVICE_GONE instead of a long TIMEOUT (peer sessions; a client session
        # finds out with the history query it makes after poll_s of silence)
        self._alive: Any = None
        try:
            self._alive = client.session.liveliness().declare_subscriber(keys.alive(self.cell), self._on_alive)
        except zenoh.ZError:
            self._alive = None

    def _on_alive(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            self._gone.set()
            self._inbox.put(None)

    # -- accepted reply ------------------------------------------------------------------------------
    @property
    def planned_duration_s(self) -> float | None:
        v = self.accepted.get("planned_duration_s")
        return float(v) if isinstance(v, int | float) else None

    @property
    def points(self) -> int | None:
        v = self.accepted.get("points")
        return int(v) if isinstance(v, int) else None

    def __repr__(self) -> str:
        return f"Job({self.job_id!r}, cell={self.cell!r})"

    # -- queries -------------------------------------------------------------------------------------
    def status(self, timeout: float | None = None) -> JobStatus:
        return JobStatus.from_wire(self.client._query(keys.job(self.cell, self.job_id), timeout=timeout))

    def cancel(self, timeout: float | None = None) -> JobStatus:
        """Ask the service to cancel; a queued job ends CANCELLED at once, a running one after its stop."""
        return JobStatus.from_wire(
            self.client._query(keys.job_cancel(self.cell, self.job_id), timeout=timeout)
        )

    def stop(self, timeout: float | None = None) -> JobStatus:
        """Stop this job with the normal deceleration (its jerk-limited stop trajectory); as `cancel()`."""
        return self.cancel(timeout=timeout)

    def emergency_stop(self, timeout: float | None = None) -> dict[str, Any]:
        """The cell's emergency stop (every axis, this job's included): `MotionClient.stop(emergency=True)`."""
        return self.client.stop(emergency=True, timeout=timeout)

    def halt(self, timeout: float | None = None) -> dict[str, Any]:
        """Halt: the running job stops with the normal deceleration, the queue is NOT held (the next job may
        start): `MotionClient.halt()`."""
        return self.client.halt(timeout=timeout)

    def change(
        self,
        target: Sequence[float] | Mapping[str, float],
        *,
        mode: str = "absolute",
        axes: Sequence[str] | None = None,
        buffer: str = "aborting",
        job_id: str | None = None,
        lead_ms: int | None = None,
        timeout: float | None = None,
    ) -> Job:
        """A new target for this running job: a move submitted with `buffer` ("aborting": it replaces this
        job's remainder without stopping; this job then ends `aborted`). The new job's handle; MotionError
        COMMAND_REJECTED (with the reason) when the change cannot be made, and this job goes on untouched.
        `target`: by axis name, or a list in the order of `axes` (default: this job's axes); with
        `mode="velocity"` the velocities of a velocity move (then in the running job's axis order)."""
        if isinstance(target, Mapping):
            names = list(target)
            values = [float(target[n]) for n in names]
        else:
            known = axes if axes is not None else (self.body or {}).get("axes")
            if not isinstance(known, Sequence) or isinstance(known, str):
                raise MotionError(E.BAD_REQUEST, "change(): give the target by axis name, or the axes (this handle "
                                  "does not know the job's axes)", path="axes")
            names = [str(a) for a in known]
            values = [float(x) for x in target]
        # a velocity move (mode "velocity") gives per axis a signed velocity instead of a target
        body: dict[str, Any] = {"kind": "move", "axes": names, "velocity" if mode == "velocity" else "target": values,
                                "mode": mode, "buffer": buffer}
        if lead_ms is not None:
            body["lead_ms"] = lead_ms
        return self.client.submit(body, job_id=job_id, timeout=timeout)

    def history(self, after: int = 0, timeout: float | None = None) -> list[JobEvent]:
        """The journalled events (seq > after), from the service."""
        msg = self.client._query(
            keys.job_events(self.cell, self.job_id), parameters=f"after={after}", timeout=timeout
        )
        return [JobEvent.from_wire(e) for e in msg.get("events", [])] if isinstance(msg, Mapping) else []

    # -- events --------------------------------------------------------------------------------------
    def events(
        self, timeout: float | None = None, *, poll_s: float = 0.5, total_timeout: float | None = None
    ) -> Iterator[JobEvent]:
        """Every event of the job in sequence order, from the first; ends after done/failed/cancelled.

        `timeout` bounds the wait for each next event, `total_timeout` the whole iteration (MotionError
        TIMEOUT; the job itself goes on); None waits for ever, however long the job waits in the queue.
        MotionError SERVICE_GONE when the service's liveliness token vanishes before the job ended.
        Iterating again replays from the first event.
        """
        index = 0
        deadline = None if total_timeout is None else time.monotonic() + total_timeout
        while True:
            with self._lock:
                if index < len(self._seen):
                    ev = self._seen[index]
                else:
                    if self._seen and self._seen[-1].final:
                        return
                    wait = timeout
                    if deadline is not None:
                        left = deadline - time.monotonic()
                        wait = left if wait is None else min(wait, left)
                        if left <= 0:
                            state = self._seen[-1].state if self._seen else "unknown"
                            raise MotionError(
                                E.TIMEOUT,
                                f"job {self.job_id!r} is still {state} after {total_timeout:g} s (it goes on)",
                                detail={"state": state},
                            )
                    try:
                        ev = self._next(wait, poll_s)
                    except MotionError as err:
                        if err.code == E.TIMEOUT and deadline is not None and time.monotonic() >= deadline:
                            continue  # the whole-iteration timeout says it (above)
                        raise
            index += 1
            yield ev
            if ev.final:
                self._unsubscribe()
                return

    def wait(self, timeout: float | None = None) -> JobStatus:
        """Block until the job ends; its final status. Raises JobFailedError (with the job's error code)
        if it failed, MotionError TIMEOUT if it has not ended within `timeout` seconds."""
        deadline = None if timeout is None else time.monotonic() + timeout
        index = 0
        while True:
            with self._lock:
                if index < len(self._seen):
                    ev = self._seen[index]
                else:
                    remaining = None if deadline is None else deadline - time.monotonic()
                    if remaining is not None and remaining <= 0:
                        raise MotionError(E.TIMEOUT, f"job {self.job_id!r} did not end within {timeout} s")
                    try:
                        ev = self._next(remaining, 0.5)
                    except MotionError as err:
                        if err.code == E.TIMEOUT:
                            raise MotionError(
                                E.TIMEOUT, f"job {self.job_id!r} did not end within {timeout} s"
                            ) from None
                        raise
            index += 1
            if ev.final:
                self._unsubscribe()
                break
        status = self.status()
        if status.state == JobState.FAILED:
            failure = status.error or {}
            raise JobFailedError(
                str(failure.get("code", E.INTERNAL)),
                str(failure.get("message", "job failed")),
                path=str(failure.get("path", "") or ""),
                detail={"node": failure.get("node")} if failure.get("node") is not None else None,
                status=status,
            )
        return status

    def _next(self, timeout: float | None, poll_s: float) -> JobEvent:
        """The next event in sequence (caller holds the lock)."""
        want = len(self._seen) + 1
        deadline = None if timeout is None else time.monotonic() + timeout
        if not self._history_checked and not self.accepted:
            self._history_checked = True  # a handle on an existing job: catch up from the journal first
            self._fill_from_history()
        while want not in self._buffer:
            if self._gone.is_set():
                self._drain_inbox()
                if want in self._buffer:
                    break
                state = self._seen[-1].state if self._seen else "unknown"
                raise MotionError(
                    E.SERVICE_GONE,
                    f"the job service of cell {self.cell!r} went away while job {self.job_id!r} was {state} "
                    "(its liveliness token vanished); the job did not report its end. When the service is "
                    "back, its journal shows the job (failed SERVICE_RESTART if it was queued or running)",
                    detail={"state": state},
                )
            wait = poll_s if deadline is None else max(0.0, min(poll_s, deadline - time.monotonic()))
            try:
                raw = self._inbox.get(timeout=wait)
            except queue.Empty:
                self._fill_from_history()  # quiet for a while: the journal may have what we missed
                if want in self._buffer:
                    break
                if self._gone.is_set():
                    continue  # reported at the top of the loop
                if deadline is not None and time.monotonic() >= deadline:
                    raise MotionError(
                        E.TIMEOUT, f"no event of job {self.job_id!r} within {timeout} s"
                    ) from None
                continue
            if raw is None:
                continue  # the service's token vanished: checked at the top
            self._take(raw, want)
        ev = self._buffer.pop(want)
        self._seen.append(ev)
        return ev

    def _take(self, raw: bytes, want: int) -> None:
        ev = JobEvent.from_wire(unpack(raw))
        if ev.type == "rejected":
            self._unsubscribe()
            raise MotionError.from_dict(ev.error or {})
        if ev.seq >= want:
            self._buffer[ev.seq] = ev
            if ev.seq > want and not self._gone.is_set():
                self._fill_from_history()  # a gap: the journal has everything before this event

    def _drain_inbox(self) -> None:
        want = len(self._seen) + 1
        while True:
            try:
                raw = self._inbox.get_nowait()
            except queue.Empty:
                return
            if raw is not None:
                self._take(raw, want)

    def _fill_from_history(self) -> None:
        try:
            for ev in self.history(after=len(self._seen), timeout=self.client.timeout):
                if ev.seq > len(self._seen):
                    self._buffer.setdefault(ev.seq, ev)
        except MotionError as err:
            if err.code == E.NO_SERVICE:
                # nothing answered and the liveliness token is gone: a Zenoh *client* session is not told
                # when the peer it is linked to dies (no DELETE of its token), but this query finds out
                self._gone.set()
            elif err.code not in (E.NOT_FOUND, E.TIMEOUT):
                raise

    def _unsubscribe(self) -> None:
        sub: Any = self._sub
        alive: Any = self._alive
        self._sub = self._alive = None
        for declared in (sub, alive):
            if declared is not None:
                with contextlib.suppress(Exception):
                    declared.undeclare()

    @property
    def subscribed(self) -> bool:
        """True while the handle listens to the job's events (until its final event or `close()`)."""
        return self._sub is not None

    def close(self) -> None:
        """Stop listening to the job's events (the job itself is not affected)."""
        self._unsubscribe()


def open_session(
    connect: str | Sequence[str] = DEFAULT_CONNECT,
    mode: str = "auto",
    security: ClientSecurity | None = None,
) -> zenoh.Session:
    """Open a client-side Zenoh session (no listen endpoint, multicast scouting off).

    mode "auto" (the default): with one endpoint, Zenoh client mode (one link, opens in ~1 ms, good
    for short-lived clients), falling back to a peer that keeps retrying in the background when
    nothing listens there yet (so `wait_for_service` can wait for a service that starts later);
    with several endpoints, a peer that connects to all of them. "peer"/"client" force the mode.
    `security`: TLS (CA, client certificate and key) and login for a secured service.
    """
    endpoints = [connect] if isinstance(connect, str) else list(connect)
    if mode == "auto":
        if len(endpoints) == 1:
            try:
                return zenoh.open(client_config(endpoints, mode="client", security=security))
            except zenoh.ZError:
                pass  # nothing listens yet: a peer retries in the background
        return zenoh.open(client_config(endpoints, mode="peer", security=security))
    try:
        return zenoh.open(client_config(endpoints, mode=mode, security=security))
    except zenoh.ZError as exc:
        hint = (
            "nothing listens there, or the service refused this client's certificate or login"
            if security is not None or any(e.startswith("tls/") for e in endpoints)
            else "nothing listens there (a TLS-only service needs tls/ endpoints and --ca/--cert/--key)"
        )
        raise MotionError(E.NO_SERVICE, f"cannot connect to {endpoints}: {hint} ({exc})"[:800]) from None


class MotionClient:
    """A Zenoh client of one cell's job service. Use as a context manager (closes its session).

    `connect`: the service's (or a router's) endpoint(s). `mode`: "auto" (see `open_session`), "client"
    or "peer"; the session never listens and never scouts by multicast. `session`: use an already open
    session instead (it is not closed by `close()`). `timeout`: default seconds for every query.
    `security`: the CA, this client's certificate and key, and its login, for a secured service
    (docs/security.md); a request its role does not allow raises MotionError PERMISSION_DENIED.
    """

    def __init__(
        self,
        connect: str | Sequence[str] = DEFAULT_CONNECT,
        cell: str = "demo",
        *,
        mode: str = "auto",
        timeout: float = 10.0,
        session: zenoh.Session | None = None,
        security: ClientSecurity | None = None,
    ):
        self.cell = keys.check_cell(cell)
        self.timeout = float(timeout)
        self.connect = connect
        self.security = security
        self._own_session = session is None
        self.session: zenoh.Session = session if session is not None else open_session(connect, mode, security)
        self._jobs: list[Job] = []
        self._closed = False

    def __enter__(self) -> MotionClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for job in self._jobs:
            job.close()
        self._jobs.clear()
        if self._own_session:
            session: Any = self.session
            session.close()

    # -- the service ---------------------------------------------------------------------------------
    def wait_for_service(self, timeout: float = 10.0) -> None:
        """Block until the cell's service is up (its liveliness token is seen); MotionError TIMEOUT if not."""
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            try:
                replies = list(
                    self.session.liveliness().get(
                        keys.alive(self.cell), timeout=max(0.05, min(1.0, remaining))
                    )
                )
            except zenoh.ZError:
                replies = []
            if any(r.ok is not None for r in replies):
                return
            if time.monotonic() >= deadline:
                secured = self.security is not None or "tls/" in str(self.connect)
                raise MotionError(
                    E.TIMEOUT,
                    f"no job service for cell {self.cell!r} appeared within {timeout} s "
                    f"(connect {self.connect!r}"
                    + ("; or the service refused this client's certificate or login" if secured else "")
                    + ")",
                )
            time.sleep(min(0.05, max(0.0, deadline - time.monotonic())))

    def cells(self, timeout: float = 1.0) -> list[str]:
        """Cells whose service is alive on this Zenoh network (from the liveliness tokens)."""
        out = set()
        for r in self.session.liveliness().get(keys.alive_any(), timeout=timeout):
            if r.ok is not None:
                parts = str(r.ok.key_expr).split("/")
                if len(parts) == 3:
                    out.add(parts[1])
        return sorted(out)

    def service_status(self, timeout: float | None = None) -> dict[str, Any]:
        msg = self._query(keys.service(self.cell), timeout=timeout)
        return dict(msg) if isinstance(msg, Mapping) else {}

    def reset(self, timeout: float | None = None) -> dict[str, Any]:
        """Reset a faulted cell (fault reset on the drives); {ready, reason} afterwards."""
        msg = self._query(keys.reset(self.cell), timeout=timeout)
        return dict(msg) if isinstance(msg, Mapping) else {}

    def stop(self, *, emergency: bool = False, timeout: float | None = None) -> dict[str, Any]:
        """Stop all: cancel the running job (its jerk-limited stop) and hold the queue; `emergency`: the
        fastest stop the runtime has (quick stop on every drive, then `resume` re-enables). The answer
        says what was done: {held, emergency, method, job_id, message, queued_jobs}."""
        msg = self._query(keys.stop(self.cell), parameters=f"emergency={'true' if emergency else 'false'}",
                          timeout=timeout)
        return dict(msg) if isinstance(msg, Mapping) else {}

    def halt(self, timeout: float | None = None) -> dict[str, Any]:
        """Halt: the running job stops with the normal deceleration (its jerk-limited stop trajectory) and ends
        cancelled, but the queue is not held: the next queued job starts from where the axes stopped. The
        answer: {cell, held, job_id, method, message}."""
        msg = self._query(keys.halt(self.cell), timeout=timeout)
        return dict(msg) if isinstance(msg, Mapping) else {}

    def hold(self, timeout: float | None = None) -> dict[str, Any]:
        """Hold the queue: the running job goes on, no further job starts until `resume()`."""
        msg = self._query(keys.hold(self.cell), timeout=timeout)
        return dict(msg) if isinstance(msg, Mapping) else {}

    def resume(self, *, reset: bool = False, timeout: float | None = None) -> dict[str, Any]:
        """Release the hold (after a stop, a cancel or a hold); `reset`: clear a drive fault first (after an
        emergency stop the drives are re-enabled without it). MotionError NOT_READY if the cell is faulted."""
        msg = self._query(keys.resume(self.cell), parameters=f"reset={'true' if reset else 'false'}",
                          timeout=timeout)
        return dict(msg) if isinstance(msg, Mapping) else {}

    def telemetry(self, timeout: float = 2.0) -> dict[str, Any]:
        """The next telemetry sample of the cell ({cell, t, seq, ready, job_id, axes: [...]})."""
        box: queue.Queue[bytes] = queue.Queue()
        sub: Any = self.session.declare_subscriber(
            keys.telemetry(self.cell), lambda s: box.put(s.payload.to_bytes())
        )
        try:
            raw = box.get(timeout=timeout)
        except queue.Empty:
            raise MotionError(E.TIMEOUT, f"no telemetry from cell {self.cell!r} within {timeout} s") from None
        finally:
            sub.undeclare()
        msg = unpack(raw)
        return dict(msg) if isinstance(msg, Mapping) else {}

    # -- jobs ----------------------------------------------------------------------------------------
    def submit(
        self,
        job: Mapping[str, Any] | str | os.PathLike[str],
        *,
        job_id: str | None = None,
        timeout: float | None = None,
    ) -> Job:
        """Submit a job (a dict with a job file's fields, or a TOML/JSON job file) and return its handle.

        The answer comes after the service validated, planned and journalled the job: the handle's
        `accepted` holds {job_id, state, planned_duration_s, points, existing}. The job's own `job_id`
        is a name: each call is a new run `<job_id>-<8 hex>` (as `pvt submit`). `job_id=` is exact:
        resubmitting the same id with the same body returns the existing job (existing=True). Raises
        MotionError with the rejection's code (SCHEMA, INFEASIBLE, BUSY, CONFLICT, NOT_READY, ...). On
        TIMEOUT or NO_SERVICE the job may still have been accepted: resubmit with the same exact
        `job_id` (idempotent) to find out.
        """
        body = load_job_file(job) if isinstance(job, str | os.PathLike) else dict(job)
        name = body.pop("job_id", None)
        jid = checked_job_id(job_id) if job_id is not None else run_job_id(name)
        handle = Job(self, jid, accepted={"job_id": jid})  # subscribed before the job exists
        try:
            reply = self._query(keys.submit(self.cell), payload=encode_submission(body, jid), timeout=timeout)
        except BaseException:
            handle.close()
            raise
        handle.accepted = dict(reply) if isinstance(reply, Mapping) else {"job_id": jid}
        handle.body = body
        self._track(handle)
        return handle

    def submit_put(
        self, job: Mapping[str, Any] | str | os.PathLike[str], *, job_id: str | None = None
    ) -> Job:
        """Fire-and-forget submission (a Zenoh put); the outcome arrives as the handle's events
        (a rejection raises MotionError from `events()`/`wait()`)."""
        body = load_job_file(job) if isinstance(job, str | os.PathLike) else dict(job)
        name = body.pop("job_id", None)
        jid = checked_job_id(job_id) if job_id is not None else run_job_id(name)
        handle = Job(self, jid, accepted={"job_id": jid, "via": "put"})
        self.session.put(
            keys.submit(self.cell),
            encode_submission(body, jid),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        self._track(handle)
        return handle

    def job(self, job_id: str) -> Job:
        """A handle on an existing job (its events replay from the journal)."""
        handle = Job(self, checked_job_id(job_id))
        self._track(handle)
        return handle

    def _track(self, handle: Job) -> None:
        """Keep handles with a live subscription (closed at `close()`); forget finished ones."""
        self._jobs = [j for j in self._jobs if j.subscribed]
        self._jobs.append(handle)

    def jobs(
        self, state: str | Sequence[str] | None = None, limit: int = 100, timeout: float | None = None
    ) -> list[JobStatus]:
        """Journalled jobs of the cell, newest first (optionally only some states)."""
        params = [f"limit={int(limit)}"]
        if state:
            params.append("state=" + (state if isinstance(state, str) else ",".join(state)))
        msg = self._query(keys.jobs(self.cell), parameters=";".join(params), timeout=timeout)
        raw = msg.get("jobs", []) if isinstance(msg, Mapping) else []
        return [JobStatus.from_wire(j) for j in raw]

    # -- plumbing ------------------------------------------------------------------------------------
    def _query(
        self,
        key: str,
        *,
        payload: bytes | None = None,
        parameters: str | None = None,
        timeout: float | None = None,
    ) -> Any:
        """One query; the first reply decoded, an error reply raised as MotionError."""
        t = self.timeout if timeout is None else float(timeout)
        selector = f"{key}?{parameters}" if parameters else key
        t0 = time.monotonic()
        try:
            replies = self.session.get(selector, payload=payload, timeout=t)
            for reply in replies:
                if reply.ok is not None:
                    return unpack(reply.ok.payload.to_bytes())
                if reply.err is not None:
                    raise _reply_error(reply.err.payload.to_bytes(), key, t)
        except zenoh.ZError as exc:
            raise MotionError(E.NO_SERVICE, f"query {key!r} failed: {exc}") from None
        if time.monotonic() - t0 >= 0.9 * t:  # a service matched but did not answer in time
            raise MotionError(E.TIMEOUT, f"no answer to {key!r} within {t} s")
        if self._service_alive():
            # The service is up, yet nothing answered: its access rules dropped the request (Zenoh
            # answers a refused query with no reply at all, so this is the only way to tell).
            raise MotionError(
                E.PERMISSION_DENIED,
                f"the job service of cell {self.cell!r} is up but refused {key!r} from this client: "
                "the identity it connected with (certificate common name or login) has no role that "
                "allows it (writes need the operator role; see docs/security.md)",
                path=key,
            )
        raise MotionError(
            E.NO_SERVICE,
            f"no job service answered {key!r} (is `pvt serve` for cell "
            f"{self.cell!r} running and reachable at {self.connect!r}?)",
        )

    def _service_alive(self) -> bool:
        try:
            replies = self.session.liveliness().get(keys.alive(self.cell), timeout=min(1.0, self.timeout))
            return any(r.ok is not None for r in replies)
        except zenoh.ZError:
            return False
