"""Errors of the job API: one exception type with a stable machine-readable code.

Every rejection the service sends (an error reply to a submit query, a `rejected` event for a put, a
failed job's `error`) is the same triple `{code, path, message}`, and the Python client raises it
back as a `MotionError` carrying that code, so a program can `except MotionError as e: if e.code ==
"BUSY": ...` without parsing text. The codes of the planner (`planner.errors`) pass through
unchanged; the API adds the ones below. docs/api.md has the full table.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

# Codes the API adds to the planner's (SCHEMA, TYPE, NONFINITE, AXIS_COUNT, ... from planner.errors).
MALFORMED_PAYLOAD = "MALFORMED_PAYLOAD"  # not msgpack, truncated, trailing bytes, nested too deep
TOO_LARGE = "TOO_LARGE"  # payload over the size limit, more waypoints than the limit
SCHEMA = "SCHEMA"  # missing/unknown/duplicate fields, non-string keys
TYPE = "TYPE"  # wrong types: strings or bools as numbers, huge ints, binary
NONFINITE = "NONFINITE"  # NaN or infinity
CONFLICT = "CONFLICT"  # same job_id, different body
BUSY = "BUSY"  # the queue is full
NOT_READY = "NOT_READY"  # the cell is faulted and not reset
NOT_FOUND = "NOT_FOUND"  # no job with that job_id
BAD_RECORD = "BAD_RECORD"  # a job's `record` section (the drives' recorders): streamer/recording/drive.py
BAD_REQUEST = "BAD_REQUEST"  # a status/list/cancel query that cannot be served (glob key, bad parameter)
INTERNAL = "INTERNAL"  # a bug: an unexpected exception in the service or the backend
SERVICE_RESTART = "SERVICE_RESTART"  # the service died while the job was queued or running
SERVICE_STOPPED = "SERVICE_STOPPED"  # the service was shut down while the job was queued
EMERGENCY_STOP = "EMERGENCY_STOP"  # the job was ended by an emergency stop (quick stop on every drive)
COMMAND_REJECTED = "COMMAND_REJECTED"  # a change of the running motion that cannot be made (seed 002)
INFEASIBLE = "INFEASIBLE"  # (planner code) a queued job that no longer starts where the axes stand
TIMEOUT = "TIMEOUT"  # client side: no answer in time
NO_SERVICE = "NO_SERVICE"  # client side: no service answered for this cell
SERVICE_GONE = "SERVICE_GONE"  # client side: the service's liveliness token vanished while waiting
PERMISSION_DENIED = "PERMISSION_DENIED"  # client side: the service is up but its access rules refused

API_CODES = frozenset(
    {
        MALFORMED_PAYLOAD,
        TOO_LARGE,
        SCHEMA,
        TYPE,
        NONFINITE,
        CONFLICT,
        BUSY,
        NOT_READY,
        NOT_FOUND,
        BAD_RECORD,
        BAD_REQUEST,
        INTERNAL,
        SERVICE_RESTART,
        SERVICE_STOPPED,
        EMERGENCY_STOP,
        COMMAND_REJECTED,
        TIMEOUT,
        NO_SERVICE,
        SERVICE_GONE,
        PERMISSION_DENIED,
    }
)


class MotionError(Exception):
    """A rejection or failure with a stable `code`, the offending field's `path` and a `message`.

    Raised by the service's decoding and admission steps, and by `MotionClient` for every error
    reply, failed job (`JobFailedError`) and timeout.
    """

    def __init__(self, code: str, message: str, *, path: str = "", detail: Mapping[str, Any] | None = None):
        super().__init__(message)
        self.code = str(code)
        self.path = str(path)
        self.message = str(message)
        self.detail: dict[str, Any] = dict(detail or {})
        # the submission's job id when it could be read despite the error (not part of the wire form):
        # a rejected put is then also announced on that job's events key
        self.job_id: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """The wire form `{code, path, message}` (plus `detail` when there is any)."""
        out: dict[str, Any] = {"code": self.code, "path": self.path, "message": self.message}
        if self.detail:
            out["detail"] = self.detail
        return out

    @classmethod
    def from_dict(cls, data: Any) -> MotionError:
        """Rebuild an error from its wire form; tolerant of missing fields (it is read, not trusted)."""
        if not isinstance(data, Mapping):
            return cls(INTERNAL, f"malformed error reply: {data!r}"[:500])
        detail = data.get("detail")
        return cls(
            str(data.get("code", INTERNAL)),
            str(data.get("message", "")),
            path=str(data.get("path", "") or ""),
            detail=detail if isinstance(detail, Mapping) else None,
        )

    def __str__(self) -> str:
        where = f" at {self.path}" if self.path else ""
        return f"{self.code}{where}: {self.message}"

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.code!r}, {self.message!r}, path={self.path!r})"


class JobFailedError(MotionError):
    """A job ended FAILED (raised by `Job.wait()`); `status` is its final status."""

    def __init__(
        self,
        code: str,
        message: str,
        *,
        path: str = "",
        detail: Mapping[str, Any] | None = None,
        status: Any = None,
    ):
        super().__init__(code, message, path=path, detail=detail)
        self.status = status


def error_from_exception(exc: BaseException) -> MotionError:
    """Map any exception raised while admitting a job to a `MotionError` (never loses the code).

    `PlanningError` (from the planner) keeps its code, path and message; anything else is a bug and
    becomes INTERNAL with the exception's type and text, so the caller still gets a coded reply.
    """
    if isinstance(exc, MotionError):
        return exc
    code = getattr(exc, "code", None)
    message = getattr(exc, "message", None)
    if isinstance(code, str) and code and isinstance(message, str):
        path = getattr(exc, "path", "")
        detail = getattr(exc, "detail", None)
        return MotionError(
            code,
            message,
            path=path if isinstance(path, str) else "",
            detail=detail if isinstance(detail, Mapping) else None,
        )
    return MotionError(INTERNAL, f"{type(exc).__name__}: {exc}"[:1000])
