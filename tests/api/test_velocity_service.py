"""Velocity jobs and the last commanded target through the service (issue 15 follow-up C), on the real backend
with simulated drives (real time, 3 axes): a velocity job streams past its first chunk until it is stopped or
changed; an additive move after a stop at an arbitrary position ends at the last target + its offset."""

from __future__ import annotations

import time

from streamer.api.client import Job, MotionClient
from tests.api.conftest import Served

AXES = ["j1", "j2", "j3"]


def wait_running(job: Job, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if job.status(timeout=5).state.value == "running":
            return
        time.sleep(0.05)
    raise AssertionError(f"job {job.job_id} not running after {timeout} s")


def positions(real: Served) -> dict[str, float]:
    return dict(real.backend.current_positions())  # type: ignore[attr-defined]


def at(real: Served, want: dict[str, float]) -> None:
    here = positions(real)
    cell = real.backend.cell
    for name, x in want.items():
        assert abs(here[name] - x) * cell.axis(name).counts_per_unit < 0.5, (name, here[name], x)


def resume(client: MotionClient) -> None:
    client.resume(timeout=10)


def test_an_additive_move_after_a_stop_ends_at_the_last_target_plus_its_offset(real: Served) -> None:
    first = {"j1": 2.5, "j2": -1.8, "j3": 2.2}
    offset = [0.1, 0.2, -0.3]
    try:
        with real.client() as client:
            a = client.submit({"kind": "move", "axes": AXES, "target": list(first.values())}, job_id="add-a")
            wait_running(a)
            time.sleep(0.4)
            a.stop(timeout=10)
            assert a.wait(timeout=30).state.value == "cancelled"
            here = positions(real)
            assert all(abs(here[n] - first[n]) > 0.05 for n in AXES), here  # stopped somewhere on the way
            resume(client)
            b = client.submit({"kind": "move", "axes": AXES, "mode": "additive", "target": offset}, job_id="add-b")
            assert b.wait(timeout=60).state.value == "done"
            at(real, {n: first[n] + d for n, d in zip(AXES, offset, strict=True)})
            # and the next additive move counts from that target (not from where a rounding left the axes)
            c = client.submit({"kind": "move", "axes": AXES, "mode": "additive", "target": offset}, job_id="add-c")
            assert c.wait(timeout=60).state.value == "done"
            at(real, {n: first[n] + 2 * d for n, d in zip(AXES, offset, strict=True)})
    finally:
        real.service.close()
        real.backend.close()  # type: ignore[attr-defined]


def test_a_velocity_job_runs_past_its_first_chunk_until_stopped_then_an_additive_move_counts_from_the_position(
        real: Served) -> None:
    try:
        with real.client() as client:
            v = client.submit({"kind": "move", "axes": AXES, "mode": "velocity", "velocity": [0.2, -0.15, 0.1]},
                              job_id="vel-a")
            wait_running(v)
            time.sleep(3.5)  # the first chunk is the ramp + 2 s of cruise: this is past it
            assert v.status(timeout=5).state.value == "running"
            moved = positions(real)
            assert moved["j1"] > 0.2 * 2.5 and moved["j2"] < -0.15 * 2.5, moved
            running = [e for e in v.history() if e.type == "running"]
            assert running and running[-1].data.get("endless") is True
            v.stop(timeout=10)
            assert v.wait(timeout=30).state.value == "cancelled"
            here = positions(real)
            time.sleep(0.3)
            assert positions(real) == here  # at rest
            resume(client)
            # a velocity move leaves no target: additive counts from where the axes stand
            b = client.submit({"kind": "move", "axes": AXES, "mode": "additive", "target": [-0.1, 0.1, -0.1]},
                              job_id="vel-b")
            assert b.wait(timeout=60).state.value == "done"
            at(real, {n: here[n] + d for n, d in zip(AXES, [-0.1, 0.1, -0.1], strict=True)})
    finally:
        real.service.close()
        real.backend.close()  # type: ignore[attr-defined]


def test_a_velocity_job_changed_to_an_absolute_target_ends_there(real: Served) -> None:
    target = [0.5, -0.4, 0.3]
    try:
        with real.client() as client:
            v = client.submit({"kind": "move", "axes": AXES, "mode": "velocity", "velocity": [0.2, -0.15, 0.1]},
                              job_id="vel-c")
            wait_running(v)
            time.sleep(2.8)
            b = v.change(target=target, job_id="vel-d")
            assert b.wait(timeout=60).state.value == "done"
            assert v.wait(timeout=10).state.value == "aborted"
            at(real, dict(zip(AXES, target, strict=True)))
    finally:
        real.service.close()
        real.backend.close()  # type: ignore[attr-defined]
