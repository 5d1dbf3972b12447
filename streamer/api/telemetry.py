"""Telemetry and status of the job service: the cell's state as a reader sees it.

Theory of operation. The telemetry thread (`_telemetry_loop`) publishes, at `telemetry_hz`, the
backend's per-axis snapshot (`backend.telemetry()`, each axis with its unit) with the cell's readiness,
the hold and the running job's state and progress (the latest its emitter, progress.py, saw) on
`pvt/<cell>/telemetry`, best effort (a slow subscriber loses samples, never stalls the service; a
stalled process skips periods rather than bursting). `service_status()` is the same picture, fuller
(the queue, the limits, the store), for the `service` query and the stop verb's answer.
"""

from __future__ import annotations

import logging
import time
from typing import Any

from streamer.api import keys
from streamer.api.payload import plain
from streamer.api.service_state import API_VERSION, ServiceState

# every part of the service logs as `streamer.api.service`, the logger it always had (log filters name it)
log = logging.getLogger("streamer.api.service")


class TelemetryMixin(ServiceState):
    """The status snapshot and the telemetry publisher of `JobService`."""

    def service_status(self) -> dict[str, Any]:
        ready, reason = self._ready()
        with self._cv:
            current = self._current
            pending = list(self._pending.values())
            held, hold_reason, hold_t = self._held, self._hold_reason, self._hold_t
        running = None
        if current is not None:
            emitter = current.emitter
            running = {
                "job_id": current.job_id,
                "kind": current.kind,
                "state": "cancelling" if current.cancel_requested else ("running" if current.started else "starting"),
                "progress": emitter.progress if emitter is not None else 0.0,
                "planned_duration_s": current.planned.duration_s,
            }
        return {
            "cell": self.cell,
            "api_version": API_VERSION,
            "ready": ready,
            "reason": reason,
            "held": held,
            "hold_reason": hold_reason,
            "hold_t": hold_t,
            "running_job": current.job_id if current is not None else None,
            "running": running,
            "queued_jobs": [q.job_id for q in pending],
            "queue": [
                {"job_id": q.job_id, "kind": q.kind, "planned_duration_s": q.planned.duration_s}
                for q in pending
            ],
            "queue_length": len(pending),
            "queue_limit": self.options.queue_limit,
            "axes": [a.name for a in self.backend.cell.axes],
            "units": {a.name: a.unit for a in self.backend.cell.axes},
            "velocity_limits": {a.name: a.velocity for a in self.backend.cell.axes},  # unit/s (pvt jog's default)
            "drives": self._drives(),
            "telemetry_hz": self.telemetry_hz,
            "started_t": self._started_t,
            "store": str(self.store.path),
            "recordings": str(self.recordings.directory) if self.recordings is not None else None,
        }

    def _drives(self) -> list[dict[str, Any]]:
        """The backend's telemetry snapshot, each axis with its unit (the status and telemetry's `axes`)."""
        units = {a.name: a.unit for a in self.backend.cell.axes}
        try:
            axes = plain(list(self.backend.telemetry()))
        except Exception as exc:
            log.warning("backend.telemetry() raised %s: %s", type(exc).__name__, exc)
            return []
        for a in axes:
            if isinstance(a, dict) and isinstance(a.get("name"), str):
                a.setdefault("unit", units.get(a["name"], ""))
        return [a for a in axes if isinstance(a, dict)]


    def _telemetry_loop(self) -> None:
        period = 1.0 / self.telemetry_hz
        units = {a.name: a.unit for a in self.backend.cell.axes}
        next_t = time.monotonic()
        while True:
            next_t += period
            delay = next_t - time.monotonic()
            if delay < -period:  # fell behind (stalled process): skip, do not burst
                next_t = time.monotonic()
                delay = 0.0
            if self._stop_telemetry.wait(max(0.0, delay)):
                return
            try:
                axes = plain(list(self.backend.telemetry()))
                error = None
            except Exception as exc:
                axes, error = [], f"backend.telemetry() raised {type(exc).__name__}: {exc}"
            for a in axes:
                if isinstance(a, dict) and isinstance(a.get("name"), str):
                    a.setdefault("unit", units.get(a["name"], ""))
            ready, reason = self._ready()
            with self._cv:
                item = self._current
                held = self._held
            emitter = item.emitter if item is not None else None
            self._telemetry_seq += 1
            msg: dict[str, Any] = {
                "cell": self.cell,
                "t": self._clock(),
                "seq": self._telemetry_seq,
                "ready": ready,
                "reason": reason,
                "held": held,
                "job_id": item.job_id if item is not None else None,
                "job_state": None if item is None else (
                    "cancelling" if item.cancel_requested else "running" if item.started else "starting"),
                "progress": emitter.progress if emitter is not None else None,
                "axes": axes,
            }
            if error:
                msg["error"] = error
            self._put(keys.telemetry(self.cell), msg, reliable=False)

