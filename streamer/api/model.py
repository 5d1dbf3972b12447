"""Job states, event types and the transition table of the job service.

`transition()` is the only way a state changes; an event without an entry for the current state raises,
so a late or duplicated event never resurrects a finished job. Some events keep the state (`planned`,
progress updates).

    (new)      --accepted-->   QUEUED     --planned-->    QUEUED
    QUEUED     --priming-->    RUNNING    --running-->    RUNNING
    RUNNING    --cancelling--> CANCELLING --cancelling--> CANCELLING   (progress while stopping)
    RUNNING    --done/failed/cancelled--> DONE/FAILED/CANCELLED
    RUNNING    --aborted-->    ABORTED    (a change replaced it: `replaced_by` names the job that took over)
    CANCELLING --done/failed/cancelled--> DONE/FAILED/CANCELLED        (done: the plan's end was queued)
    QUEUED     --failed/cancelled-->      FAILED/CANCELLED   (restart, not ready, shutdown, cancel)
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any


class JobState(enum.Enum):
    QUEUED = "queued"
    RUNNING = "running"
    CANCELLING = "cancelling"
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"
    ABORTED = "aborted"  # replaced while it moved by a change (`replaced_by` names the job that took over)

    @property
    def final(self) -> bool:
        return self in _FINAL


_FINAL = frozenset({JobState.DONE, JobState.FAILED, JobState.CANCELLED, JobState.ABORTED})


class EventType(enum.Enum):
    ACCEPTED = "accepted"
    PLANNED = "planned"
    PRIMING = "priming"
    RUNNING = "running"
    CANCELLING = "cancelling"
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"
    ABORTED = "aborted"

    @property
    def final(self) -> bool:
        return self in (EventType.DONE, EventType.FAILED, EventType.CANCELLED, EventType.ABORTED)


class InvalidTransition(RuntimeError):
    """An event arrived that the job's current state does not allow (a bug or a late event)."""


# (state before, event) -> state after; None is "no job yet".
TRANSITIONS: Mapping[tuple[JobState | None, EventType], JobState] = {
    (None, EventType.ACCEPTED): JobState.QUEUED,
    (JobState.QUEUED, EventType.PLANNED): JobState.QUEUED,
    (JobState.QUEUED, EventType.PRIMING): JobState.RUNNING,
    (JobState.QUEUED, EventType.FAILED): JobState.FAILED,
    (JobState.QUEUED, EventType.CANCELLED): JobState.CANCELLED,
    (JobState.RUNNING, EventType.RUNNING): JobState.RUNNING,
    (JobState.RUNNING, EventType.DONE): JobState.DONE,
    (JobState.RUNNING, EventType.FAILED): JobState.FAILED,
    (JobState.RUNNING, EventType.CANCELLED): JobState.CANCELLED,
    (JobState.RUNNING, EventType.CANCELLING): JobState.CANCELLING,
    (JobState.RUNNING, EventType.ABORTED): JobState.ABORTED,
    (JobState.CANCELLING, EventType.CANCELLING): JobState.CANCELLING,
    (JobState.CANCELLING, EventType.DONE): JobState.DONE,
    (JobState.CANCELLING, EventType.FAILED): JobState.FAILED,
    (JobState.CANCELLING, EventType.CANCELLED): JobState.CANCELLED,
}


def transition(state: JobState | None, event: EventType) -> JobState:
    try:
        return TRANSITIONS[(state, event)]
    except KeyError:
        before = state.value if state is not None else "(new)"
        raise InvalidTransition(f"event {event.value!r} is not allowed in state {before!r}") from None


@dataclass(frozen=True)
class Event:
    """One journalled job event. `data` holds the type-specific fields (already wire-safe)."""

    job_id: str
    seq: int
    type: EventType
    t: float
    state: JobState
    data: Mapping[str, Any] = field(default_factory=dict)

    def to_wire(self, cell: str) -> dict[str, Any]:
        """The published/queried form: common fields first, then the type's own fields."""
        out: dict[str, Any] = {
            "job_id": self.job_id,
            "cell": cell,
            "seq": self.seq,
            "type": self.type.value,
            "t": self.t,
            "state": self.state.value,
        }
        for k, v in self.data.items():
            out.setdefault(k, v)
        return out


@dataclass(frozen=True)
class JobRecord:
    """A job as journalled in the store (one row of `jobs`)."""

    number: int  # submission order in this store, 1-based
    job_id: str
    cell: str
    kind: str
    state: JobState
    via: str  # "query" or "put"
    body_hash: str
    planned_duration_s: float | None
    points: int | None
    progress: float
    error: Mapping[str, Any] | None
    report: Mapping[str, Any] | None
    last_seq: int
    submitted_t: float
    started_t: float | None
    finished_t: float | None
    updated_t: float

    def to_status(self) -> dict[str, Any]:
        """The status form sent by `pvt/<cell>/jobs/<job_id>` and listed by `pvt/<cell>/jobs`."""
        return {
            "job_id": self.job_id,
            "cell": self.cell,
            "number": self.number,
            "kind": self.kind,
            "state": self.state.value,
            "via": self.via,
            "planned_duration_s": self.planned_duration_s,
            "points": self.points,
            "progress": self.progress,
            "error": dict(self.error) if self.error is not None else None,
            "report": dict(self.report) if self.report is not None else None,
            "last_seq": self.last_seq,
            "submitted_t": self.submitted_t,
            "started_t": self.started_t,
            "finished_t": self.finished_t,
            "updated_t": self.updated_t,
        }
