"""Home jobs through the job service (issue 14): the motion runtime with in-process simulated drives in real
time (what `pvt serve --sim` runs), the Python client. The example home job runs on the demo cell as shipped
(configs/homing/home-demo.toml: j1 searches the home switch of its simulated drive), its events end `done`,
the service status says per axis that it is referenced, and with `require_homing` a move is refused
NOT_HOMED before and accepted after. A homing error (j2's simulated drive has no home switch within its
travel) fails the job HOMING_ERROR naming the axis, un-references it, and a move queued behind that home job
fails NOT_HOMED when it comes up."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import pytest

from planner.config import CellConfig
from streamer.api.backend import BackendUnavailable, load_backend
from streamer.api.errors import JobFailedError, MotionError
from streamer.api.model import JobState
from tests.api.conftest import Served
from tests.bus.bus_testkit import wait_until
from tests.conftest import CONFIGS

Serve = Callable[..., Served]
HOME_DEMO = CONFIGS / "homing" / "home-demo.toml"


def _homing_cell(demo_cell: CellConfig) -> CellConfig:
    """The demo cell with `require_homing = true`; j2's simulated drive has no home switch and a short
    homing travel (0.1 rad: a search for a switch fails there, homing error)."""
    j2 = demo_cell.axes[1]
    j2 = dataclasses.replace(j2, sim=dataclasses.replace(j2.sim, home_switch=None, homing_travel=0.1))
    return dataclasses.replace(demo_cell, require_homing=True, axes=(demo_cell.axes[0], j2, *demo_cell.axes[2:]))


def _move(axis: str, target: float) -> dict[str, Any]:
    return {"kind": "move", "axes": [axis], "target": [target]}


def _referenced(client: Any) -> dict[str, bool]:
    return {d["name"]: d["referenced"] for d in client.service_status()["drives"]}


def test_home_job_through_the_service_references_the_axes(serve: Serve, demo_cell: CellConfig) -> None:
    assert demo_cell.axes[0].sim.home_switch is not None  # the shipped demo cell's j1 has a home switch
    cell = _homing_cell(demo_cell)
    try:
        backend = load_backend("streamer.runtime.bus_backend:open_backend", cell, sim=True)
    except BackendUnavailable as exc:  # pragma: no cover - the runtime is part of the product
        pytest.skip(f"motion runtime not available: {exc}")
    try:
        served = serve(backend=backend)
        with served.client() as client:
            assert _referenced(client) == {a.name: False for a in cell.axes}
            # require_homing: a move on an unreferenced axis is refused at once, naming the axis
            with pytest.raises(MotionError) as refused:
                client.submit(_move("j1", 0.1))
            assert refused.value.code == "NOT_HOMED" and "'j1'" in refused.value.message

            home = client.submit(HOME_DEMO, job_id="home-demo")
            events = list(home.events(timeout=60))
            kinds = [e.type for e in events]
            assert kinds[:3] == ["accepted", "planned", "priming"] and kinds[-1] == "done", kinds
            progress = [e.progress for e in events if e.type == "running"]
            assert progress and all(0.0 <= (p or 0.0) < 1.0 for p in progress)
            status = home.wait(timeout=10)
            assert status.state == JobState.DONE
            report = status.raw["report"]
            assert report["kind"] == "home"
            assert [(r["name"], r["method"], r["result"]) for r in report["axes"]] == [
                ("j1", 19, "attained"), *((f"j{k}", 35, "attained") for k in range(2, 7))]
            assert _referenced(client) == {a.name: True for a in cell.axes}
            j1 = next(d for d in client.service_status()["drives"] if d["name"] == "j1")
            assert j1["position_demand"] == pytest.approx(0.0, abs=1e-6)  # stands at its home position (offset)
            # the drive's own view, over SDO (its model runs in a process of its own, as hardware): it stands
            # at its home position, the switch edge plus the home offset it was given
            assert wait_until(lambda: abs(backend.adapter.read(1, 0x6064, 0)) <= 1, timeout_s=5.0)

            # referenced: the move is accepted and runs
            assert client.submit(_move("j1", 0.1)).wait(timeout=30).state == JobState.DONE

            # a homing error: j2 searches a switch its drive does not have; a move on j2 queued behind it was
            # accepted (the home job would reference j2) and fails NOT_HOMED when it comes up
            failing = client.submit({"kind": "home", "axes": ["j2"], "method": 19, "search_speed": 0.2,
                                     "zero_speed": 0.02, "acceleration": 2.0, "timeout_s": 30.0}, job_id="home-j2")
            behind = client.submit(_move("j2", 0.0), job_id="behind")
            with pytest.raises(JobFailedError) as failed:
                failing.wait(timeout=30)
            err = failed.value
            assert err.code == "HOMING_ERROR" and "'j2'" in err.message and "node 2" in err.message
            assert err.status.raw["error"]["detail"]["axes"] == ["j2"] and err.status.raw["error"]["node"] == 2
            assert err.status.raw["report"]["axes"][0]["result"] == "error"
            with pytest.raises(JobFailedError) as late:
                behind.wait(timeout=30)
            assert late.value.code == "NOT_HOMED" and "'j2'" in late.value.message
            assert _referenced(client) == {"j1": True, "j2": False, **{f"j{k}": True for k in range(3, 7)}}
            with pytest.raises(MotionError) as again:
                client.submit(_move("j2", 0.0))
            assert again.value.code == "NOT_HOMED"
            # a homing error is no fault of the cell: it stays ready, j1 still moves
            assert client.service_status()["ready"] is True
            assert client.submit(_move("j1", 0.0)).wait(timeout=30).state == JobState.DONE
    finally:
        backend.close()
