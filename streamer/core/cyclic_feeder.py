"""Cyclic feeder: the per-axis state machine that sends a drive of a cyclic family one set point per SYNC.

A cyclic drive latches the set point that arrived since the last SYNC and interpolates towards it over
the next period (planner/encoding/cyclic.py). With S the start SYNC: from READY it gets holds of x_0 (so
enabling moves nothing); it is PRIMED once bit 12 shows and two more holds went out (P3 uses three); after
SYNC m it gets x_j, j = m + 2 - S, reached at SYNC S + j in step with the EPOS drives; after x_N holds again
until finished (XtrapulsPac: bit 4 cleared, bit 12 seen clear; CSP: demand at x_N). A stop replaces the set
points from the end of what the EPOS FIFOs hold, else the next one. The demand is checked against x_j.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bus.events import Send
from bus.profile import SetpointSlot, pack_setpoints
from planner.encoding.cyclic import Setpoints, sample
from planner.motion.reference import FloatArray
from streamer.core.axis_state import CYCLIC_TRANSITIONS, AxisStateMachine, FeederInput, FeederState
from streamer.core.fifo_feeder import AxisTelemetry

HOLD_AFTER_ACTIVE = 2  # holds sent after the SYNC ip mode was seen active, before the axis counts as primed


@dataclass(frozen=True)
class CyclicAxis:
    """What the core knows of one cyclic axis: where its set point travels, how its drive interpolates,
    and whether controlword bit 4 starts the interpolation (XtrapulsPac IP) or not (CSP)."""

    slot: SetpointSlot
    interpolation: str  # "linear" | "pv" | "p3"
    starts_with_bit4: bool = True
    sync_lock_ms: int = 0  # SYNC the drive must have seen before bit 4 (XtrapulsPac: 180 ms, else it refuses)


class CyclicFeeder(AxisStateMachine):
    """One cyclic axis. The coordinator owns the timing and calls `setpoint`, `fire` and the checks."""

    kind = "cyclic"
    transitions = CYCLIC_TRANSITIONS

    def __init__(self, axis: int, node_id: int, start_position: int, spec: CyclicAxis, period_ms: int,
                 positions: FloatArray, velocities_per_ms: FloatArray) -> None:
        self.axis = axis
        self.node_id = node_id
        self.start_position = start_position
        self.spec = spec
        self.period_ms = period_ms
        self.pv = spec.interpolation == "pv"
        self.setpoints: Setpoints = sample(positions, velocities_per_ms, period_ms, pv=self.pv)
        # the first set point is the start position to the count (the plan's knot 0 is)
        self.setpoints.positions[0] = start_position
        self.state = FeederState.WAITING
        self.last_tpdo1 = -1
        self.last_tpdo2 = -1
        self.first_status: int | None = None  # statusword of the first TPDO1 of the job
        self.first_demand: int | None = None
        self.status_heard = -1  # the newest SYNC on the wire when first_status / first_demand arrived
        self.demand_heard = -1
        self.ready_sync: int | None = None  # the SYNC after which it got its first hold
        self.bit4_sync: int | None = None  # the SYNC after which it got controlword bit 4 (ip mode requested)
        self.bit4_sync_ran_ms = 0  # how long SYNC had run at the SYNC that applied bit 4
        self.bit4_first_sync: int | None = None  # the first request's SYNC: the activation timeout runs from it
        self.bit4_requests = 0  # rising edges of bit 4 sent (a refused request is dropped and asked again)
        self.bit4_low_sync: int | None = None  # bit 4 dropped after this SYNC, to be raised again after the next
        self.active_sync: int | None = None  # the SYNC bit 12 was first seen set (ip mode active)
        self.holds_after_active = 0
        self.sent_index = -1  # the last set point index sent (-1: only holds so far)
        self.bit4_off_sync: int | None = None  # the SYNC bit 4 was cleared for (end of job)
        # telemetry
        self.points_sent = 0
        self.frames_sent = 0
        self.start_sync: int | None = None
        self.end_sync: int | None = None
        self.max_demand_error = 0
        self.errors: list[str] = []
        self.last_statusword: int | None = None

    # ---- the moves the coordinator makes on the axis (it owns the timing, the feeder its fields) -------
    def ready(self, sync: int | None) -> None:
        """Checked ready after SYNC `sync`: WAITING -> PRIMING; it gets its first hold after that SYNC."""
        self.fire(FeederInput.READY)
        self.ready_sync = sync

    def ip_requested(self, m: int, sync_ran_ms: int) -> None:
        """Controlword bit 4 went out after SYNC m; SYNC had run `sync_ran_ms` at the SYNC that applies it."""
        self.bit4_sync = m
        self.bit4_sync_ran_ms = sync_ran_ms
        self.bit4_low_sync = None
        self.bit4_requests += 1
        if self.bit4_first_sync is None:
            self.bit4_first_sync = m

    def ip_dropped(self, m: int) -> None:
        """Bit 4 cleared after SYNC m, the request not taken: the drive sees it low at SYNC m + 1, and a new
        rising edge goes out after that SYNC."""
        self.bit4_sync = None
        self.bit4_low_sync = m

    def seen_active(self, m: int) -> None:
        """Statusword bit 12 (ip mode active / following the set point) first seen at SYNC m, priming."""
        self.active_sync = m

    def ip_released(self, m: int) -> None:
        """Controlword bit 4 cleared for SYNC m (end of job: the drive holds its last set point)."""
        self.bit4_off_sync = m

    # ---- set points ---------------------------------------------------------------------------------
    @property
    def n(self) -> int:
        return self.setpoints.n

    @property
    def end_ms(self) -> int:
        return self.setpoints.end_ms

    def index_after(self, m: int, start_sync: int | None) -> int:
        """The set point index to send after SYNC m (0 = hold x_0 before the start)."""
        if start_sync is None:
            return 0
        return max(0, min(self.n, m + 2 - start_sync))

    def value(self, j: int) -> tuple[int, int]:
        """(position counts, velocity counts/s) of set point j (clamped to the last)."""
        j = max(0, min(self.n, j))
        return int(self.setpoints.positions[j]), int(self.setpoints.velocities[j])

    def sent(self, j: int) -> None:
        if j > self.sent_index:
            self.points_sent += j - max(self.sent_index, 0)
            self.sent_index = j
        self.frames_sent += 1

    def expected_demand(self, m: int, start_sync: int | None) -> tuple[int, int]:
        """[low, high] of the position demand the drive may report at SYNC m: the set point it reached at
        m, widened by one internal cycle (1 ms) of motion either way for a drive that samples off the SYNC."""
        if start_sync is None or m <= start_sync:
            x = self.value(0)[0]
            return x, x
        j = m - start_sync
        x = self.value(j)[0]
        step = max(abs(x - self.value(j - 1)[0]), abs(self.value(j + 1)[0] - x))
        tick = -(-step // self.period_ms)  # ceil: one 1 ms tick of the fastest neighbouring period
        return x - tick, x + tick

    def splice(self, t0_ms: int, positions: FloatArray, velocities_per_ms: FloatArray) -> int:
        """From time t0 on, the set points of a stop trajectory that starts at t0 (its own time 0); set
        points already sent are kept. Returns the first index that changed."""
        p = self.period_ms
        j0 = max(self.sent_index + 1, -(-t0_ms // p))  # first j with j*P >= t0, not sent yet
        if j0 > self.n + 1:
            j0 = self.n + 1
        stop = sample(positions, velocities_per_ms, p, pv=self.pv, start_ms=j0 * p - t0_ms)
        old = self.setpoints
        pos = np.concatenate([old.positions[:j0], stop.positions])
        vel = np.concatenate([old.velocities[:j0], stop.velocities])
        self.setpoints = Setpoints(p, pos, vel)
        return j0

    # ---- telemetry ----------------------------------------------------------------------------------
    def telemetry(self) -> AxisTelemetry:
        return AxisTelemetry(
            node_id=self.node_id,
            state=self.state.value,
            points_sent=self.points_sent,
            frames_sent=self.frames_sent,
            resends=0,
            losses_detected=0,
            losses_repaired=0,
            late_batches=0,
            min_fifo=None,
            max_fifo=None,
            underflow_warnings=0,
            overflow_warnings=0,
            start_sync=self.start_sync,
            end_sync=self.end_sync,
            last_fill=None,
            max_demand_error_counts=self.max_demand_error,
            errors=tuple(self.errors),
        )


def pack_frame(slots: dict[int, SetpointSlot], members: tuple[int, ...], values: dict[int, tuple[int, int]]) -> Send:
    """The frame of one group (or one axis): each member's (position counts, velocity counts/s) at its
    offset (bus.profile.pack_setpoints)."""
    first = slots[members[0]]
    frame = bytearray(first.frame_bytes)
    for node in members:
        pos, vel = values[node]
        pack_setpoints(slots[node], frame, pos, vel)
    return Send(first.cob_id, bytes(frame))
