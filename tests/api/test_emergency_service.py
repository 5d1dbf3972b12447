"""The planned emergency stop and the positioning state through the service (issue 15 sections 2 and 3), on
the real backend with simulated drives (real time, 3 axes): `stop?emergency=true` while a move runs stops it
on the emergency deceleration (reply `method` "emergency_trajectory"), the drives stay enabled, the job
fails EMERGENCY_STOP saying so; events, the report and telemetry carry each axis' positioning state."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import pytest

from streamer.api.client import JobFailedError
from tests.api.conftest import Served
from tests.api.test_change_service import wait_moving

AXES = ["j1", "j2", "j3"]
FIRST = [2.5, -1.8, 2.2]


def _wait(what: str, check: Callable[[], bool], timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if check():
            return
        time.sleep(0.05)
    raise AssertionError(f"not {what} after {timeout} s")


def test_a_move_reports_its_positioning_states_and_ends_in_target(real: Served) -> None:
    backend: Any = real.backend
    try:
        assert {a["positioning"] for a in backend.telemetry()} == {"IDLE"}
        with real.client() as client:
            job = client.submit({"kind": "move", "axes": AXES, "target": [0.4, -0.3, 0.35]}, job_id="m")
            done = job.wait(timeout=60)
            assert done.state.value == "done", done
            seen: set[str] = set()
            for ev in job.history():
                seen |= set((ev.data.get("positioning") or {}).values())
            assert {"ACCEL", "DECEL"} <= seen, seen
            report = job.history()[-1].data["report"]
            assert report["positioning"] == {a: "TARGET" for a in AXES}
            assert "warnings" not in report
        assert {a["positioning"] for a in backend.telemetry() if a["name"] in AXES} == {"TARGET"}
    finally:
        real.service.close()
        backend.close()


def test_the_emergency_stop_of_a_running_move_is_planned_at_the_emergency_deceleration(real: Served) -> None:
    backend: Any = real.backend
    try:
        with real.client() as client:
            job = client.submit({"kind": "move", "axes": AXES, "target": FIRST}, job_id="hit")
            wait_moving(job)
            reply = client.stop(emergency=True)
            assert reply["method"] == "emergency_trajectory", reply
            assert reply["job_id"] == "hit" and "emergency deceleration" in reply["message"]
            with pytest.raises(JobFailedError) as info:
                job.wait(timeout=30)
            err = info.value.status.raw["error"]
            assert err["code"] == "EMERGENCY_STOP" and err["detail"]["method"] == "emergency_trajectory", err
            assert "emergency deceleration" in err["message"]
            states = [set((ev.data.get("positioning") or {}).values()) for ev in job.history()]
            assert any("EMCY" in s for s in states), states
            assert info.value.status.raw["report"]["positioning"] == {a: "STOP" for a in AXES}
            # planned: the drives were never quick-stopped; they stand enabled where the stop ended
            assert all(d["state"] == "operation enabled" for d in client.service_status()["drives"])
            assert client.service_status()["ready"] is False  # until resume, as every emergency stop
            assert client.resume()["ready"] is True
            assert client.submit({"kind": "move", "axes": AXES, "target": [0.0, 0.0, 0.0]}).wait(
                timeout=60).state.value == "done"
    finally:
        real.service.close()
        backend.close()


def test_the_emergency_stop_with_nothing_running_is_the_quick_stop(real: Served) -> None:
    backend: Any = real.backend
    try:
        with real.client() as client:
            reply = client.stop(emergency=True)
            assert reply["method"] == "quick_stop" and "0x000B" in reply["message"], reply
            _wait("every drive quick-stopped", lambda: all(
                d["state"] == "switch on disabled" for d in client.service_status()["drives"]))
            assert client.resume()["reset"] is True
    finally:
        real.service.close()
        backend.close()
