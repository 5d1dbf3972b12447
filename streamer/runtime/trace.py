"""What happened on the bus during a job, seen from the master: per-SYNC traces and a frame tally.

`JobTrace` is fed the same events the streamer core is fed (plus every frame, for the tally and the
bus-load measurement) and keeps, per axis, one sample per SYNC: FIFO fill, position actual and
position demand. It is shared by the virtual-time and the real-time runtimes, so the report and the
plot are built the same way whatever bus ran the job. No I/O, no clock: timestamps come with the
events.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from bus.cob import SYNC_COB_ID
from bus.codec import frame_bits
from bus.events import BufferStatus, PositionFeedback

IP_ACTIVE_BIT = 1 << 15  # 0x20C4:01 bit 15
FIFO_SIZE = 64


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

    def max_following_error(self) -> int:
        return max((abs(a - d) for a, d in zip(self.actual, self.demand, strict=True)), default=0)


class JobTrace:
    """Per-axis samples per SYNC and the bus traffic per SYNC cycle (for bus-load peak)."""

    def __init__(self, nodes: Sequence[tuple[int, str]], *, sync_period_s: float, bitrate: int):
        self.axes: dict[int, AxisTrace] = {n: AxisTrace(n, name) for n, name in nodes}
        self.sync_period_s = sync_period_s
        self.bitrate = bitrate
        self.frames = 0
        self._cycle_bits: dict[int, int] = {}
        self._sync = -1
        self._cycle = 0
        self.sync_times: dict[int, float] = {}

    # ---- feeding
    def on_sync(self, count: int, t: float) -> None:
        self._sync = count
        self.sync_times[count] = t

    def on_frame(self, cob_id: int, dlc: int) -> None:
        """Every frame on the bus, whoever sent it. A SYNC frame opens a new cycle for the bus-load tally
        (counted from the frames themselves, so it does not matter which thread sees the events)."""
        self.frames += 1
        if cob_id == SYNC_COB_ID:
            self._cycle += 1
        self._cycle_bits[self._cycle] = self._cycle_bits.get(self._cycle, 0) + frame_bits(dlc)

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
        elif isinstance(ev, PositionFeedback):
            ax = self.axes.get(ev.node)
            if ax is None:
                return
            ax.pos_sync.append(self._sync if ev.sync_count is None else ev.sync_count)
            ax.actual.append(ev.position_actual)
            ax.demand.append(ev.position_demand)

    def feed(self, events: Iterable[object]) -> None:
        for ev in events:
            self.on_event(ev)

    # ---- results
    def bus_load_peak(self) -> float:
        """Largest share of one SYNC cycle's bit time used by all frames of that cycle (worst-case stuffing)."""
        cycle = self.bitrate * self.sync_period_s
        return max(self._cycle_bits.values(), default=0) / cycle if cycle > 0 else 0.0

    def final_actual(self, node: int) -> int | None:
        ax = self.axes[node]
        return ax.actual[-1] if ax.actual else None

    def final_demand(self, node: int) -> int | None:
        ax = self.axes[node]
        return ax.demand[-1] if ax.demand else None
