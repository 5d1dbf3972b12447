"""Axis state machine: the states, inputs and transition tables of the two axis kinds, and the moves on them.

    WAITING --READY--> PRIMING --PRIMED--> PRIMED --START--> STARTING --ACTIVE--> STREAMING
    STREAMING --END_QUEUED--> DRAINING --STOPPED--> FINISHED
    STARTING/STREAMING --HALT--> HALTING --STOPPED--> FINISHED
    WAITING/PRIMING/PRIMED --ABANDON--> FINISHED          (cancel before the start)
    any state but FAULTED --FAULT--> FAULTED             (poisoned: never sends again)

FIFO and cyclic axes share the states, each with its table (a cyclic axis drains once its last set point
is sent, so DRAINING also takes EXTENDED and HALT); a missing entry raises `InvalidTransition`.
`AxisStateMachine` holds the state and the named moves the coordinator makes on an axis.
"""

from __future__ import annotations

from collections.abc import Mapping
from enum import Enum
from typing import ClassVar


class InvalidTransition(RuntimeError):
    """An input arrived that the current state has no transition for (a bug in the caller)."""


class FeederState(Enum):
    WAITING = "waiting"
    PRIMING = "priming"
    PRIMED = "primed"
    STARTING = "starting"
    STREAMING = "streaming"
    DRAINING = "draining"
    HALTING = "halting"
    FINISHED = "finished"
    FAULTED = "faulted"


class FeederInput(Enum):
    READY = "ready"  # first feedback checked: drive ready, FIFO empty, at the plan's start
    PRIMED = "primed"  # priming level confirmed in the FIFO
    START = "start"  # start controlword sent
    ACTIVE = "active"  # drive reports ip mode active at/after the start SYNC
    END_QUEUED = "end_queued"  # the end record is confirmed in the FIFO (cyclic: the last set point sent)
    EXTENDED = "extended"  # a splice gave a draining cyclic axis set points after its last one
    HALT = "halt"  # cancel fell back to halt (controlword bit 8)
    STOPPED = "stopped"  # ip mode inactive and target reached (or halt standstill)
    ABANDON = "abandon"  # cancelled before the start
    FAULT = "fault"


_S, _I = FeederState, FeederInput
FIFO_TRANSITIONS: Mapping[tuple[FeederState, FeederInput], FeederState] = {
    (_S.WAITING, _I.READY): _S.PRIMING,
    (_S.PRIMING, _I.PRIMED): _S.PRIMED,
    (_S.PRIMED, _I.START): _S.STARTING,
    (_S.STARTING, _I.ACTIVE): _S.STREAMING,
    (_S.STREAMING, _I.END_QUEUED): _S.DRAINING,
    (_S.DRAINING, _I.STOPPED): _S.FINISHED,
    (_S.STARTING, _I.HALT): _S.HALTING,
    (_S.STREAMING, _I.HALT): _S.HALTING,
    (_S.HALTING, _I.STOPPED): _S.FINISHED,
    (_S.WAITING, _I.ABANDON): _S.FINISHED,
    (_S.PRIMING, _I.ABANDON): _S.FINISHED,
    (_S.PRIMED, _I.ABANDON): _S.FINISHED,
    **{(state, _I.FAULT): _S.FAULTED for state in FeederState if state is not _S.FAULTED},
}
CYCLIC_TRANSITIONS: Mapping[tuple[FeederState, FeederInput], FeederState] = {
    **FIFO_TRANSITIONS,
    (_S.DRAINING, _I.EXTENDED): _S.STREAMING,
    (_S.DRAINING, _I.HALT): _S.HALTING,
}


class AxisStateMachine:
    """The state of one axis of either kind and the moves on it; a subclass names its table."""

    transitions: ClassVar[Mapping[tuple[FeederState, FeederInput], FeederState]]
    node_id: int
    state: FeederState
    start_sync: int | None  # the SYNC the axis started interpolating at (telemetry)
    end_sync: int | None  # the SYNC the axis was seen stopped at (telemetry)
    frames_sent: int  # records or set points, and controlwords, sent to this node
    max_demand_error: int  # counts: the largest distance of a reported position demand from the plan
    errors: list[str]  # the failure codes the job reported against this node
    last_tpdo1: int  # the newest SYNC a TPDO1 of this node was attributed to (feedback.py)
    last_tpdo2: int  # the same for TPDO2

    def fire(self, inp: FeederInput) -> FeederState:
        nxt = self.transitions.get((self.state, inp))
        if nxt is None:
            raise InvalidTransition(
                f"feeder of node {self.node_id}: no transition from {self.state.name} on {inp.name}"
            )
        self.state = nxt
        return nxt

    def activated(self, start_sync: int) -> None:
        """The drive reports ip mode active from the job's start SYNC on: STARTING -> STREAMING."""
        self.fire(FeederInput.ACTIVE)
        self.start_sync = start_sync

    def stopped(self, m: int) -> None:
        """The drive is seen stopped at SYNC m (ip mode off, halt standstill, or its last set point reached)."""
        self.fire(FeederInput.STOPPED)
        self.end_sync = m

    def answers_from(self, m: int) -> None:
        """SYNC m is the job's first: every TPDO of this node from now on answers m or a later SYNC."""
        self.last_tpdo1 = self.last_tpdo2 = m - 1

    def answered(self, pdo: int, m: int) -> None:
        """Its TPDO `pdo` (1 or 2) was attributed to SYNC m (its later ones answer later SYNCs)."""
        if pdo == 1:
            self.last_tpdo1 = m
        else:
            self.last_tpdo2 = m

    def controlword_sent(self) -> None:
        """A controlword frame went to this node (it counts in the axis' frames)."""
        self.frames_sent += 1

    def demand_checked(self, err: int) -> None:
        """A position demand was `err` counts from the plan (telemetry keeps the largest)."""
        self.max_demand_error = max(self.max_demand_error, err)

    def failed(self, code: str) -> None:
        """The job failed with `code` against this node."""
        self.errors.append(code)
