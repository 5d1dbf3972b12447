"""The SQLite journal and the job state machine."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from streamer.api.model import TRANSITIONS, Event, EventType, InvalidTransition, JobState, transition
from streamer.api.store import JobStore, ServiceLock, StoreError, journal_path, state_dir


def ev(job_id: str, seq: int, etype: EventType, state: JobState, t: float = 1.0, **data: object) -> Event:
    return Event(job_id, seq, etype, t, state, dict(data))


def test_insert_append_read_back(tmp_path: Path) -> None:
    with JobStore(tmp_path / "j.db") as store:
        store.insert(
            job_id="a",
            cell="demo",
            kind="path",
            via="query",
            body_hash="h",
            body=b"\x80",
            events=[
                ev("a", 1, EventType.ACCEPTED, JobState.QUEUED),
                ev("a", 2, EventType.PLANNED, JobState.QUEUED, planned_duration_s=1.5),
            ],
            planned_duration_s=1.5,
            points=10,
        )
        rec = store.get("a")
        assert rec is not None and rec.state == JobState.QUEUED and rec.last_seq == 2 and rec.points == 10
        store.append(ev("a", 3, EventType.PRIMING, JobState.RUNNING, t=2.0), {"started_t": 2.0})
        store.append(
            ev("a", 4, EventType.FAILED, JobState.FAILED, t=3.0, error={"code": "X"}),
            {
                "error": {"code": "X", "message": "m"},
                "report": {"result": "failed", "v": float("nan")},
                "finished_t": 3.0,
            },
        )
        rec = store.get("a")
        assert rec is not None and rec.state == JobState.FAILED and rec.error == {"code": "X", "message": "m"}
        assert rec.report == {"result": "failed", "v": None}
        assert [e.seq for e in store.events("a")] == [1, 2, 3, 4]
        assert [e.type for e in store.events("a", after_seq=2)] == [EventType.PRIMING, EventType.FAILED]
        assert store.events("a")[1].data == {"planned_duration_s": 1.5}
        assert store.body("a") == b"\x80"
        assert store.unfinished() == []
        with pytest.raises(StoreError):
            store.append(ev("zzz", 1, EventType.PLANNED, JobState.QUEUED))
        with pytest.raises(StoreError):  # duplicate seq
            store.append(ev("a", 4, EventType.DONE, JobState.DONE))


def test_list_order_filters_and_unfinished(tmp_path: Path) -> None:
    with JobStore(tmp_path / "j.db", synchronous="NORMAL") as store:
        for i, state in enumerate([JobState.QUEUED, JobState.RUNNING, JobState.DONE]):
            jid = f"j{i}"
            events = [ev(jid, 1, EventType.ACCEPTED, JobState.QUEUED)]
            store.insert(
                job_id=jid, cell="demo", kind="move", via="put", body_hash="h", body=b"", events=events
            )
            if state != JobState.QUEUED:
                store.append(ev(jid, 2, EventType.PRIMING, JobState.RUNNING))
            if state == JobState.DONE:
                store.append(ev(jid, 3, EventType.DONE, JobState.DONE))
        assert [r.job_id for r in store.list_jobs()] == ["j2", "j1", "j0"]
        assert [r.job_id for r in store.list_jobs(limit=1)] == ["j2"]
        assert [r.job_id for r in store.unfinished()] == ["j0", "j1"]
        assert [r.job_id for r in store.list_jobs(states=[JobState.DONE])] == ["j2"]
        assert store.list_jobs(states=[]) == []
        assert store.count() == 3
    ro = JobStore(tmp_path / "j.db", readonly=True)
    assert ro.count() == 3
    ro.close()


def test_store_is_wal_and_versioned(tmp_path: Path) -> None:
    JobStore(tmp_path / "j.db").close()
    conn = sqlite3.connect(tmp_path / "j.db")
    assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    conn.execute("PRAGMA user_version=99")
    conn.close()
    with pytest.raises(StoreError):
        JobStore(tmp_path / "j.db")
    with pytest.raises(StoreError):
        JobStore(tmp_path / "missing.db", readonly=True)
    assert not (tmp_path / "missing.db").exists()


def test_service_lock_is_exclusive(tmp_path: Path) -> None:
    with ServiceLock(tmp_path / "j.db"), pytest.raises(StoreError, match="in use"):
        ServiceLock(tmp_path / "j.db").acquire()
    with ServiceLock(tmp_path / "j.db") as lock:
        assert lock.path.exists()
    assert not lock.path.exists()  # removed on release


def test_journals_live_in_a_data_directory_not_beside_the_config(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    assert state_dir() == tmp_path / "state" / "pvt"
    assert journal_path("line1") == tmp_path / "state" / "pvt" / "line1.jobs.sqlite"
    assert journal_path("line1", tmp_path / "data") == tmp_path / "data" / "line1.jobs.sqlite"  # --store DIR
    assert journal_path("line1", tmp_path / "j.db") == tmp_path / "j.db"  # --store FILE.db/.sqlite
    monkeypatch.delenv("XDG_STATE_HOME")
    assert state_dir() == Path.home() / ".local" / "state" / "pvt"


def test_transition_table_rejects_everything_else() -> None:
    states: list[JobState | None] = [None, *JobState]
    for s in states:
        for e in EventType:
            if (s, e) in TRANSITIONS:
                assert transition(s, e) == TRANSITIONS[(s, e)]
            else:
                with pytest.raises(InvalidTransition):
                    transition(s, e)
    for s in (JobState.DONE, JobState.FAILED, JobState.CANCELLED):
        assert s.final and all((s, e) not in TRANSITIONS for e in EventType)


@given(st.lists(st.sampled_from(list(EventType)), max_size=12))
def test_any_event_sequence_never_leaves_a_final_state(events: list[EventType]) -> None:
    state: JobState | None = None
    for e in events:
        try:
            new = transition(state, e)
        except InvalidTransition:
            continue
        assert state is None or not state.final
        state = new
