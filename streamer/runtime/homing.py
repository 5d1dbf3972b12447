"""Home jobs on the master side: homing mode on the drives, and which axes are referenced.

Theory of operation. A home job is not planned: `run_homing` has all its axes reference themselves through
a `HomingPort`: enable as for a job; write the family's homing objects (`homing_writes`: 0x6098, 0x6099,
0x609A, 0x607C, then 0x6060 = 6) and controlword 0x001F; read each statusword every period until bit 13
(error) or bits 12 and 10 (seed 003), or `timeout_s`; always restore (bit 4 low, set points, `mode_writes`,
the enable sequence). Done when every axis attained, else HOMING_ERROR or HOMING_TIMEOUT naming the axes;
a cancel interrupts. `Referencing` keeps the axes homed since their drive last faulted or booted (a
boot-up forgets the reference, seed 003 0x3218); with `cell.require_homing` a job on an unreferenced axis
is refused NOT_HOMED, at admission and again when it comes up.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, Protocol

from bus.families import PROFILES, setpoint_slots
from planner.config import CellConfig
from planner.job import HomeData, Job

HOMING_ERROR = "HOMING_ERROR"
HOMING_TIMEOUT = "HOMING_TIMEOUT"
NOT_HOMED = "NOT_HOMED"
SW_TARGET_REACHED = 1 << 10
SW_HOMING_ATTAINED = 1 << 12
SW_HOMING_ERROR = 1 << 13
CW_ENABLE_OPERATION = 0x000F
CW_START_HOMING = 0x001F

# What each homing method (0x6098) does, in one line (`pvt plan` of a home job; docs/drive-model.md, "Homing")
METHOD_NOTES: dict[int, str] = {
    17: "negative limit switch: searched moving negative, its inner edge",
    18: "positive limit switch: searched moving positive, its inner edge",
    19: "home switch active above its edge: the edge, left moving negative",
    20: "home switch active above its edge: the edge, entered moving positive",
    21: "home switch active below its edge: the edge, left moving positive",
    22: "home switch active below its edge: the edge, entered moving negative",
    23: "cam (home switch): searched moving positive, left at the zero speed on the side met",
    27: "cam (home switch): searched moving negative, left at the zero speed on the side met",
    35: "current position: no motion",
    37: "current position: no motion",
}


def method_note(method: int) -> str:
    """One line on what homing `method` does (the method number for one without a note)."""
    return METHOD_NOTES.get(method, f"method {method}")


class HomingPort(Protocol):
    """What `run_homing` needs of a runtime: SDO access, the enable sequence and a clock that advances."""

    def write(self, node: int, index: int, sub: int, value: int) -> None: ...

    def read(self, node: int, index: int, sub: int) -> int: ...

    def enable(self) -> None: ...

    def wait(self, seconds: float) -> None: ...

    def now(self) -> float: ...


def run_homing(cell: CellConfig, job: Job, port: HomingPort, *, cancelled: Callable[[], bool] = lambda: False,
               progress: Callable[[float], None] | None = None) -> dict[str, Any]:
    """Home the job's axes (see the module docstring); returns the report (result done/failed/cancelled)."""
    data = job.data
    if not isinstance(data, HomeData):
        raise TypeError(f"run_homing needs a home job, got kind {job.kind!r}")
    axes = [cell.axis(a) for a in job.axes]
    slots = setpoint_slots(cell.axes)
    t0 = port.now()
    outcome: dict[str, str] = {}
    started: list[int] = []
    try:
        port.enable()
        for j, a in enumerate(axes):
            profile = PROFILES[a.profile]
            for w in profile.homing_writes(a, data.method[j], data.search_speed[j], data.zero_speed[j],
                                           data.acceleration[j], data.offset[j]):
                port.write(a.node_id, w.index, w.sub, w.value)
            started.append(j)
            port.write(a.node_id, 0x6040, 0, CW_START_HOMING)
        deadline = t0 + data.timeout_s
        while len(outcome) < len(axes):
            if cancelled():
                break
            for a in axes:
                if a.name in outcome:
                    continue
                sw = port.read(a.node_id, 0x6041, 0)
                if sw & SW_HOMING_ERROR:
                    outcome[a.name] = "error"
                elif sw & SW_HOMING_ATTAINED and sw & SW_TARGET_REACHED:
                    outcome[a.name] = "attained"
            if progress is not None:
                progress(min(0.99, len(outcome) / len(axes)))
            if len(outcome) == len(axes):
                break
            if port.now() > deadline:
                for a in axes:
                    outcome.setdefault(a.name, "timeout")
                break
            port.wait(cell.sync_period_s)
    finally:
        for j in started:  # back to streaming: bit 4 low, hold where it is, the family's mode, enabled
            a = axes[j]
            profile = PROFILES[a.profile]
            port.write(a.node_id, 0x6040, 0, CW_ENABLE_OPERATION)
            here = port.read(a.node_id, 0x6064, 0)
            for w in (*profile.hold_writes(here), *profile.mode_writes(a, cell.drive, cell.sync_period_ms,
                                                                        slots.get(a.node_id))):
                port.write(a.node_id, w.index, w.sub, w.value)
        if started:
            port.enable()
    duration = port.now() - t0
    rows = []
    for j, a in enumerate(axes):
        pos = port.read(a.node_id, 0x6064, 0)
        rows.append({"name": a.name, "node_id": a.node_id, "method": data.method[j],
                     "result": outcome.get(a.name, "cancelled"), "position": pos / a.counts_per_unit,
                     "home_position": data.offset[j]})
    report: dict[str, Any] = {"result": "done", "kind": "home", "sync_period_ms": cell.sync_period_ms,
                              "duration_s": round(duration, 6), "faults": [], "axes": rows}
    errors = [r for r in rows if r["result"] == "error"]
    late = [r for r in rows if r["result"] == "timeout"]
    if cancelled() and len(outcome) < len(axes):
        report.update(result="cancelled", message="homing interrupted (controlword bit 4 low)")
    elif errors:
        names = ", ".join(f"{r['name']!r} (node {r['node_id']}, method {r['method']})" for r in errors)
        report.update(result="failed", error={
            "code": HOMING_ERROR, "node": errors[0]["node_id"], "path": "method",
            "message": f"homing error (statusword bit 13) on axis {names}: the drive did not find its home "
                       "position (a switch not found within its travel, a limit switch, or a method it does "
                       "not perform); the axis is not referenced",
            "detail": {"axes": [r["name"] for r in errors]}})
    elif late:
        names = ", ".join(f"{r['name']!r} (node {r['node_id']})" for r in late)
        report.update(result="failed", error={
            "code": HOMING_TIMEOUT, "node": late[0]["node_id"], "path": "timeout_s",
            "message": f"homing of axis {names} neither attained (statusword bits 12 and 10) nor failed (bit 13) "
                       f"within timeout_s = {data.timeout_s:g} s; interrupted (bit 4 low), not referenced",
            "detail": {"axes": [r["name"] for r in late]}})
    return report


def home_end_positions(job: Job) -> dict[str, float]:
    """Where a home job leaves its axes when it succeeds: each at its home position (0x607C)."""
    assert isinstance(job.data, HomeData)
    return dict(zip(job.axes, job.data.offset, strict=True))


class Referencing:
    """Which axes are referenced, and the `require_homing` check (see the module docstring). Thread-safe."""

    def __init__(self, cell: CellConfig):
        self.cell = cell
        self._lock = threading.Lock()
        self._referenced: set[str] = set()
        self._pending: dict[str, int] = {}  # axis -> home jobs accepted and not run yet

    @property
    def referenced(self) -> frozenset[str]:
        with self._lock:
            return frozenset(self._referenced)

    def check(self, job: Job, *, at_start: bool = False) -> None:
        """Raise NOT_HOMED (a MotionError) if `require_homing` and a job that moves axes is on unreferenced
        ones (at admission, axes a queued home job will reference count as referenced)."""
        if not self.cell.require_homing or job.kind == "home":
            return
        with self._lock:
            ok = self._referenced if at_start else self._referenced | {a for a, n in self._pending.items() if n}
            missing = [a for a in job.axes if a not in ok]
        if missing:
            from streamer.api.errors import MotionError

            raise MotionError(
                NOT_HOMED,
                f"cell {self.cell.name!r} requires homing (cell.require_homing) and axis(es) {missing} are not "
                "referenced (no home job since their drive powered on or faulted); submit a home job for them "
                "first", path="axes", detail={"axes": missing})

    def planned(self, job: Job) -> None:
        """A home job was accepted: its axes will be referenced when it runs."""
        if job.kind == "home":
            with self._lock:
                for a in job.axes:
                    self._pending[a] = self._pending.get(a, 0) + 1

    def finished(self, job: Job, report: Mapping[str, Any]) -> None:
        """A job ended: a home job references (attained) or un-references its axes; a failed job un-references
        the axes of the drive that faulted (all its axes when no node is named)."""
        with self._lock:
            if job.kind == "home":
                for a in job.axes:
                    if self._pending.get(a):
                        self._pending[a] -= 1
                for row in report.get("axes", ()):
                    if isinstance(row, Mapping) and row.get("name") in job.axes:
                        if row.get("result") == "attained":
                            self._referenced.add(str(row["name"]))
                        else:
                            self._referenced.discard(str(row["name"]))
                return
            if report.get("result") == "failed":
                err = report.get("error")
                node = err.get("node") if isinstance(err, Mapping) else None
                names = {a.name for a in self.cell.axes if a.node_id == node} if node is not None else set(job.axes)
                self._referenced -= names

    def forget(self, nodes: Iterable[int]) -> None:
        """These drives booted (power cycle, reset node) or faulted: their axes are not referenced."""
        nodes = set(nodes)
        with self._lock:
            self._referenced -= {a.name for a in self.cell.axes if a.node_id in nodes}

    def status(self) -> dict[str, Sequence[str] | bool]:
        with self._lock:
            return {"require_homing": self.cell.require_homing, "referenced": sorted(self._referenced)}
