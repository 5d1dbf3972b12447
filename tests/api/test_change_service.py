"""A change of the running motion through the service (issue 15 section 2): `buffer = "aborting"` on the
real backend with simulated drives (real time, 3 axes): the running job ends aborted naming the new one,
which runs to its own target; a change out of reach is COMMAND_REJECTED and the running job goes on to its
own end. And the `buffer` / `lead_ms` fields' checks (fake backend)."""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest

from planner.config import CellConfig
from streamer.api.client import Job
from streamer.api.errors import MotionError
from tests.api.conftest import Served
from tests.api.fakes import timed_job

AXES = ["j1", "j2", "j3"]
FIRST = [2.5, -1.8, 2.2]


def wait_moving(job: Job, progress: float = 0.15, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        st = job.status(timeout=5)
        if st.state.value == "running" and st.progress >= progress:
            return
        time.sleep(0.05)
    raise AssertionError(f"job {job.job_id} not moving after {timeout} s")


def test_an_aborting_move_replaces_the_running_job_and_runs_to_its_own_target(real: Served) -> None:
    target = [-0.5, 0.6, -0.8]
    try:
        with real.client() as client:
            a = client.submit({"kind": "move", "axes": AXES, "target": FIRST}, job_id="run-a")
            wait_moving(a)
            b = a.change(target=target, job_id="run-b")
            assert b.accepted["state"] == "running"
            done = b.wait(timeout=60)
            assert done.state.value == "done", done
            first = a.wait(timeout=10)
            assert first.state.value == "aborted"
            last = a.history()[-1]
            assert last.type == "aborted" and last.data["replaced_by"] == "run-b"
            started = next(e for e in b.history() if e.type == "priming")
            assert started.data["replaces"] == "run-a" and started.data["change"]["reaction_ms"] >= 0
        here = real.backend.current_positions()  # type: ignore[attr-defined]
        cell = real.backend.cell
        for name, x in zip(AXES, target, strict=True):
            assert abs(here[name] - x) * cell.axis(name).counts_per_unit < 0.5, (name, here[name], x)
    finally:
        real.service.close()
        real.backend.close()  # type: ignore[attr-defined]


def test_a_change_that_cannot_be_made_is_rejected_and_the_running_job_goes_on(real: Served) -> None:
    # (the planner's refusals, out of reach within the limits or not streamable in time, and the running
    # job's records exactly as planned after one: tests/streamer/test_change.py, in virtual time)
    try:
        with real.client() as client:
            a = client.submit({"kind": "move", "axes": AXES, "target": FIRST}, job_id="run-a")
            wait_moving(a)
            with pytest.raises(MotionError) as info:
                client.submit({"kind": "move", "axes": AXES[:2], "target": [0.0, 0.0], "buffer": "aborting"},
                              job_id="run-c")
            assert info.value.code == "COMMAND_REJECTED" and "same axes" in info.value.message
            assert info.value.path == "axes"
            # a target outside the software limits (j1: -3..3 rad) is the change's refusal too (docs/api.md)
            with pytest.raises(MotionError) as info:
                client.submit({"kind": "move", "axes": AXES, "target": [3.5, 0.0, 0.0], "buffer": "aborting"},
                              job_id="run-d")
            assert info.value.code == "COMMAND_REJECTED", info.value
            assert info.value.detail["planner_code"] == "POSITION_LIMIT" and "j1" in info.value.message
            done = a.wait(timeout=60)
            assert done.state.value == "done", done
        here = real.backend.current_positions()  # type: ignore[attr-defined]
        for name, x in zip(AXES, FIRST, strict=True):
            assert abs(here[name] - x) * real.backend.cell.axis(name).counts_per_unit < 0.5
    finally:
        real.service.close()
        real.backend.close()  # type: ignore[attr-defined]


@pytest.mark.parametrize(("extra", "code", "path", "words"), [
    ({"buffer": "later"}, "SCHEMA", "buffer", "aborting"),
    ({"buffer": 3}, "TYPE", "buffer", "string"),
    ({"lead_ms": 10}, "SCHEMA", "lead_ms", "lead_ms = 10 is outside 30..5000"),
    ({"lead_ms": 1.5}, "TYPE", "lead_ms", "integer"),
])
def test_buffer_and_lead_are_checked(serve: Callable[..., Served], extra: dict[str, object], code: str, path: str,
                                     words: str) -> None:
    served = serve()
    with served.client() as client, pytest.raises(MotionError) as info:
        client.submit({"kind": "move", "axes": ["j1"], "target": [0.1], **extra})
    assert info.value.code == code and info.value.path == path and words in info.value.message


def test_a_change_outside_the_position_limits_is_command_rejected_with_the_planner_code(
        serve: Callable[..., Served]) -> None:
    """Issue 23 item 5: what the validation finds (here the fake's POSITION_LIMIT) about an aborting move while a
    job runs is the change's refusal, as docs/api.md's table says; with nothing running the move is a job like
    any other and keeps the planner's code."""
    served = serve(time_scale=1.0)
    out_of_reach = {"kind": "move", "axes": ["j1"], "target": [0.1], "buffer": "aborting", "tolerance_counts": 904}
    with served.client() as client:
        with pytest.raises(MotionError) as alone:
            client.submit(out_of_reach)
        assert alone.value.code == "POSITION_LIMIT"
        running = client.submit(timed_job(3.0))
        deadline = time.monotonic() + 10
        while running.status(timeout=5).state.value != "running" and time.monotonic() < deadline:
            time.sleep(0.02)
        with pytest.raises(MotionError) as info:
            client.submit(out_of_reach)
        assert info.value.code == "COMMAND_REJECTED" and info.value.path == "tolerance_counts"
        assert info.value.detail == {"planner_code": "POSITION_LIMIT"} and "j1" in info.value.message
        with pytest.raises(MotionError) as schema:  # bad input keeps its own code
            client.submit({**out_of_reach, "tolerance_counts": 1, "bogus": 1})
        assert schema.value.code == "SCHEMA"
        assert running.status(timeout=5).state.value == "running"  # untouched
        running.cancel()


def test_an_aborting_move_with_nothing_running_is_queued_like_any_job(serve: Callable[..., Served]) -> None:
    served = serve()
    with served.client() as client:
        job = client.submit({"kind": "move", "axes": ["j1"], "target": [0.1], "buffer": "aborting", "lead_ms": 50})
        assert job.wait(timeout=30).state.value == "done"


def test_a_short_lead_bounds_the_segments_of_the_plan(demo_cell: CellConfig) -> None:
    """`lead_ms` shorter than the cell's: the backend plans with segments bounded for it
    (StreamerSettings.segment_cap_ms), so the few segments the feeders keep queued span about the lead."""
    from planner.job import job_from_dict
    from streamer.runtime.bus_backend import RuntimeBackend

    cell = demo_cell.with_axes(3)
    backend = RuntimeBackend(cell, sim=True)
    try:
        job = job_from_dict({"kind": "move", "axes": AXES, "target": FIRST}, cell)
        free = backend.plan(job, {a: 0.0 for a in AXES})
        short = backend.plan(job, {a: 0.0 for a in AXES}, lead_ms=60)
        cap = backend.runtime.settings.segment_cap_ms(60)
        assert free.trajectory is not None and short.trajectory is not None
        assert max(free.trajectory.dt_ms) > cap
        assert max(short.trajectory.dt_ms) <= max(cap, short.trajectory.info["max_segment_ms"])
        assert short.trajectory.duration_ms == free.trajectory.duration_ms
    finally:
        backend.close()
