"""Issue 23 item 8: a queued job is re-planned at most once, by the service, with the travel memory it reported
the target with. The runtime backend used to re-plan a plan that did not start where the axes stood once more,
without that memory, so an additive move queued behind a stopped job could go to another target than the
service had reported. Now the backend streams the plan it is given or fails START_MISMATCH."""

from __future__ import annotations

import dataclasses
import uuid
from typing import Any

import pytest

from planner.config import CellConfig
from streamer.api.backend import CancelToken
from streamer.runtime.bus_backend import RuntimeBackend
from tests.api.conftest import Served
from tests.api.test_change_service import wait_moving


def cell3(demo_cell: CellConfig) -> CellConfig:
    cell = demo_cell.with_axes(3)
    return dataclasses.replace(cell, bus=dataclasses.replace(cell.bus, channel=f"once-{uuid.uuid4().hex[:12]}"))


def ignore(event: str, fields: Any = None) -> None:
    return None


def test_the_backend_never_re_plans_a_job_the_service_planned(demo_cell: CellConfig) -> None:
    cell = cell3(demo_cell)
    backend = RuntimeBackend(cell, sim=True)
    try:
        cpu = cell.axis("j1").counts_per_unit
        go = backend.plan(backend.validate({"kind": "move", "axes": ["j1"], "target": [0.3]}), None)
        assert backend.execute(go, ignore, CancelToken())["result"] == "done"
        # an additive move as the service planned it behind a job that was to end at 0.5 (target 0.5); that job
        # was stopped, the axis stands at 0.3
        add = backend.plan(backend.validate({"kind": "move", "axes": ["j1"], "target": [0.1], "mode": "additive"}),
                           {"j1": 0.5}, last_target={"j1": 0.5})
        assert add.commanded_target["j1"] == pytest.approx(0.6)
        report = backend.execute(add, ignore, CancelToken())
        # before: re-planned here without the last target, it went to 0.4 (done), a target nobody reported
        assert report["result"] == "failed" and report["error"]["code"] == "START_MISMATCH", report
        assert "'j1'" in report["error"]["message"]
        assert abs(backend.current_positions()["j1"] - 0.3) * cpu < 0.5  # nothing moved
    finally:
        backend.close()


def test_an_additive_move_queued_behind_a_stopped_job_goes_to_the_target_the_service_reported(real: Served) -> None:
    backend: Any = real.backend
    try:
        with real.client() as client:
            first = client.submit({"kind": "move", "axes": ["j1"], "target": [2.5]}, job_id="long")
            second = client.submit({"kind": "move", "axes": ["j1"], "target": [0.1], "mode": "additive"},
                                   job_id="add")
            wait_moving(first)
            client.stop()  # the running job stops short of 2.5; the queue holds
            assert first.wait(timeout=30).state.value == "cancelled"
            stopped = backend.current_positions()["j1"]
            assert stopped < 2.4
            client.resume()
            assert second.wait(timeout=60).state.value == "done"
        cpu = backend.cell.axis("j1").counts_per_unit
        # additive: the last commanded target (2.5) + 0.1, as the service reported, not the stop's end + 0.1
        assert abs(backend.current_positions()["j1"] - 2.6) * cpu < 0.5, (stopped, backend.current_positions())
    finally:
        real.service.close()
        backend.close()
