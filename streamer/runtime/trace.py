"""What happened on the bus during a job, seen from the master: per-SYNC traces and a frame tally.

`JobTrace` is fed the events the core is fed (plus every frame, for the tally and the bus load) and keeps
per axis one sample per TPDO (fill, position actual and demand) with the runtime's tag, the newest SYNC on
the wire when it arrived; the report uses the core's attribution (`JobReport.feedback`), not these tags.
Shared by both runtimes, so report and plot are built alike. No I/O, no clock. An endless job's trace
spills to a `store` (streamer/runtime/spill.py, `Column`s of streamer/core/spool.py), so an hour costs no
more memory than a minute. With `record=True` it also keeps what the recording needs (frames with data,
TPDO1 words, events, state changes, set points), each an append costing the streaming thread a few
hundred nanoseconds (benchmarks/bench_recording.py); the MCAP file is written after the job.
"""

from __future__ import annotations

import dataclasses
from array import array
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from bus.cob import SYNC_COB_ID
from bus.codec import frame_bits
from bus.events import (
    AdapterError,
    Bootup,
    BufferStatus,
    Cancel,
    Emcy,
    HeartbeatLost,
    PositionFeedback,
    SendFailed,
    StatusWord,
)
from streamer.core.spool import Column, StoreFactory

IP_ACTIVE_BIT = 1 << 15  # 0x20C4:01 bit 15
FIFO_SIZE = 64
# 1e6 frames keep about 19 MB (8 data bytes, a double, a COB-ID and a DLC each): about 8 minutes of a
# 6-axis job at a 10 ms SYNC; beyond that the frames are counted, not kept
DEFAULT_MAX_FRAMES = 1_000_000
_NOTED = (Emcy, HeartbeatLost, Bootup, Cancel, SendFailed, AdapterError)
_PAD = bytes(8)


def answered(ev: object, sync: int | None) -> object:
    """`ev` as the trace keeps it: a drive's answer tagged with the SYNC the core attributed it to (`sync`,
    Coordinator.answered_sync), not the one it arrived after; anything else as it is."""
    if sync is None or not isinstance(ev, (BufferStatus, StatusWord, PositionFeedback)):
        return ev
    return dataclasses.replace(ev, sync_count=sync)


@dataclass(frozen=True)
class NotedEvent:
    """An event of the job that is not a per-SYNC sample, with the last SYNC fed before it."""

    sync: int
    event: object


@dataclass(frozen=True)
class NotedChange:
    """A job state change the core reported, as plain data (the trace is pickled to the process that
    writes the recording): the new state's value, the SYNC and time, and the outcome's code, node and
    message when the change carried one."""

    state: str
    sync: int | None
    t: float
    code: str | None = None
    node: int | None = None
    message: str = ""

    @classmethod
    def of(cls, change: Any) -> NotedChange:
        """From a `streamer.core.coordinator.StateChange` (duck-typed: `state` an enum with `.value`,
        `sync`, `t`, `outcome` None or with `code`, `node`, `message`)."""
        state = getattr(change.state, "value", change.state)
        outcome = change.outcome
        if outcome is None:
            return cls(str(state), change.sync, float(change.t))
        return cls(str(state), change.sync, float(change.t), outcome.code, outcome.node, str(outcome.message))


class FrameLog:
    """Frames in compact arrays: time (s, the runtime's clock), COB-ID, DLC and 8 data bytes each. Given a
    `store` (an endless job), four `Column`s that keep their old blocks there instead (the data bytes as one
    little-endian int64), so that the `max_frames` it keeps cost one block each in memory."""

    def __init__(self, max_frames: int, store: StoreFactory | None = None):
        if max_frames < 0:
            raise ValueError(f"max_frames must be >= 0, got {max_frames}")
        self.max_frames = max_frames
        self.t = array("d")
        self.cob_id = array("H")
        self.dlc = array("B")
        self.data = bytearray()
        self.dropped = 0
        self._columns = None if store is None else (
            Column("d", store), Column("q", store), Column("q", store), Column("q", store))

    def __len__(self) -> int:
        return len(self.t) if self._columns is None else len(self._columns[0])

    @property
    def held(self) -> int:
        """Frames held in memory."""
        return len(self.t) if self._columns is None else self._columns[0].held

    def add(self, t: float, cob_id: int, dlc: int, data: bytes) -> None:
        if len(self) >= self.max_frames:
            self.dropped += 1
            return
        if self._columns is not None:
            ct, cc, cd, cx = self._columns
            ct.append(t)
            cc.append(cob_id)
            cd.append(dlc)
            cx.append(int.from_bytes((data[:8] + _PAD)[:8], "little", signed=True))
            return
        self.t.append(t)
        self.cob_id.append(cob_id)
        self.dlc.append(dlc)
        n = len(data)
        if n == 8:  # most frames (PVT records, TPDOs): one copy, no padding
            self.data += data
        else:
            self.data += data[:8]
            self.data += _PAD[min(n, 8):]

    def frame(self, i: int) -> tuple[float, int, int, bytes]:
        if self._columns is not None:
            ct, cc, cd, cx = self._columns
            n = int(cd[i])
            return float(ct[i]), int(cc[i]), n, int(cx[i]).to_bytes(8, "little", signed=True)[:min(n, 8)]
        n = self.dlc[i]
        return self.t[i], self.cob_id[i], n, bytes(self.data[8 * i: 8 * i + min(n, 8)])

    def frames(self) -> Iterator[tuple[float, int, int, bytes]]:
        """Every frame kept, in order (reads a store's blocks in sequence, never frame by frame)."""
        if self._columns is None:
            yield from (self.frame(i) for i in range(len(self)))
            return
        for t, c, n, x in zip(*self._columns, strict=True):
            yield float(t), int(c), int(n), int(x).to_bytes(8, "little", signed=True)[:min(int(n), 8)]


@dataclass
class AxisTrace:
    node_id: int
    name: str
    fill_sync: list[int] = field(default_factory=list)
    fill: list[int] = field(default_factory=list)
    pos_sync: list[int] = field(default_factory=list)
    actual: list[int] = field(default_factory=list)
    demand: list[int] = field(default_factory=list)
    ip_active_syncs: list[int] = field(default_factory=list)  # SYNCs answered with ip mode active
    # recorded only with JobTrace(record=True): TPDO1's other two objects, aligned with fill_sync
    statusword: list[int] = field(default_factory=list)
    buffer_status: list[int] = field(default_factory=list)
    # a cyclic drive's statusword (TPDO1 carries nothing else), with the SYNC it answers
    statusword_sync: list[int] = field(default_factory=list)
    statusword_only: list[int] = field(default_factory=list)
    # the set point sent per SYNC by a cyclic (one set point per SYNC) drive family, counts
    setpoint_sync: list[int] = field(default_factory=list)
    setpoint: list[int] = field(default_factory=list)

    def max_following_error(self) -> int:
        return max((abs(a - d) for a, d in zip(self.actual, self.demand, strict=True)), default=0)

    @classmethod
    def spilled(cls, node_id: int, name: str, store: StoreFactory) -> AxisTrace:
        """An axis trace whose per-SYNC samples are `Column`s that keep their old blocks in `store`."""
        return cls(node_id, name, **{f.name: Column("q", store) for f in dataclasses.fields(cls)  # type: ignore[arg-type]
                                     if f.name not in ("node_id", "name")})

    @property
    def held(self) -> int:
        """Samples held in memory, over every per-SYNC series."""
        return sum(getattr(v, "held", len(v)) for k, v in vars(self).items() if k not in ("node_id", "name"))


class SyncTimes(Mapping[int, float]):
    """SYNC count -> time it was sent, in two columns (the counts increase): what `JobTrace.sync_times` is for
    an endless job (a dict of an hour's SYNCs holds tens of MB)."""

    def __init__(self, store: StoreFactory) -> None:
        self._counts = Column("q", store)
        self._times = Column("d", store)

    def add(self, count: int, t: float) -> None:
        n = len(self._counts)
        if n and count <= self._counts[-1]:
            raise ValueError(f"SYNC count {count} after {self._counts[-1]}: counts must increase")
        self._counts.append(count)
        self._times.append(t)

    def _index(self, count: int) -> int | None:
        n = len(self._counts)
        if not n:
            return None
        i = count - int(self._counts[0])  # consecutive counts: the usual case, one look
        if 0 <= i < n and self._counts[i] == count:
            return i
        lo, hi = 0, n  # else bisect (a gap: a SYNC the runtime did not see)
        while lo < hi:
            mid = (lo + hi) // 2
            if self._counts[mid] < count:
                lo = mid + 1
            else:
                hi = mid
        return lo if lo < n and self._counts[lo] == count else None

    def __getitem__(self, count: int) -> float:
        i = self._index(count)
        if i is None:
            raise KeyError(count)
        return float(self._times[i])

    def __contains__(self, count: object) -> bool:
        return isinstance(count, int) and self._index(count) is not None

    def __iter__(self) -> Iterator[int]:
        return (int(c) for c in self._counts)

    def __len__(self) -> int:
        return len(self._counts)

    @property
    def held(self) -> int:
        return self._counts.held + self._times.held


class JobTrace:
    """Per-axis samples per SYNC and the bus traffic per SYNC cycle (for bus-load peak)."""

    def __init__(self, nodes: Sequence[tuple[int, str]], *, sync_period_s: float, bitrate: int,
                 record: bool = True, max_frames: int = DEFAULT_MAX_FRAMES, store: StoreFactory | None = None):
        # an endless job's samples (`store` given: streamer/runtime/spill.py) keep all but their newest block
        # in the store, so its memory stays flat and the report and recording still read every sample
        self.store = store
        self.axes: dict[int, AxisTrace] = {
            n: AxisTrace(n, name) if store is None else AxisTrace.spilled(n, name, store) for n, name in nodes}
        self.sync_period_s = sync_period_s
        self.bitrate = bitrate
        self.frames = 0
        # bus load: the bits of the open cycle and the most of any closed one (a frame counts in the cycle open
        # when it is seen, so a closed cycle never changes): constant memory however long the job runs
        self._cycle_bits = 0
        self._peak_bits = 0
        self._sync = -1
        self._cycle = 0
        self.sync_times: dict[int, float] | SyncTimes = {} if store is None else SyncTimes(store)
        self.record = record
        self.frame_log = FrameLog(max_frames if record else 0, store)
        self.noted: list[NotedEvent] = []
        self.changes: list[NotedChange] = []

    # ---- feeding
    def on_sync(self, count: int, t: float) -> None:
        self._sync = count
        if isinstance(self.sync_times, SyncTimes):
            self.sync_times.add(count, t)
        else:
            self.sync_times[count] = t

    def on_frame(self, cob_id: int, dlc: int, data: bytes | None = None, t: float | None = None) -> None:
        """Every frame on the bus, whoever sent it. A SYNC frame opens a new cycle for the bus-load tally
        (counted from the frames themselves, so it does not matter which thread sees the events).
        With `data` and `t` given and record=True the frame is also kept for the recording."""
        self.frames += 1
        if cob_id == SYNC_COB_ID:
            self._cycle += 1
            self._peak_bits = max(self._peak_bits, self._cycle_bits)
            self._cycle_bits = 0
        self._cycle_bits += frame_bits(dlc)
        if self.record and data is not None and t is not None:
            self.frame_log.add(t, cob_id, dlc, data)

    def on_changes(self, changes: Sequence[Any]) -> None:
        """The job state changes of one `Reaction` (usually none)."""
        if self.record:
            for c in changes:
                self.changes.append(NotedChange.of(c))

    def on_setpoint(self, node: int, sync: int, setpoint: int) -> None:
        """The set point (counts) a cyclic drive family sent to `node` for SYNC `sync`."""
        ax = self.axes.get(node)
        if ax is not None:
            ax.setpoint_sync.append(sync)
            ax.setpoint.append(setpoint)

    def on_event(self, ev: object) -> None:
        if isinstance(ev, BufferStatus):
            ax = self.axes.get(ev.node)
            if ax is None:
                return
            s = self._sync if ev.sync_count is None else ev.sync_count
            ax.fill_sync.append(s)
            ax.fill.append(FIFO_SIZE - ev.free_size)
            if ev.buffer_status & IP_ACTIVE_BIT:
                ax.ip_active_syncs.append(s)
            if self.record:
                ax.statusword.append(ev.statusword)
                ax.buffer_status.append(ev.buffer_status)
        elif isinstance(ev, StatusWord):  # a cyclic drive: no FIFO, the statusword alone
            ax = self.axes.get(ev.node)
            if ax is None:
                return
            s = self._sync if ev.sync_count is None else ev.sync_count
            if ev.statusword & 0x1000:
                ax.ip_active_syncs.append(s)
            if self.record:
                ax.statusword_sync.append(s)
                ax.statusword_only.append(ev.statusword)
        elif isinstance(ev, PositionFeedback):
            ax = self.axes.get(ev.node)
            if ax is None:
                return
            ax.pos_sync.append(self._sync if ev.sync_count is None else ev.sync_count)
            ax.actual.append(ev.position_actual)
            ax.demand.append(ev.position_demand)
        elif self.record and isinstance(ev, _NOTED):
            node = getattr(ev, "node", None)
            if node is None or node in self.axes:
                self.noted.append(NotedEvent(self._sync, ev))

    def feed(self, events: Iterable[object]) -> None:
        for ev in events:
            self.on_event(ev)

    # ---- results
    def bus_load_peak(self) -> float:
        """Largest share of one SYNC cycle's bit time used by all frames of that cycle (worst-case stuffing)."""
        cycle = self.bitrate * self.sync_period_s
        return max(self._peak_bits, self._cycle_bits) / cycle if cycle > 0 else 0.0

    def final_actual(self, node: int) -> int | None:
        ax = self.axes[node]
        return ax.actual[-1] if ax.actual else None

    def final_demand(self, node: int) -> int | None:
        ax = self.axes[node]
        return ax.demand[-1] if ax.demand else None


def positions_by_sync(axis: AxisTrace | None, log: Any = None) -> tuple[list[int], list[int], list[int]]:
    """(sync, actual, demand) of one axis' TPDO2 samples, each at the SYNC it answers: within the span the
    streamer core attributed (`log`, its `FeedbackLog` for the node: `JobReport.feedback`) as the core
    attributed them; outside it (before the core's first, after its last: the core stopped at the job's end,
    the runtime goes on tracing the settling) and for a node without a log, by their arrival tag (`axis`):
    after a job that ended at rest a late answer one SYNC off shows the same position."""
    if log is None or len(log.sync) == 0:
        if axis is None:
            return [], [], []
        return list(axis.pos_sync), list(axis.actual), list(axis.demand)
    lo, hi = log.sync[0], log.sync[-1]
    before: list[tuple[int, int, int]] = []
    after: list[tuple[int, int, int]] = []
    if axis is not None:
        for s, a, d in zip(axis.pos_sync, axis.actual, axis.demand, strict=True):
            if s < lo:
                before.append((s, a, d))
            elif s > hi:  # after the job, at rest: a late answer to hi tagged hi + 1 shows the same
                after.append((s, a, d))
    rows = before + list(zip(log.sync, log.actual, log.demand, strict=True)) + after
    return [r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows]
