"""The job journal: every accepted job, every event and every result, in SQLite (stdlib sqlite3, WAL).

Theory of operation: a job's row and its first events are written in one transaction before the
submitter is answered, each later event in its own, so a job a client was told about is on disk and
after a crash (even SIGKILL) `unfinished()` finds it; the next start fails it SERVICE_RESTART.
`synchronous=FULL` survives power loss (NORMAL for tests). One writer (the service's event thread);
readers use their own connections, WAL lets them read while it writes. `ServiceLock` (an flock on
`<db>-lock`) keeps a second service out. Tables: `jobs`, `events` (job_id, seq), `meta`.
"""

from __future__ import annotations

import fcntl
import json
import os
import sqlite3
import threading
from collections.abc import Collection, Iterator, Mapping, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

from streamer.api.model import Event, EventType, JobRecord, JobState
from streamer.api.payload import plain

SCHEMA_VERSION = 1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    number INTEGER PRIMARY KEY AUTOINCREMENT,
    job_id TEXT NOT NULL UNIQUE,
    cell TEXT NOT NULL,
    kind TEXT NOT NULL,
    state TEXT NOT NULL,
    via TEXT NOT NULL,
    body_hash TEXT NOT NULL,
    body BLOB NOT NULL,
    planned_duration_s REAL,
    points INTEGER,
    progress REAL NOT NULL DEFAULT 0,
    error TEXT,
    report TEXT,
    last_seq INTEGER NOT NULL DEFAULT 0,
    submitted_t REAL NOT NULL,
    started_t REAL,
    finished_t REAL,
    updated_t REAL NOT NULL
);
CREATE INDEX IF NOT EXISTS jobs_state ON jobs(state);
CREATE TABLE IF NOT EXISTS events (
    job_id TEXT NOT NULL,
    seq INTEGER NOT NULL,
    type TEXT NOT NULL,
    t REAL NOT NULL,
    state TEXT NOT NULL,
    data TEXT NOT NULL,
    PRIMARY KEY (job_id, seq)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
"""

_UPDATABLE = frozenset(
    {"planned_duration_s", "points", "progress", "error", "report", "started_t", "finished_t"}
)
_JSON_COLUMNS = frozenset({"error", "report"})

_COLUMNS = (
    "number, job_id, cell, kind, state, via, body_hash, planned_duration_s, points, progress, error, "
    "report, last_seq, submitted_t, started_t, finished_t, updated_t"
)


class StoreError(RuntimeError):
    """The journal cannot be opened or written (disk full, wrong schema, locked by another service)."""


STATE_DIR_ENV = "XDG_STATE_HOME"
JOURNAL_SUFFIXES = (".sqlite", ".db")


def state_dir() -> Path:
    """The user's state directory for pvt: `$XDG_STATE_HOME/pvt`, else `~/.local/state/pvt` (the XDG base
    directory default). Journals and recordings are machine state, not configuration: they never go
    beside a cell config (which may be in git, read-only, or shared by several machines)."""
    base = os.environ.get(STATE_DIR_ENV, "").strip()
    root = Path(base) if base and Path(base).is_absolute() else Path.home() / ".local" / "state"
    return root / "pvt"


def journal_path(cell_name: str, store: str | os.PathLike[str] | None = None) -> Path:
    """Where the journal of cell `cell_name` is: `<data dir>/<cell>.jobs.sqlite`, the data dir being `store`
    (`pvt serve --store DIR`) or `state_dir()`. A `store` that ends in .sqlite/.db (or is an existing
    file) names the journal file itself. Its recordings go beside it (`<cell>.jobs.recordings/`)."""
    if store is None:
        return state_dir() / f"{cell_name}.jobs.sqlite"
    p = Path(store).expanduser()
    if p.suffix.lower() in JOURNAL_SUFFIXES or p.is_file():
        return p
    return p / f"{cell_name}.jobs.sqlite"


def _dumps(value: Any) -> str:
    return json.dumps(plain(value), allow_nan=False, separators=(",", ":"))


def _loads(text: str | None) -> Any:
    if text is None:
        return None
    return json.loads(text)


class JobStore:
    """SQLite journal of jobs and events. Thread-safe: one connection per thread."""

    def __init__(self, path: str | os.PathLike[str], *, synchronous: str = "FULL", readonly: bool = False):
        """Open (creating it unless `readonly`) the journal at `path`. Readers such as `pvt jobs` pass
        readonly=True: no schema writes, so they never contend with the running service."""
        if synchronous.upper() not in ("FULL", "NORMAL", "EXTRA"):
            raise ValueError(f"synchronous must be FULL, NORMAL or EXTRA, got {synchronous!r}")
        self.path = Path(path)
        self._synchronous = synchronous.upper()
        self._local = threading.local()
        self._all: list[sqlite3.Connection] = []
        self._all_lock = threading.Lock()
        self._closed = False
        if readonly:
            if not self.path.exists():
                raise StoreError(f"job store {self.path} does not exist")
            try:
                version = self._conn().execute("PRAGMA user_version").fetchone()[0]
            except sqlite3.Error as exc:
                raise StoreError(f"cannot open job store {self.path}: {exc}") from exc
            if version != SCHEMA_VERSION:
                raise StoreError(f"{self.path} is not a job store (schema version {version})")
            return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            conn = self._conn()
            conn.execute("PRAGMA journal_mode=WAL")
            conn.executescript(_SCHEMA)
            version = conn.execute("PRAGMA user_version").fetchone()[0]
            if version == 0:
                conn.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
            elif version != SCHEMA_VERSION:
                raise StoreError(
                    f"job store {self.path} has schema version {version}, expected {SCHEMA_VERSION}"
                )
        except sqlite3.Error as exc:
            raise StoreError(f"cannot open job store {self.path}: {exc}") from exc

    # -- connections ---------------------------------------------------------------------------
    def _conn(self) -> sqlite3.Connection:
        if self._closed:
            raise StoreError(f"job store {self.path} is closed")
        conn: sqlite3.Connection | None = getattr(self._local, "conn", None)
        if conn is None:
            conn = sqlite3.connect(
                str(self.path), isolation_level=None, timeout=30.0, check_same_thread=False
            )
            conn.execute("PRAGMA busy_timeout=30000")
            conn.execute(f"PRAGMA synchronous={self._synchronous}")
            self._local.conn = conn
            with self._all_lock:
                self._all.append(conn)
        return conn

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        conn = self._conn()
        conn.execute("BEGIN IMMEDIATE")
        try:
            yield conn
        except BaseException:
            conn.execute("ROLLBACK")
            raise
        else:
            conn.execute("COMMIT")

    def close(self) -> None:
        with self._all_lock:
            conns, self._all = self._all, []
            self._closed = True
        for c in conns:
            with suppress(sqlite3.Error):
                c.close()

    def __enter__(self) -> JobStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- writes --------------------------------------------------------------------------------
    def insert(
        self,
        *,
        job_id: str,
        cell: str,
        kind: str,
        via: str,
        body_hash: str,
        body: bytes,
        events: Sequence[Event],
        planned_duration_s: float | None = None,
        points: int | None = None,
    ) -> None:
        """Journal a newly accepted job and its first events in one transaction."""
        if not events:
            raise ValueError("a new job needs at least its 'accepted' event")
        last = events[-1]
        try:
            with self._tx() as conn:
                conn.execute(
                    "INSERT INTO jobs (job_id, cell, kind, state, via, body_hash, body, planned_duration_s,"
                    " points, last_seq, submitted_t, updated_t) VALUES (?,?,?,?,?,?,?,?,?,?,?,?)",
                    (
                        job_id,
                        cell,
                        kind,
                        last.state.value,
                        via,
                        body_hash,
                        body,
                        planned_duration_s,
                        points,
                        last.seq,
                        events[0].t,
                        last.t,
                    ),
                )
                self._insert_events(conn, events)
        except sqlite3.Error as exc:
            raise StoreError(f"cannot journal job {job_id!r}: {exc}") from exc

    def append(self, event: Event, updates: Mapping[str, Any] | None = None) -> None:
        """Journal one event and the job row changes it brings (state, last_seq and `updates`)."""
        sets = ["state = ?", "last_seq = ?", "updated_t = ?"]
        args: list[Any] = [event.state.value, event.seq, event.t]
        for key, value in (updates or {}).items():
            if key not in _UPDATABLE:
                raise ValueError(f"column {key!r} cannot be updated")
            sets.append(f"{key} = ?")
            args.append(_dumps(value) if key in _JSON_COLUMNS and value is not None else value)
        try:
            with self._tx() as conn:
                self._insert_events(conn, [event])
                cur = conn.execute(
                    f"UPDATE jobs SET {', '.join(sets)} WHERE job_id = ?", (*args, event.job_id)
                )
                if cur.rowcount != 1:
                    raise StoreError(f"job {event.job_id!r} is not in the store")
        except sqlite3.Error as exc:
            raise StoreError(
                f"cannot journal event {event.type.value!r} of job {event.job_id!r}: {exc}"
            ) from exc

    @staticmethod
    def _insert_events(conn: sqlite3.Connection, events: Sequence[Event]) -> None:
        conn.executemany(
            "INSERT INTO events (job_id, seq, type, t, state, data) VALUES (?,?,?,?,?,?)",
            [(e.job_id, e.seq, e.type.value, e.t, e.state.value, _dumps(dict(e.data))) for e in events],
        )

    # -- reads ---------------------------------------------------------------------------------
    @staticmethod
    def _record(row: Sequence[Any]) -> JobRecord:
        return JobRecord(
            number=int(row[0]),
            job_id=row[1],
            cell=row[2],
            kind=row[3],
            state=JobState(row[4]),
            via=row[5],
            body_hash=row[6],
            planned_duration_s=row[7],
            points=row[8],
            progress=float(row[9]),
            error=_loads(row[10]),
            report=_loads(row[11]),
            last_seq=int(row[12]),
            submitted_t=float(row[13]),
            started_t=row[14],
            finished_t=row[15],
            updated_t=float(row[16]),
        )

    def get(self, job_id: str) -> JobRecord | None:
        row = self._conn().execute(f"SELECT {_COLUMNS} FROM jobs WHERE job_id = ?", (job_id,)).fetchone()
        return self._record(row) if row is not None else None

    def body(self, job_id: str) -> bytes | None:
        row = self._conn().execute("SELECT body FROM jobs WHERE job_id = ?", (job_id,)).fetchone()
        return bytes(row[0]) if row is not None else None

    def list_jobs(
        self,
        *,
        states: Collection[JobState] | None = None,
        limit: int | None = 100,
        cell: str | None = None,
        oldest_first: bool = False,
    ) -> list[JobRecord]:
        """Jobs, newest first (or oldest first), optionally only those in `states` / of `cell`."""
        where: list[str] = []
        args: list[Any] = []
        if states is not None:
            where.append(f"state IN ({','.join('?' * len(states))})" if states else "0")
            args.extend(s.value for s in states)
        if cell is not None:
            where.append("cell = ?")
            args.append(cell)
        sql = f"SELECT {_COLUMNS} FROM jobs"
        if where:
            sql += " WHERE " + " AND ".join(where)
        sql += " ORDER BY number " + ("ASC" if oldest_first else "DESC")
        if limit is not None:
            sql += " LIMIT ?"
            args.append(int(limit))
        return [self._record(r) for r in self._conn().execute(sql, args).fetchall()]

    def unfinished(self) -> list[JobRecord]:
        """Jobs that were queued or running (oldest first): after a crash, these need SERVICE_RESTART."""
        return self.list_jobs(
            states=(JobState.QUEUED, JobState.RUNNING, JobState.CANCELLING), limit=None, oldest_first=True
        )

    def events(self, job_id: str, after_seq: int = 0) -> list[Event]:
        rows = (
            self._conn()
            .execute(
                "SELECT seq, type, t, state, data FROM events WHERE job_id = ? AND seq > ? ORDER BY seq",
                (job_id, after_seq),
            )
            .fetchall()
        )
        return [
            Event(
                job_id=job_id,
                seq=int(r[0]),
                type=EventType(r[1]),
                t=float(r[2]),
                state=JobState(r[3]),
                data=json.loads(r[4]),
            )
            for r in rows
        ]

    def count(self) -> int:
        return int(self._conn().execute("SELECT COUNT(*) FROM jobs").fetchone()[0])


class ServiceLock:
    """An exclusive advisory lock (flock) on `<store>-lock`: one service per journal file.

    The file is removed on release; after a crash a stale file stays but holds no lock (the kernel
    dropped it with the process), so the next service starts normally."""

    def __init__(self, store_path: str | os.PathLike[str]):
        self.store_path = Path(store_path)
        self.path = Path(f"{os.fspath(store_path)}-lock")
        self._fd: int | None = None

    def acquire(self) -> ServiceLock:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise StoreError(
                f"job store {self.store_path} is in use by another service (lock {self.path} is held)"
            ) from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            with suppress(OSError):
                self.path.unlink()  # while still holding the lock: no one else can be using it
            try:
                fcntl.flock(self._fd, fcntl.LOCK_UN)
            finally:
                os.close(self._fd)
                self._fd = None

    def __enter__(self) -> ServiceLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()
