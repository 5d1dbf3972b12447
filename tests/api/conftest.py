"""Fixtures of the API tests: free loopback ports, a Zenoh peer per test, services on the FakeBackend."""

from __future__ import annotations

import socket
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from planner.config import CellConfig
from streamer.api.client import MotionClient
from streamer.api.service import JobService, ServiceOptions
from streamer.api.store import JobStore
from streamer.api.zenoh_config import build_config
from tests.api.fakes import FakeBackend


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


class Served:
    """A running service on its own Zenoh peer: endpoint, backend, store, service."""

    def __init__(
        self,
        service: JobService,
        backend: FakeBackend,
        store: JobStore,
        endpoint: str,
        session: zenoh.Session,
    ):
        self.service = service
        self.backend = backend
        self.store = store
        self.endpoint = endpoint
        self.session = session

    def client(self, **kw: Any) -> MotionClient:
        return MotionClient(connect=self.endpoint, cell=self.backend.cell.name, **kw)


@pytest.fixture
def serve(tmp_path: Path, demo_cell: CellConfig) -> Iterator[Callable[..., Served]]:
    """serve(backend=None, options=None, **fake_kwargs) -> Served; everything is closed at teardown."""
    opened: list[tuple[JobService, JobStore, zenoh.Session]] = []

    def _serve(
        backend: FakeBackend | None = None,
        options: ServiceOptions | None = None,
        store_path: Path | None = None,
        **kw: Any,
    ) -> Served:
        be = backend or FakeBackend(demo_cell, **kw)
        port = free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        session = zenoh.open(build_config(mode="peer", listen=[endpoint]))
        store = JobStore(store_path or tmp_path / f"jobs-{port}.db", synchronous="NORMAL")
        service = JobService(session, be, store, options).start()
        opened.append((service, store, session))
        return Served(service, be, store, endpoint, session)

    yield _serve
    for service, store, session in opened:
        hold = getattr(service.backend, "hold", None)  # only the FakeBackend has one
        if hold is not None:
            hold.set()
        service.close()
        store.close()
        session.close()
