"""The Zenoh job API: payload decoding, the job journal, the job service and the Python client.

`MotionClient` (client.py) is the public entry point for users; `JobService` (service.py) serves one
cell behind a `MotionBackend` (backend.py), put together from intake.py, cell_queue.py (the queue and the
hold), control_verbs.py, journal.py, progress.py, telemetry.py and handlers.py (the Zenoh side).
docs/api.md documents the key space and the wire format.
Names are imported lazily, so `streamer.api.store` (used by `pvt jobs`) does not load Zenoh.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from streamer.api.client import Job, JobEvent, JobStatus, MotionClient
    from streamer.api.errors import JobFailedError, MotionError
    from streamer.api.model import JobState

_EXPORTS = {
    "Job": "streamer.api.client",
    "JobEvent": "streamer.api.client",
    "JobStatus": "streamer.api.client",
    "MotionClient": "streamer.api.client",
    "JobFailedError": "streamer.api.errors",
    "MotionError": "streamer.api.errors",
    "JobState": "streamer.api.model",
}

__all__ = ["Job", "JobEvent", "JobFailedError", "JobState", "JobStatus", "MotionClient", "MotionError"]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'streamer.api' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)
