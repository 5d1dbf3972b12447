"""Bus-load accounting: worst-case bit length of standard CAN frames, and the per-SYNC frame budget.

The streamer keeps its own traffic plus the traffic it causes (SYNC, two TPDOs per drive per SYNC,
heartbeats) under a fraction of the bitrate (70% by default). Lengths are worst case, so the budget
holds whatever the payload bits are.

A classic CAN 2.0A data frame with n data bytes has 44 + 8n bits between SOF and EOF, plus 3 bits of
intermission before the next frame may start: 47 + 8n. Bit stuffing applies from SOF to the end of the
CRC sequence, 34 + 8n bits, and adds at most floor((34 + 8n - 1) / 4) bits (a stuff bit after every
4 equal bits once the first 5 have been counted; Davis et al., "Controller Area Network (CAN)
schedulability analysis: refuted, revisited and revised", 2007). So 8 data bytes cost 135 bits and
an empty SYNC 55. The formula itself is `bus.codec.frame_bits` (one definition for the whole product).
"""

from __future__ import annotations

from dataclasses import dataclass

from bus.codec import frame_bits

RECORD_FRAME_BITS = frame_bits(8)  # RPDO2 0x20C1 record
CONTROLWORD_FRAME_BITS = frame_bits(2)  # RPDO1 controlword
TPDO_FRAME_BITS = frame_bits(8)  # TPDO1 (2+2+4 bytes) and TPDO2 (4+4 bytes)
SYNC_FRAME_BITS = frame_bits(0)
HEARTBEAT_FRAME_BITS = frame_bits(1)


@dataclass(frozen=True)
class CycleBudget:
    """Bits per SYNC cycle: the limit, the part the drives and the SYNC use anyway, and what is left."""

    cycle_bits: float  # bitrate * period
    limit_bits: float  # bus_load_limit * cycle_bits
    fixed_bits: float  # SYNC + 2 TPDOs per node + heartbeats (averaged per cycle)

    @property
    def streamer_bits(self) -> float:
        """Bits per cycle left for the streamer's own frames."""
        return self.limit_bits - self.fixed_bits

    def record_frames_per_axis(self, n_axes: int) -> int:
        """How many records every axis may get per cycle, all axes the same, within the budget."""
        return max(0, int(self.streamer_bits // (n_axes * RECORD_FRAME_BITS)))


def cycle_budget(
    n_nodes: int, sync_period_ms: int, bitrate: int, bus_load_limit: float, heartbeat_ms: int
) -> CycleBudget:
    cycle_bits = bitrate * sync_period_ms / 1000.0
    heartbeats_per_cycle = sync_period_ms / heartbeat_ms if heartbeat_ms > 0 else 0.0
    fixed = SYNC_FRAME_BITS + n_nodes * (2 * TPDO_FRAME_BITS + heartbeats_per_cycle * HEARTBEAT_FRAME_BITS)
    return CycleBudget(cycle_bits=cycle_bits, limit_bits=bus_load_limit * cycle_bits, fixed_bits=fixed)
