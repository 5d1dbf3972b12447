"""Zenoh configs never scout by multicast and use only the endpoints they are given."""

from __future__ import annotations

import json

import pytest

from planner.config import ZenohSettings
from streamer.api.zenoh_config import build_config, client_config, service_config


def get(conf: object, key: str) -> object:
    return json.loads(conf.get_json(key))  # type: ignore[attr-defined]


def test_service_config_defaults_and_overrides() -> None:
    conf = service_config(ZenohSettings())
    assert get(conf, "mode") == "peer"
    assert get(conf, "scouting/multicast/enabled") is False
    assert get(conf, "listen/endpoints") == ["tcp/127.0.0.1:7447"]
    assert get(conf, "connect/endpoints") == []
    conf = service_config(
        ZenohSettings(), mode="router", listen=["tcp/127.0.0.1:9000"], connect=["tcp/127.0.0.1:9001"]
    )
    assert get(conf, "mode") == "router"
    assert get(conf, "listen/endpoints") == ["tcp/127.0.0.1:9000"]
    assert get(conf, "connect/endpoints") == ["tcp/127.0.0.1:9001"]


def test_client_config_only_dials() -> None:
    conf = client_config("tcp/127.0.0.1:7447")
    assert get(conf, "listen/endpoints") == [] and get(conf, "scouting/multicast/enabled") is False
    assert get(conf, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert get(client_config(["tcp/127.0.0.1:1", "tcp/127.0.0.1:2"], mode="client"), "mode") == "client"
    with pytest.raises(ValueError):
        client_config([])
    with pytest.raises(ValueError):
        client_config("tcp/127.0.0.1:1", mode="router")


def test_bad_settings_are_refused() -> None:
    with pytest.raises(ValueError):
        build_config(mode="satellite")
    with pytest.raises(ValueError):
        build_config(listen=["127.0.0.1:7447"])
    with pytest.raises(ValueError):
        build_config(extra={"scouting/multicast/enabled": True})
    conf = build_config(extra={"transport/unicast/max_links": 2})
    assert get(conf, "transport/unicast/max_links") == 2
