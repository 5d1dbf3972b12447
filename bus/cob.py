"""COB-IDs and the PDO layout the product uses with EPOS-style drives (the wire contract).

    SYNC          0x080               DLC 0, or DLC 1 = the SYNC counter 1..0x1019 when TPDO2 is staggered
    TIME          0x100               DLC 4: high-resolution time stamp 0x1013 (us) of the last SYNC sent
    EMCY          0x080 + n           DLC 8: error code u16, error register u8, 5 manufacturer bytes
    TPDO1         0x180 + n           statusword 0x6041 u16 | free buffer size 0x60C4:02 u32   (type 1)
    RPDO1         0x200 + n           controlword 0x6040 u16   (type 1: applied at next SYNC)
    TPDO2         0x280 + n           position actual 0x6064 i32 | position demand 0x6062 i32   (type 1)
    RPDO2         0x300 + n           PVT record 0x20C1 (8 bytes)   (type 255: on reception)
    RPDO3         0x400 + n           cyclic families: the next SYNC's set point (type 1; multiplexed
                                      groups share their lowest node's COB-ID)
    SDO tx / rx   0x580 + n / 0x600 + n
    Heartbeat     0x700 + n           DLC 1: NMT state (0x00 boot-up, 0x04 stopped, 0x05 op, 0x7F pre-op)

TPDO1 carries the true FIFO fill every cycle (DESIGN.md) and not 0x20C4:01, whose news comes by the fill,
EMCY and the statusword: six bytes fit 24 drives on 1 Mbit/s at 10 ms (bus/budget.py). Little-endian.
"""

from __future__ import annotations

import struct
from typing import NamedTuple

SYNC_COB_ID = 0x080
TIME_STAMP_COB_ID = 0x100  # the master's high-resolution time stamp 0x1013 (4 bytes, us), after each SYNC
EMCY_BASE = 0x080
TPDO1_BASE = 0x180
RPDO1_BASE = 0x200
TPDO2_BASE = 0x280
RPDO2_BASE = 0x300
TPDO3_BASE = 0x380
RPDO3_BASE = 0x400  # one set point per SYNC (cyclic families: 0x60C1 / 0x607A), or a multiplexed group's
TPDO4_BASE = 0x480
RPDO4_BASE = 0x500
SDO_TX_BASE = 0x580
SDO_RX_BASE = 0x600
HEARTBEAT_BASE = 0x700
NMT_COB_ID = 0x000


def emcy_id(node: int) -> int:
    return EMCY_BASE + node


def tpdo1_id(node: int) -> int:
    return TPDO1_BASE + node


def rpdo1_id(node: int) -> int:
    return RPDO1_BASE + node


def tpdo2_id(node: int) -> int:
    return TPDO2_BASE + node


def rpdo2_id(node: int) -> int:
    return RPDO2_BASE + node


def rpdo3_id(node: int) -> int:
    return RPDO3_BASE + node


def heartbeat_id(node: int) -> int:
    return HEARTBEAT_BASE + node


class CobClass(NamedTuple):
    """What a COB-ID is, and for which node (0 for broadcast objects)."""

    # "NMT", "SYNC", "TIME", "EMCY", "TPDO1".."TPDO4", "RPDO1".."RPDO4", "SDO_TX", "SDO_RX", "HEARTBEAT",
    # "OTHER"
    kind: str
    node: int


_RANGES = (
    (EMCY_BASE, "EMCY"),
    (TPDO1_BASE, "TPDO1"),
    (RPDO1_BASE, "RPDO1"),
    (TPDO2_BASE, "TPDO2"),
    (RPDO2_BASE, "RPDO2"),
    (TPDO3_BASE, "TPDO3"),
    (RPDO3_BASE, "RPDO3"),
    (TPDO4_BASE, "TPDO4"),
    (RPDO4_BASE, "RPDO4"),
    (SDO_TX_BASE, "SDO_TX"),
    (SDO_RX_BASE, "SDO_RX"),
    (HEARTBEAT_BASE, "HEARTBEAT"),
)


def classify(cob_id: int) -> CobClass:
    if cob_id == NMT_COB_ID:
        return CobClass("NMT", 0)
    if cob_id == SYNC_COB_ID:
        return CobClass("SYNC", 0)
    if cob_id == TIME_STAMP_COB_ID:
        return CobClass("TIME", 0)
    for base, kind in _RANGES:
        if base + 1 <= cob_id <= base + 127:
            return CobClass(kind, cob_id - base)
    return CobClass("OTHER", 0)


# TPDO1 / TPDO2 / RPDO1 payloads
_TPDO1 = struct.Struct("<HI")
_TPDO2 = struct.Struct("<ii")
_RPDO1 = struct.Struct("<H")


def pack_tpdo1(statusword: int, free_size: int) -> bytes:
    return _TPDO1.pack(statusword, free_size)


def unpack_tpdo1(data: bytes) -> tuple[int, int]:
    """(statusword, free_size). Raises ValueError on a wrong length."""
    if len(data) != _TPDO1.size:
        raise ValueError(f"TPDO1 needs {_TPDO1.size} bytes, got {len(data)}")
    sw, free = _TPDO1.unpack(data)
    return int(sw), int(free)


def pack_tpdo2(position_actual: int, position_demand: int) -> bytes:
    return _TPDO2.pack(position_actual, position_demand)


def unpack_tpdo2(data: bytes) -> tuple[int, int]:
    if len(data) != _TPDO2.size:
        raise ValueError(f"TPDO2 needs {_TPDO2.size} bytes, got {len(data)}")
    actual, demand = _TPDO2.unpack(data)
    return int(actual), int(demand)


def pack_controlword(controlword: int) -> bytes:
    return _RPDO1.pack(controlword)


def unpack_controlword(data: bytes) -> int:
    if len(data) != _RPDO1.size:
        raise ValueError(f"RPDO1 needs {_RPDO1.size} bytes, got {len(data)}")
    return int(_RPDO1.unpack(data)[0])
