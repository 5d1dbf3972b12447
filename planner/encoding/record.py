"""The PVT record of maxon's interpolated position mode (object 0x20C1, seed 000 section 4.3.1).

Eight bytes, little-endian: position int32 (bytes 0-3, position units = quadcounts), velocity
int24 (bytes 4-6, velocity units = rpm of the motor shaft), time uint8 (byte 7, ms; 1..255 for a
segment, 0 ends interpolation without error).

This is the one implementation of the codec: the planner uses it to prove its output fits the wire,
the bus layer and the simulated drive use it to send and receive. Values that do not fit raise
`EncodingRangeError`; nothing ever wraps.
"""

from __future__ import annotations

from typing import NamedTuple

from planner.errors import EncodingRangeError

RECORD_SIZE = 8
POSITION_MIN, POSITION_MAX = -(2**31), 2**31 - 1
VELOCITY_MIN, VELOCITY_MAX = -(2**23), 2**23 - 1
TIME_MIN_MS, TIME_MAX_MS = 0, 255
SEGMENT_TIME_MIN_MS, SEGMENT_TIME_MAX_MS = 1, 255


class PvtRecord(NamedTuple):
    """One reference point: where the segment ends, how fast, and how long it takes to get there."""

    position: int  # counts (quadcounts)
    velocity: int  # rpm
    time_ms: int  # 1..255, or 0 = end of interpolation

    @property
    def is_end(self) -> bool:
        return self.time_ms == 0


def _check_int(name: str, value: object, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        # numpy integers are accepted through __index__, floats are not (no silent truncation)
        try:
            value = value.__index__()  # type: ignore[attr-defined]
        except AttributeError:
            raise EncodingRangeError(
                f"PVT {name} {value!r} is not an integer", path=name, detail={"value": repr(value)}
            ) from None
    assert isinstance(value, int)
    if not lo <= value <= hi:
        raise EncodingRangeError(
            f"PVT {name} {value} does not fit its field [{lo}, {hi}]",
            path=name,
            detail={"value": value, "min": lo, "max": hi},
        )
    return value


def pack(record: PvtRecord | tuple[int, int, int]) -> bytes:
    """Encode one record to its 8 wire bytes. Raises EncodingRangeError for any out-of-range field."""
    position, velocity, time_ms = record
    p = _check_int("position", position, POSITION_MIN, POSITION_MAX)
    v = _check_int("velocity", velocity, VELOCITY_MIN, VELOCITY_MAX)
    t = _check_int("time_ms", time_ms, TIME_MIN_MS, TIME_MAX_MS)
    return p.to_bytes(4, "little", signed=True) + v.to_bytes(3, "little", signed=True) + bytes((t,))


def unpack(data: bytes | bytearray | memoryview) -> PvtRecord:
    """Decode 8 wire bytes. Raises EncodingRangeError when the length is not exactly 8."""
    raw = bytes(data)
    if len(raw) != RECORD_SIZE:
        raise EncodingRangeError(
            f"PVT record must be {RECORD_SIZE} bytes, got {len(raw)}",
            path="record",
            detail={"length": len(raw)},
        )
    return PvtRecord(
        int.from_bytes(raw[0:4], "little", signed=True),
        int.from_bytes(raw[4:7], "little", signed=True),
        raw[7],
    )
