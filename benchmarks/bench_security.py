"""What security costs: submit -> accepted latency with TLS + access control against plain TCP.

In one run, on loopback, with a job service and a Zenoh client in the same process (certificates made
for the run by `streamer.api.certs`), the same submissions three ways:

1. plain TCP, no access control (the default, the baseline);
2. TLS with mutual authentication, no access control (what the encryption costs);
3. TLS with mutual authentication and the access rules of the roles (`[security]` as documented).

Each submission is the demo's default job through the strict decoder and the SQLite journal (full
sync, as in production) with a trivial planner (a fixed 1-point plan), so the measurement is the API
path where the link and the rules act, not the planner. Also: the time to open a client session
(the TLS and mutual-authentication handshake).

Target: TLS + access control submit->accepted p50 <= 1.5 x plain TCP.

Run: python -m benchmarks.bench_security [--n 100]
"""

from __future__ import annotations

import argparse
import tempfile
import time
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import zenoh

from benchmarks.bench_api import ROOT, _Backend, _free_port, _pct, find_job
from planner.config import CellConfig, SecuritySettings, ZenohSettings, load_cell
from streamer.api.backend import Planned
from streamer.api.certs import CertSet, init_certs
from streamer.api.client import MotionClient
from streamer.api.security import ClientSecurity
from streamer.api.service import JobService
from streamer.api.store import JobStore
from streamer.api.zenoh_config import service_config


def _security(certs: CertSet) -> SecuritySettings:
    return SecuritySettings(
        enabled=True,
        ca=str(certs.ca_certificate),
        certificate=str(certs["service"].certificate),
        private_key=str(certs["service"].private_key),
        operator=("cn:pvt-operator",),
        observer=("cn:pvt-observer",),
        service=("cn:pvt-service",),
    )


def measure(
    cell: CellConfig, job: dict[str, Any], n: int, *, certs: CertSet | None, acl: bool
) -> tuple[list[float], list[float]]:
    """(submit->accepted seconds n times after 3 warm-ups, client session open seconds 5 times)."""
    port = _free_port()
    endpoint = f"{'tls' if certs else 'tcp'}/127.0.0.1:{port}"
    settings = ZenohSettings(listen=(endpoint,))
    if certs is not None:
        conf = service_config(settings, security=_security(certs))
        if not acl:  # TLS and mutual TLS as configured, but the rules switched off
            conf.insert_json5("access_control/enabled", "false")
        client_security: ClientSecurity | None = ClientSecurity(
            ca=certs.ca_certificate,
            certificate=certs["operator"].certificate,
            private_key=certs["operator"].private_key,
        )
    else:
        conf = service_config(settings)
        client_security = None
    session: Any = zenoh.open(conf)
    backend = _Backend(
        cell, lambda body: dict(body), lambda j: Planned(job=j, trajectory=None, duration_s=0.0, points=1)
    )
    with tempfile.TemporaryDirectory() as tmp:
        store = JobStore(Path(tmp) / "bench.jobs.sqlite")  # synchronous=FULL, as in production
        service = JobService(session, backend, store).start()
        try:
            opens = []
            for _ in range(5):
                t0 = time.perf_counter()
                with MotionClient(connect=endpoint, cell=cell.name, mode="client", security=client_security):
                    opens.append(time.perf_counter() - t0)
            with MotionClient(connect=endpoint, cell=cell.name, timeout=60, security=client_security) as client:
                client.wait_for_service(timeout=10)
                out = []
                for i in range(n + 3):
                    t0 = time.perf_counter()
                    handle = client.submit(job, job_id=uuid.uuid4().hex)
                    dt = time.perf_counter() - t0
                    handle.close()
                    if i >= 3:
                        out.append(dt)
                    while service.queue_length:  # keep the queue from filling up (BUSY)
                        time.sleep(0.001)
                return out, opens
        finally:
            service.close()
            store.close()
            session.close()


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Security cost benchmark (TLS + access control vs plain TCP)")
    parser.add_argument("--n", type=int, default=100, help="submits per measurement (default 100)")
    parser.add_argument("--config", default=str(ROOT / "configs" / "demo.toml"))
    args = parser.parse_args(argv)
    cell = load_cell(args.config)
    label, job = find_job(None)
    job.pop("job_id", None)
    with tempfile.TemporaryDirectory() as tmp:
        certs = init_certs(Path(tmp) / "certs")
        # interleave the three setups twice, so a slow phase of a shared machine hits all of them
        runs: dict[str, tuple[list[float], list[float]]] = {"plain": ([], []), "tls": ([], []), "tls+acl": ([], [])}
        for _ in range(2):
            for name, kw in (
                ("plain", {"certs": None, "acl": False}),
                ("tls", {"certs": certs, "acl": False}),
                ("tls+acl", {"certs": certs, "acl": True}),
            ):
                lat, opens = measure(cell, job, args.n // 2, **kw)
                runs[name][0].extend(lat)
                runs[name][1].extend(opens)
    plain = _pct(runs["plain"][0], 0.5)
    rows = []
    for name, title in (
        ("plain", "plain TCP (baseline)"),
        ("tls", "TLS + mutual TLS, no access control"),
        ("tls+acl", "TLS + mutual TLS + access control"),
    ):
        lat, opens = runs[name]
        rows.append(
            (
                f"{title}: submit->accepted p50 / p99",
                f"{1e3 * _pct(lat, 0.5):.2f} ms / {1e3 * _pct(lat, 0.99):.2f} ms"
                f"   (x{_pct(lat, 0.5) / plain:.2f} of plain p50)",
            )
        )
        rows.append((f"{title}: client session open p50", f"{1e3 * _pct(opens, 0.5):.2f} ms"))
    ratio = _pct(runs["tls+acl"][0], 0.5) / plain
    rows.append(("TLS + access control p50 / plain TCP p50 (target <= 1.5)", f"{ratio:.2f}"))
    print(f"Security cost ({label}, n={2 * (args.n // 2)} per setup, loopback, trivial planner, SQLite FULL)")
    width = max(len(r[0]) for r in rows)
    for name, value in rows:
        print(f"  {name:<{width}}  {value}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

