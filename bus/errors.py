"""Errors of the bus layer, each with a stable machine-readable code.

`BusError` (from the master-side adapter): NO_RESPONSE, SDO_ABORT, VERIFY, MISSING_OBJECT, PROBE,
BUS_OPEN, SEND_FAILED; the message names the node and the object ("node 3 did not answer reading
0x1000:00"). `ProtocolError` (from the pure codecs) for a frame that cannot be decoded; also a
`ValueError`.
"""

from __future__ import annotations

from typing import Any

# Stable codes.
BUS_OPEN = "BUS_OPEN"
NO_RESPONSE = "NO_RESPONSE"
SDO_ABORT = "SDO_ABORT"
VERIFY = "VERIFY"
SEND_FAILED = "SEND_FAILED"
CLOSED = "CLOSED"
PROTOCOL = "PROTOCOL"
CALLBACK = "CALLBACK"
CONFIG = "CONFIG"
MISSING_OBJECT = "MISSING_OBJECT"  # the drive lacks an object the product cannot do without
PROBE = "PROBE"  # the standstill probe could not tell how a drive settles the manuals' open points

CODES = frozenset({BUS_OPEN, NO_RESPONSE, SDO_ABORT, VERIFY, SEND_FAILED, CLOSED, PROTOCOL, CALLBACK, CONFIG,
                   MISSING_OBJECT, PROBE})


class BusError(Exception):
    """A failure on the wire. `code` is stable; `node` and `obj` say where (0 / None when not applicable)."""

    def __init__(
        self,
        code: str,
        message: str,
        *,
        node: int = 0,
        obj: tuple[int, int] | None = None,
        detail: dict[str, Any] | None = None,
    ):
        if code not in CODES:
            raise ValueError(f"unknown bus error code {code!r}")
        super().__init__(message)
        self.code = code
        self.message = message
        self.node = node
        self.obj = obj
        self.detail = dict(detail or {})

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"code": self.code, "message": self.message, "node": self.node}
        if self.obj is not None:
            out["object"] = f"0x{self.obj[0]:04X}:{self.obj[1]:02X}"
        if self.detail:
            out["detail"] = self.detail
        return out

    def __repr__(self) -> str:
        return f"BusError({self.code!r}, {self.message!r}, node={self.node})"


class ProtocolError(BusError, ValueError):
    """A frame that does not decode (wrong DLC, unknown enumeration value, ...)."""

    def __init__(self, message: str, *, cob_id: int | None = None, detail: dict[str, Any] | None = None):
        d = dict(detail or {})
        if cob_id is not None:
            d["cob_id"] = cob_id
        super().__init__(PROTOCOL, message, detail=d)
        self.cob_id = cob_id


def format_object(index: int, subindex: int) -> str:
    return f"0x{index:04X}:{subindex:02X}"
