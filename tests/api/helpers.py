"""Small helpers for API tests: raw Zenoh queries and event collection."""

from __future__ import annotations

import queue
import time
from collections.abc import Callable
from typing import Any

import msgpack
import zenoh

from streamer.api.zenoh_config import client_config


def raw_session(endpoint: str) -> zenoh.Session:
    return zenoh.open(client_config(endpoint))


def raw_get(
    session: zenoh.Session, selector: str, payload: bytes | None = None, timeout: float = 10.0
) -> tuple[str, Any]:
    """('ok', decoded) or ('err', decoded) of the first reply; ('none', None) without any."""
    for reply in session.get(selector, payload=payload, timeout=timeout):
        if reply.ok is not None:
            return "ok", msgpack.unpackb(reply.ok.payload.to_bytes())
        if reply.err is not None:
            return "err", msgpack.unpackb(reply.err.payload.to_bytes())
    return "none", None


class Collector:
    """Subscribes to a key and keeps every decoded message in arrival order."""

    def __init__(self, session: zenoh.Session, key: str):
        self.items: queue.Queue[Any] = queue.Queue()
        self.all: list[Any] = []
        self._sub = session.declare_subscriber(
            key, lambda s: self.items.put(msgpack.unpackb(s.payload.to_bytes()))
        )

    def until(self, pred: Callable[[Any], bool], timeout: float = 10.0) -> Any:
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise AssertionError(f"timed out; got {self.all!r}"[:2000])
            try:
                msg = self.items.get(timeout=remaining)
            except queue.Empty:
                continue
            self.all.append(msg)
            if pred(msg):
                return msg

    def close(self) -> None:
        self._sub.undeclare()


def wait_for(pred: Callable[[], bool], timeout: float = 10.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.01)
