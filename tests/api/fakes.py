"""Test doubles for the job service: `FakeBackend` (a MotionBackend with deterministic timing and
configurable failures; NOT a motion simulator) and helpers. Test-only code: never imported by streamer/.

Fake job semantics (enough to exercise the service, not the planner):
- kinds path/move/timed/pvt with the planner's field names; unknown fields -> SCHEMA; strings in
  numeric arrays -> TYPE; rows of the wrong length -> AXIS_COUNT; unknown/duplicate axes -> AXIS_ID;
- planned duration: `times[-1] - times[0]` for timed jobs (so a test picks a job's length), else
  `default_duration_s`; points = number of rows + 1;
- `fail_codes`: a map job-field-value -> planning error, e.g. {"INFEASIBLE": ...} is triggered by
  `tolerance_counts` equal to a magic value (see `MAGIC_ERRORS`);
- positions: a job starts at its first row (a move: at `start`, else where the axes stand) and moves
  its axes linearly to its last row (a move: its target) with the progress; a cancel stops them where
  they are. `TrackingFake.current_positions()` reports them; `emergency_stop()` ends a running job at once (failed
  EMERGENCY_STOP) and leaves the cell not ready until `reset()`.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from planner.config import CellConfig
from planner.errors import PlanningError
from planner.job import job_fields
from streamer.api.backend import CancelToken, Emit, MotionBackend, Planned

# kind: (required fields, optional fields), the planner's own (planner/job.py `job_fields`); "name" is fake-only
KINDS: dict[str, tuple[set[str], set[str]]] = {
    kind: (set(job_fields(kind)[0]), set(job_fields(kind)[1]) | {"name"}) for kind in ("path", "move", "timed", "pvt")
}

# tolerance_counts values that make the fake planner fail with a given code (planning-stage errors)
MAGIC_ERRORS = {
    901: "INFEASIBLE",
    902: "ENCODING_RANGE",
    903: "LIMITS_EXCEED_DRIVE",
    904: "POSITION_LIMIT",
    905: "NON_MONOTONIC",
    906: "LIMITS",
    907: "DEGENERATE",
    908: "TOO_LARGE",
}


class FakeBackend(MotionBackend):
    """A MotionBackend test double. Deterministic: a job of duration D runs D * time_scale wall seconds. Its
    `plan` ignores the travel memory and the lead (as the `plan` callback it may be given, which takes the job
    and the start)."""

    can_emergency_stop = True

    def __init__(
        self,
        cell: CellConfig,
        *,
        default_duration_s: float = 0.2,
        time_scale: float = 1.0,
        step_s: float = 0.01,
        fail_code: str | None = None,
        fail_at_progress: float = 0.5,
        plan_delay_s: float = 0.0,
        validate: Callable[[Mapping[str, Any]], Any] | None = None,
        plan: Callable[[Any, Mapping[str, float] | None], Planned] | None = None,
    ):
        self.cell = cell
        self.default_duration_s = default_duration_s
        self.time_scale = time_scale
        self.step_s = step_s
        self.fail_code = fail_code  # next executed job fails with this code (then the cell is faulted)
        self.fail_at_progress = fail_at_progress
        self.plan_delay_s = plan_delay_s
        self._validate = validate
        self._plan = plan
        self.hold = threading.Event()  # execute() waits for this before moving (set by default)
        self.hold.set()
        self.started = threading.Event()  # set when a job starts executing
        self.executed: list[str] = []  # job names/ids executed, in order (names from the 'name' field)
        self.validated = 0
        self.planned = 0
        self.plan_starts: list[dict[str, float] | None] = []  # the `start` of every plan() call
        self.faulted = ""
        self.closed = False
        self._lock = threading.Lock()
        self._position = {a.name: 0.0 for a in cell.axes}
        self._fifo = 0
        self._state = "operation_enabled"
        self._emergency = threading.Event()
        self.emergency_stops = 0

    # -- planning ----------------------------------------------------------------------------------
    def validate(self, body: Mapping[str, Any]) -> Any:
        self.validated += 1
        if self._validate is not None:
            return self._validate(body)
        kind = body.get("kind")
        if not isinstance(kind, str) or kind not in KINDS:
            raise PlanningError("SCHEMA", f"kind {kind!r} must be one of {sorted(KINDS)}", path="kind")
        required, optional = KINDS[kind]
        missing = sorted(required - set(body))
        if missing:
            raise PlanningError("SCHEMA", f"missing field {missing[0]!r} for a {kind} job", path=missing[0])
        unknown = sorted(set(body) - required - optional)
        if unknown:
            raise PlanningError("SCHEMA", f"unknown field {unknown[0]!r} in a {kind} job", path=unknown[0])
        axes = body["axes"]
        if not isinstance(axes, list) or not all(isinstance(a, str) for a in axes):
            raise PlanningError("TYPE", "axes must be a list of axis names", path="axes")
        if not axes:
            raise PlanningError("AXIS_COUNT", "axes is empty: a job needs at least one axis", path="axes")
        names = self.cell.axis_names()
        for i, a in enumerate(axes):
            if a not in names:
                raise PlanningError(
                    "AXIS_ID", f"unknown axis {a!r} (cell has {list(names)})", path=f"axes[{i}]"
                )
            if axes.index(a) != i:
                raise PlanningError("AXIS_ID", f"axis {a!r} appears twice", path=f"axes[{i}]")
        rows_field = {"path": "waypoints", "timed": "positions", "pvt": "positions", "move": None}[kind]
        if rows_field is None:
            field = "velocity" if body.get("mode") == "velocity" else "target"
            if field not in body:
                raise PlanningError("SCHEMA", f"missing field {field!r} for a move job", path=field)
            self._numbers(body[field], field, axes)
            if len(body[field]) != len(axes):
                raise PlanningError(
                    "AXIS_COUNT",
                    f"{field} has {len(body[field])} values for {len(axes)} axes",
                    path=field,
                )
            rows: list[Any] = [body[field]]
        else:
            rows = body[rows_field]
            if not isinstance(rows, list):
                raise PlanningError("TYPE", f"{rows_field} must be a list of rows", path=rows_field)
            for i, row in enumerate(rows):
                if not isinstance(row, list):
                    raise PlanningError(
                        "TYPE", f"{rows_field}[{i}] must be a list", path=f"{rows_field}[{i}]"
                    )
                if len(row) != len(axes):
                    raise PlanningError(
                        "AXIS_COUNT",
                        f"{rows_field}[{i}] has {len(row)} values for {len(axes)} axes",
                        path=f"{rows_field}[{i}]",
                    )
                self._numbers(row, f"{rows_field}[{i}]", axes)
        tol = body.get("tolerance_counts", 1)
        if isinstance(tol, int) and tol in MAGIC_ERRORS:
            code = MAGIC_ERRORS[tol]
            if code in (
                "LIMITS",
                "DEGENERATE",
                "NON_MONOTONIC",
                "POSITION_LIMIT",
                "LIMITS_EXCEED_DRIVE",
                "TOO_LARGE",
            ):
                raise PlanningError(code, f"fake {code} of axis {axes[0]!r}", path="tolerance_counts")
        duration = self.default_duration_s
        if kind in ("timed", "pvt"):
            times = body["times"]
            self._numbers(times, "times", None)
            duration = float(times[-1]) - float(times[0]) if len(times) >= 2 else 0.0
        last = rows[-1] if rows else None
        first = rows[0] if rows and kind != "move" else None
        return {
            "first": list(first) if isinstance(first, list) else None,
            "kind": kind,
            "axes": axes,
            "rows": len(rows),
            "duration": duration,
            "tol": tol,
            "name": body.get("name", ""),
            "end": list(last) if isinstance(last, list) else None,
        }

    @staticmethod
    def _numbers(values: Any, path: str, axes: Sequence[str] | None) -> None:
        if not isinstance(values, list):
            raise PlanningError("TYPE", f"{path} must be a list", path=path)
        for j, v in enumerate(values):
            if isinstance(v, bool) or not isinstance(v, int | float):
                axis = f" of axis {axes[j]!r}" if axes is not None and j < len(axes) else ""
                raise PlanningError(
                    "TYPE", f"{path}[{j}]{axis} is {v!r}, expected a number", path=f"{path}[{j}]"
                )
            if not math.isfinite(v):
                raise PlanningError("NONFINITE", f"{path}[{j}] is {v}", path=f"{path}[{j}]")

    def plan(self, job: Any, start: Mapping[str, float] | None = None, *,
             last_target: Mapping[str, float | None] | None = None,
             last_direction: Mapping[str, int] | None = None, lead_ms: int | None = None) -> Planned:
        self.planned += 1
        self.plan_starts.append(dict(start) if start is not None else None)
        if self._plan is not None:
            return self._plan(job, start)
        if self.plan_delay_s:
            time.sleep(self.plan_delay_s)
        code = MAGIC_ERRORS.get(job["tol"]) if isinstance(job["tol"], int) else None
        if code in ("INFEASIBLE", "ENCODING_RANGE"):
            raise PlanningError(code, f"fake {code} on axis {job['axes'][0]!r}", path="waypoints")
        end = {a: float(v) for a, v in zip(job["axes"], job["end"], strict=True)} if job.get("end") else {}
        with self._lock:
            here = dict(self._position)
        if job.get("first") is not None:
            begin = {a: float(v) for a, v in zip(job["axes"], job["first"], strict=True)}
        else:
            begin = {a: float((start or {}).get(a, here[a])) for a in job["axes"]}
        return Planned(
            job=job, trajectory=None, duration_s=job["duration"], points=job["rows"] + 1, end_positions=end,
            start_positions=begin,
        )

    # -- motion ------------------------------------------------------------------------------------
    def execute(self, planned: Planned, emit: Emit, cancel: CancelToken) -> Mapping[str, Any]:
        self.hold.wait()
        job = planned.job
        with self._lock:
            self.executed.append(job.get("name") or "?")
        self.started.set()
        duration = planned.duration_s * self.time_scale
        t0 = time.monotonic()
        fail_code, self.fail_code = self.fail_code, None
        begin = dict(planned.start_positions)
        end = dict(planned.end_positions)
        emit("running", {"progress": 0.0})
        while True:
            elapsed = time.monotonic() - t0
            progress = 1.0 if duration <= 0 else min(1.0, elapsed / duration)
            if self._emergency.is_set():
                with self._lock:
                    self._fifo = 0
                return self._report(
                    "failed", planned, elapsed,
                    error={"code": "EMERGENCY_STOP", "node": None, "message": "emergency stop: quick stop"},
                )
            with self._lock:
                self._fifo = 32 if progress < 1.0 else 0
                for a in job["axes"]:
                    a0 = begin.get(a, 0.0)
                    self._position[a] = a0 + (end.get(a, a0) - a0) * progress
            if cancel.cancelled:
                with self._lock:
                    self._fifo = 0
                return self._report("cancelled", planned, elapsed)
            if fail_code is not None and progress >= self.fail_at_progress:
                self.faulted = f"fake fault {fail_code}"
                return self._report(
                    "failed",
                    planned,
                    elapsed,
                    error={"code": fail_code, "node": 3, "message": f"node 3 raised {fail_code}"},
                )
            if progress >= 1.0:
                emit("running", {"progress": 1.0})
                return self._report("done", planned, elapsed)
            emit("running", {"progress": progress})
            cancel.wait(self.step_s)

    def _report(
        self, result: str, planned: Planned, elapsed: float, error: Mapping[str, Any] | None = None
    ) -> dict[str, Any]:
        rep: dict[str, Any] = {
            "result": result,
            "sync_period_ms": self.cell.sync_period_ms,
            "duration_s": elapsed,
            "syncs": int(elapsed / self.cell.sync_period_s),
            "frames": 0,
            "bus_load_peak": 0.0,
            "faults": [dict(error)] if error else [],
            "axes": [
                {
                    "name": a,
                    "node_id": self.cell.axis(a).node_id,
                    "points_sent": planned.points,
                    "max_deviation_counts": 0,
                    "final_position_error_counts": 0,
                }
                for a in planned.job["axes"]
            ],
        }
        if error:
            rep["error"] = dict(error)
        return rep

    def telemetry(self) -> list[dict[str, Any]]:
        with self._lock:
            return [
                {"name": n, "position": p, "velocity": 0.0, "fifo_fill": self._fifo, "state": self._state}
                for n, p in self._position.items()
            ]

    def emergency_stop(self) -> str:
        self.emergency_stops += 1
        self.faulted = "EMERGENCY_STOP: quick stop on every drive"
        self._emergency.set()
        self._state = "switch_on_disabled"
        return "quick stop (0x000B) to every drive"

    def ready(self) -> tuple[bool, str]:
        return (not self.faulted, self.faulted)

    def reset(self) -> tuple[bool, str]:
        self.faulted = ""
        self._emergency.clear()
        self._state = "operation_enabled"
        return self.ready()

    def close(self) -> None:
        self.closed = True


class TrackingFake(FakeBackend):
    """A FakeBackend that reports where its axes stand (`current_positions()`), so the service checks that a
    queued job still starts there. (The plain fake does not: most tests queue jobs that all start at 0.)"""

    def current_positions(self) -> dict[str, float]:
        with self._lock:
            return dict(self._position)


def open_fake_backend(
    cell: CellConfig,
    *,
    sim: bool = False,
    interface: str | None = None,
    channel: str | None = None,
    bitrate: int | None = None,
) -> FakeBackend:
    """Factory for `pvt serve --backend tests.api.fakes:open_fake_backend` (subprocess tests)."""
    return FakeBackend(cell)


def timed_job(duration_s: float, *, axes: Sequence[str] = ("j1",), name: str = "") -> dict[str, Any]:
    """A job whose fake duration is `duration_s` (the real planner would run it as a timed job)."""
    job: dict[str, Any] = {
        "kind": "timed",
        "axes": list(axes),
        "times": [0.0, float(duration_s)],
        "positions": [[0.0] * len(axes), [0.1] * len(axes)],
    }
    if name:
        job["name"] = name
    return job
