"""Operating a cell from the command line (issue 14, section 2): `pvt status`, `pvt watch`, `pvt cancel`,
`pvt stop` (and `--emergency`), `pvt hold`, `pvt resume`; the queue holds after a stop or a cancel of the
running job; a queued job that no longer starts where the axes stand fails INFEASIBLE naming the axis and
both positions, or is re-planned (a move, a path with start = "current"). Every command runs as a
subprocess at 80 columns against a service on the FakeBackend (TrackingFake: it knows where its axes
stand)."""

from __future__ import annotations

import json
import os
import pty
import re
import select
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any

import pytest

from planner.config import CellConfig
from streamer.api.errors import JobFailedError, MotionError
from streamer.api.model import JobState
from tests.api.conftest import Served
from tests.api.fakes import TrackingFake, timed_job
from tests.api.helpers import wait_for
from tests.cli.conftest import ROOT, assert_fits, cli_env, flat, pvt, words_in

Serve = Callable[..., Served]


def ramp(
    start: float, end: float, duration_s: float, *, axes: tuple[str, ...] = ("j1",), name: str = ""
) -> dict[str, Any]:
    """A timed job moving `axes` from `start` to `end` in `duration_s` (the fake moves them linearly)."""
    job = timed_job(duration_s, axes=axes, name=name)
    job["positions"] = [[start] * len(axes), [end] * len(axes)]
    return job


def running(served: Served, job_id: str, at_least: float = 0.0) -> None:
    """Wait until `job_id` runs (and has made `at_least` progress)."""
    with served.client() as client:
        wait_for(lambda: client.job(job_id).status().state == JobState.RUNNING
                 and client.job(job_id).status().progress >= at_least, timeout=10, what=f"{job_id} running")


def test_status_shows_service_drives_positions_running_job_and_queue(serve: Serve, demo_cell: CellConfig) -> None:
    served = serve(backend=TrackingFake(demo_cell))
    with served.client() as client:
        client.submit(ramp(0.0, 1.0, 5.0, name="a"), job_id="status-running")
        client.submit(ramp(1.0, 0.5, 1.0), job_id="status-queued")
        running(served, "status-running", 0.05)
        out = pvt("status", "--connect", served.endpoint, "--cell", "demo")
        assert out.returncode == 0, out.stderr
        assert_fits(out.stdout)
        text = flat(out.stdout)
        assert "cell demo: ready" in text
        assert "running: job status-running (timed), running" in text
        assert "position" in text and "[rad]" in text and "velocity" in text and "FIFO" in text
        for name in demo_cell.axis_names():
            assert f" {name} " in text
        assert "status-queued" in text and "queue: 1 of 16" in text
        raw = json.loads(pvt("status", "--connect", served.endpoint, "--json").stdout)
        assert raw["running"]["job_id"] == "status-running" and raw["queue"][0]["job_id"] == "status-queued"
        assert [d["name"] for d in raw["drives"]] == list(demo_cell.axis_names())
        assert all(d["unit"] == "rad" for d in raw["drives"]) and raw["held"] is False
        client.job("status-running").cancel()


def test_a_wrong_cell_lists_the_cells_that_are_up(serve: Serve) -> None:
    served = serve()
    for command in ("status", "watch", "stop", "resume", "hold"):
        out = pvt(command, "--connect", served.endpoint, "--cell", "nocell", "--connect-timeout", "0.5")
        assert out.returncode == 5, (command, out.stderr)
        said = flat(out.stderr)
        assert "no job service for cell 'nocell'" in said and "cells up there: demo" in said, said
        assert_fits(out.stderr)
    out = pvt("jobs", "--connect", served.endpoint, "--cell", "nocell", "--timeout", "0.5")
    assert out.returncode == 5 and "cells up there: demo" in flat(out.stderr)


def test_watch_prints_live_telemetry_with_units(serve: Serve, demo_cell: CellConfig) -> None:
    served = serve(backend=TrackingFake(demo_cell))
    with served.client() as client:
        client.submit(ramp(0.0, 1.0, 3.0), job_id="watched")
        running(served, "watched")
        out = pvt("watch", "--connect", served.endpoint, "--count", "3")
        assert out.returncode == 0, out.stderr
        assert_fits(out.stdout)
        assert out.stdout.count("drives") == 3  # a pipe gets one table per sample
        assert "job watched running" in flat(out.stdout) and "[rad]" in flat(out.stdout)
        client.job("watched").cancel()


def test_watch_in_a_terminal_is_a_live_display(serve: Serve) -> None:
    served = serve()
    leader, follower = pty.openpty()
    env = cli_env(TERM="xterm-256color")
    env.pop("NO_COLOR", None)
    proc = subprocess.Popen([sys.executable, "-m", "streamer.cli", "watch", "--connect", served.endpoint,
                             "--duration", "1.5", "--refresh-hz", "8"], cwd=ROOT, stdin=follower, stdout=follower,
                            stderr=follower, env=env, close_fds=True)
    os.close(follower)
    chunks = []
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        ready, _, _ = select.select([leader], [], [], 0.2)
        if ready:
            try:
                data = os.read(leader, 65536)
            except OSError:
                break
            if not data:
                break
            chunks.append(data)
        elif proc.poll() is not None:
            break
    os.close(leader)
    assert proc.wait(timeout=10) == 0
    screen = b"".join(chunks).decode("utf-8", "replace")
    assert "\x1b[" in screen  # redrawn in place (cursor movement), not printed line after line
    assert "drives" in screen and "cell demo" in screen


def test_stop_then_hold_then_resume(serve: Serve, demo_cell: CellConfig) -> None:
    served = serve(backend=TrackingFake(demo_cell))
    with served.client() as client:
        client.submit(ramp(0.0, 1.0, 5.0), job_id="stopped")
        queued = client.submit(ramp(0.0, 0.2, 0.3, axes=("j2",)), job_id="waits")
        running(served, "stopped", 0.05)
        out = pvt("stop", "--connect", served.endpoint)
        assert out.returncode == 0, out.stderr
        assert_fits(out.stdout)
        said = flat(out.stdout)
        assert "jerk-limited stop" in said and "(job stopped)" in said and "queue held" in said
        assert "job stopped: cancelled" in flat(out.stdout)  # it waited until the job had ended
        assert client.job("stopped").status().state == JobState.CANCELLED
        time.sleep(0.5)  # the queue holds: the next job does not start
        assert queued.status().state == JobState.QUEUED
        status = flat(pvt("status", "--connect", served.endpoint).stdout)
        assert "queue HELD" in status and "stop requested" in status and "(held)" in status
        # a new job is accepted while held, and says so; it waits too
        late = pvt("submit", str(write_job(served, ramp(0.0, 0.1, 0.2, axes=("j3",)))), "--connect", served.endpoint,
                   "--job-id", "late")
        assert late.returncode == 0 and "the queue is held" in flat(late.stderr)
        out = pvt("resume", "--connect", served.endpoint)
        assert out.returncode == 0 and "resumed" in flat(out.stdout) and "next waits" in flat(out.stdout), out.stdout
        assert queued.wait(timeout=10).state == JobState.DONE
        assert client.job("late").wait(timeout=10).state == JobState.DONE
        # hold: the running job goes on to its end, the next one waits until resume
        client.submit(ramp(0.0, 0.3, 3.0, axes=("j4",)), job_id="goes-on")  # longer than `pvt hold` takes to start
        nxt = client.submit(ramp(0.0, 0.3, 0.2, axes=("j5",)), job_id="after-hold")
        running(served, "goes-on")
        out = pvt("hold", "--connect", served.endpoint)
        assert out.returncode == 0 and "job goes-on runs on to its end" in flat(out.stdout), out.stdout
        assert client.job("goes-on").wait(timeout=10).state == JobState.DONE
        time.sleep(0.5)
        assert nxt.status().state == JobState.QUEUED
        assert pvt("resume", "--connect", served.endpoint).returncode == 0
        assert nxt.wait(timeout=10).state == JobState.DONE
        out = pvt("stop", "--connect", served.endpoint)  # nothing moving: says so, and holds
        assert out.returncode == 0 and "nothing was moving" in flat(out.stdout)
        assert client.service_status()["held"] is True


def write_job(served: Served, job: dict[str, Any]) -> Any:
    path = served.store.path.parent / f"job-{time.monotonic_ns()}.json"
    path.write_text(json.dumps(job), encoding="utf-8")
    return path


def test_cancel_the_running_job_holds_the_queue_and_a_second_cancel_says_so(
    serve: Serve, demo_cell: CellConfig
) -> None:
    served = serve(backend=TrackingFake(demo_cell))
    with served.client() as client:
        job = client.submit(ramp(0.0, 1.0, 5.0), job_id="to-cancel")
        nxt = client.submit(ramp(0.0, 0.1, 0.2, axes=("j2",)), job_id="behind")
        running(served, "to-cancel", 0.1)
        first = pvt("cancel", "to-cancel", "--connect", served.endpoint)
        assert first.returncode == 0, first.stderr
            # cancelling, or already cancelled when the stop was quick (the fake's is)
        assert re.search(r"job to-cancel: cancel(ling|led);", flat(first.stdout)), first.stdout
        assert "the queue is held" in flat(first.stdout)
        assert_fits(first.stdout)
        status = job.wait(timeout=10)
        assert status.state == JobState.CANCELLED
        again = job.cancel()  # answered honestly: nothing more was requested
        assert again.raw["cancel_requested"] is False and "nothing to cancel" in again.raw["message"]
        out = pvt("cancel", "to-cancel", "--connect", served.endpoint)
        assert out.returncode == 1 and "nothing to cancel" in flat(out.stdout)
        events = list(job.events())
        kinds = [e.type for e in events]
        cut = kinds.index("cancelling")
        assert kinds[cut - 1] == "running" and kinds[-1] == "cancelled"
        assert all(k == "cancelling" for k in kinds[cut:-1])
        cancelling = events[cut]
        assert cancelling.state == "cancelling" and cancelling.data["reason"] == "cancel requested"
        # the true progress, not 1.0 (when: a `pvt cancel` process started 0.5 s into the 5 s job, on a loaded machine)
        assert 0.05 < (cancelling.progress or 0.0) < 0.95
        assert status.progress == pytest.approx(cancelling.progress, abs=0.05)
        time.sleep(0.4)
        assert nxt.status().state == JobState.QUEUED  # held
        assert pvt("cancel", "behind", "--connect", served.endpoint).returncode == 0  # a queued job: at once
        assert nxt.status().state == JobState.CANCELLED
        assert pvt("cancel", "no-such-job", "--connect", served.endpoint).returncode == 2


def test_a_second_cancel_while_the_job_is_stopping_is_not_a_new_request(serve: Serve, demo_cell: CellConfig) -> None:
    backend = TrackingFake(demo_cell)
    served = serve(backend=backend)
    stopping = __import__("threading").Event()
    original = backend.execute

    def slow_stop(planned: Any, emit: Any, cancel: Any) -> Any:
        cancel.add_callback(lambda: None)
        report = original(planned, emit, cancel)
        if report["result"] == "cancelled":  # a stop that takes a while: the job stays cancelling
            emit("running", {"progress": 0.3, "stop_progress": 0.5})
            stopping.wait(5)
        return report

    backend.execute = slow_stop  # type: ignore[method-assign]
    with served.client() as client:
        job = client.submit(ramp(0.0, 1.0, 5.0), job_id="slow-stop")
        running(served, "slow-stop", 0.05)
        first = job.cancel()
        second = job.cancel()
        assert first.raw["cancel_requested"] is True and second.raw["cancel_requested"] is False
        assert second.state == JobState.CANCELLING and "already requested" in second.raw["message"]
        stopping.set()
        assert job.wait(timeout=10).state == JobState.CANCELLED
        assert [e.type for e in job.events()][-3:] == ["cancelling", "cancelling", "cancelled"]


def test_a_queued_job_after_a_cancel_ends_infeasible_with_the_axis_and_both_positions(
    serve: Serve, demo_cell: CellConfig
) -> None:
    served = serve(backend=TrackingFake(demo_cell))
    with served.client() as client:
        first = client.submit(ramp(0.0, 1.0, 4.0), job_id="cut-short")
        after = client.submit(ramp(1.0, 2.0, 0.5), job_id="planned-from-its-end")  # starts where the first ends
        running(served, "cut-short", 0.15)
        assert pvt("cancel", "cut-short", "--connect", served.endpoint).returncode == 0
        assert first.wait(timeout=10).state == JobState.CANCELLED
        stood = served.backend.current_positions()["j1"]
        assert 0.1 < stood < 1.0  # cut short (where: a `pvt cancel` process started 0.6 s into the 4 s job)
        assert pvt("resume", "--connect", served.endpoint).returncode == 0
        with pytest.raises(JobFailedError) as info:
            after.wait(timeout=10)
        err = info.value
        assert err.code == "INFEASIBLE" and err.path == "positions[0][0]"  # never INTERNAL
        assert "axis 'j1'" in err.message and f"stands at {stood:.6g} rad" in err.message
        assert "starts at 1 rad" in err.message and 'start = "current"' in err.message
        detail = err.status.raw["error"]["detail"]
        assert detail["axis"] == "j1" and detail["position"] == pytest.approx(stood) and detail["job_start"] == 1.0
        out = pvt("jobs", "--connect", served.endpoint)
        assert out.returncode == 0 and all(len(line) <= 80 for line in out.stdout.splitlines()), out.stdout
        assert "INFEASIBLE" in out.stdout  # one line per job, the error cut to it (issue 23 item 6) ...
        shown = pvt("jobs", "show", "planned-from-its-end", "--store", str(served.store.path))
        # ... and whole in `pvt jobs show` (the job never started: no recording, exit 1, the journal's row)
        assert words_in(shown.stdout, f"INFEASIBLE: positions[0][0]: axis 'j1' stands at {stood:.6g} rad"), shown


def test_after_a_cancel_a_move_and_a_start_current_path_are_replanned(serve: Serve, demo_cell: CellConfig) -> None:
    served = serve(backend=TrackingFake(demo_cell))
    with served.client() as client:
        first = client.submit(ramp(0.0, 1.0, 4.0), job_id="first")
        move = client.submit({"kind": "move", "axes": ["j1"], "target": [1.5]}, job_id="a-move")
        path = client.submit({"kind": "path", "axes": ["j1"], "waypoints": [[1.5], [2.0]], "start": "current"},
                             job_id="a-path")
        running(served, "first", 0.15)
        first.cancel()
        first.wait(timeout=10)
        client.resume()
        assert move.wait(timeout=10).state == JobState.DONE  # a move starts where the axes stand
        # the path was planned from 1.5 (the move's end) and still starts there: run as planned
        assert path.wait(timeout=10).state == JobState.DONE
        # the same path queued behind a job that is cancelled: planned again from where the axes stand
        second = client.submit(ramp(2.0, 1.0, 4.0), job_id="second")
        back = client.submit({"kind": "path", "axes": ["j1"], "waypoints": [[1.0], [0.5]], "start": "current"},
                             job_id="back")
        running(served, "second", 0.15)
        second.cancel()
        second.wait(timeout=10)
        stood = served.backend.current_positions()["j1"]
        client.resume()
        done = back.wait(timeout=10)
        assert done.state == JobState.DONE
        assert done.report is not None and done.report["axes"][0]["points_sent"] == 4  # 3 waypoints: here, 1, 0.5
        assert served.backend.current_positions()["j1"] == pytest.approx(0.5)
        assert stood != pytest.approx(1.0)
        # timed and pvt jobs keep their own timing: start = "current" is refused
        with pytest.raises(MotionError) as info:
            client.submit({**ramp(0.0, 1.0, 1.0), "start": "current"})
        assert info.value.code == "SCHEMA" and info.value.path == "start"


def test_emergency_stop_quick_stops_everything_and_resume_reenables(serve: Serve, demo_cell: CellConfig) -> None:
    served = serve(backend=TrackingFake(demo_cell))
    with served.client() as client:
        job = client.submit(ramp(0.0, 1.0, 5.0), job_id="hit")
        waiting = client.submit(ramp(0.0, 0.1, 0.2, axes=("j2",)), job_id="waiting")
        running(served, "hit", 0.05)
        out = pvt("stop", "--emergency", "--connect", served.endpoint)
        assert out.returncode == 0, out.stderr
        assert_fits(out.stdout)
        assert "EMERGENCY STOP of cell demo: quick stop" in flat(out.stdout) and "job hit: failed" in flat(out.stdout)
        assert "EMERGENCY_STOP" in flat(out.stdout) and "re-enables the drives" in flat(out.stdout)
        with pytest.raises(JobFailedError) as info:
            job.wait(timeout=5)
        assert info.value.code == "EMERGENCY_STOP"
        assert served.backend.emergency_stops == 1
        status = flat(pvt("status", "--connect", served.endpoint).stdout)
        assert "NOT READY (EMERGENCY_STOP" in status and "queue HELD" in status and "emergency stop" in status
        with pytest.raises(MotionError) as refused:
            client.submit(ramp(0.0, 0.1, 0.2, axes=("j3",)))
        assert refused.value.code == "NOT_READY" and "pvt resume --reset" in refused.value.message
        assert waiting.status().state == JobState.QUEUED
        out = pvt("resume", "--connect", served.endpoint)
        assert out.returncode == 0 and "resumed after a reset" in flat(out.stdout), out.stdout
        assert waiting.wait(timeout=10).state == JobState.DONE
        # a drive fault is not cleared by a plain resume
        served.backend.faulted = "DRIVE_FAULT: node 3"
        out = pvt("resume", "--connect", served.endpoint)
        assert out.returncode == 2 and "NOT_READY" in flat(out.stderr) and "--reset" in flat(out.stderr)
        assert pvt("resume", "--reset", "--connect", served.endpoint).returncode == 0
        assert client.service_status()["ready"] is True
