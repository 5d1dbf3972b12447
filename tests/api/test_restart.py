"""Kill the service mid-job (SIGKILL, a subprocess running `pvt serve` on the FakeBackend), restart it:
every accepted job is accounted for, the interrupted ones as SERVICE_RESTART."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from streamer.api.client import MotionClient
from streamer.api.errors import JobFailedError
from streamer.api.model import JobState
from tests.api.conftest import free_port
from tests.api.fakes import timed_job
from tests.api.helpers import wait_for

ROOT = Path(__file__).resolve().parents[2]


def start_service(config: Path, port: int, *extra: str, env: dict[str, str] | None = None) -> subprocess.Popen[str]:
    cmd = [
        sys.executable,
        "-m",
        "streamer.cli.serve",
        "--config",
        str(config),
        "--listen",
        f"tcp/127.0.0.1:{port}",
        "--backend",
        "tests.api.fakes:open_fake_backend",
        "--log-level",
        "WARNING",
        *extra,
    ]
    env = {**os.environ, **(env or {}), "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    assert proc.stdout is not None
    line = proc.stdout.readline()  # "pvt serve: cell 'demo' ready on ..."
    if "ready" not in line:
        proc.kill()
        raise AssertionError(f"service did not start: {line!r} {proc.stderr.read() if proc.stderr else ''}")
    return proc


def stop(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.wait(timeout=10)


@pytest.fixture
def cell_config(tmp_path: Path) -> Path:
    config = tmp_path / "demo.toml"
    shutil.copy(ROOT / "configs" / "demo.toml", config)
    return config


def test_sigkill_mid_job_then_restart_reports_service_restart(cell_config: Path, tmp_path: Path) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    # the journal's default place is the user's state directory: this test's own
    state = {"XDG_STATE_HOME": str(tmp_path / "state")}
    beside_config = set(cell_config.parent.iterdir())
    proc = start_service(cell_config, port, env=state)
    try:
        with MotionClient(connect=endpoint, cell="demo", timeout=10) as client:
            client.wait_for_service(timeout=10)
            done = client.submit(timed_job(0.05), job_id="finished-before")
            assert done.wait(timeout=10).state == JobState.DONE
            running = client.submit(timed_job(30.0), job_id="running-at-kill")
            queued = [client.submit(timed_job(1.0), job_id=f"queued-{i}") for i in range(2)]
            for ev in running.events(timeout=10):
                if ev.type == "running":
                    break
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=10)
            wait_for(lambda: client.cells(timeout=0.3) == [], timeout=10, what="liveliness token gone")

            proc = start_service(cell_config, port, env=state)
            client.wait_for_service(timeout=15)
            for jid in ("running-at-kill", "queued-0", "queued-1"):
                with pytest.raises(JobFailedError) as info:
                    client.job(jid).wait(timeout=10)
                assert info.value.code == "SERVICE_RESTART", jid
            hist = [e.type for e in client.job("running-at-kill").events(timeout=10)]
            assert hist[:4] == ["accepted", "planned", "priming", "running"] and hist[-1] == "failed"
            assert [e.type for e in queued[0].history()] == ["accepted", "planned", "failed"]
            assert client.job("finished-before").status().state == JobState.DONE
            # the restarted service works
            assert (
                client.submit(timed_job(0.05), job_id="after-restart").wait(timeout=10).state == JobState.DONE
            )

        # the journal and the recordings are in the state directory, nothing was written beside the config
        assert (tmp_path / "state" / "pvt" / "demo.jobs.sqlite").exists()
        assert set(cell_config.parent.iterdir()) == beside_config | {tmp_path / "state"}
        # `pvt jobs` (reading the journal of the config's cell) lists every accepted job
        out = subprocess.run(
            [sys.executable, "-m", "streamer.cli.jobs", "--config", str(cell_config), "--json"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=60,
            check=True,
            env={**os.environ, **state},
        )
        listed = {j["job_id"]: j for j in json.loads(out.stdout)}
        assert set(listed) == {"finished-before", "running-at-kill", "queued-0", "queued-1", "after-restart"}
        assert listed["running-at-kill"]["error"]["code"] == "SERVICE_RESTART"
        assert listed["finished-before"]["state"] == "done"

        # a second service on the same journal is refused
        second = subprocess.run(
            [
                sys.executable,
                "-m",
                "streamer.cli.serve",
                "--config",
                str(cell_config),
                "--listen",
                f"tcp/127.0.0.1:{free_port()}",
                "--backend",
                "tests.api.fakes:open_fake_backend",
            ],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=60,
            env={**os.environ, **state},
        )
        assert second.returncode == 2 and "in use" in second.stderr

        # SIGTERM is a clean stop
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=20) == 0
    finally:
        stop(proc)
