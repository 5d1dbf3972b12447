"""Positioning state per axis (seed 002's state machine, EP7047 object 9020:03), as the coordinator sees it.

Theory of operation. Per axis the state a PLC would read: IDLE, START (configuring, priming), ACCEL /
CONST / DECEL (the plan's phases), PRE_TARGET (plan ended, in-target timeout running), TARGET (within the
window), EMCY (an emergency stop runs), STOP (stopped after a stop), ERROR. Fed by the coordinator
without I/O or clock: `start()`, `splice(t0, plan, kind)`, `on_time(elapsed_ms)` per SYNC,
`on_actual(node, counts, elapsed_ms)` per TPDO2, and `halted()`, `stopped()`, `failed()`, `emergency()`.
`settled()` says whether every axis is in its target or timed out (a `NotInTarget` warning).
Phases are precomputed per plan so a SYNC bisects one array per axis: a segment is ACCEL or DECEL when
|v| changes by more than the dead band (1 % of the peak speed, at least 1 rpm, so a cruise's rpm
rounding does not flicker), a reversal DECEL. States are an enum with a transition table.
"""

from __future__ import annotations

from bisect import bisect_left
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import Enum

from streamer.core.plan_source import StreamPlan
from streamer.core.schedule import segment_ends


class PositioningState(Enum):
    """Seed 002's 9020:03 states the streamer reports (value: the EP7047 state id)."""

    IDLE = 0x0001
    START = 0x0010
    ACCEL = 0x0011
    CONST = 0x0012
    DECEL = 0x0013
    EMCY = 0x0020
    STOP = 0x0021
    PRE_TARGET = 0x1000
    TARGET = 0x1001
    ERROR = 0x8000


_P = PositioningState
_MOTION = frozenset({_P.ACCEL, _P.CONST, _P.DECEL})
_TRANSITIONS: dict[PositioningState, frozenset[PositioningState]] = {
    _P.IDLE: frozenset({_P.START, _P.ERROR}),
    _P.START: _MOTION | {_P.IDLE, _P.PRE_TARGET, _P.TARGET, _P.EMCY, _P.STOP, _P.ERROR},
    _P.ACCEL: _MOTION | {_P.PRE_TARGET, _P.TARGET, _P.EMCY, _P.STOP, _P.ERROR},
    _P.CONST: _MOTION | {_P.PRE_TARGET, _P.TARGET, _P.EMCY, _P.STOP, _P.ERROR},
    _P.DECEL: _MOTION | {_P.PRE_TARGET, _P.TARGET, _P.EMCY, _P.STOP, _P.ERROR},
    _P.PRE_TARGET: frozenset({_P.TARGET, _P.EMCY, _P.STOP, _P.ERROR}),
    _P.TARGET: frozenset({_P.ERROR}),
    _P.EMCY: frozenset({_P.STOP, _P.ERROR}),
    _P.STOP: frozenset({_P.ERROR}),
    _P.ERROR: frozenset(),
}
_AT_REST = frozenset({_P.TARGET, _P.STOP, _P.ERROR})


class BadTransition(RuntimeError):
    """A positioning state change that the transition table does not allow."""


@dataclass(frozen=True)
class NotInTarget:
    """The warning of an axis still outside its target window when its in-target timeout ran out."""

    node: int
    error_counts: int  # actual - target at the last position actual, counts
    window_counts: int
    timeout_ms: int
    elapsed_ms: int  # when the timeout ran out, ms from the start SYNC

    code: str = "not_in_target"


@dataclass(frozen=True)
class PositioningChange:
    node: int
    state: PositioningState
    elapsed_ms: int | None  # ms from the start SYNC (None before it)


def plan_phases(plan: StreamPlan, axis: int, start_rpm: int = 0) -> list[PositioningState]:
    """ACCEL / CONST / DECEL of every segment of one axis of `plan` (module docstring)."""
    recs = plan.records[axis] if plan.open_end else plan.records[axis][:-1]  # an open-ended plan has no end record
    peak = max((abs(r.velocity) for r in recs), default=0)
    band = max(1, peak // 100)
    out: list[PositioningState] = []
    prev = start_rpm
    for r in recs:
        v = r.velocity
        if (prev > 0 > v) or (prev < 0 < v):
            out.append(_P.DECEL)
        elif abs(v) - abs(prev) > band:
            out.append(_P.ACCEL)
        elif abs(prev) - abs(v) > band:
            out.append(_P.DECEL)
        else:
            out.append(_P.CONST)
        prev = v
    return out


class _Timeline:
    """One axis' phases over the stream: run ends (ms from the start SYNC, increasing) and their state."""

    def __init__(self) -> None:
        self.ends: list[int] = []
        self.states: list[PositioningState] = []

    def cut(self, t0: int) -> None:
        """Drop everything after t0 (a splice replaces it)."""
        i = bisect_left(self.ends, t0)  # the run that covers t0 (its end is at or after it)
        del self.ends[i + 1:]
        del self.states[i + 1:]
        if i < len(self.ends):
            if (self.ends[i - 1] if i > 0 else 0) >= t0:
                del self.ends[i:]
                del self.states[i:]
            else:
                self.ends[i] = t0

    def extend(self, t0: int, seg_ends: Sequence[int], phases: Sequence[PositioningState]) -> None:
        for end, st in zip(seg_ends, phases, strict=True):
            if self.states and self.states[-1] is st:
                self.ends[-1] = t0 + end
            else:
                self.ends.append(t0 + end)
                self.states.append(st)

    def at(self, t: int) -> PositioningState | None:
        """The phase interpolated at t (the segment that ends at or after t); None after the end."""
        i = bisect_left(self.ends, t)
        return self.states[i] if i < len(self.states) else None

    @property
    def end_ms(self) -> int:
        return self.ends[-1] if self.ends else 0


class PositioningTracker:
    """Per-axis positioning state of one job (module docstring). Nodes without a target window in
    `windows_counts` are TARGET at the plan's end (nothing to check them against)."""

    def __init__(self, plan: StreamPlan, windows_counts: Mapping[int, int] | None = None,
                 timeouts_ms: Mapping[int, int] | None = None) -> None:
        self._nodes = tuple(plan.node_ids)
        self._windows = {n: int(w) for n, w in (windows_counts or {}).items() if n in self._nodes}
        self._timeouts = {n: int(t) for n, t in (timeouts_ms or {}).items() if n in self._nodes}
        self._state: dict[int, PositioningState] = {n: _P.IDLE for n in self._nodes}
        self._lines = {n: _Timeline() for n in self._nodes}
        self._target: dict[int, int] = {}
        self._actual: dict[int, tuple[int, int]] = {}  # node -> (counts, elapsed ms it was sampled at)
        self._timed_out: set[int] = set()
        self._end_kind = "plan"  # what the stream's last piece is: "plan" / "change", "stop", "emergency"
        self._emergency_from: int | None = None  # the emergency stop's first ms (EMCY from there)
        self._frozen = False  # halt or quick stop: no plan to follow; the end of the job decides
        self.warnings: list[NotInTarget] = []
        self.changes: list[PositioningChange] = []
        self._install(0, plan, [0] * len(self._nodes))

    # ---- what the coordinator feeds ---------------------------------------------------------------
    def start(self) -> None:
        """Priming begins: the command is being carried out (START)."""
        for n in self._nodes:
            if self._state[n] is _P.IDLE:
                self._go(n, _P.START, None)

    def splice(self, t0: int, plan: StreamPlan, kind: str, start_rpm: Sequence[int]) -> None:
        """`plan` replaces the stream from t0 on (ms from the start SYNC); `kind` "change", "stop" or
        "emergency"; `start_rpm`: each axis' velocity at t0 (the state the plan starts from)."""
        if kind not in ("change", "stop", "emergency"):
            raise ValueError(f"unknown splice kind {kind!r}")
        for line in self._lines.values():
            line.cut(t0)
        self._install(t0, plan, start_rpm)
        self._end_kind = kind
        self._emergency_from = t0 if kind == "emergency" else None

    def on_time(self, elapsed_ms: int) -> None:
        """One SYNC: the drives interpolate at `elapsed_ms` from the start SYNC."""
        if self._frozen:
            return
        for n in self._nodes:
            st = self._state[n]
            if st in _AT_REST or st is _P.IDLE:
                continue
            line = self._lines[n]
            if elapsed_ms < line.end_ms:
                if self._emergency_from is not None and elapsed_ms >= self._emergency_from:
                    new = _P.EMCY
                else:
                    phase = line.at(elapsed_ms) if elapsed_ms > 0 else None
                    new = phase if phase is not None else st
                    if st is _P.EMCY:
                        new = st
                if new is not st:
                    self._go(n, new, elapsed_ms)
                continue
            if self._end_kind in ("stop", "emergency"):
                self._go(n, _P.STOP, elapsed_ms)
                continue
            if st is not _P.PRE_TARGET:
                self._go(n, _P.PRE_TARGET, elapsed_ms)
            if self._in_window(n, line.end_ms):
                self._go(n, _P.TARGET, elapsed_ms)
                continue
            timeout = self._timeouts.get(n)
            if timeout is not None and n not in self._timed_out and elapsed_ms >= line.end_ms + timeout:
                self._timed_out.add(n)
                err = self._actual[n][0] - self._target[n] if n in self._actual else 0
                self.warnings.append(NotInTarget(n, err, self._windows.get(n, 0), timeout, elapsed_ms))

    def on_actual(self, node: int, position_counts: int, elapsed_ms: int) -> None:
        """A position actual of `node`, sampled `elapsed_ms` after the start SYNC."""
        if node not in self._state:
            return
        self._actual[node] = (int(position_counts), int(elapsed_ms))
        if self._state[node] is _P.PRE_TARGET and self._in_window(node, self._lines[node].end_ms):
            self._go(node, _P.TARGET, elapsed_ms)

    def emergency(self, elapsed_ms: int | None) -> None:
        """An emergency stop with no plan (the drives' quick stop): EMCY now on every axis in motion."""
        self._frozen = True
        for n in self._nodes:
            if self._state[n] not in _AT_REST and self._state[n] is not _P.IDLE:
                self._go(n, _P.EMCY, elapsed_ms)

    def halted(self, elapsed_ms: int | None) -> None:
        """Halt (bit 8): every moving axis decelerates on its drive's own profile until it stands."""
        for n in self._nodes:
            if self._state[n] in (_P.START, _P.ACCEL, _P.CONST, _P.PRE_TARGET):
                self._go(n, _P.DECEL, elapsed_ms)
        self._frozen = True

    def stopped(self, elapsed_ms: int | None) -> None:
        """The job ended cancelled: every axis stands (STOP), or never moved (IDLE before the start)."""
        for n in self._nodes:
            st = self._state[n]
            if st is _P.START and elapsed_ms is None:
                self._go(n, _P.IDLE, None)
            elif st not in _AT_REST and st is not _P.IDLE:
                self._go(n, _P.STOP, elapsed_ms)

    def failed(self, elapsed_ms: int | None) -> None:
        """The job failed: ERROR on every axis (an emergency stop's axes stay EMCY: that is why they stop)."""
        for n in self._nodes:
            if self._state[n] not in (_P.ERROR, _P.EMCY):
                self._go(n, _P.ERROR, elapsed_ms)

    # ---- what it says -----------------------------------------------------------------------------
    def states(self) -> dict[int, PositioningState]:
        return dict(self._state)

    def state(self, node: int) -> PositioningState:
        return self._state[node]

    def settled(self) -> bool:
        """Every axis is in its target window, or stopped, or its in-target timeout ran out."""
        return all(self._state[n] in _AT_REST or n in self._timed_out for n in self._nodes)

    @property
    def end_ms(self) -> int:
        return max(line.end_ms for line in self._lines.values())

    def target(self, node: int) -> int | None:
        return self._target.get(node)

    # ---- internals --------------------------------------------------------------------------------
    def _install(self, t0: int, plan: StreamPlan, start_rpm: Sequence[int]) -> None:
        ends = segment_ends(plan.segment_ms)[:-1]  # one per segment (the end record, if any, adds no time)
        for axis, n in enumerate(plan.node_ids):
            self._lines[n].extend(t0, ends, plan_phases(plan, axis, int(start_rpm[axis])))
            self._target[n] = plan.records[axis][-1].position

    def _in_window(self, node: int, end_ms: int) -> bool:
        window = self._windows.get(node)
        if window is None:
            return True
        got = self._actual.get(node)
        return got is not None and got[1] >= end_ms and abs(got[0] - self._target[node]) <= window

    def _go(self, node: int, new: PositioningState, elapsed_ms: int | None) -> None:
        old = self._state[node]
        if new is old:
            return
        if new not in _TRANSITIONS[old]:
            raise BadTransition(f"node {node}: positioning state {old.name} cannot go to {new.name}")
        self._state[node] = new
        self.changes.append(PositioningChange(node, new, elapsed_ms))
