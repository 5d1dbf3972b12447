"""`pvt submit --wait` says what happened with its exit status (issue 14, section 3): 0 done, 1 failed,
2 rejected (never accepted), 3 cancelled, 4 its own --timeout ran out while the job still waits or runs
(the job goes on), 5 no service or the service went away (found out at once from its liveliness
token). It waits as long as the job is queued. And `pvt submit` and `client.submit(path)` treat a job
file's job_id alike; job ids and cell names follow one rule everywhere."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from streamer.api.errors import MotionError
from streamer.api.model import JobState
from streamer.api.payload import pack
from tests.api.conftest import Served, free_port
from tests.api.fakes import timed_job
from tests.api.helpers import raw_get, raw_session, wait_for
from tests.cli.conftest import ROOT, cli_env, flat, pvt, start_pvt

Serve = Callable[..., Served]


def job_file(tmp_path: Path, job: dict[str, object], name: str = "job.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(job), encoding="utf-8")
    return path


def test_wait_keeps_waiting_while_the_job_is_queued_and_exits_0_when_done(serve: Serve, tmp_path: Path) -> None:
    served = serve()
    with served.client() as client:
        first = client.submit(timed_job(4.0, name="long"), job_id="ahead")
        t0 = time.monotonic()
        # the job waits about 4 s in the queue: no TIMEOUT, no "rejected"
        out = pvt("submit", str(job_file(tmp_path, timed_job(0.2))), "--connect", served.endpoint, "--wait",
                  "--job-id", "behind", "--connect-timeout", "2")
        assert out.returncode == 0, out.stderr
        assert time.monotonic() - t0 > 3.0
        assert first.status().state == JobState.DONE and client.job("behind").status().state == JobState.DONE
        assert "job behind: done" in flat(out.stderr)


def test_timeout_is_its_own_exit_code_and_the_job_goes_on(serve: Serve, tmp_path: Path) -> None:
    served = serve()
    with served.client() as client:
        client.submit(timed_job(3.0, name="long"), job_id="ahead")
        t0 = time.monotonic()
        out = pvt("submit", str(job_file(tmp_path, timed_job(0.2))), "--connect", served.endpoint, "--wait",
                  "--timeout", "1", "--job-id", "still-queued")
        assert out.returncode == 4, out.stderr
        assert time.monotonic() - t0 < 10.0
        said = flat(out.stderr)
        assert "still waiting" in said and "is still queued after 1 s" in said and "not cancelled" in said
        assert client.job("still-queued").wait(timeout=10).state == JobState.DONE  # it went on


def test_rejected_failed_and_cancelled_have_their_own_exit_codes(serve: Serve, tmp_path: Path) -> None:
    served = serve(fail_code="FOLLOWING_ERROR")
    bad = pvt("submit", str(job_file(tmp_path, {"kind": "path", "axes": ["j1"], "waypoints": [["x"]]})),
              "--connect", served.endpoint, "--wait")
    assert bad.returncode == 2 and "rejected: TYPE at waypoints[0][0]" in flat(bad.stderr)
    failed = pvt("submit", str(job_file(tmp_path, timed_job(0.2))), "--connect", served.endpoint, "--wait")
    assert failed.returncode == 1 and "failed: FOLLOWING_ERROR" in flat(failed.stderr)
    served.backend.reset()
    with served.client() as client:
        proc = start_pvt("submit", str(job_file(tmp_path, timed_job(5.0))), "--connect", served.endpoint, "--wait",
                         "--job-id", "to-cancel")
        wait_for(lambda: client.job("to-cancel").status().state == JobState.RUNNING if _exists(client, "to-cancel")
                 else False, timeout=20, what="the job runs")
        client.job("to-cancel").cancel()
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 3, err
    assert "job to-cancel: cancelled" in flat(err)


def _exists(client: object, job_id: str) -> bool:
    try:
        client.job(job_id).status()  # type: ignore[attr-defined]
        return True
    except MotionError:
        return False


def test_the_service_going_away_is_seen_at_once(tmp_path: Path) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    serve_env = cli_env(XDG_STATE_HOME=str(tmp_path / "state"))
    server = subprocess.Popen(
        [sys.executable, "-m", "streamer.cli", "serve", "--config", str(ROOT / "configs" / "demo.toml"), "--listen",
         endpoint, "--backend", "tests.api.fakes:open_fake_backend", "--log-level", "WARNING"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=serve_env)
    try:
        assert server.stdout is not None
        assert "ready" in server.stdout.readline()
        proc = start_pvt("submit", str(job_file(tmp_path, timed_job(30.0))), "--connect", endpoint, "--wait",
                         "--job-id", "orphan")
        from streamer.api.client import MotionClient

        with MotionClient(connect=endpoint, cell="demo") as client:
            wait_for(lambda: _exists(client, "orphan") and client.job("orphan").status().state == JobState.RUNNING,
                     timeout=20, what="the job runs")
        server.send_signal(signal.SIGKILL)
        server.wait(timeout=10)
        t_kill = time.monotonic()
        _, err = proc.communicate(timeout=30)
        assert proc.returncode == 5, err
        assert time.monotonic() - t_kill < 5.0  # not a 30 s TIMEOUT
        said = flat(err)
        assert "service gone: SERVICE_GONE" in said and "went away while job 'orphan' was running" in said
        assert "TIMEOUT" not in said
    finally:
        if server.poll() is None:
            server.kill()
            server.wait(timeout=10)


def test_no_service_is_not_a_rejection(tmp_path: Path) -> None:
    out = pvt("submit", str(job_file(tmp_path, timed_job(0.2))), "--connect", f"tcp/127.0.0.1:{free_port()}",
              "--connect-timeout", "0.5")
    assert out.returncode == 5 and "no cell is up there" in flat(out.stderr)


def test_a_file_submitted_twice_runs_twice_with_pvt_submit_and_the_client_alike(serve: Serve) -> None:
    served = serve()
    job = ROOT / "configs" / "jobs" / "move.toml"
    for _ in range(2):
        assert pvt("submit", str(job), "--connect", served.endpoint, "--wait").returncode == 0
    with served.client() as client:
        runs = [client.submit(job) for _ in range(2)]
        assert all(r.accepted["existing"] is False for r in runs)
        for r in runs:
            assert r.wait(timeout=10).state == JobState.DONE
        ids = [r.job_id for r in served.store.list_jobs()]
        assert len(ids) == 4 and len(set(ids)) == 4 and all(i.startswith("demo-move-") for i in ids)
        # an exact id (--job-id / job_id=) is idempotent: the way to resubmit without moving twice
        exact = client.submit(job, job_id="exactly-once")
        again = client.submit(job, job_id="exactly-once")
        assert exact.accepted["existing"] is False and again.accepted["existing"] is True
        out = pvt("submit", str(job), "--connect", served.endpoint, "--job-id", "exactly-once")
        assert out.returncode == 0 and "(existing)" in flat(out.stderr)
        assert served.store.count() == 5


BAD_ID = "pick:1@station+A"
RULE = "names are 1-64 characters of letters, digits, '_', '-' and '.', not starting with '.'"


def test_one_rule_for_job_ids_everywhere(serve: Serve, tmp_path: Path) -> None:
    served = serve()
    body = {"kind": "move", "axes": ["j1"], "target": [0.1], "job_id": BAD_ID}
    path = job_file(tmp_path, body, "bad-id.json")
    plan = pvt("plan", str(path))
    submit = pvt("submit", str(path), "--connect", served.endpoint)
    explicit = pvt("submit", str(job_file(tmp_path, {"kind": "move", "axes": ["j1"], "target": [0.1]}, "ok.json")),
                   "--connect", served.endpoint, "--job-id", BAD_ID)
    for out in (plan, submit, explicit):
        assert out.returncode == 2, out.stderr
        said = flat(out.stderr)
        assert f"SCHEMA at job_id: job_id '{BAD_ID}' contains '+', ':', '@', which is not allowed" in said, said
        assert RULE in said
    with served.client() as client:
        for call in (lambda: client.submit(path), lambda: client.submit(body), lambda: client.job(BAD_ID)):
            with pytest.raises(MotionError) as info:
                call()
            assert info.value.code == "SCHEMA" and RULE in info.value.message
    session = raw_session(served.endpoint)
    try:
        kind, err = raw_get(session, "pvt/demo/submit", pack({**body, "job_id": BAD_ID}))
    finally:
        session.close()
    assert kind == "err" and err["code"] == "SCHEMA" and RULE in err["message"]
    assert served.store.count() == 0


def test_one_rule_for_cell_names(tmp_path: Path) -> None:
    text = (ROOT / "configs" / "demo.toml").read_text(encoding="utf-8").replace('name = "demo"', 'name = "my cell"', 1)
    config = tmp_path / "my-cell.toml"
    config.write_text(text, encoding="utf-8")
    job = ROOT / "configs" / "jobs" / "move.toml"
    env = cli_env(XDG_STATE_HOME=str(tmp_path / "state"))
    outs = [
        pvt("plan", str(job), "--config", str(config), env=env),
        pvt("demo", "--fast", "--config", str(config), "--out", str(tmp_path / "out"), env=env),
        pvt("serve", "--config", str(config), "--listen", f"tcp/127.0.0.1:{free_port()}", env=env),
        pvt("status", "--cell", "my cell", "--connect-timeout", "0.5", env=env),
    ]
    for out in outs:
        said = flat(out.stdout + out.stderr)
        assert out.returncode == 2, said
        assert "'my cell' contains ' ', which is not allowed" in said and RULE in said, said
        assert "Traceback" not in said
    assert not (tmp_path / "state").exists()  # the service refused before it made any state


def test_the_run_suffix_leaves_the_name_whole(serve: Serve, tmp_path: Path) -> None:
    served = serve()
    long_name = "n" * 56
    path = job_file(tmp_path, {"kind": "move", "axes": ["j1"], "target": [0.1], "job_id": long_name})
    out = pvt("submit", str(path), "--connect", served.endpoint)
    assert out.returncode == 2 and "as a name for runs" in flat(out.stderr) and "55" in out.stderr
