"""`pvt halt` and `pvt submit --buffer/--lead-ms` as a user runs them: subprocesses at 80 columns against a
service with the fake backend (which has no `change`: an aborting move while a job runs is refused)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

from tests.api.conftest import Served
from tests.cli.conftest import assert_fits, pvt


def _job_file(tmp_path: Path, target: float) -> Path:
    path = tmp_path / f"move-{target}.json"
    path.write_text(json.dumps({"kind": "move", "axes": ["j1"], "target": [target]}))
    return path


def _running(served: Served, timeout: float = 10.0) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = served.service.running_job
        if job is not None:
            return job
        time.sleep(0.02)
    raise AssertionError("no job started")


def test_halt_stops_the_running_job_and_the_queue_goes_on(serve: Callable[..., Served], tmp_path: Path) -> None:
    served = serve(default_duration_s=30.0)
    with served.client() as client:
        first = client.submit(_job_file(tmp_path, 0.3), job_id="first")
        second = client.submit(_job_file(tmp_path, 0.1), job_id="second")
        _running(served)
        out = pvt("halt", "--connect", served.endpoint, "--cell", "demo")
        assert out.returncode == 0, out.stderr
        assert "job first: the running job stops" in out.stdout
        assert_fits(out.stdout + out.stderr)
        assert first.wait(timeout=20).state.value == "cancelled"
        assert not served.service.held
        second.cancel()


def test_halt_with_nothing_running(serve: Callable[..., Served]) -> None:
    served = serve()
    out = pvt("halt", "--connect", served.endpoint, "--cell", "demo")
    assert out.returncode == 0 and "nothing was moving" in out.stdout


def test_submit_buffer_aborting_is_refused_by_a_backend_without_change(serve: Callable[..., Served],
                                                                      tmp_path: Path) -> None:
    served = serve(default_duration_s=30.0)
    with served.client() as client:
        first = client.submit(_job_file(tmp_path, 0.3), job_id="first")
        _running(served)
        out = pvt("submit", str(_job_file(tmp_path, 0.1)), "--buffer", "aborting", "--connect", served.endpoint,
                  "--cell", "demo")
        assert out.returncode == 2, out.stdout + out.stderr
        text = " ".join(out.stderr.split())  # rich wraps at 80 columns
        assert "COMMAND_REJECTED" in text and "cannot change a running motion" in text
        assert_fits(out.stdout + out.stderr)
        assert served.service.running_job == "first"  # untouched
        first.cancel()


def test_submit_lead_ms_below_the_minimum_names_it(serve: Callable[..., Served], tmp_path: Path) -> None:
    served = serve()
    out = pvt("submit", str(_job_file(tmp_path, 0.1)), "--lead-ms", "5", "--connect", served.endpoint,
              "--cell", "demo")
    assert out.returncode == 2
    assert "lead_ms = 5" in out.stderr and "30..5000" in out.stderr
    assert_fits(out.stdout + out.stderr)
