"""Who may do what on the job API: TLS links, logins, and Zenoh access rules built from roles.

Zenoh enforces; this module builds its configuration. With `[security] enabled` every endpoint is TLS,
mutual by default (no certificate from the cell's CA, no link), with optional logins. A session's subjects
(certificate CN, login name) map to roles observer (reads), operator (reads and writes), service (all).
`KEY_ACCESS` is the one table of the least role per key; `access_control()` turns it into Zenoh's
default-deny rules for the messages each operation needs both ways (docs/security.md). A new write key is
operator-only without an edit. The client (`ClientSecurity`) needs its CA, certificate, key and login.
"""

from __future__ import annotations

import enum
import ipaddress
import os
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from streamer.api.keys import PREFIX

OBSERVER = "observer"
OPERATOR = "operator"
SERVICE = "service"
ROLES = (OBSERVER, OPERATOR, SERVICE)  # each role may do everything the roles before it may
_RANK = {role: i for i, role in enumerate(ROLES)}


class Op(enum.Enum):
    """How a key is used (docs/api.md section 2)."""

    QUERY = "query"  # clients `get` it; the service replies
    PUT = "put"  # clients `put` on it; the service subscribes
    SUBSCRIBE = "subscribe"  # the service publishes on it; clients subscribe
    LIVELINESS = "liveliness"  # the service's liveliness token; clients query or watch it


# Zenoh message kinds an operation needs, (coming in from the client, going out to the client).
MESSAGES: dict[Op, tuple[tuple[str, ...], tuple[str, ...]]] = {
    Op.QUERY: (("query",), ("reply", "declare_queryable")),
    Op.PUT: (("put",), ("declare_subscriber",)),
    Op.SUBSCRIBE: (("declare_subscriber",), ("put",)),
    Op.LIVELINESS: (("liveliness_query", "declare_liveliness_subscriber"), ("liveliness_token",)),
}
ALL_MESSAGES = (
    "put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
    "liveliness_token", "liveliness_query", "declare_liveliness_subscriber",
)


@dataclass(frozen=True)
class KeyAccess:
    """One row of the key space: `pattern` under `pvt/<cell>/`, how it is used, the least role."""

    pattern: str
    op: Op
    role: str
    what: str

    def __post_init__(self) -> None:
        if self.role not in (OBSERVER, OPERATOR):
            raise ValueError(f"KEY_ACCESS row {self.pattern!r}: role must be observer or operator")
        if not self.pattern or self.pattern.startswith("/") or self.pattern.endswith("/"):
            raise ValueError(f"KEY_ACCESS row {self.pattern!r}: not a relative key expression")

    def key_expr(self, cell: str = "*") -> str:
        return f"{PREFIX}/{cell}/{self.pattern}"


# THE table: add a new key here (one line) and every role's rules follow. docs/security.md shows it.
KEY_ACCESS: tuple[KeyAccess, ...] = (
    KeyAccess("alive", Op.LIVELINESS, OBSERVER, "the service's liveliness token"),
    KeyAccess("service", Op.QUERY, OBSERVER, "service status"),
    KeyAccess("jobs", Op.QUERY, OBSERVER, "list jobs"),
    KeyAccess("jobs/*", Op.QUERY, OBSERVER, "one job's status"),
    KeyAccess("jobs/*/events", Op.QUERY, OBSERVER, "a job's journalled events"),
    KeyAccess("jobs/*/events", Op.SUBSCRIBE, OBSERVER, "a job's events as they happen"),
    KeyAccess("rejected", Op.SUBSCRIBE, OBSERVER, "rejected put submissions"),
    KeyAccess("telemetry", Op.SUBSCRIBE, OBSERVER, "per-axis telemetry"),
    KeyAccess("submit", Op.QUERY, OPERATOR, "submit a job"),
    KeyAccess("submit", Op.PUT, OPERATOR, "submit a job by put"),
    KeyAccess("jobs/*/cancel", Op.QUERY, OPERATOR, "cancel a job"),
    KeyAccess("reset", Op.QUERY, OPERATOR, "reset a faulted cell"),
    KeyAccess("stop", Op.QUERY, OPERATOR, "stop all (emergency=true: quick stop), hold the queue"),
    KeyAccess("hold", Op.QUERY, OPERATOR, "hold the queue"),
    KeyAccess("resume", Op.QUERY, OPERATOR, "release the hold (reset=true: clear a fault first)"),
    KeyAccess("**", Op.QUERY, OPERATOR, "every other request (change, halt, record, ...)"),
)


class SecurityError(Exception):
    """A security setting that cannot work; `code` is machine-readable, `path` names the setting."""

    def __init__(self, code: str, message: str, *, path: str = ""):
        super().__init__(message)
        self.code = code
        self.message = message
        self.path = path

    def __str__(self) -> str:
        return f"{self.code}: {self.message}"


SECURITY_CONFIG = "SECURITY_CONFIG"  # settings that contradict each other or an endpoint
SECURITY_FILE = "SECURITY_FILE"  # a certificate, key or users file that is missing or unreadable


# -- subjects and rules --------------------------------------------------------------------------
@dataclass(frozen=True)
class Subject:
    """Who a remote session is: its certificate's common name and/or its login (both must match)."""

    cert_common_name: str | None = None
    username: str | None = None

    @classmethod
    def parse(cls, text: str) -> Subject:
        """'cn:NAME', 'user:NAME' or 'cn:NAME+user:NAME' (the form of the [security] role lists)."""
        cn = user = None
        for part in text.split("+"):
            kind, sep, value = part.strip().partition(":")
            value = value.strip()
            if not sep or not value or kind.strip() not in ("cn", "user"):
                raise SecurityError(
                    SECURITY_CONFIG, f"subject {text!r}: write 'cn:NAME', 'user:NAME' or 'cn:NAME+user:NAME'"
                )
            if kind.strip() == "cn":
                if cn is not None:
                    raise SecurityError(SECURITY_CONFIG, f"subject {text!r} names two common names")
                cn = value
            else:
                if user is not None:
                    raise SecurityError(SECURITY_CONFIG, f"subject {text!r} names two users")
                user = value
        return cls(cn, user)

    def to_zenoh(self, subject_id: str) -> dict[str, Any]:
        out: dict[str, Any] = {"id": subject_id}
        if self.cert_common_name is not None:
            out["cert_common_names"] = [self.cert_common_name]
        if self.username is not None:
            out["usernames"] = [self.username]
        return out


def _allowed(role: str, cell: str) -> dict[tuple[str, str], list[str]]:
    """(flow, message) -> key expressions a client of `role` may use."""
    out: dict[tuple[str, str], list[str]] = {}
    for row in KEY_ACCESS:
        if _RANK[row.role] > _RANK[role]:
            continue
        ingress, egress = MESSAGES[row.op]
        for flow, messages in (("ingress", ingress), ("egress", egress)):
            for message in messages:
                keys = out.setdefault((flow, message), [])
                if row.key_expr(cell) not in keys:
                    keys.append(row.key_expr(cell))
    return out


def access_control(roles: Mapping[str, Sequence[str]], *, cell: str = "*") -> dict[str, Any]:
    """Zenoh's `access_control` section for these roles ({role: [subject, ...]}).

    Default deny. Observers and operators get the rows of `KEY_ACCESS` their role allows; `service`
    subjects (other services, routers of the deployment) get every message on `pvt/**`. `cell`
    narrows the rules to one cell (default: every cell).
    """
    unknown = sorted(set(roles) - set(ROLES))
    if unknown:
        raise SecurityError(SECURITY_CONFIG, f"unknown role(s) {unknown}; roles are {list(ROLES)}")
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for role in ROLES:
        names = list(roles.get(role, ()))
        if not names:
            continue
        subject_ids = []
        for i, text in enumerate(names):
            sid = f"{role}-{i}"
            subjects.append(Subject.parse(text).to_zenoh(sid))
            subject_ids.append(sid)
        if role == SERVICE:
            grants = {
                (flow, message): [f"{PREFIX}/**"] for flow in ("ingress", "egress") for message in ALL_MESSAGES
            }
        else:
            grants = _allowed(role, cell)
        rule_ids = []
        for (flow, message), keys in grants.items():
            rid = f"{role}-{flow}-{message}"
            rules.append(
                {"id": rid, "messages": [message], "flows": [flow], "permission": "allow", "key_exprs": keys}
            )
            rule_ids.append(rid)
        policies.append({"id": f"{role}-policy", "rules": rule_ids, "subjects": subject_ids})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


# -- endpoints -----------------------------------------------------------------------------------
def endpoint_protocol(endpoint: str) -> str:
    return endpoint.split("/", 1)[0].lower()


def endpoint_host(endpoint: str) -> str:
    """The host part of 'proto/host:port[?meta][#config]' ('' when there is none)."""
    address = endpoint.split("/", 1)[1] if "/" in endpoint else endpoint
    address = address.split("#", 1)[0].split("?", 1)[0]
    if address.startswith("["):
        return address[1 : address.find("]")] if "]" in address else address[1:]
    host, _, _port = address.rpartition(":")
    return host


def is_loopback(endpoint: str) -> bool:
    """True if the endpoint stays on this machine (127.0.0.0/8, ::1, localhost)."""
    host = endpoint_host(endpoint)
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a DNS name or 0.0.0.0-like wildcard: assume it leaves the machine


def exposure_warnings(
    listen: Iterable[str], connect: Iterable[str], *, tls: bool, access_control: bool
) -> list[str]:
    """What an unprotected service exposes beyond loopback (empty when protected or loopback-only)."""
    if tls and access_control:
        return []
    missing = " and ".join(w for w, ok in (("TLS", tls), ("access control", access_control)) if not ok)
    out = []
    for ep in listen:
        if not is_loopback(ep):
            out.append(
                f"listening on {ep} beyond loopback without {missing}: any process that reaches it can "
                "submit, change and cancel motion jobs (set [security] in the cell config, docs/security.md)"
            )
    for ep in connect:
        if not is_loopback(ep):
            out.append(f"connecting to {ep} beyond loopback without {missing}: jobs and telemetry cross the "
                       "network unprotected (docs/security.md)")
    return out


# -- files ---------------------------------------------------------------------------------------
_PEM = {
    "CERTIFICATE": re.compile(r"-----BEGIN CERTIFICATE-----"),
    "PRIVATE KEY": re.compile(r"-----BEGIN (?:EC |RSA )?PRIVATE KEY-----"),
}


def _file(path: str | os.PathLike[str], setting: str, *, base: Path | None = None, pem: str = "") -> str:
    """The file's path (relative ones against `base`) after checking it reads and holds the PEM block:
    Zenoh's own errors for a missing or wrong file do not name the setting."""
    p = Path(path)
    if base is not None and not p.is_absolute():
        p = base / p
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SecurityError(SECURITY_FILE, f"{setting} {str(p)!r} cannot be read: {exc}", path=setting) from None
    if pem and not _PEM[pem].search(text):
        raise SecurityError(SECURITY_FILE, f"{setting} {str(p)!r} holds no PEM {pem.lower()}", path=setting)
    return str(p)


@dataclass(frozen=True)
class ClientSecurity:
    """What a client needs to reach a secured service: the CA, its own certificate and key (mutual
    TLS), and its login when the service asks for one. Files are checked when the object is made."""

    ca: str | os.PathLike[str] | None = None
    certificate: str | os.PathLike[str] | None = None
    private_key: str | os.PathLike[str] | None = None
    user: str | None = None
    password: str | None = None
    verify_name: bool = True  # the service's certificate must name the host dialled (127.0.0.1, ...)

    def __post_init__(self) -> None:
        if (self.certificate is None) != (self.private_key is None):
            raise SecurityError(SECURITY_CONFIG, "a client certificate needs its private key (and vice versa)",
                                path="certificate")
        if self.certificate is not None and self.ca is None:
            raise SecurityError(SECURITY_CONFIG, "a client certificate needs the CA (TLS)", path="ca")
        if (self.user is None) != (self.password is None):
            raise SecurityError(SECURITY_CONFIG, "a login needs both user and password", path="user")
        if self.ca is not None:
            _file(self.ca, "ca", pem="CERTIFICATE")
        if self.certificate is not None and self.private_key is not None:
            _file(self.certificate, "certificate", pem="CERTIFICATE")
            _file(self.private_key, "private_key", pem="PRIVATE KEY")

    @property
    def tls(self) -> bool:
        return self.ca is not None

    def zenoh_settings(self) -> dict[str, Any]:
        """Settings by Zenoh config path for a connecting session."""
        out: dict[str, Any] = {}
        if self.ca is not None:
            out["transport/link/tls/root_ca_certificate"] = str(self.ca)
            out["transport/link/tls/verify_name_on_connect"] = self.verify_name
        if self.certificate is not None:
            out["transport/link/tls/enable_mtls"] = True
            out["transport/link/tls/connect_certificate"] = str(self.certificate)
            out["transport/link/tls/connect_private_key"] = str(self.private_key)
        if self.user is not None:
            out["transport/auth/usrpwd/user"] = self.user
            out["transport/auth/usrpwd/password"] = self.password
        return out

    def check_endpoints(self, endpoints: Iterable[str]) -> None:
        """TLS options and `tcp/` endpoints (or the reverse) are a mistake: say so before dialling."""
        for ep in endpoints:
            proto = endpoint_protocol(ep)
            if self.tls and proto not in ("tls", "quic"):
                raise SecurityError(
                    SECURITY_CONFIG, f"TLS options are given but endpoint {ep!r} is {proto}: use tls/...",
                    path="connect",
                )


def service_settings(security: Any, *, base: Path | None = None) -> dict[str, Any]:
    """Zenoh settings by config path for a service from a cell's `[security]` section (a
    `planner.config.SecuritySettings`); relative file names are relative to `base` (the cell
    config's folder). Empty when security is off."""
    if not security.enabled:
        return {}
    out: dict[str, Any] = {
        "transport/link/tls/root_ca_certificate": _file(security.ca, "security.ca", base=base, pem="CERTIFICATE"),
        "transport/link/tls/listen_certificate": _file(
            security.certificate, "security.certificate", base=base, pem="CERTIFICATE"
        ),
        "transport/link/tls/listen_private_key": _file(
            security.private_key, "security.private_key", base=base, pem="PRIVATE KEY"
        ),
        "transport/link/tls/enable_mtls": bool(security.mtls),
        "transport/link/tls/verify_name_on_connect": True,
    }
    # the same identity when the service dials a router
    out["transport/link/tls/connect_certificate"] = out["transport/link/tls/listen_certificate"]
    out["transport/link/tls/connect_private_key"] = out["transport/link/tls/listen_private_key"]
    if security.users_file:
        out["transport/auth/usrpwd/dictionary_file"] = _file(
            security.users_file, "security.users_file", base=base
        )
    if security.user:
        password_file = _file(security.password_file, "security.password_file", base=base)
        password = Path(password_file).read_text(encoding="utf-8").strip()
        if not password:
            raise SecurityError(SECURITY_FILE, f"security.password_file {password_file!r} is empty",
                                path="security.password_file")
        out["transport/auth/usrpwd/user"] = security.user
        out["transport/auth/usrpwd/password"] = password
    out["access_control"] = access_control(
        {OPERATOR: security.operator, OBSERVER: security.observer, SERVICE: security.service}
    )
    return out


def check_service_endpoints(security: Any, listen: Iterable[str], connect: Iterable[str]) -> None:
    """With security on, every endpoint is TLS: a plain `tcp/` one would carry jobs unencrypted."""
    if not security.enabled:
        return
    for name, endpoints in (("listen", listen), ("connect", connect)):
        for ep in endpoints:
            if endpoint_protocol(ep) not in ("tls", "quic"):
                raise SecurityError(
                    SECURITY_CONFIG,
                    f"[security] is enabled but the {name} endpoint {ep!r} is not tls/...: every endpoint of a "
                    "secured service must be TLS",
                    path=f"zenoh.{name}",
                )
