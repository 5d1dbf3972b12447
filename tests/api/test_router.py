"""Two services for two cells behind one router-mode Zenoh session; clients address each by cell.

Runs plain and with security on (TLS, mutual TLS, the access rules on the router), and with the
services as separate peers that dial a secured router with the service identity (the scale-out
layout: the router enforces the rules for every client behind it).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from planner.config import CellConfig, ZenohSettings
from streamer.api.certs import CertSet
from streamer.api.client import MotionClient
from streamer.api.errors import MotionError
from streamer.api.model import JobState
from streamer.api.service import JobService
from streamer.api.store import JobStore
from streamer.api.zenoh_config import build_config, service_config
from tests.api.conftest import free_port, identity, secure_settings
from tests.api.fakes import FakeBackend, timed_job


@pytest.fixture
def cells(tmp_path: Path, demo_cell: CellConfig) -> Iterator[dict[str, tuple[FakeBackend, JobStore]]]:
    cell_b = dataclasses.replace(demo_cell.with_axes(3), name="line-b")
    out = {
        c.name: (FakeBackend(c), JobStore(tmp_path / f"{c.name}.db", synchronous="NORMAL"))
        for c in (demo_cell, cell_b)
    }
    yield out
    for _, store in out.values():
        store.close()


def _two_cells_through(endpoint: str, cells: dict[str, tuple[FakeBackend, JobStore]], **client_kw: Any) -> None:
    # a client (mode client, through the router) and a peer client, each addressing one cell
    with (
        MotionClient(connect=endpoint, cell="demo", mode="client", **client_kw) as a,
        MotionClient(connect=endpoint, cell="line-b", **client_kw) as b,
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
    assert cells["demo"][0].executed == ["on-demo", "?"]
    assert cells["line-b"][0].executed == ["on-b", "?"]


@pytest.mark.parametrize("secure", [False, True], ids=["plain", "secured"])
def test_two_cells_on_one_router_session(
    cells: dict[str, tuple[FakeBackend, JobStore]], certs: CertSet, secure: bool
) -> None:
    port = free_port()
    if secure:
        endpoint = f"tls/127.0.0.1:{port}"
        router = zenoh.open(
            service_config(ZenohSettings(mode="router", listen=(endpoint,)), security=secure_settings(certs))
        )
    else:
        endpoint = f"tcp/127.0.0.1:{port}"
        router = zenoh.open(build_config(mode="router", listen=[endpoint]))
    services = [JobService(router, backend, store).start() for backend, store in cells.values()]
    try:
        _two_cells_through(endpoint, cells, **({"security": identity(certs, "operator")} if secure else {}))
        if secure:  # and the observer of either cell reads but cannot write
            with MotionClient(connect=endpoint, cell="line-b", security=identity(certs, "observer")) as ob:
                ob.wait_for_service(timeout=5)
                assert len(ob.jobs()) == 2
                with pytest.raises(MotionError) as info:
                    ob.submit(timed_job(0.05))
                assert info.value.code == "PERMISSION_DENIED"
    finally:
        for s in services:
            s.close()
        router.close()


def test_services_dial_a_secured_router_with_the_service_identity(
    cells: dict[str, tuple[FakeBackend, JobStore]], certs: CertSet
) -> None:
    endpoint = f"tls/127.0.0.1:{free_port()}"
    security = secure_settings(certs)
    router = zenoh.open(service_config(ZenohSettings(mode="router", listen=(endpoint,)), security=security))
    # each service is its own peer: no listen endpoint, it dials the router with the service certificate
    peers = [
        zenoh.open(service_config(ZenohSettings(mode="peer", listen=(), connect=(endpoint,)), security=security))
        for _ in cells
    ]
    services = [JobService(p, b, s).start() for p, (b, s) in zip(peers, cells.values(), strict=True)]
    try:
        _two_cells_through(endpoint, cells, security=identity(certs, "operator"))
        with MotionClient(connect=endpoint, cell="demo", security=identity(certs, "observer")) as ob:
            ob.wait_for_service(timeout=5)
            with pytest.raises(MotionError) as info:
                ob.submit(timed_job(0.05))
            assert info.value.code == "PERMISSION_DENIED"
        # a peer with a client identity cannot stand in for a service behind the router
        impostor = zenoh.open(
            service_config(
                ZenohSettings(mode="peer", listen=(), connect=(endpoint,)),
                security=dataclasses.replace(
                    security,
                    certificate=str(certs["operator"].certificate),
                    private_key=str(certs["operator"].private_key),
                ),
            )
        )
        try:
            token = impostor.liveliness().declare_token("pvt/impostor/alive")
            with MotionClient(connect=endpoint, cell="demo", security=identity(certs, "operator")) as op:
                assert op.cells() == ["demo", "line-b"]
            token.undeclare()
        finally:
            impostor.close()
    finally:
        for s in services:
            s.close()
        for p in peers:
            p.close()
        router.close()
