"""Events the bus adapters feed to the streamer core, and actions the core returns.

Pure data (frozen dataclasses), no I/O: the master-side adapter (`bus.network`) turns received frames
and timer ticks into these events; the streamer core (`streamer.core`) consumes them and returns
actions; the adapter turns `Send` actions back into frames. Times are seconds on whatever clock the
runtime uses (wall clock in real time, a virtual clock in tests).
"""

from __future__ import annotations

from dataclasses import dataclass


# ---- events (bus -> streamer) -------------------------------------------------------------------
@dataclass(frozen=True)
class Sync:
    """The master sent SYNC number `count` (0, 1, 2, ...) at time `t`; `counter` is the CiA 301 SYNC
    counter byte it carried (None: a SYNC without counter). `since`: when the SYNC producer's current
    unbroken run began (the time of its first SYNC, on the clock of `t`), if the runtime knows; None: the
    core takes the first Sync it was fed (a drive that locks on SYNC, the XtrapulsPac, needs 180 ms of it)."""

    count: int
    t: float
    counter: int | None = None
    since: float | None = None


@dataclass(frozen=True)
class SyncOnWire:
    """SYNC `count` is on the wire, and every frame the bus carried before it has been fed (a runtime that
    feeds the core each `Sync` ahead of the wire says so when the SYNC goes out: answers overdue are judged
    from here, not from the Sync fed ahead)."""

    count: int
    t: float


@dataclass(frozen=True)
class RecordOnWire:
    """One PVT record frame (RPDO2) of drive `node` as the bus carried it: the master's own frame, received
    back (the cycle engine forwards what it sent; python-can's `receive_own_messages` otherwise). It is on the
    wire after SYNC `sync_count` (the newest SYNC received back before it; None before the first), so the drive
    has it from SYNC `sync_count` + 1 on. Frames received back keep the bus's order with the SYNCs and the
    drives' answers, so an answer fed before a record's echo was sampled before that record was on the wire."""

    node: int
    t: float
    sync_count: int | None


@dataclass(frozen=True)
class BufferStatus:
    """TPDO1 of one drive: statusword 0x6041, interpolation buffer status 0x20C4:01, free size 0x60C4:02.

    `sync_count` is the newest SYNC on the wire when this TPDO arrived, when the adapter knows it (it does:
    it sent that SYNC): the TPDO answers that SYNC or an earlier one (a drive may answer after the next
    SYNC), and the streamer core decides which by what the TPDO contains (streamer/core/attribution.py).
    With None the core takes the last `Sync` it was fed as that bound.
    """

    node: int
    statusword: int
    buffer_status: int
    free_size: int
    t: float
    sync_count: int | None = None


@dataclass(frozen=True)
class StatusWord:
    """TPDO1 of a drive of a cyclic family (bus/families.py): the statusword 0x6041 alone (no FIFO)."""

    node: int
    statusword: int
    t: float
    sync_count: int | None = None  # the newest SYNC on the wire when it arrived (see BufferStatus)


@dataclass(frozen=True)
class PositionFeedback:
    """TPDO2 of one drive: position actual 0x6064 and position demand 0x6062, counts."""

    node: int
    position_actual: int
    position_demand: int
    t: float
    sync_count: int | None = None  # the newest SYNC on the wire when it arrived (see BufferStatus)


@dataclass(frozen=True)
class Emcy:
    node: int
    code: int
    register: int
    data: bytes
    t: float


@dataclass(frozen=True)
class HeartbeatLost:
    node: int
    t: float


@dataclass(frozen=True)
class Bootup:
    """A boot-up message (heartbeat with state 0) from a node: it rebooted."""

    node: int
    t: float


@dataclass(frozen=True)
class Cancel:
    t: float


@dataclass(frozen=True)
class SendFailed:
    """The bus refused a frame (bus-off, buffer full...). `reason` says what the adapter saw."""

    reason: str
    t: float


@dataclass(frozen=True)
class AdapterError:
    """An exception in a bus callback or adapter thread, turned into an event instead of being swallowed."""

    where: str
    reason: str
    t: float


@dataclass(frozen=True)
class BusLoad:
    """The adapter's measured bus load (all senders, frame bits / bitrate) over its last window, 0..1+."""

    load: float
    t: float


Event = (
    Sync | RecordOnWire | BufferStatus | StatusWord | PositionFeedback | Emcy | HeartbeatLost | Bootup | Cancel
    | SendFailed | AdapterError | BusLoad
)


# ---- actions (streamer -> bus) ------------------------------------------------------------------
@dataclass(frozen=True)
class Send:
    cob_id: int
    data: bytes


Action = Send
