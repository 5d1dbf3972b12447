"""Build `zenoh.Config` objects that never leave the endpoints they are given.

A default Zenoh peer listens everywhere and scouts by multicast; every config here has multicast scouting
off and explicit endpoints only (services on tcp/127.0.0.1:7447 unless configured; clients listen on
nothing). `service_config` adds the cell's `[security]` (streamer/api/security.py) and warns when a
service is reachable beyond loopback without TLS and access control; `client_config` adds `ClientSecurity`.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import zenoh

from streamer.api import security as sec

log = logging.getLogger(__name__)

MODES = ("peer", "client", "router")
DEFAULT_LISTEN = ("tcp/127.0.0.1:7447",)
DEFAULT_CONNECT = "tcp/127.0.0.1:7447"


def _endpoints(name: str, values: Iterable[str]) -> list[str]:
    out = []
    for v in values:
        if not isinstance(v, str) or "/" not in v or v.startswith("/") or v.endswith("/"):
            raise ValueError(f"zenoh {name} endpoint {v!r} must look like 'tcp/127.0.0.1:7447'")
        out.append(v)
    return out


def build_config(
    *,
    mode: str = "peer",
    listen: Sequence[str] = DEFAULT_LISTEN,
    connect: Sequence[str] = (),
    extra: Mapping[str, Any] | None = None,
) -> zenoh.Config:
    """A Zenoh config with multicast scouting off and exactly these endpoints.

    `extra` inserts further settings by path ("transport/unicast/max_links": 4); it may not turn
    multicast scouting back on.
    """
    if mode not in MODES:
        raise ValueError(f"zenoh mode must be one of {MODES}, got {mode!r}")
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(_endpoints("listen", listen)))
    conf.insert_json5("connect/endpoints", json.dumps(_endpoints("connect", connect)))
    for key, value in (extra or {}).items():
        if key.startswith("scouting/multicast"):
            raise ValueError("multicast scouting stays off (network rule)")
        conf.insert_json5(key, json.dumps(value))
    return conf


def service_config(
    settings: Any,
    *,
    mode: str | None = None,
    listen: Sequence[str] | None = None,
    connect: Sequence[str] | None = None,
    security: Any = None,
    base: Path | None = None,
) -> zenoh.Config:
    """The service's config from a cell's `[zenoh]` section (a `planner.config.ZenohSettings`),
    with overrides, and its `[security]` section (a `planner.config.SecuritySettings`; files relative
    to `base`). Raises `security.SecurityError` when security is on and an endpoint is not TLS or a
    file is missing; warns (log) when the service is reachable beyond loopback unprotected."""
    listen_eps = tuple(listen) if listen is not None else tuple(settings.listen)
    connect_eps = tuple(connect) if connect is not None else tuple(settings.connect)
    extra: dict[str, Any] = {}
    enabled = security is not None and security.enabled
    if enabled:
        sec.check_service_endpoints(security, listen_eps, connect_eps)
        extra = sec.service_settings(security, base=base)
    for warning in sec.exposure_warnings(listen_eps, connect_eps, tls=enabled, access_control=enabled):
        log.warning("%s", warning)
    return build_config(mode=mode or settings.mode, listen=listen_eps, connect=connect_eps, extra=extra)


def client_config(
    connect: str | Sequence[str] = DEFAULT_CONNECT,
    *,
    mode: str = "peer",
    security: sec.ClientSecurity | None = None,
) -> zenoh.Config:
    """A connecting peer (or client) with no listen endpoint: it only dials `connect` (with TLS
    and a login when `security` says so)."""
    endpoints = [connect] if isinstance(connect, str) else list(connect)
    if not endpoints:
        raise ValueError("a client needs at least one connect endpoint")
    if mode == "router":
        raise ValueError("a client session cannot be a router")
    extra: dict[str, Any] = {}
    if security is not None:
        security.check_endpoints(endpoints)
        extra = security.zenoh_settings()
    return build_config(mode=mode, listen=(), connect=endpoints, extra=extra)
