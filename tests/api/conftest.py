"""Fixtures of the API tests: free loopback ports, a Zenoh peer per test, services on the FakeBackend."""

from __future__ import annotations

import dataclasses
import socket
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from planner.config import CellConfig, SecuritySettings, ZenohSettings
from streamer.api.certs import DEFAULT_IDENTITIES, CertSet, init_certs
from streamer.api.client import MotionClient
from streamer.api.security import ClientSecurity
from streamer.api.service import JobService, ServiceOptions
from streamer.api.store import JobStore
from streamer.api.zenoh_config import build_config, service_config
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
    """serve(backend=None, options=None, security=None, **fake_kwargs) -> Served; everything is closed at
    teardown. With `security` (enabled), the service listens on tls/127.0.0.1 with its access rules."""
    opened: list[tuple[JobService, JobStore, zenoh.Session]] = []

    def _serve(
        backend: FakeBackend | None = None,
        options: ServiceOptions | None = None,
        store_path: Path | None = None,
        security: SecuritySettings | None = None,
        **kw: Any,
    ) -> Served:
        be = backend or FakeBackend(demo_cell, **kw)
        port = free_port()
        if security is not None and security.enabled:
            endpoint = f"tls/127.0.0.1:{port}"
            session = zenoh.open(service_config(ZenohSettings(listen=(endpoint,)), security=security))
        else:
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


@pytest.fixture(scope="session")
def certs(tmp_path_factory: pytest.TempPathFactory) -> CertSet:
    """A CA and certificates made for this test run: service, operator, observer, and `stranger` (same
    CA, a common name in no role)."""
    return init_certs(
        tmp_path_factory.mktemp("certs"), identities={**DEFAULT_IDENTITIES, "stranger": "pvt-stranger"}
    )


@pytest.fixture(scope="session")
def other_certs(tmp_path_factory: pytest.TempPathFactory) -> CertSet:
    """Another CA with certificates of the same names: trusted by nobody here."""
    return init_certs(tmp_path_factory.mktemp("other-certs"))


def secure_settings(certs: CertSet, **changes: Any) -> SecuritySettings:
    """[security] on with the test certificates and the default roles (pvt-operator, ...)."""
    values: dict[str, Any] = {
        "enabled": True,
        "ca": str(certs.ca_certificate),
        "certificate": str(certs["service"].certificate),
        "private_key": str(certs["service"].private_key),
        "operator": ("cn:pvt-operator",),
        "observer": ("cn:pvt-observer",),
        "service": ("cn:pvt-service",),
    }
    values.update(changes)
    return SecuritySettings(**values)


def identity(certs: CertSet, name: str, **kw: Any) -> ClientSecurity:
    """A client's security options: the CA of `certs`, and the certificate `name` of `certs`."""
    return ClientSecurity(
        ca=certs.ca_certificate, certificate=certs[name].certificate, private_key=certs[name].private_key, **kw
    )


@pytest.fixture
def real(serve: Callable[..., Served], demo_cell: CellConfig) -> Served:
    """A service on the real backend with 3 simulated axes of the demo cell in this process (real time)."""
    from streamer.runtime.bus_backend import RuntimeBackend

    # a virtual channel of its own: the same-named channel of an earlier test in this process may still
    # carry that test's simulated drives or their shutdown while this job runs
    cell = demo_cell.with_axes(3)
    cell = dataclasses.replace(cell, bus=dataclasses.replace(cell.bus, channel=f"real-{uuid.uuid4().hex[:12]}"))
    backend = RuntimeBackend(cell, sim=True)
    try:
        return serve(backend=backend)
    except BaseException:
        backend.close()
        raise
