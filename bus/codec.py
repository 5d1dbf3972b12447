"""Pure CANopen codecs: what the bits on the wire mean, and nothing else (no I/O, no clock).

The buffer status word 0x20C4:01 (seed 000 table 4-35); the CiA 402 state machine (`Command`,
`Cia402State`, `TRANSITIONS`: `next_state` raises `InvalidTransition` for a trigger without an entry);
EMCY, NMT, SYNC and heartbeat frames; the TPDO payloads of bus.cob's layout; the worst-case bit length of
a classic frame (`frame_bits`). The PVT record is `planner.encoding.record`. Every decoder returns a value
or raises `ProtocolError`; nothing wraps silently.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from enum import Enum, IntEnum
from types import MappingProxyType
from typing import NamedTuple

from bus import cob
from bus.errors import ProtocolError

# --------------------------------------------------------------------------------------------------
# frames


class Frame(NamedTuple):
    """One CAN frame: 11-bit COB-ID and 0..8 data bytes."""

    cob_id: int
    data: bytes


def frame_bits(dlc: int) -> int:
    """Bits on the wire of a classic CAN data frame with an 11-bit identifier, worst-case stuffing.

    Fields subject to stuffing: SOF 1 + ID 11 + RTR 1 + IDE 1 + r0 1 + DLC 4 + data 8*dlc + CRC 15
    = 34 + 8*dlc bits, at most one stuff bit per 4 bits after the first: floor((34 + 8*dlc - 1) / 4).
    Fixed-form tail: CRC delimiter 1 + ACK 2 + EOF 7 + intermission 3 = 13 bits.
    Total = 47 + 8*dlc + floor((33 + 8*dlc) / 4): 55 bits for DLC 0, 135 bits for DLC 8.
    """
    if isinstance(dlc, bool) or not isinstance(dlc, int) or not 0 <= dlc <= 8:
        raise ValueError(f"DLC must be an integer 0..8, got {dlc!r}")
    return 47 + 8 * dlc + (33 + 8 * dlc) // 4


def bus_load(frames: Mapping[int, float], bitrate: int) -> float:
    """Fraction of the bus used by `frames` = {dlc: frames per second} at `bitrate` bit/s."""
    if bitrate <= 0:
        raise ValueError(f"bitrate must be > 0, got {bitrate}")
    return sum(frame_bits(dlc) * rate for dlc, rate in frames.items()) / bitrate


# --------------------------------------------------------------------------------------------------
# interpolation buffer status 0x20C4:01 (seed 000 table 4-34 / 4-35)

BS_UNDERFLOW_WARNING = 1 << 0
BS_OVERFLOW_WARNING = 1 << 1
BS_VELOCITY_WARNING = 1 << 2
BS_ACCELERATION_WARNING = 1 << 3
BS_UNDERFLOW_ERROR = 1 << 8
BS_OVERFLOW_ERROR = 1 << 9
BS_VELOCITY_ERROR = 1 << 10
BS_ACCELERATION_ERROR = 1 << 11
BS_BUFFER_ENABLED = 1 << 14
BS_IP_ACTIVE = 1 << 15
BS_WARNINGS = 0x000F
BS_ERRORS = 0x0F00
BS_RESERVED = 0x30F0


@dataclass(frozen=True)
class BufferStatusWord:
    """Decoded 0x20C4:01. Warnings are bits 0-3, errors bits 8-11 (trajectory abort)."""

    underflow_warning: bool = False
    overflow_warning: bool = False
    velocity_warning: bool = False
    acceleration_warning: bool = False
    underflow_error: bool = False
    overflow_error: bool = False
    velocity_error: bool = False
    acceleration_error: bool = False
    buffer_enabled: bool = False
    ip_active: bool = False

    @property
    def any_warning(self) -> bool:
        return (self.underflow_warning or self.overflow_warning or self.velocity_warning
                or self.acceleration_warning)

    @property
    def any_error(self) -> bool:
        return self.underflow_error or self.overflow_error or self.velocity_error or self.acceleration_error

    def encode(self) -> int:
        return encode_buffer_status(self)


_BS_FIELDS = (
    ("underflow_warning", BS_UNDERFLOW_WARNING),
    ("overflow_warning", BS_OVERFLOW_WARNING),
    ("velocity_warning", BS_VELOCITY_WARNING),
    ("acceleration_warning", BS_ACCELERATION_WARNING),
    ("underflow_error", BS_UNDERFLOW_ERROR),
    ("overflow_error", BS_OVERFLOW_ERROR),
    ("velocity_error", BS_VELOCITY_ERROR),
    ("acceleration_error", BS_ACCELERATION_ERROR),
    ("buffer_enabled", BS_BUFFER_ENABLED),
    ("ip_active", BS_IP_ACTIVE),
)


def decode_buffer_status(word: int) -> BufferStatusWord:
    """Decode 0x20C4:01. Raises ProtocolError for a value outside u16 or with reserved bits set."""
    if isinstance(word, bool) or not isinstance(word, int) or not 0 <= word <= 0xFFFF:
        raise ProtocolError(f"buffer status must be a u16, got {word!r}")
    if word & BS_RESERVED:
        raise ProtocolError(f"buffer status 0x{word:04X} has reserved bits 0x{word & BS_RESERVED:04X} set")
    return BufferStatusWord(**{name: bool(word & bit) for name, bit in _BS_FIELDS})


def encode_buffer_status(status: BufferStatusWord) -> int:
    return sum(bit for name, bit in _BS_FIELDS if getattr(status, name))


# --------------------------------------------------------------------------------------------------
# CiA 402 power state machine

CW_SWITCH_ON = 1 << 0
CW_ENABLE_VOLTAGE = 1 << 1
CW_QUICK_STOP = 1 << 2  # active low: 0 = quick stop
CW_ENABLE_OPERATION = 1 << 3
CW_ENABLE_IP = 1 << 4  # mode specific (ip): enable ip mode
CW_FAULT_RESET = 1 << 7
CW_HALT = 1 << 8

SW_READY_TO_SWITCH_ON = 1 << 0
SW_SWITCHED_ON = 1 << 1
SW_OPERATION_ENABLED = 1 << 2
SW_FAULT = 1 << 3
SW_VOLTAGE_ENABLED = 1 << 4
SW_QUICK_STOP = 1 << 5  # active low: 0 = quick stop active
SW_SWITCH_ON_DISABLED = 1 << 6
SW_WARNING = 1 << 7
SW_REMOTE = 1 << 9
SW_TARGET_REACHED = 1 << 10
SW_IP_ACTIVE = 1 << 12  # mode specific (ip): ip mode active


class Cia402State(Enum):
    NOT_READY_TO_SWITCH_ON = "not ready to switch on"
    SWITCH_ON_DISABLED = "switch on disabled"
    READY_TO_SWITCH_ON = "ready to switch on"
    SWITCHED_ON = "switched on"
    OPERATION_ENABLED = "operation enabled"
    QUICK_STOP_ACTIVE = "quick stop active"
    FAULT_REACTION_ACTIVE = "fault reaction active"
    FAULT = "fault"

    @property
    def statusword_bits(self) -> int:
        """The state's canonical statusword bits (0-3, 5, 6)."""
        return _STATE_BITS[self]

    @property
    def power_enabled(self) -> bool:
        """The motor is under closed-loop control in this state."""
        return self in (Cia402State.OPERATION_ENABLED, Cia402State.QUICK_STOP_ACTIVE,
                        Cia402State.FAULT_REACTION_ACTIVE)


_STATE_BITS: dict[Cia402State, int] = {
    Cia402State.NOT_READY_TO_SWITCH_ON: 0x0000,
    Cia402State.SWITCH_ON_DISABLED: 0x0040,
    Cia402State.READY_TO_SWITCH_ON: 0x0021,
    Cia402State.SWITCHED_ON: 0x0023,
    Cia402State.OPERATION_ENABLED: 0x0027,
    Cia402State.QUICK_STOP_ACTIVE: 0x0007,
    Cia402State.FAULT_REACTION_ACTIVE: 0x000F,
    Cia402State.FAULT: 0x0008,
}

# (mask, value, state) in CiA 402 table order
_SW_PATTERNS: tuple[tuple[int, int, Cia402State], ...] = (
    (0x4F, 0x00, Cia402State.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, Cia402State.SWITCH_ON_DISABLED),
    (0x6F, 0x21, Cia402State.READY_TO_SWITCH_ON),
    (0x6F, 0x23, Cia402State.SWITCHED_ON),
    (0x6F, 0x27, Cia402State.OPERATION_ENABLED),
    (0x6F, 0x07, Cia402State.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, Cia402State.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, Cia402State.FAULT),
)


def state_from_statusword(statusword: int) -> Cia402State:
    """The CiA 402 state a statusword reports. Raises ProtocolError for a pattern of no state."""
    if isinstance(statusword, bool) or not isinstance(statusword, int) or not 0 <= statusword <= 0xFFFF:
        raise ProtocolError(f"statusword must be a u16, got {statusword!r}")
    for mask, value, state in _SW_PATTERNS:
        if statusword & mask == value:
            return state
    raise ProtocolError(f"statusword 0x{statusword:04X} encodes no CiA 402 state")


class Command(Enum):
    """Controlword device-control commands (bits 0-3 and 7). The value is the canonical controlword."""

    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007  # from ready to switch on; the same bits mean "disable operation" in OE
    ENABLE_OPERATION = 0x000F  # "switch on + enable operation" from ready to switch on
    DISABLE_VOLTAGE = 0x0000
    QUICK_STOP = 0x0002
    FAULT_RESET = 0x0080  # acts on the rising edge of bit 7

    @classmethod
    def disable_operation(cls) -> Command:
        return cls.SWITCH_ON


class Internal(Enum):
    """Transitions the drive makes by itself (CiA 402 transitions 1, 13, 14 and the end of quick stop)."""

    INIT_DONE = "init done"
    FAULT_DETECTED = "fault detected"
    FAULT_REACTION_DONE = "fault reaction done"
    QUICK_STOP_DONE = "quick stop done"


Trigger = Command | Internal


class InvalidTransition(ValueError):
    """A trigger that has no entry in the transition table for the current state."""

    def __init__(self, state: Cia402State, trigger: Trigger):
        super().__init__(f"no CiA 402 transition from {state.value!r} on {trigger.name}")
        self.state = state
        self.trigger = trigger


S = Cia402State
_TABLE: dict[tuple[Cia402State, Trigger], Cia402State] = {
    (S.NOT_READY_TO_SWITCH_ON, Internal.INIT_DONE): S.SWITCH_ON_DISABLED,  # 1
    (S.SWITCH_ON_DISABLED, Command.SHUTDOWN): S.READY_TO_SWITCH_ON,  # 2
    (S.SWITCH_ON_DISABLED, Command.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,
    (S.SWITCH_ON_DISABLED, Command.QUICK_STOP): S.SWITCH_ON_DISABLED,
    (S.READY_TO_SWITCH_ON, Command.SHUTDOWN): S.READY_TO_SWITCH_ON,
    (S.READY_TO_SWITCH_ON, Command.SWITCH_ON): S.SWITCHED_ON,  # 3
    (S.READY_TO_SWITCH_ON, Command.ENABLE_OPERATION): S.OPERATION_ENABLED,  # 3 + 4
    (S.READY_TO_SWITCH_ON, Command.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 7
    (S.READY_TO_SWITCH_ON, Command.QUICK_STOP): S.SWITCH_ON_DISABLED,  # 7
    (S.SWITCHED_ON, Command.SWITCH_ON): S.SWITCHED_ON,
    (S.SWITCHED_ON, Command.ENABLE_OPERATION): S.OPERATION_ENABLED,  # 4
    (S.SWITCHED_ON, Command.SHUTDOWN): S.READY_TO_SWITCH_ON,  # 6
    (S.SWITCHED_ON, Command.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 10
    (S.SWITCHED_ON, Command.QUICK_STOP): S.SWITCH_ON_DISABLED,  # 10
    (S.OPERATION_ENABLED, Command.ENABLE_OPERATION): S.OPERATION_ENABLED,
    (S.OPERATION_ENABLED, Command.SWITCH_ON): S.SWITCHED_ON,  # 5 (disable operation)
    (S.OPERATION_ENABLED, Command.SHUTDOWN): S.READY_TO_SWITCH_ON,  # 8
    (S.OPERATION_ENABLED, Command.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 9
    (S.OPERATION_ENABLED, Command.QUICK_STOP): S.QUICK_STOP_ACTIVE,  # 11
    (S.QUICK_STOP_ACTIVE, Command.QUICK_STOP): S.QUICK_STOP_ACTIVE,
    (S.QUICK_STOP_ACTIVE, Command.DISABLE_VOLTAGE): S.SWITCH_ON_DISABLED,  # 12
    (S.QUICK_STOP_ACTIVE, Internal.QUICK_STOP_DONE): S.SWITCH_ON_DISABLED,  # 12 (option codes 1, 2)
    (S.QUICK_STOP_ACTIVE, Command.ENABLE_OPERATION): S.OPERATION_ENABLED,  # 16 (option codes 5, 6)
    (S.FAULT_REACTION_ACTIVE, Internal.FAULT_REACTION_DONE): S.FAULT,  # 14
    (S.FAULT, Command.FAULT_RESET): S.SWITCH_ON_DISABLED,  # 15
}
del S
# 13: any state except the two fault states -> fault reaction active
for _s in Cia402State:
    if _s not in (Cia402State.FAULT_REACTION_ACTIVE, Cia402State.FAULT):
        _TABLE[(_s, Internal.FAULT_DETECTED)] = Cia402State.FAULT_REACTION_ACTIVE
TRANSITIONS: Mapping[tuple[Cia402State, Trigger], Cia402State] = MappingProxyType(_TABLE)


def next_state(state: Cia402State, trigger: Trigger) -> Cia402State:
    """The state after `trigger`. Raises InvalidTransition when the table has no entry."""
    try:
        return TRANSITIONS[(state, trigger)]
    except KeyError:
        raise InvalidTransition(state, trigger) from None


def decode_command(controlword: int) -> Command:
    """The device-control command in a controlword (bit 7 set reads as FAULT_RESET; the drive acts on
    its rising edge). Every u16 decodes to exactly one command."""
    if isinstance(controlword, bool) or not isinstance(controlword, int) or not 0 <= controlword <= 0xFFFF:
        raise ProtocolError(f"controlword must be a u16, got {controlword!r}")
    if controlword & CW_FAULT_RESET:
        return Command.FAULT_RESET
    if not controlword & CW_ENABLE_VOLTAGE:
        return Command.DISABLE_VOLTAGE
    if not controlword & CW_QUICK_STOP:
        return Command.QUICK_STOP
    if not controlword & CW_SWITCH_ON:
        return Command.SHUTDOWN
    if controlword & CW_ENABLE_OPERATION:
        return Command.ENABLE_OPERATION
    return Command.SWITCH_ON


def controlword(command: Command, *, enable_ip: bool = False, halt: bool = False) -> int:
    """The controlword for `command`, with the ip-mode bits (seed 000 table 4-29/4-30)."""
    cw = command.value
    if enable_ip:
        cw |= CW_ENABLE_IP
    if halt:
        cw |= CW_HALT
    return cw


# --------------------------------------------------------------------------------------------------
# EMCY (CiA 301 7.2.7): code u16 | error register u8 | 5 manufacturer bytes

EMCY_ERROR_RESET = 0x0000
EMCY_FOLLOWING_ERROR = 0x8611  # seed 003 (Infranor 35 -> DS-402 0x8611)
# seed 003 (Infranor 50, IP reference underflow/overflow); bit 8/9 of 0x20C4:01 tell which
EMCY_IP_BUFFER = 0x8782
EMCY_SYNC_LOST = 0x8780  # seed 003 (Infranor 49, SYNC cycle)
EMCY_HEARTBEAT = 0x8130  # CiA 301 life guard / heartbeat error; seed 003 (Infranor 51)
EMCY_PDO_LENGTH = 0x8210  # CiA 301: PDO not processed due to length error (too short)
EMCY_PDO_LENGTH_EXCEEDED = 0x8220  # CiA 301: PDO length exceeded (too long)
EMCY_IP_VELOCITY = 0xFF10  # device specific: ip velocity above 0x607F (velocity error, bit 10)
EMCY_IP_ACCELERATION = 0xFF11  # device specific: ip acceleration above 0x60C5 (acceleration error, bit 11)

EMCY_NAMES: Mapping[int, str] = {
    EMCY_ERROR_RESET: "error reset / no error",
    EMCY_FOLLOWING_ERROR: "following error",
    EMCY_IP_BUFFER: "ip buffer underflow/overflow",
    EMCY_SYNC_LOST: "SYNC lost / SYNC cycle error",
    EMCY_HEARTBEAT: "heartbeat / life guarding error",
    EMCY_PDO_LENGTH: "PDO not processed: too short",
    EMCY_PDO_LENGTH_EXCEEDED: "PDO length exceeded: too long",
    EMCY_IP_VELOCITY: "ip velocity error (0x607F)",
    EMCY_IP_ACCELERATION: "ip acceleration error (0x60C5)",
}

# error register 0x1001 bits
ER_GENERIC = 1 << 0
ER_CURRENT = 1 << 1
ER_VOLTAGE = 1 << 2
ER_TEMPERATURE = 1 << 3
ER_COMMUNICATION = 1 << 4
ER_DEVICE_PROFILE = 1 << 5
ER_MANUFACTURER = 1 << 7

EMCY_SIZE = 8


class EmcyMessage(NamedTuple):
    code: int
    register: int
    manufacturer: bytes  # 5 bytes; bytes 0-1 = 0x20C4:01 buffer status (agreed layout)

    @property
    def buffer_status(self) -> int:
        """0x20C4:01 at the time of the EMCY (frame bytes 3-4, little-endian)."""
        return int.from_bytes(self.manufacturer[0:2], "little")

    @property
    def is_error_reset(self) -> bool:
        """CiA 301: code 0x00xx = error reset / no error (the drive left the error state)."""
        return self.code & 0xFF00 == 0

    @property
    def name(self) -> str:
        return EMCY_NAMES.get(self.code, f"EMCY 0x{self.code:04X}")


def emcy_manufacturer_bytes(buffer_status: int) -> bytes:
    return (buffer_status & 0xFFFF).to_bytes(2, "little") + b"\x00\x00\x00"


def encode_emcy(code: int, register: int, manufacturer: bytes = b"") -> bytes:
    """8-byte EMCY payload. Raises ValueError for a field that does not fit."""
    if not 0 <= code <= 0xFFFF:
        raise ValueError(f"EMCY code {code} does not fit u16")
    if not 0 <= register <= 0xFF:
        raise ValueError(f"error register {register} does not fit u8")
    if len(manufacturer) > 5:
        raise ValueError(f"EMCY manufacturer field is 5 bytes, got {len(manufacturer)}")
    return code.to_bytes(2, "little") + bytes((register,)) + bytes(manufacturer).ljust(5, b"\x00")


def decode_emcy(data: bytes | bytearray | memoryview) -> EmcyMessage:
    raw = bytes(data)
    if len(raw) != EMCY_SIZE:
        raise ProtocolError(f"EMCY needs {EMCY_SIZE} bytes, got {len(raw)}")
    return EmcyMessage(int.from_bytes(raw[0:2], "little"), raw[2], raw[3:8])


# --------------------------------------------------------------------------------------------------
# NMT, SYNC, heartbeat


class NmtCommand(IntEnum):
    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(IntEnum):
    """The state byte of a heartbeat (0 = boot-up message)."""

    BOOTUP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


def nmt_frame(command: NmtCommand, node: int = 0) -> Frame:
    """NMT command to `node` (0 = all nodes)."""
    if not 0 <= node <= 127:
        raise ValueError(f"NMT node id must be 0..127, got {node}")
    return Frame(cob.NMT_COB_ID, bytes((int(command), node)))


def decode_nmt(data: bytes | bytearray | memoryview) -> tuple[NmtCommand, int]:
    raw = bytes(data)
    if len(raw) != 2:
        raise ProtocolError(f"NMT command needs 2 bytes, got {len(raw)}")
    try:
        command = NmtCommand(raw[0])
    except ValueError:
        raise ProtocolError(f"unknown NMT command specifier 0x{raw[0]:02X}") from None
    if raw[1] > 127:
        raise ProtocolError(f"NMT node id {raw[1]} is not 0..127")
    return command, raw[1]


def sync_frame(counter: int | None = None) -> Frame:
    if counter is None:
        return Frame(cob.SYNC_COB_ID, b"")
    if not 1 <= counter <= 240:
        raise ValueError(f"SYNC counter must be 1..240, got {counter}")
    return Frame(cob.SYNC_COB_ID, bytes((counter,)))


def decode_sync(data: bytes | bytearray | memoryview) -> int | None:
    """The SYNC counter, or None for a SYNC without counter. Raises ProtocolError for DLC > 1."""
    raw = bytes(data)
    if len(raw) == 0:
        return None
    if len(raw) == 1:
        return raw[0]
    raise ProtocolError(f"SYNC has DLC 0 or 1, got {len(raw)}")


def heartbeat_frame(node: int, state: NmtState) -> Frame:
    if not 1 <= node <= 127:
        raise ValueError(f"node id must be 1..127, got {node}")
    return Frame(cob.heartbeat_id(node), bytes((int(state),)))


def decode_heartbeat(data: bytes | bytearray | memoryview) -> NmtState:
    """The NMT state in a heartbeat (toggle bit 7 ignored). Raises ProtocolError otherwise."""
    raw = bytes(data)
    if len(raw) != 1:
        raise ProtocolError(f"heartbeat needs 1 byte, got {len(raw)}")
    try:
        return NmtState(raw[0] & 0x7F)
    except ValueError:
        raise ProtocolError(f"unknown NMT state 0x{raw[0] & 0x7F:02X} in heartbeat") from None


# --------------------------------------------------------------------------------------------------
# TPDO payloads of the product layout (bus/cob.py)


class Tpdo1(NamedTuple):
    statusword: int
    free_size: int

    @property
    def buffer_status(self) -> int:
        """0x20C4:01 as far as TPDO1 tells: ip mode active (statusword bit 12) in bit 15; the buffer
        status itself is not in the PDO (bus/cob.py)."""
        return BS_IP_ACTIVE if self.statusword & SW_IP_ACTIVE else 0


class Tpdo2(NamedTuple):
    position_actual: int
    position_demand: int


def decode_tpdo1(data: bytes | bytearray | memoryview) -> Tpdo1:
    try:
        return Tpdo1(*cob.unpack_tpdo1(bytes(data)))
    except ValueError as e:
        raise ProtocolError(str(e)) from None


def decode_statusword(data: bytes | bytearray | memoryview) -> int:
    """TPDO1 of a cyclic family: the statusword alone (2 bytes)."""
    if len(data) != 2:
        raise ProtocolError(f"TPDO1 (statusword) needs 2 bytes, got {len(data)}")
    return int.from_bytes(bytes(data), "little")


def decode_tpdo2(data: bytes | bytearray | memoryview) -> Tpdo2:
    try:
        return Tpdo2(*cob.unpack_tpdo2(bytes(data)))
    except ValueError as e:
        raise ProtocolError(str(e)) from None
