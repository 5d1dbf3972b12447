"""Job outcomes and the stable failure codes of the streamer core.

A job ends exactly once: DONE, CANCELLED, or FAILED with one of the codes below, the node that caused
it (None when no single node is to blame), a message naming the node and the values, the SYNC it was
decided on and a `detail` mapping with machine-readable extras (e.g. `emcy_code`, `predicted`). The
codes are a public contract (the API and the reliability report switch on them): never rename one,
only add.

EMCY codes are mapped here too, because the mapping decides the code of most drive-side failures.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum
from types import MappingProxyType
from typing import Any

# ---- failure codes (stable strings) -------------------------------------------------------------
BUFFER_UNDERFLOW = "BUFFER_UNDERFLOW"  # drive reported it (EMCY 0x8782 / bit 8), or the core predicted it
BUFFER_OVERFLOW = "BUFFER_OVERFLOW"  # drive reported it (EMCY 0x8782 / bit 9)
DRIVE_FAULT = "DRIVE_FAULT"  # any other EMCY (detail carries emcy_code), fault bit, IP velocity/accel error
FOLLOWING_ERROR = "FOLLOWING_ERROR"  # EMCY 0x8611
NODE_LOST = "NODE_LOST"  # heartbeat consumer timeout on the master side
NODE_REBOOT = "NODE_REBOOT"  # boot-up message from a job node
SYNC_LOST = "SYNC_LOST"  # EMCY 0x8780, a SYNC count that jumped, or an optional core-side gap check
TPDO_TIMEOUT = "TPDO_TIMEOUT"  # no TPDO1 or TPDO2 from a node for `tpdo_timeout_syncs` SYNCs
POINT_LOST = "POINT_LOST"  # a record was lost and cannot be resent without changing execution order
BUS_ERROR = "BUS_ERROR"  # the adapter could not send (bus-off...) or reported an adapter exception
BUS_OVERLOAD = "BUS_OVERLOAD"  # the plan or the bus cannot keep the FIFOs above the underflow watermark
START_MISMATCH = "START_MISMATCH"  # the drive's position demand is not the plan's knot 0
PROTOCOL = "PROTOCOL"  # duplicate or reordered record, fill below anything losses explain, ip mode off early
# additions beyond the list (same contract: stable, documented here)
DRIVE_NOT_READY = "DRIVE_NOT_READY"  # at configure: not operation enabled, buffer disabled, FIFO not empty
START_FAILED = "START_FAILED"  # a drive did not report ip mode active at the start SYNC
FINISH_TIMEOUT = "FINISH_TIMEOUT"  # ip mode inactive + target reached (or halt standstill) never reported
SETPOINT_LATE = "SETPOINT_LATE"  # a cyclic drive missed a set point (EMCY 0x8782: missing, or < 100 us before SYNC)
SETPOINT_RANGE = "SETPOINT_RANGE"  # a cyclic axis' set points do not fit their frame (16-bit step, group)
EMERGENCY_STOP = "EMERGENCY_STOP"  # an emergency stop with no plan possible in time: quick stop on every axis
EXTENSION_FAILED = "EXTENSION_FAILED"  # an open-ended (velocity) stream got no next chunk in time: stopped, at rest

FAILURE_CODES = frozenset(
    {
        BUFFER_UNDERFLOW,
        BUFFER_OVERFLOW,
        DRIVE_FAULT,
        FOLLOWING_ERROR,
        NODE_LOST,
        NODE_REBOOT,
        SYNC_LOST,
        TPDO_TIMEOUT,
        POINT_LOST,
        BUS_ERROR,
        BUS_OVERLOAD,
        START_MISMATCH,
        PROTOCOL,
        DRIVE_NOT_READY,
        START_FAILED,
        FINISH_TIMEOUT,
        SETPOINT_LATE,
        SETPOINT_RANGE,
        EMERGENCY_STOP,
        EXTENSION_FAILED,
    }
)

# ---- EMCY codes (common.md) ---------------------------------------------------------------------
EMCY_NO_ERROR = 0x0000  # "error reset / no error": not a fault, ignored
EMCY_FOLLOWING_ERROR = 0x8611
EMCY_IP_BUFFER = 0x8782  # underflow or overflow: buffer status (manufacturer bytes 3-4) tells which
EMCY_SYNC_LOST = 0x8780
EMCY_HEARTBEAT = 0x8130
EMCY_PDO_SHORT = 0x8210
EMCY_PDO_LONG = 0x8220
EMCY_IP_VELOCITY = 0xFF10
EMCY_IP_ACCELERATION = 0xFF11

BUFFER_UNDERFLOW_ERROR_BIT = 1 << 8
BUFFER_OVERFLOW_ERROR_BIT = 1 << 9


def classify_emcy(code: int, data: bytes, *, cyclic: bool = False) -> tuple[str, str]:
    """(failure code, description) of an EMCY. Generic codes map to DRIVE_FAULT. `cyclic`: the drive takes
    one set point per SYNC, so 0x8782 means a set point came late or not at all (seed 003 error 50)."""
    if code == EMCY_IP_BUFFER and cyclic:
        return SETPOINT_LATE, "IP set point missing or late (less than 100 us before its SYNC)"
    if code == EMCY_FOLLOWING_ERROR:
        return FOLLOWING_ERROR, "following error"
    if code == EMCY_SYNC_LOST:
        return SYNC_LOST, "SYNC lost / SYNC cycle error"
    if code == EMCY_IP_BUFFER:
        # buffer status = EMCY frame bytes 3-4; accept the whole frame's 8 bytes or the 5 manufacturer bytes
        raw = data[3:5] if len(data) == 8 else data[0:2] if len(data) == 5 else b""
        status = int.from_bytes(raw, "little")
        if status & BUFFER_OVERFLOW_ERROR_BIT:
            return BUFFER_OVERFLOW, "IP buffer overflow"
        if status & BUFFER_UNDERFLOW_ERROR_BIT:
            return BUFFER_UNDERFLOW, "IP buffer underflow"
        # the code alone means "underflow or overflow"; underflow is the one a streamer causes by silence
        return BUFFER_UNDERFLOW, "IP buffer underflow/overflow (buffer status not in the EMCY)"
    names = {
        EMCY_HEARTBEAT: "heartbeat/guarding error on the drive",
        EMCY_PDO_SHORT: "PDO too short",
        EMCY_PDO_LONG: "PDO too long",
        EMCY_IP_VELOCITY: "IP velocity error (0x607F exceeded)",
        EMCY_IP_ACCELERATION: "IP acceleration error (0x60C5 exceeded)",
    }
    return DRIVE_FAULT, names.get(code, "drive error")


class JobResult(Enum):
    DONE = "done"
    CANCELLED = "cancelled"
    FAILED = "failed"


_EMPTY: Mapping[str, Any] = MappingProxyType({})


@dataclass(frozen=True)
class JobOutcome:
    """How a job ended. `code` is None unless FAILED; `sync` is the SYNC count the decision was made on."""

    result: JobResult
    code: str | None
    node: int | None
    message: str
    sync: int | None
    t: float
    detail: Mapping[str, Any] = field(default_factory=lambda: _EMPTY)

    def __post_init__(self) -> None:
        if self.result is JobResult.FAILED:
            if self.code not in FAILURE_CODES:
                raise ValueError(f"a FAILED outcome needs a known failure code, got {self.code!r}")
        elif self.code is not None:
            raise ValueError(f"a {self.result.value} outcome carries no failure code, got {self.code!r}")
        object.__setattr__(self, "detail", MappingProxyType(dict(self.detail)))

    def to_dict(self) -> dict[str, Any]:
        return {
            "result": self.result.value,
            "code": self.code,
            "node": self.node,
            "message": self.message,
            "sync": self.sync,
            "t": self.t,
            "detail": dict(self.detail),
        }
