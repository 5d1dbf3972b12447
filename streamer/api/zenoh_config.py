"""Build `zenoh.Config` objects that never leave the endpoints they are given.

A default Zenoh peer listens on every interface and scouts by UDP multicast. This product never wants
that: every config built here has multicast scouting off and explicit endpoints only. Services listen
on `tcp/127.0.0.1:7447` unless the cell config says otherwise; clients are connecting peers (or
clients) with no listen endpoint at all.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import zenoh

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
) -> zenoh.Config:
    """The service's config from a cell's `[zenoh]` section (a `planner.config.ZenohSettings`),
    with overrides."""
    return build_config(
        mode=mode or settings.mode,
        listen=tuple(listen) if listen is not None else tuple(settings.listen),
        connect=tuple(connect) if connect is not None else tuple(settings.connect),
    )


def client_config(connect: str | Sequence[str] = DEFAULT_CONNECT, *, mode: str = "peer") -> zenoh.Config:
    """A connecting peer (or client) with no listen endpoint: it only dials `connect`."""
    endpoints = [connect] if isinstance(connect, str) else list(connect)
    if not endpoints:
        raise ValueError("a client needs at least one connect endpoint")
    if mode == "router":
        raise ValueError("a client session cannot be a router")
    return build_config(mode=mode, listen=(), connect=endpoints)
