"""Two services for two cells on one router-mode Zenoh session; clients address each by cell."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import zenoh

from planner.config import CellConfig
from streamer.api.client import MotionClient
from streamer.api.errors import MotionError
from streamer.api.model import JobState
from streamer.api.service import JobService
from streamer.api.store import JobStore
from streamer.api.zenoh_config import build_config
from tests.api.conftest import free_port
from tests.api.fakes import FakeBackend, timed_job


def test_two_cells_on_one_router_session(tmp_path: Path, demo_cell: CellConfig) -> None:
    cell_b = dataclasses.replace(demo_cell.with_axes(3), name="line-b")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(build_config(mode="router", listen=[endpoint]))
    backends = {"demo": FakeBackend(demo_cell), "line-b": FakeBackend(cell_b)}
    stores = {name: JobStore(tmp_path / f"{name}.db", synchronous="NORMAL") for name in backends}
    services = [JobService(router, backends[n], stores[n]).start() for n in backends]
    try:
        # a client (mode client, through the router) and a peer client, each addressing one cell
        with (
            MotionClient(connect=endpoint, cell="demo", mode="client") as a,
            MotionClient(connect=endpoint, cell="line-b") as b,
        ):
            a.wait_for_service(timeout=5)
            b.wait_for_service(timeout=5)
            assert a.cells() == ["demo", "line-b"]
            ja = a.submit(timed_job(0.1, axes=["j1", "j6"], name="on-demo"))
            jb = b.submit(timed_job(0.1, axes=["j1", "j3"], name="on-b"))
            assert ja.wait(timeout=5).state == JobState.DONE
            assert jb.wait(timeout=5).state == JobState.DONE
            assert [j.job_id for j in a.jobs()] == [ja.job_id]
            assert [j.job_id for j in b.jobs()] == [jb.job_id]
            with pytest.raises(MotionError) as info:  # line-b has only 3 axes
                b.submit(timed_job(0.1, axes=["j6"]))
            assert info.value.code == "AXIS_ID"
            assert a.service_status()["axes"] == ["j1", "j2", "j3", "j4", "j5", "j6"]
            assert b.service_status()["axes"] == ["j1", "j2", "j3"]
            # the same job id in two cells is two jobs
            a.submit(timed_job(0.05), job_id="shared").wait(timeout=5)
            b.submit(timed_job(0.05), job_id="shared").wait(timeout=5)
        assert backends["demo"].executed == ["on-demo", "?"]
        assert backends["line-b"].executed == ["on-b", "?"]
    finally:
        for s in services:
            s.close()
        for st in stores.values():
            st.close()
        router.close()
