"""The same operations on the real motion runtime and the simulated drives (streamer.runtime.bus_backend with
sim=True), in real time: a cancel's `cancelling` events carry the true progress of the job's plan, the
queue holds, a queued path planned from the cancelled job's end fails INFEASIBLE naming the axis and both
positions (never INTERNAL), and the emergency stop (planned while a job runs, else the quick stop of every drive)
holds the cell until resume.

The requests go through the Python client here (the same API requests `pvt cancel/stop/resume` make,
tested as subprocesses in test_operate.py): starting a Python process takes a CPU core for a second,
and the simulated drives share this process' SYNC timing with the master."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import pytest

from planner.config import CellConfig
from streamer.api.backend import BackendUnavailable, load_backend
from streamer.api.errors import JobFailedError
from streamer.api.model import JobState
from tests.api.conftest import Served
from tests.api.helpers import wait_for
from tests.cli.conftest import ROOT

Serve = Callable[..., Served]
HOME = {"kind": "move", "axes": ["j1", "j2", "j3", "j4", "j5", "j6"], "target": [0.0] * 6}


def _runtime(cell: CellConfig) -> Any:
    # the drives are simulated in this process and share its CPU with the master: a loaded machine stalls
    # them longer than the three SYNCs a real drive gets before TPDO_TIMEOUT (what this file tests is the
    # service's behaviour, not that timeout: tests/streamer/core/test_fault_paths.py has it)
    cell = dataclasses.replace(cell, drive=dataclasses.replace(cell.drive, tpdo_timeout_syncs=10))
    try:
        return load_backend("streamer.runtime.bus_backend:open_backend", cell, sim=True)
    except BackendUnavailable as exc:  # pragma: no cover - the runtime is part of the product
        pytest.skip(f"motion runtime not available: {exc}")


def _progress_over(job: Any, share: float) -> None:
    last = None
    for last in job.events(timeout=30):
        if last.type == "running" and (last.progress or 0.0) > share:
            return
    raise AssertionError(f"job {job.job_id} ended before {share:.0%}: {last.data if last else None}")


@pytest.mark.slow
@pytest.mark.isolated
def test_cancel_hold_infeasible_and_emergency_stop_on_simulated_drives(serve: Serve, demo_cell: CellConfig) -> None:
    backend = _runtime(demo_cell)
    try:
        served = serve(backend=backend)
        with served.client() as client:
            first = client.submit(ROOT / "configs" / "jobs" / "demo-path.toml", job_id="cycle")
            # a path from home, planned from where the cycle ends (home): valid when it is accepted
            after = client.submit({"kind": "path", "axes": ["j1", "j6"], "waypoints": [[0.0, 0.0], [0.2, 0.3]]},
                                  job_id="from-home")
            _progress_over(first, 0.3)
            reply = first.cancel()
            assert reply.raw["cancel_requested"] is True and reply.state == JobState.CANCELLING
            status = first.wait(timeout=30)
            assert status.state == JobState.CANCELLED
            events = list(first.events())
            kinds = [e.type for e in events]
            cut = kinds.index("cancelling")
            assert all(k == "cancelling" for k in kinds[cut:-1]) and len(kinds) - cut > 2
            progress = [e.progress or 0.0 for e in events[cut:-1]]
            before = events[cut - 1].progress or 0.0
            # the share of the cycle's own plan that ran: it stops growing where the stop begins, never 1.0
            assert progress == sorted(progress) and before <= progress[0] and progress[-1] < 0.75
            assert status.progress == pytest.approx(progress[-1])
            assert events[-2].data.get("stop_progress") == pytest.approx(1.0)
            assert client.service_status()["held"] is True
            here = {a["name"]: a["position_demand"] for a in client.service_status()["drives"]}
            assert client.resume()["was_held"] is True
            with pytest.raises(JobFailedError) as info:
                after.wait(timeout=30)
            err = info.value
            assert err.code == "INFEASIBLE", err  # never INTERNAL
            axis = err.status.raw["error"]["detail"]["axis"]
            j = ["j1", "j6"].index(axis)
            assert err.path == f"waypoints[0][{j}]" and f"axis {axis!r} stands at {here[axis]:.6g} rad" in err.message
            assert "but the job starts at 0 rad" in err.message
            # a move starts where the axes stand: home again
            assert client.submit(HOME).wait(timeout=30).state == JobState.DONE

            # emergency stop: the running job stops on its planned emergency deceleration, fails EMERGENCY_STOP
            hit = client.submit(ROOT / "configs" / "jobs" / "demo-path.toml", job_id="hit")
            _progress_over(hit, 0.2)
            reply = client.stop(emergency=True)
            assert reply["method"] == "emergency_trajectory" and reply["job_id"] == "hit", reply
            with pytest.raises(JobFailedError) as stopped:
                hit.wait(timeout=30)
            assert stopped.value.code == "EMERGENCY_STOP"
            assert client.service_status()["ready"] is False
            # with nothing running it is the quick stop on every drive; resume re-enables them
            assert client.stop(emergency=True)["method"] == "quick_stop"
            wait_for(lambda: all(d["state"] == "switch on disabled" for d in client.service_status()["drives"]),
                     timeout=10, what="every drive quick-stopped (switch on disabled)")
            assert client.resume()["reset"] is True
            assert client.service_status()["ready"] is True
            wait_for(lambda: all(d["state"] == "operation enabled" for d in client.service_status()["drives"]),
                     timeout=10, what="every drive enabled again (its next TPDO1)")
            assert client.submit(HOME).wait(timeout=30).state == JobState.DONE
    finally:
        backend.close()
