"""Security on loopback with real TLS: certificates made in the test (conftest `certs`), a service with
[security] (TLS, mutual TLS, access rules from the roles), operator / observer / stranger clients.

What each test shows is in its name; every refusal has a positive control beside it, so a test cannot
pass because something is broken in general.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import pytest
import zenoh

from planner.config import CellConfig
from streamer.api import keys
from streamer.api.certs import CertSet
from streamer.api.client import MotionClient
from streamer.api.errors import MotionError
from streamer.api.model import JobState
from streamer.api.payload import pack
from streamer.api.security import ClientSecurity, SecurityError
from streamer.api.zenoh_config import client_config
from tests.api.conftest import Served, identity, secure_settings
from tests.api.fakes import timed_job
from tests.api.helpers import Collector, wait_for

Serve = Callable[..., Served]


def _runtime(cell: CellConfig) -> Any:
    from streamer.api.backend import DEFAULT_BACKEND, BackendUnavailable, load_backend

    try:
        return load_backend(DEFAULT_BACKEND, cell, sim=True)
    except BackendUnavailable as exc:
        pytest.skip(f"motion runtime not available: {exc}")


def _refused(action: Callable[[], object]) -> MotionError:
    with pytest.raises(MotionError) as info:
        action()
    assert info.value.code == "PERMISSION_DENIED", info.value
    assert "operator" in info.value.message and "docs/security.md" in info.value.message
    return info.value


def test_operator_moves_the_simulated_drives_while_an_observer_watches(
    serve: Serve, certs: CertSet, demo_cell: CellConfig
) -> None:
    backend = _runtime(demo_cell)
    try:
        served = serve(backend=backend, security=secure_settings(certs))
        assert served.endpoint.startswith("tls/127.0.0.1:")
        with (
            served.client(security=identity(certs, "operator")) as op,
            served.client(security=identity(certs, "observer")) as ob,
        ):
            op.wait_for_service(timeout=10)
            ob.wait_for_service(timeout=10)
            seen = Collector(ob.session, keys.job_events_any("demo"))
            job = op.submit({"kind": "move", "axes": ["j1", "j2"], "target": [0.3, -0.2]})
            status = job.wait(timeout=60)
            assert status.state == JobState.DONE
            assert status.report is not None and status.report["result"] == "done"
            seen.until(lambda m: m["job_id"] == job.job_id and m["type"] == "done", timeout=10)
            types = [m["type"] for m in seen.all if m["job_id"] == job.job_id]
            assert types[:4] == ["accepted", "planned", "priming", "running"] and types[-1] == "done"
            tele = ob.telemetry(timeout=5)
            axes = {a["name"]: a for a in tele["axes"]}
            assert abs(axes["j1"]["position"] - 0.3) < 1e-3 and abs(axes["j2"]["position"] + 0.2) < 1e-3
            seen.close()
    finally:
        backend.close()


@pytest.mark.parametrize("mode", ["auto", "peer"])
def test_observer_writes_are_refused_while_it_reads_events_and_telemetry(
    serve: Serve, certs: CertSet, mode: str
) -> None:
    served = serve(security=secure_settings(certs))
    # a stand-in for the change request of issue 15: a handler the service declares on its session
    changes: list[str] = []

    def on_change(query: zenoh.Query) -> None:
        changes.append(str(query.key_expr))
        query.reply(str(query.key_expr), pack({"changed": True}))

    change_handler = served.session.declare_queryable(f"{keys.base('demo')}/jobs/*/change", on_change)
    with (
        served.client(security=identity(certs, "operator"), mode=mode) as op,
        served.client(security=identity(certs, "observer"), mode=mode) as ob,
    ):
        op.wait_for_service(timeout=5)
        ob.wait_for_service(timeout=5)
        job = op.submit(timed_job(1.5, axes=["j1"]), job_id="operator-job")
        watched = ob.job(job.job_id)  # the observer follows the operator's job
        for ev in watched.events(timeout=10):
            if ev.type == "running":
                break
        _refused(lambda: ob.submit(timed_job(0.1), job_id="observer-job"))
        _refused(lambda: ob.job(job.job_id).cancel())
        _refused(lambda: ob._query(f"{keys.job('demo', job.job_id)}/change", payload=pack({"target": [0.0]})))
        _refused(lambda: ob.reset())
        _refused(lambda: ob.stop())  # stop, emergency stop, hold and resume: operators only
        _refused(lambda: ob.stop(emergency=True))
        _refused(lambda: ob.hold())
        _refused(lambda: ob.resume())
        assert ob.service_status()["held"] is False  # nothing of it reached the service
        ob.submit_put(timed_job(0.1), job_id="observer-put").close()  # a put has no answer: dropped
        assert changes == []
        # the operator's change reaches the handler (the rule, not a missing handler, refused the observer)
        assert op._query(f"{keys.job('demo', job.job_id)}/change", payload=pack({})) == {"changed": True}
        assert changes == [f"pvt/demo/jobs/{job.job_id}/change"]
        # the observer still reads: the job's events to the end (it was not cancelled), telemetry, lists
        events = list(watched.events(timeout=10))
        assert events[-1].type == "done" and [e.seq for e in events] == list(range(1, len(events) + 1))
        assert ob.telemetry(timeout=3)["cell"] == "demo"
        assert [s.job_id for s in ob.jobs()] == ["operator-job"]
        assert ob.service_status()["cell"] == "demo"
        # an operator's put is accepted, so the observer's was refused by the rules, not lost
        assert op.submit_put(timed_job(0.05), job_id="operator-put").wait(timeout=10).state == JobState.DONE
    change_handler.undeclare()
    assert [r.job_id for r in served.store.list_jobs()] == ["operator-put", "operator-job"]
    assert served.store.get("observer-job") is None and served.store.get("observer-put") is None
    assert served.backend.executed == ["?", "?"]  # the operator's two jobs, nothing else ran


@pytest.mark.parametrize("secure", [True, False], ids=["secured", "plain"])
def test_clients_cannot_pose_as_the_service(serve: Serve, certs: CertSet, secure: bool) -> None:
    """An operator or observer that declares the service's queryable or publishes its telemetry reaches
    nobody when the rules are on; without them (plain), the same fake is answered and seen."""
    served = serve(security=secure_settings(certs) if secure else None)

    def client(name: str) -> MotionClient:
        return served.client(security=identity(certs, name) if secure else None, mode="client")

    with client("operator") as op, client("observer") as ob, client("observer") as watcher:
        watcher.wait_for_service(timeout=5)
        def fake_status(query: zenoh.Query) -> None:
            query.reply(keys.service("demo"), pack({"fake": 1}))

        fakes = [c.session.declare_queryable(keys.service("demo"), fake_status) for c in (op, ob)]
        tele = Collector(watcher.session, keys.telemetry("demo"))
        time.sleep(0.5)  # let the declarations travel
        for c in (op, ob):
            c.session.put(keys.telemetry("demo"), pack({"fake": 1}))
        every_reply = watcher.session.get(  # no consolidation: see every answer, not the latest one
            keys.service("demo"),
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=3,
        )
        replies = [msgpack.unpackb(r.ok.payload.to_bytes()) for r in every_reply if r.ok is not None]
        time.sleep(0.3)
        tele.until(lambda m: "axes" in m, timeout=3)
        fake_samples = [m for m in tele.all if "fake" in m]
        while not tele.items.empty():
            m = tele.items.get()
            fake_samples += [m] if "fake" in m else []
        tele.close()
        for f in fakes:
            f.undeclare()
    real = [r for r in replies if r.get("cell") == "demo"]
    assert len(real) == 1
    if secure:
        assert len(replies) == 1 and fake_samples == []
    else:
        assert len(replies) == 3 and len(fake_samples) == 2


def test_a_certificate_of_the_ca_without_a_role_gets_nothing(serve: Serve, certs: CertSet) -> None:
    served = serve(security=secure_settings(certs))
    with served.client(security=identity(certs, "stranger"), mode="client", timeout=2) as stranger:
        with pytest.raises(MotionError) as info:
            stranger.wait_for_service(timeout=1)  # not even the liveliness token is visible
        assert info.value.code == "TIMEOUT"
        with pytest.raises(MotionError) as info:
            stranger.submit(timed_job(0.1), job_id="stranger-job")
        assert info.value.code in ("NO_SERVICE", "PERMISSION_DENIED")
        with pytest.raises(MotionError):
            stranger.jobs()
    with served.client(security=identity(certs, "operator"), mode="client") as op:
        op.wait_for_service(timeout=5)
        assert op.jobs() == []
    assert served.store.count() == 0


def _cannot_connect(endpoint: str, security: ClientSecurity | None) -> None:
    """Refused at the link: no Zenoh client session opens, and a retrying peer never sees the service."""
    with pytest.raises(zenoh.ZError):
        zenoh.open(client_config(endpoint, mode="client", security=security))
    with pytest.raises(MotionError) as info:
        MotionClient(connect=endpoint, cell="demo", mode="client", security=security)
    assert info.value.code == "NO_SERVICE" and "cannot connect" in info.value.message
    with MotionClient(connect=endpoint, cell="demo", security=security) as peer:  # auto: a peer retries
        with pytest.raises(MotionError) as info:
            peer.wait_for_service(timeout=1)
        assert info.value.code == "TIMEOUT"
        assert ("refused this client's certificate or login" in info.value.message) == (security is not None)


def test_no_certificate_or_one_from_another_ca_cannot_connect(
    serve: Serve, certs: CertSet, other_certs: CertSet
) -> None:
    served = serve(security=secure_settings(certs))
    ep = served.endpoint
    _cannot_connect(ep, ClientSecurity(ca=certs.ca_certificate))  # no client certificate (mutual TLS)
    foreign = other_certs["operator"]  # same common name, signed by another CA
    _cannot_connect(
        ep, ClientSecurity(ca=certs.ca_certificate, certificate=foreign.certificate, private_key=foreign.private_key)
    )
    _cannot_connect(ep, identity(other_certs, "operator"))  # trusts another CA: the service is refused too
    with served.client(security=identity(certs, "operator"), mode="client") as op:  # positive control
        op.wait_for_service(timeout=5)
        assert op.submit(timed_job(0.05)).wait(timeout=10).state == JobState.DONE
    assert served.store.count() == 1


def test_plain_tcp_client_cannot_reach_a_tls_only_service(serve: Serve, certs: CertSet) -> None:
    served = serve(security=secure_settings(certs))
    plain = served.endpoint.replace("tls/", "tcp/")
    _cannot_connect(plain, None)
    with pytest.raises(SecurityError) as info:  # TLS options with a tcp/ endpoint: a mistake, said at once
        MotionClient(connect=plain, cell="demo", security=identity(certs, "operator"))
    assert info.value.code == "SECURITY_CONFIG" and "tls/" in info.value.message


def test_login_wrong_password_is_refused(serve: Serve, certs: CertSet, tmp_path: Path) -> None:
    users = tmp_path / "users.txt"
    users.write_text("alice:correct-horse\nbob:battery-staple\n", encoding="utf-8")
    served = serve(security=secure_settings(certs, users_file=str(users)))
    ep = served.endpoint
    _cannot_connect(ep, identity(certs, "operator", user="alice", password="wrong"))
    _cannot_connect(ep, identity(certs, "operator"))  # no login at all
    _cannot_connect(ep, identity(certs, "operator", user="mallory", password="correct-horse"))
    with served.client(security=identity(certs, "operator", user="alice", password="correct-horse")) as op:
        op.wait_for_service(timeout=5)
        assert op.submit(timed_job(0.05)).wait(timeout=10).state == JobState.DONE


def test_roles_by_login_and_by_certificate_plus_login(serve: Serve, certs: CertSet, tmp_path: Path) -> None:
    users = tmp_path / "users.txt"
    users.write_text("alice:correct-horse\nbob:battery-staple\n", encoding="utf-8")
    # logins only (no client certificates): alice operates, bob observes
    by_login = secure_settings(
        certs, mtls=False, users_file=str(users), operator=("user:alice",), observer=("user:bob",), service=()
    )
    served = serve(security=by_login)
    ca_only = {"ca": certs.ca_certificate}
    with (
        served.client(security=ClientSecurity(**ca_only, user="alice", password="correct-horse")) as alice,
        served.client(security=ClientSecurity(**ca_only, user="bob", password="battery-staple")) as bob,
    ):
        alice.wait_for_service(timeout=5)
        bob.wait_for_service(timeout=5)
        _refused(lambda: bob.submit(timed_job(0.05), job_id="bob-job"))
        assert alice.submit(timed_job(0.05), job_id="alice-job").wait(timeout=10).state == JobState.DONE
        assert [s.job_id for s in bob.jobs()] == ["alice-job"]
    # both: the operator certificate *and* alice's login; the operator certificate with bob's login is nobody
    both = secure_settings(
        certs, users_file=str(users), operator=("cn:pvt-operator+user:alice",), observer=("cn:pvt-observer",)
    )
    served = serve(security=both)
    with (
        served.client(security=identity(certs, "operator", user="alice", password="correct-horse")) as op,
        served.client(security=identity(certs, "operator", user="bob", password="battery-staple"),
                      mode="client", timeout=2) as wrong,
    ):
        op.wait_for_service(timeout=5)
        assert op.submit(timed_job(0.05)).wait(timeout=10).state == JobState.DONE
        with pytest.raises(MotionError):
            wrong.submit(timed_job(0.05), job_id="bob-as-operator")
    assert served.store.get("bob-as-operator") is None


def test_the_rules_follow_the_roles_of_the_config(serve: Serve, certs: CertSet) -> None:
    """The observer certificate given the operator role may write: the config, not the certificate, decides."""
    swapped = secure_settings(certs, operator=("cn:pvt-observer",), observer=("cn:pvt-operator",))
    served = serve(security=swapped)
    with (
        served.client(security=identity(certs, "observer")) as now_operator,
        served.client(security=identity(certs, "operator")) as now_observer,
    ):
        now_operator.wait_for_service(timeout=5)
        now_observer.wait_for_service(timeout=5)
        assert now_operator.submit(timed_job(0.05)).wait(timeout=10).state == JobState.DONE
        _refused(lambda: now_observer.submit(timed_job(0.05)))


def test_unprotected_service_beyond_loopback_warns(caplog: pytest.LogCaptureFixture, certs: CertSet) -> None:
    from planner.config import ZenohSettings
    from streamer.api.zenoh_config import service_config

    with caplog.at_level("WARNING", logger="streamer.api.zenoh_config"):
        service_config(ZenohSettings())  # the default: loopback only
        service_config(ZenohSettings(listen=("tcp/127.0.0.1:7447", "tcp/[::1]:7447", "tcp/localhost:7447")))
        assert caplog.records == []
        service_config(ZenohSettings(listen=("tcp/0.0.0.0:7447",)))
        service_config(ZenohSettings(listen=("tcp/127.0.0.1:7447",), connect=("tcp/192.168.1.20:7447",)))
        messages = [r.getMessage() for r in caplog.records]
        assert len(messages) == 2
        assert "tcp/0.0.0.0:7447 beyond loopback without TLS and access control" in messages[0]
        assert "192.168.1.20" in messages[1]
        caplog.clear()
        service_config(ZenohSettings(listen=("tls/0.0.0.0:7447",)), security=secure_settings(certs))
        assert caplog.records == []


def test_a_secured_service_refuses_plain_endpoints_and_missing_files(certs: CertSet, tmp_path: Path) -> None:
    from planner.config import ZenohSettings
    from streamer.api.zenoh_config import service_config

    with pytest.raises(SecurityError) as info:
        service_config(
            ZenohSettings(listen=("tls/127.0.0.1:7447", "tcp/127.0.0.1:7448")), security=secure_settings(certs)
        )
    assert info.value.code == "SECURITY_CONFIG" and "tcp/127.0.0.1:7448" in info.value.message
    with pytest.raises(SecurityError) as info:
        service_config(ZenohSettings(connect=("tcp/127.0.0.1:7448",), listen=()), security=secure_settings(certs))
    assert info.value.path == "zenoh.connect"
    missing = dataclasses.replace(secure_settings(certs), private_key=str(tmp_path / "nope.key"))
    with pytest.raises(SecurityError) as info:
        service_config(ZenohSettings(listen=("tls/127.0.0.1:7447",)), security=missing)
    assert info.value.code == "SECURITY_FILE" and info.value.path == "security.private_key"
    not_pem = tmp_path / "ca.txt"
    not_pem.write_text("hello")
    with pytest.raises(SecurityError) as info:
        service_config(ZenohSettings(listen=("tls/127.0.0.1:7447",)),
                       security=dataclasses.replace(secure_settings(certs), ca=str(not_pem)))
    assert info.value.code == "SECURITY_FILE" and "PEM" in info.value.message


def test_operator_cancels_and_the_observer_sees_the_job_cancelled(serve: Serve, certs: CertSet) -> None:
    """An operator's cancel works, and the observer sees the job end cancelled."""
    served = serve(security=secure_settings(certs))
    with (
        served.client(security=identity(certs, "operator")) as op,
        served.client(security=identity(certs, "observer")) as ob,
    ):
        op.wait_for_service(timeout=5)
        job = op.submit(timed_job(5.0), job_id="long")
        wait_for(lambda: served.service.running_job == "long", timeout=5, what="the job to start")
        assert op.job("long").cancel().raw["cancel_requested"] is True
        assert [e.type for e in ob.job("long").events(timeout=10)][-1] == "cancelled"
        assert job.wait(timeout=10).state == JobState.CANCELLED
