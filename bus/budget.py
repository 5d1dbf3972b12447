"""Bus-load accounting: worst-case frame lengths, the per-SYNC frame budget, and the feedback rate that fits.

The streamer keeps its own traffic and the traffic it causes (SYNC, time stamp, TPDOs, heartbeats) under a
share of the bitrate (70 % by default), with worst-case lengths. TPDO2 every n-th SYNC is staggered by the
SYNC counter (`bus.profile.FeedbackSchedule`), so the busiest cycle carries ceil(nodes / n). A classic
frame with n data bytes is 47 + 8n bits with intermission plus at most floor((34 + 8n - 1) / 4) stuff bits
(Davis et al., "Controller Area Network (CAN) schedulability analysis: refuted, revisited and revised",
2007): 135 bits for 8 bytes, 55 for an empty SYNC (`bus.codec.frame_bits`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from bus.codec import frame_bits

RECORD_FRAME_BITS = frame_bits(8)  # RPDO2 0x20C1 record
CONTROLWORD_FRAME_BITS = frame_bits(2)  # RPDO1 controlword
TPDO_FRAME_BITS = frame_bits(8)  # TPDO2 (4+4 bytes), the larger of the two
TPDO1_FRAME_BITS = frame_bits(6)  # TPDO1 (statusword 2 + free size 4 bytes)
STATUS_FRAME_BITS = frame_bits(2)  # TPDO1 of a cyclic drive (statusword alone)
SYNC_FRAME_BITS = frame_bits(0)
COUNTED_SYNC_FRAME_BITS = frame_bits(1)  # SYNC with the counter byte
TIME_STAMP_FRAME_BITS = frame_bits(4)  # 0x1013 after every SYNC
HEARTBEAT_FRAME_BITS = frame_bits(1)
MAX_FEEDBACK_EVERY = 16


@dataclass(frozen=True)
class CycleBudget:
    """Bits per SYNC cycle: the limit, the part the drives and the SYNC use anyway, and what is left."""

    cycle_bits: float  # bitrate * period
    limit_bits: float  # bus_load_limit * cycle_bits
    # SYNC (+ time stamp) + TPDO1 per node + the busiest cycle's TPDO2s + heartbeats + the cyclic drives'
    # set point frames (one per axis or multiplexed group, every SYNC)
    fixed_bits: float

    @property
    def streamer_bits(self) -> float:
        """Bits per cycle left for the streamer's own frames."""
        return self.limit_bits - self.fixed_bits

    def record_frames_per_axis(self, n_axes: int) -> int:
        """How many records every axis may get per cycle, all axes the same, within the budget."""
        return max(0, int(self.streamer_bits // (n_axes * RECORD_FRAME_BITS)))


def cycle_budget(
    n_nodes: int, sync_period_ms: int, bitrate: int, bus_load_limit: float, heartbeat_ms: int,
    *, feedback_every: int = 1, time_stamp: bool = False, cyclic_nodes: int = 0, setpoint_bits: float = 0.0,
) -> CycleBudget:
    """The budget of a cell of `n_nodes` drives, `cyclic_nodes` of them of a cyclic family (TPDO1 = the
    statusword alone), whose set point frames take `setpoint_bits` every SYNC (`setpoint_frame_bits`)."""
    cycle_bits = bitrate * sync_period_ms / 1000.0
    heartbeats_per_cycle = sync_period_ms / heartbeat_ms if heartbeat_ms > 0 else 0.0
    sync = COUNTED_SYNC_FRAME_BITS if feedback_every > 1 else SYNC_FRAME_BITS
    feedback_frames = math.ceil(n_nodes / max(1, feedback_every))
    # heartbeats: the drives' producer times are spread (bus.profile), so a cycle carries about the
    # average number, plus a margin for the cycles where a few coincide
    heartbeat_frames = min(n_nodes, math.ceil(n_nodes * heartbeats_per_cycle) + 2) if heartbeat_ms > 0 else 0
    fixed = (sync + (TIME_STAMP_FRAME_BITS if time_stamp else 0)
             + (n_nodes - cyclic_nodes) * TPDO1_FRAME_BITS + cyclic_nodes * STATUS_FRAME_BITS
             + heartbeat_frames * HEARTBEAT_FRAME_BITS + feedback_frames * TPDO_FRAME_BITS + setpoint_bits)
    return CycleBudget(cycle_bits=cycle_bits, limit_bits=bus_load_limit * cycle_bits, fixed_bits=fixed)


def setpoint_frame_bits(frame_bytes: Iterable[int]) -> float:
    """Worst-case bits of the set point frames of one SYNC: one per cyclic axis or multiplexed group."""
    return float(sum(frame_bits(b) for b in frame_bytes))


def feedback_every(
    n_nodes: int, sync_period_ms: int, bitrate: int, bus_load_limit: float, heartbeat_ms: int,
    *, requested: int = 0, time_stamp: bool = False, cyclic_nodes: int = 0, setpoint_bits: float = 0.0,
) -> int:
    """TPDO2 every n-th SYNC: `requested` when given (>= 1), else the smallest n (1..16) whose budget
    leaves every FIFO axis one record per SYNC, and the cyclic drives' frames room under the limit (16
    when none does: the core then refuses BUS_OVERLOAD)."""
    if requested >= 1:
        return requested
    fifo = n_nodes - cyclic_nodes
    for n in range(1, MAX_FEEDBACK_EVERY + 1):
        budget = cycle_budget(n_nodes, sync_period_ms, bitrate, bus_load_limit, heartbeat_ms,
                              feedback_every=n, time_stamp=time_stamp, cyclic_nodes=cyclic_nodes,
                              setpoint_bits=setpoint_bits)
        if (budget.record_frames_per_axis(fifo) >= 1) if fifo else budget.streamer_bits >= 0:
            return n
    return MAX_FEEDBACK_EVERY


def cell_traffic(cell: Any) -> tuple[int, float]:
    """(cyclic nodes, their set point frames' bits per SYNC) of a `planner.config.CellConfig`."""
    from bus.families import setpoint_slots

    slots = setpoint_slots(cell.axes)
    frames = {s.cob_id: s.frame_bytes for s in slots.values()}
    return len(slots), setpoint_frame_bits(frames.values())


def cell_feedback_every(cell: Any, bus_load_limit: float = 0.7) -> int:
    """`feedback_every` for a `planner.config.CellConfig` (its `feedback_every_syncs`, 0 = auto)."""
    cyclic, bits = cell_traffic(cell)
    return feedback_every(len(cell.axes), cell.sync_period_ms, cell.bus.bitrate, bus_load_limit,
                          cell.drive.heartbeat_ms, requested=cell.feedback_every_syncs, time_stamp=cell.time_stamp,
                          cyclic_nodes=cyclic, setpoint_bits=bits)
