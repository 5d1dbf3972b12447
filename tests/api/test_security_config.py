"""The [security] section, the rule builder over the key table, and the certificate tool (no network)."""

from __future__ import annotations

import dataclasses
import stat
import tomllib
from pathlib import Path
from typing import Any

import pytest
import zenoh
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import NameOID

from planner.config import SecuritySettings, cell_from_dict
from planner.errors import PlanningError
from streamer.api import security as sec
from streamer.api.certs import CertError, common_name, init_certs
from streamer.api.security import KEY_ACCESS, KeyAccess, Op, SecurityError, Subject, access_control

ROOT = Path(__file__).resolve().parents[2]
DEMO = tomllib.loads((ROOT / "configs" / "demo.toml").read_text(encoding="utf-8"))


def cell_with(security: dict[str, Any]) -> Any:
    return cell_from_dict({**DEMO, "security": security}, source="cell.toml")


GOOD = {
    "enabled": True,
    "ca": "certs/ca.pem",
    "certificate": "certs/service.pem",
    "private_key": "certs/service.key",
    "operator": ["cn:pvt-operator"],
    "observer": ["cn:pvt-observer"],
    "service": ["cn:pvt-service"],
}


# -- [security] ------------------------------------------------------------------------------------
def test_security_is_off_by_default_and_loads_from_toml() -> None:
    assert cell_from_dict(DEMO).security == SecuritySettings()
    assert SecuritySettings().enabled is False
    s = cell_with(GOOD).security
    assert s.enabled and s.mtls and s.operator == ("cn:pvt-operator",) and s.ca == "certs/ca.pem"


@pytest.mark.parametrize(
    ("change", "path", "words"),
    [
        ({"ca": ""}, "security.ca", "required"),
        ({"enabled": "yes"}, "security.enabled", "true or false"),
        ({"mtls": 1}, "security.mtls", "true or false"),
        ({"operator": ["pvt-operator"]}, "security.operator", "cn:NAME"),
        ({"operator": "cn:pvt-operator"}, "security.operator", "list of strings"),
        ({"observer": ["cn:pvt-operator"]}, "security.observer", "both operator and observer"),
        ({"mtls": False}, "security.operator", "mtls = false"),
        ({"operator": ["user:alice"]}, "security.operator", "no users_file"),
        ({"mtls": False, "operator": [], "observer": [], "service": []}, "security.mtls", "users_file"),
        ({"operator": [], "observer": [], "service": []}, "security.operator", "nobody"),
        ({"user": "svc"}, "security.user", "password_file"),
        ({"roles": {}}, "security.roles", "unknown key"),
    ],
)
def test_bad_security_sections_name_the_field(change: dict[str, Any], path: str, words: str) -> None:
    with pytest.raises(PlanningError) as info:
        cell_with({**GOOD, **change})
    assert info.value.code == "CONFIG" and info.value.path == path and words in info.value.message


def test_logins_and_combined_subjects_are_accepted() -> None:
    s = cell_with(
        {**GOOD, "users_file": "users.txt", "operator": ["cn:pvt-operator+user:alice", "user:bob"]}
    ).security
    assert s.users_file == "users.txt" and len(s.operator) == 2
    off = cell_with({"ca": "x"}).security  # present but not enabled: nothing is required
    assert not off.enabled


# -- the rules ---------------------------------------------------------------------------------------
def _keys(acl: dict[str, Any], role: str, flow: str, message: str) -> list[str]:
    out: list[str] = []
    policy = next(p for p in acl["policies"] if p["id"] == f"{role}-policy")
    for rule in acl["rules"]:
        if rule["id"] in policy["rules"] and flow in rule["flows"] and message in rule["messages"]:
            out += rule["key_exprs"]
    return out


def _allows(patterns: list[str], key: str) -> bool:
    """Zenoh's own test: a rule applies to a message when its key expression includes the message's."""
    return any(zenoh.KeyExpr(p).includes(zenoh.KeyExpr(key)) for p in patterns)


ACL = access_control({"operator": ["cn:op"], "observer": ["cn:ob"], "service": ["cn:svc"]})
WRITES = ["pvt/demo/submit", "pvt/demo/jobs/j1/cancel", "pvt/demo/reset", "pvt/demo/stop", "pvt/demo/hold",
          "pvt/demo/resume"]
FUTURE_WRITES = ["pvt/demo/jobs/j1/change", "pvt/demo/halt", "pvt/demo/record", "pvt/demo/x/y"]
READS = ["pvt/demo/jobs", "pvt/demo/jobs/j1", "pvt/demo/jobs/j1/events", "pvt/demo/service", "pvt/*/service"]


def test_default_deny_and_one_policy_per_role() -> None:
    assert ACL["enabled"] is True and ACL["default_permission"] == "deny"
    assert [p["id"] for p in ACL["policies"]] == ["observer-policy", "operator-policy", "service-policy"]
    assert {s["id"]: s.get("cert_common_names") for s in ACL["subjects"]} == {
        "observer-0": ["ob"], "operator-0": ["op"], "service-0": ["svc"]
    }
    assert all(r["permission"] == "allow" for r in ACL["rules"])


def test_observers_read_and_never_write() -> None:
    queries = _keys(ACL, "observer", "ingress", "query")
    assert all(_allows(queries, k) for k in READS)
    assert not any(_allows(queries, k) for k in WRITES + FUTURE_WRITES)
    assert not any(_allows(queries, k) for k in ("pvt/demo/**", "pvt/**", "pvt/demo/jobs/*/*"))  # no wildcard way
    assert _keys(ACL, "observer", "ingress", "put") == []
    subs = _keys(ACL, "observer", "ingress", "declare_subscriber")
    assert all(_allows(subs, k) for k in ("pvt/demo/telemetry", "pvt/demo/jobs/j1/events", "pvt/demo/rejected"))
    assert _allows(_keys(ACL, "observer", "egress", "put"), "pvt/demo/telemetry")
    assert _allows(_keys(ACL, "observer", "ingress", "liveliness_query"), "pvt/*/alive")
    assert _allows(_keys(ACL, "observer", "egress", "liveliness_token"), "pvt/demo/alive")
    for message in ("declare_queryable", "liveliness_token", "reply", "delete"):  # never stands in for a service
        assert _keys(ACL, "observer", "ingress", message) == []


def test_operators_may_do_every_request_including_future_ones() -> None:
    queries = _keys(ACL, "operator", "ingress", "query")
    assert all(_allows(queries, k) for k in READS + WRITES + FUTURE_WRITES)
    assert _allows(_keys(ACL, "operator", "ingress", "put"), "pvt/demo/submit")
    assert not _allows(_keys(ACL, "operator", "ingress", "put"), "pvt/demo/telemetry")  # cannot fake telemetry
    assert _allows(_keys(ACL, "operator", "egress", "reply"), "pvt/demo/jobs/j1/change")
    assert _allows(_keys(ACL, "operator", "egress", "declare_subscriber"), "pvt/demo/submit")
    for message in ("declare_queryable", "liveliness_token", "reply", "delete"):
        assert _keys(ACL, "operator", "ingress", message) == []


def test_the_service_role_may_do_everything_under_pvt() -> None:
    for flow in ("ingress", "egress"):
        for message in sec.ALL_MESSAGES:
            assert _keys(ACL, "service", flow, message) == ["pvt/**"]


def test_a_new_key_is_one_line_in_the_table(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sec, "KEY_ACCESS", (*KEY_ACCESS, KeyAccess("recordings/*", Op.QUERY, "observer", "x")))
    acl = access_control({"observer": ["cn:ob"]})
    assert _allows(_keys(acl, "observer", "ingress", "query"), "pvt/demo/recordings/r1")
    assert _allows(_keys(acl, "observer", "egress", "reply"), "pvt/demo/recordings/r1")
    assert not _allows(_keys(ACL, "observer", "ingress", "query"), "pvt/demo/recordings/r1")


def test_roles_without_subjects_get_no_policy_and_unknown_roles_are_refused() -> None:
    acl = access_control({"operator": ["user:alice"], "observer": []})
    assert [p["id"] for p in acl["policies"]] == ["operator-policy"]
    assert acl["subjects"] == [{"id": "operator-0", "usernames": ["alice"]}]
    with pytest.raises(SecurityError):
        access_control({"admin": ["cn:x"]})
    with pytest.raises(ValueError):
        KeyAccess("submit", Op.QUERY, "service", "services are not a client role")


def test_subjects_parse() -> None:
    assert Subject.parse("cn:a") == Subject("a", None)
    assert Subject.parse("user:b") == Subject(None, "b")
    assert Subject.parse("cn:a+user:b") == Subject("a", "b") == Subject.parse("user:b + cn:a")
    assert Subject.parse("cn:a+user:b").to_zenoh("s") == {"id": "s", "cert_common_names": ["a"], "usernames": ["b"]}
    for bad in ("a", "cn:", "dn:a", "cn:a+cn:b", "user:a+user:b"):
        with pytest.raises(SecurityError):
            Subject.parse(bad)


@pytest.mark.parametrize(
    ("endpoint", "loopback"),
    [
        ("tcp/127.0.0.1:7447", True),
        ("tls/127.0.0.5:7447", True),
        ("tcp/[::1]:7447", True),
        ("tcp/localhost:7447", True),
        ("tcp/127.0.0.1:7447#iface=lo", True),
        ("tcp/0.0.0.0:7447", False),
        ("tcp/[::]:7447", False),
        ("tls/192.168.1.20:7447", False),
        ("tcp/cell-3.example.com:7447", False),
    ],
)
def test_loopback_endpoints(endpoint: str, loopback: bool) -> None:
    assert sec.is_loopback(endpoint) is loopback


def test_client_security_checks_its_files_and_pairs(tmp_path: Path) -> None:
    made = init_certs(tmp_path)
    ok = sec.ClientSecurity(ca=made.ca_certificate, certificate=made["operator"].certificate,
                            private_key=made["operator"].private_key, user="u", password="p")
    settings = ok.zenoh_settings()
    assert settings["transport/link/tls/enable_mtls"] is True
    assert settings["transport/auth/usrpwd/user"] == "u"
    cases: list[dict[str, Any]] = [
        {"ca": made.ca_certificate, "certificate": made["operator"].certificate},  # no key
        {"certificate": made["operator"].certificate, "private_key": made["operator"].private_key},  # no CA
        {"user": "u"},  # no password
        {"ca": tmp_path / "missing.pem"},
        {"ca": made["operator"].private_key},  # a key is not a certificate
    ]
    for kw in cases:
        with pytest.raises(SecurityError):
            sec.ClientSecurity(**kw)


# -- certificates ------------------------------------------------------------------------------------
def test_init_certs_makes_a_ca_and_loopback_certificates(tmp_path: Path) -> None:
    made = init_certs(tmp_path / "c", hosts=["10.1.2.3", "cell.example"], identities={"service": "svc", "op": "op"})
    ca = x509.load_pem_x509_certificate(made.ca_certificate.read_bytes())
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca is True
    for stem, cn in (("service", "svc"), ("op", "op")):
        ident = made[stem]
        cert = x509.load_pem_x509_certificate(ident.certificate.read_bytes())
        cert.verify_directly_issued_by(ca)
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == cn == common_name(ident.certificate)
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert {str(ip) for ip in san.get_values_for_type(x509.IPAddress)} == {"127.0.0.1", "::1", "10.1.2.3"}
        assert san.get_values_for_type(x509.DNSName) == ["localhost", "cell.example"]
        assert stat.S_IMODE(ident.private_key.stat().st_mode) == 0o600
    assert stat.S_IMODE(made.ca_private_key.stat().st_mode) == 0o600
    with pytest.raises(CertError) as info:
        init_certs(tmp_path / "c", identities={"service": "svc"})
    assert info.value.code == "CERT_EXISTS"
    again = init_certs(tmp_path / "c", identities={"service": "svc"}, force=True)
    assert again.ca_certificate.read_bytes() != ca.public_bytes(Encoding.PEM)  # a new CA


@pytest.mark.parametrize(
    ("kw", "code"),
    [
        ({"identities": {"ca": "x"}}, "CERT_NAME"),
        ({"identities": {"a/b": "x"}}, "CERT_NAME"),
        ({"identities": {"a": ""}}, "CERT_NAME"),
        ({"identities": {}}, "CERT_NAME"),
        ({"hosts": ["bad host"]}, "CERT_HOST"),
        ({"days": 0}, "CERT_DAYS"),
    ],
)
def test_init_certs_refuses_bad_input(tmp_path: Path, kw: dict[str, Any], code: str) -> None:
    with pytest.raises(CertError) as info:
        init_certs(tmp_path, **kw)
    assert info.value.code == code


def test_settings_with_relative_files_resolve_against_the_config(tmp_path: Path) -> None:
    made = init_certs(tmp_path / "certs")
    users = tmp_path / "users.txt"
    users.write_text("a:b\n")
    (tmp_path / "svc.password").write_text("s3cret\n")
    s = dataclasses.replace(
        cell_with(GOOD).security, users_file="users.txt", user="svc", password_file="svc.password"
    )
    out = sec.service_settings(s, base=tmp_path)
    assert out["transport/link/tls/root_ca_certificate"] == str(made.ca_certificate)
    assert out["transport/link/tls/listen_certificate"] == out["transport/link/tls/connect_certificate"]
    assert out["transport/auth/usrpwd/dictionary_file"] == str(users)
    assert out["transport/auth/usrpwd/password"] == "s3cret"
    assert out["access_control"]["default_permission"] == "deny"
    assert sec.service_settings(SecuritySettings(), base=tmp_path) == {}
