"""The job service on the FakeBackend, through Zenoh: lifecycle, admission, cancel, put, telemetry."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from planner.config import CellConfig
from streamer.api import keys
from streamer.api.backend import CancelToken, Planned
from streamer.api.client import MotionClient
from streamer.api.errors import JobFailedError, MotionError
from streamer.api.model import Event, EventType, JobState
from streamer.api.payload import encode_submission
from streamer.api.service import ServiceOptions
from streamer.api.store import JobStore
from tests.api.conftest import Served
from tests.api.fakes import FakeBackend, timed_job
from tests.api.helpers import Collector, raw_get, raw_session, wait_for

Serve = Callable[..., Served]

ORDER = ["accepted", "planned", "priming", "running"]


def check_order(events: list[str]) -> None:
    """accepted, planned, priming, running..., (cancelling... after a cancel), then exactly one final event."""
    assert events[:4] == ORDER, events
    middle = events[4:-1]
    first_cancelling = middle.index("cancelling") if "cancelling" in middle else len(middle)
    assert all(e == "running" for e in middle[:first_cancelling]), events
    assert all(e == "cancelling" for e in middle[first_cancelling:]), events
    assert events[-1] in ("done", "failed", "cancelled")


def test_submit_runs_and_events_arrive_in_order(serve: Serve) -> None:
    served = serve()
    with served.client() as client:
        client.wait_for_service(timeout=5)
        job = client.submit(timed_job(0.3, axes=["j1", "j2"], name="first"))
        assert job.accepted["state"] == "queued" and job.accepted["existing"] is False
        assert job.planned_duration_s == pytest.approx(0.3) and job.points == 3
        events = list(job.events(timeout=5))
        assert [e.seq for e in events] == list(range(1, len(events) + 1))
        check_order([e.type for e in events])
        assert events[-1].type == "done" and events[-1].data["report"]["result"] == "done"
        ts = [e.t for e in events]
        assert ts == sorted(ts)
        progress = [e.progress for e in events if e.type == "running"]
        assert progress[0] == 0.0 and progress[-1] == 1.0 and progress == sorted(progress)
        status = job.wait(timeout=5)
        assert status.state == JobState.DONE and status.progress == 1.0 and status.report is not None
        assert [j.job_id for j in client.jobs()] == [job.job_id]
        assert [e.seq for e in job.history()] == [e.seq for e in events]
    assert served.backend.executed == ["first"]


def test_accepted_job_is_journalled_before_the_reply(serve: Serve) -> None:
    served = serve()
    with served.client() as client:
        served.backend.hold.clear()
        job = client.submit(timed_job(0.1), job_id="journal-me")
        rec = served.store.get("journal-me")  # the reply came back: the row must already be there
        assert rec is not None and rec.state in (JobState.QUEUED, JobState.RUNNING) and rec.last_seq >= 2
        assert [e.type for e in served.store.events("journal-me")][:2] == [
            EventType.ACCEPTED,
            EventType.PLANNED,
        ]
        served.backend.hold.set()
        job.wait(timeout=5)


def test_idempotent_resubmit_and_conflict(serve: Serve) -> None:
    served = serve()
    with served.client() as client:
        job = client.submit(timed_job(0.1, name="once"), job_id="same-id")
        job.wait(timeout=5)
        again = client.submit(timed_job(0.1, name="once"), job_id="same-id")
        assert again.accepted["existing"] is True and again.accepted["state"] == "done"
        assert again.accepted["planned_duration_s"] == pytest.approx(0.1)
        with pytest.raises(MotionError) as info:
            client.submit(timed_job(0.2, name="once"), job_id="same-id")
        assert info.value.code == "CONFLICT" and info.value.path == "job_id"
    assert served.backend.executed == ["once"]


def test_busy_when_the_queue_is_full(serve: Serve) -> None:
    served = serve(options=ServiceOptions(queue_limit=2))
    served.backend.hold.clear()  # the first job blocks in execute()
    with served.client() as client:
        first = client.submit(timed_job(0.05, name="a"))
        assert served.backend.started.wait(0.1) is False  # held before start
        wait_for(lambda: served.service.running_job == first.job_id, what="first job running")
        queued = [client.submit(timed_job(0.05, name=n)) for n in ("b", "c")]
        assert [q.accepted["queue_position"] for q in queued] == [1, 2]
        with pytest.raises(MotionError) as info:
            client.submit(timed_job(0.05, name="d"))
        assert info.value.code == "BUSY"
        # an idempotent resubmit of a queued job is still answered while busy
        assert client.submit(timed_job(0.05, name="b"), job_id=queued[0].job_id).accepted["existing"] is True
        served.backend.hold.set()
        for j in [first, *queued]:
            assert j.wait(timeout=5).state == JobState.DONE
    assert served.backend.executed == ["a", "b", "c"]


def test_fault_makes_the_cell_not_ready_until_reset(serve: Serve) -> None:
    served = serve(fail_code="FOLLOWING_ERROR")
    with served.client() as client:
        job = client.submit(timed_job(0.2, name="faulty"))
        with pytest.raises(JobFailedError) as info:
            job.wait(timeout=5)
        assert info.value.code == "FOLLOWING_ERROR" and info.value.detail == {"node": 3}
        assert info.value.status is not None and info.value.status.error["node"] == 3
        events = [e.type for e in job.events()]
        check_order(events)
        assert events[-1] == "failed"
        with pytest.raises(MotionError) as info2:
            client.submit(timed_job(0.1, name="refused"))
        assert info2.value.code == "NOT_READY" and "fake fault" in info2.value.message
        assert client.service_status()["ready"] is False
        assert client.reset() == {"cell": "demo", "ready": True, "reason": ""}
        assert client.submit(timed_job(0.1, name="after")).wait(timeout=5).state == JobState.DONE
    assert served.backend.executed == ["faulty", "after"]


def test_queued_jobs_fail_not_ready_after_a_fault(serve: Serve) -> None:
    served = serve(fail_code="NODE_LOST")
    served.backend.hold.clear()
    with served.client() as client:
        first = client.submit(timed_job(0.2, name="faulty"))
        second = client.submit(timed_job(0.2, name="queued"))
        served.backend.hold.set()
        with pytest.raises(JobFailedError) as a:
            first.wait(timeout=5)
        with pytest.raises(JobFailedError) as b:
            second.wait(timeout=5)
        assert a.value.code == "NODE_LOST" and b.value.code == "NOT_READY"
        assert [e.type for e in second.events()] == ["accepted", "planned", "failed"]
    assert served.backend.executed == ["faulty"]


def test_cancel_running_and_queued_jobs(serve: Serve) -> None:
    served = serve()
    with served.client() as client:
        running = client.submit(timed_job(5.0, name="long"))
        queued = client.submit(timed_job(5.0, name="next"))
        assert served.backend.started.wait(5)
        st = queued.cancel()
        assert st.state == JobState.CANCELLED and st.raw["cancel_requested"] is True
        assert [e.type for e in queued.events(timeout=5)] == ["accepted", "planned", "cancelled"]
        t0 = time.monotonic()
        st = running.cancel()
        assert st.raw["cancel_requested"] is True and st.raw["held"] is True
        final = running.wait(timeout=5)
        assert final.state == JobState.CANCELLED and time.monotonic() - t0 < 2.0
        assert final.report is not None and final.report["result"] == "cancelled"
        events = list(running.events())
        check_order([e.type for e in events])
        assert "cancelling" in [e.type for e in events]
        again = running.cancel()  # cancelling a finished job is harmless
        assert again.state == JobState.CANCELLED and again.raw["cancel_requested"] is False
        with pytest.raises(MotionError) as info:
            client.job("no-such-job").cancel()
        assert info.value.code == "NOT_FOUND"
    assert served.backend.executed == ["long"]


def test_put_submission_runs_and_put_rejections_are_published(serve: Serve) -> None:
    served = serve()
    with served.client() as client:
        job = client.submit_put(timed_job(0.1, name="by-put"), job_id="put-1")
        assert job.wait(timeout=5).state == JobState.DONE
        rec = served.store.get("put-1")
        assert rec is not None and rec.via == "put"
        events = [e.type for e in job.events()]
        check_order(events)
        rejected = Collector(client.session, keys.rejected("demo"))
        bad = client.submit_put({"kind": "path", "axes": ["j1"], "waypoints": [["x"]]}, job_id="put-bad")
        with pytest.raises(MotionError) as info:
            bad.wait(timeout=5)
        assert info.value.code == "TYPE" and info.value.path == "waypoints[0][0]"
        msg = rejected.until(lambda m: m["job_id"] == "put-bad")
        assert msg["type"] == "rejected" and msg["error"]["code"] == "TYPE"
        client.session.put(keys.submit("demo"), b"\xc1garbage")  # no job id at all
        msg = rejected.until(lambda m: m["job_id"] is None)
        assert msg["error"]["code"] == "MALFORMED_PAYLOAD"
        client.session.put(keys.submit("demo"), encode_submission(timed_job(0.1)))  # put needs a job_id
        msg = rejected.until(lambda m: m["error"]["code"] == "SCHEMA")
        assert msg["error"]["path"] == "job_id"
        # put with a known job_id and a different body: CONFLICT on the rejected key only
        client.session.put(keys.submit("demo"), encode_submission(timed_job(0.3), "put-1"))
        msg = rejected.until(lambda m: m["job_id"] == "put-1")
        assert msg["error"]["code"] == "CONFLICT"
        rejected.close()
    assert served.backend.executed == ["by-put"]


@pytest.mark.wallclock  # a rate: judged alone, not beside the suite on every core
def test_telemetry_is_published_at_the_configured_rate(serve: Serve) -> None:
    served = serve(options=ServiceOptions(telemetry_hz=50.0))
    session = raw_session(served.endpoint)
    try:
        col = Collector(session, keys.telemetry("demo"))
        first = col.until(lambda m: True, timeout=5)
        t0 = time.monotonic()
        col.until(lambda m: m["seq"] >= first["seq"] + 25, timeout=5)
        rate = 25 / (time.monotonic() - t0)
        assert 30 < rate < 70, rate
        msg = col.all[-1]
        assert msg["cell"] == "demo" and msg["ready"] is True and msg["job_id"] is None
        assert [a["name"] for a in msg["axes"]] == [a.name for a in served.backend.cell.axes]
        assert set(msg["axes"][0]) >= {"name", "position", "velocity", "fifo_fill", "state"}
        col.close()
    finally:
        session.close()


def test_default_telemetry_rate_comes_from_the_config(serve: Serve) -> None:
    assert serve().service.telemetry_hz == 20.0


def test_liveliness_token_appears_and_vanishes(serve: Serve, tmp_path: Path, demo_cell: CellConfig) -> None:
    served = serve()
    with served.client() as client:
        client.wait_for_service(timeout=5)
        assert client.cells() == ["demo"]
        served.service.close()
        wait_for(lambda: client.cells(timeout=0.3) == [], what="token gone")
        with pytest.raises(MotionError) as info:
            client.wait_for_service(timeout=0.3)
        assert info.value.code == "TIMEOUT"
        with pytest.raises(MotionError) as info:
            client.jobs(timeout=0.5)
        assert info.value.code == "NO_SERVICE"


def test_wait_for_service_sees_a_service_that_starts_later(tmp_path: Path, demo_cell: CellConfig) -> None:
    import zenoh

    from streamer.api.service import JobService
    from streamer.api.zenoh_config import build_config
    from tests.api.conftest import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with MotionClient(connect=endpoint, cell="demo") as client:  # nothing listens yet
        result: list[BaseException | None] = []

        def waiter() -> None:
            try:
                client.wait_for_service(timeout=15)
                result.append(None)
            except BaseException as exc:
                result.append(exc)

        t = threading.Thread(target=waiter)
        t.start()
        time.sleep(0.3)
        session = zenoh.open(build_config(listen=[endpoint]))
        store = JobStore(tmp_path / "late.db")
        service = JobService(session, FakeBackend(demo_cell), store).start()
        try:
            t.join(timeout=20)
            assert result == [None]
            assert client.submit(timed_job(0.05)).wait(timeout=5).state == JobState.DONE
        finally:
            service.close()
            store.close()
            session.close()


def test_backend_exception_fails_the_job_internal(serve: Serve, demo_cell: CellConfig) -> None:
    class Exploding(FakeBackend):
        def execute(self, planned: Planned, emit: object, cancel: CancelToken) -> dict[str, object]:
            raise RuntimeError("boom")

    served = serve(backend=Exploding(demo_cell))
    with served.client() as client:
        with pytest.raises(JobFailedError) as info:
            client.submit(timed_job(0.1)).wait(timeout=5)
        assert info.value.code == "INTERNAL" and "boom" in info.value.message
        # the service keeps serving
        assert client.service_status()["ready"] is True


def test_bad_reports_become_internal_failures(serve: Serve, demo_cell: CellConfig) -> None:
    reports: list[object] = [{"result": "weird"}, {"result": "failed"}, "not a mapping"]

    class Odd(FakeBackend):
        def execute(self, planned: Planned, emit: object, cancel: CancelToken) -> object:  # type: ignore[override]
            return reports.pop(0)

    served = serve(backend=Odd(demo_cell))
    with served.client() as client:
        for _ in range(3):
            with pytest.raises(JobFailedError) as info:
                client.submit(timed_job(0.1)).wait(timeout=5)
            assert info.value.code == "INTERNAL"


def test_progress_is_throttled_but_first_and_last_kept(serve: Serve, demo_cell: CellConfig) -> None:
    class Chatty(FakeBackend):
        def execute(self, planned: Planned, emit, cancel: CancelToken):  # type: ignore[no-untyped-def]
            for i in range(1001):  # 1000 updates in ~0.2 s, some from another thread
                emit("running", {"progress": i / 1000, "i": i})
                if i % 100 == 0:
                    th = threading.Thread(target=emit, args=("running", {"progress": i / 1000, "i": i}))
                    th.start()
                    th.join()
                time.sleep(0.0002)
            emit("bogus", {})
            emit("priming", {})
            return {"result": "done"}

    served = serve(backend=Chatty(demo_cell), options=ServiceOptions(progress_hz=20))
    with served.client() as client:
        job = client.submit(timed_job(0.1))
        job.wait(timeout=10)
        running = [e for e in job.events() if e.type == "running"]
        assert running[0].progress == 0.0 and running[-1].progress == 1.0
        assert 2 <= len(running) <= 20, len(running)


def test_status_list_and_history_queries(serve: Serve) -> None:
    served = serve()
    with served.client() as client:
        jobs = [client.submit(timed_job(0.02, name=f"n{i}"), job_id=f"job-{i}") for i in range(3)]
        for j in jobs:
            j.wait(timeout=5)
        listed = client.jobs()
        assert [s.job_id for s in listed] == ["job-2", "job-1", "job-0"]
        assert all(s.report is None for s in listed)  # lists are summaries
        assert [s.job_id for s in client.jobs(limit=1)] == ["job-2"]
        assert client.jobs(state="queued") == []
        assert len(client.jobs(state=["done", "failed"])) == 3
        st = client.job("job-1").status()
        assert st.state == JobState.DONE and st.report is not None and st.number == 2
        replay = list(client.job("job-0").events(timeout=5))
        assert [e.seq for e in replay] == list(range(1, len(replay) + 1)) and replay[-1].type == "done"
        session = client.session
        for selector, code in [
            (keys.jobs("demo") + "?limit=abc", "BAD_REQUEST"),
            (keys.jobs("demo") + "?limit=0", "BAD_REQUEST"),
            (keys.jobs("demo") + "?state=bogus", "BAD_REQUEST"),
            (keys.job("demo", "nope"), "NOT_FOUND"),
            (keys.job_events("demo", "nope"), "NOT_FOUND"),
            (keys.job_events("demo", "job-0") + "?after=x", "BAD_REQUEST"),
        ]:
            kind, msg = raw_get(session, selector)
            assert (kind, msg["code"]) == ("err", code), selector
        kind, msg = raw_get(session, "pvt/demo/jobs/*")  # a glob does not name one job
        assert kind == "err" and msg["code"] == "BAD_REQUEST"
        kind, msg = raw_get(session, "pvt/*/service")  # but the service status answers globs
        assert kind == "ok" and msg["cell"] == "demo" and msg["queue_limit"] == 16


def test_reset_is_refused_while_a_job_runs(serve: Serve) -> None:
    served = serve()
    with served.client() as client:
        job = client.submit(timed_job(3.0))
        assert served.backend.started.wait(5)
        with pytest.raises(MotionError) as info:
            client.reset()
        assert info.value.code == "BUSY"
        job.cancel()
        job.wait(timeout=5)


def test_close_fails_queued_jobs_and_cancels_the_running_one(serve: Serve) -> None:
    served = serve()
    with served.client() as client:
        running = client.submit(timed_job(10.0, name="r"))
        queued = client.submit(timed_job(10.0, name="q"))
        assert served.backend.started.wait(5)
        t0 = time.monotonic()
        served.service.close()
        assert time.monotonic() - t0 < 5
    r = served.store.get(running.job_id)
    q = served.store.get(queued.job_id)
    assert r is not None and r.state == JobState.CANCELLED
    assert q is not None and q.state == JobState.FAILED and q.error is not None
    assert q.error["code"] == "SERVICE_STOPPED"


def test_restart_recovery_in_process(serve: Serve, tmp_path: Path) -> None:
    """A journal with a running and a queued job (as a killed service leaves it) -> SERVICE_RESTART."""
    store_path = tmp_path / "crashed.db"
    with JobStore(store_path) as store:  # what a SIGKILLed service leaves behind
        for jid, running in (("was-running", True), ("was-queued", False)):
            store.insert(
                job_id=jid,
                cell="demo",
                kind="timed",
                via="query",
                body_hash="h",
                body=b"\x80",
                events=[
                    Event(jid, 1, EventType.ACCEPTED, 1.0, JobState.QUEUED, {}),
                    Event(jid, 2, EventType.PLANNED, 1.0, JobState.QUEUED, {}),
                ],
            )
            if running:
                store.append(Event(jid, 3, EventType.PRIMING, 2.0, JobState.RUNNING, {}))
    served = serve(store_path=store_path)
    with served.client() as client:
        for jid in ("was-running", "was-queued"):
            with pytest.raises(JobFailedError) as info:
                client.job(jid).wait(timeout=5)
            assert info.value.code == "SERVICE_RESTART"
        events = [e.type for e in client.job("was-running").events(timeout=5)]
        assert events == ["accepted", "planned", "priming", "failed"]
        assert [e.type for e in client.job("was-queued").events(timeout=5)] == [
            "accepted",
            "planned",
            "failed",
        ]
        assert served.service.counters["recovered"] == 2
        assert client.submit(timed_job(0.05)).wait(timeout=5).state == JobState.DONE


def test_submit_timeout_then_idempotent_resubmit_finds_the_job(serve: Serve) -> None:
    served = serve(plan_delay_s=0.6)
    with served.client() as client:
        with pytest.raises(MotionError) as info:
            client.submit(timed_job(0.05, name="slow-plan"), job_id="slow", timeout=0.2)
        assert info.value.code == "TIMEOUT"
        wait_for(lambda: served.store.get("slow") is not None, what="the job journalled anyway")
        again = client.submit(timed_job(0.05, name="slow-plan"), job_id="slow")
        assert again.accepted["existing"] is True
        assert again.wait(timeout=5).state == JobState.DONE
    assert served.backend.executed == ["slow-plan"]


def test_queued_jobs_are_planned_from_where_the_queue_leaves_the_axes(serve: Serve) -> None:
    served = serve()
    served.backend.hold.clear()
    with served.client() as client:
        a = client.submit({"kind": "move", "axes": ["j1", "j2"], "target": [0.5, -0.2]})
        b = client.submit({"kind": "move", "axes": ["j2", "j3"], "target": [0.1, 0.3]})
        c = client.submit({"kind": "move", "axes": ["j1"], "target": [0.0]})
        served.backend.hold.set()
        for j in (a, b, c):
            j.wait(timeout=5)
        d = client.submit({"kind": "move", "axes": ["j1"], "target": [0.2]})
        d.wait(timeout=5)
    assert served.backend.plan_starts == [
        None,  # nothing queued: the backend plans from the drives' positions
        {"j1": 0.5, "j2": -0.2},  # after a
        {"j1": 0.5, "j2": 0.1, "j3": 0.3},  # after a and b
        None,  # the queue ran empty
    ]
