"""The object dictionaries of the simulated drive families: one table per family, three uses.

`EPOS_TABLE` (seed 000 4.3.6), `XTRAPULS_TABLE` (seed 003), `CSP_TABLE`: every object's type, access,
default and range (open values chosen in docs/drive-model.md). Used by `bus.sim.eds` to render
configs/drives/<family>.eds (tested equal to the committed files), by the drive's CiA 301 layer as its
object store with the drive's access and range checks, and by PDO mapping validation. No I/O; `SdoAbort`
carries the CiA 301 abort code.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from types import MappingProxyType
from typing import Literal

# CiA 301 SDO abort codes used by the simulated drive
ABORT_UNSUPPORTED_ACCESS = 0x06010000
ABORT_WRITE_ONLY = 0x06010001
ABORT_READ_ONLY = 0x06010002
ABORT_NO_OBJECT = 0x06020000
ABORT_CANNOT_MAP = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_PARAMETER_INCOMPATIBLE = 0x06040043
ABORT_TYPE_LENGTH = 0x06070010
ABORT_NO_SUBINDEX = 0x06090011
ABORT_INVALID_VALUE = 0x06090030
ABORT_VALUE_TOO_HIGH = 0x06090031
ABORT_VALUE_TOO_LOW = 0x06090032
ABORT_GENERAL = 0x08000000
ABORT_CANNOT_STORE = 0x08000020
ABORT_DEVICE_STATE = 0x08000022


class SdoAbort(Exception):
    """An SDO request the drive refuses, with its CiA 301 abort code."""

    def __init__(self, code: int, message: str):
        super().__init__(f"SDO abort 0x{code:08X}: {message}")
        self.code = code
        self.message = message


class DataType(IntEnum):
    """CiA 301 data types (the EDS DataType codes)."""

    BOOLEAN = 0x0001
    INTEGER8 = 0x0002
    INTEGER16 = 0x0003
    INTEGER32 = 0x0004
    UNSIGNED8 = 0x0005
    UNSIGNED16 = 0x0006
    UNSIGNED32 = 0x0007
    VISIBLE_STRING = 0x0009
    DOMAIN = 0x000F
    UNSIGNED64 = 0x001B

    @property
    def bits(self) -> int:
        return _BITS[self]

    @property
    def signed(self) -> bool:
        return self in (DataType.INTEGER8, DataType.INTEGER16, DataType.INTEGER32)

    @property
    def struct_code(self) -> str:
        return _STRUCT[self]

    def value_range(self) -> tuple[int, int]:
        b = self.bits
        if self.signed:
            return -(1 << (b - 1)), (1 << (b - 1)) - 1
        return 0, (1 << b) - 1


_BITS = {
    DataType.BOOLEAN: 8, DataType.INTEGER8: 8, DataType.INTEGER16: 16, DataType.INTEGER32: 32,
    DataType.UNSIGNED8: 8, DataType.UNSIGNED16: 16, DataType.UNSIGNED32: 32, DataType.VISIBLE_STRING: 0,
    DataType.DOMAIN: 0, DataType.UNSIGNED64: 64,
}
_STRUCT = {
    DataType.BOOLEAN: "B", DataType.INTEGER8: "b", DataType.INTEGER16: "h", DataType.INTEGER32: "i",
    DataType.UNSIGNED8: "B", DataType.UNSIGNED16: "H", DataType.UNSIGNED32: "I", DataType.VISIBLE_STRING: "",
    DataType.DOMAIN: "", DataType.UNSIGNED64: "Q",
}

Access = Literal["ro", "rw", "wo", "const"]
Key = tuple[int, int]


@dataclass(frozen=True)
class ObjectSpec:
    """One object dictionary entry (a VAR, or one sub-index of a RECORD/ARRAY)."""

    index: int
    sub: int
    name: str
    dtype: DataType
    access: Access
    default: int | str | None = None
    low: int | None = None
    high: int | None = None
    pdo: bool = False
    node_relative: bool = False  # default is $NODEID + default (COB-IDs)

    @property
    def key(self) -> Key:
        return (self.index, self.sub)

    @property
    def readable(self) -> bool:
        return self.access != "wo"

    @property
    def writable(self) -> bool:
        return self.access in ("rw", "wo")

    def default_for(self, node_id: int) -> int:
        if not isinstance(self.default, int):
            raise TypeError(f"0x{self.index:04X}:{self.sub:02X} has no integer default")
        return self.default + (node_id if self.node_relative else 0)


@dataclass(frozen=True)
class GroupSpec:
    """A RECORD (0x9) or ARRAY (0x8) object: its name; its entries are ObjectSpecs with sub >= 0."""

    index: int
    name: str
    object_type: Literal[8, 9]


U8, U16, U32, U64 = DataType.UNSIGNED8, DataType.UNSIGNED16, DataType.UNSIGNED32, DataType.UNSIGNED64
I8, I16, I32 = DataType.INTEGER8, DataType.INTEGER16, DataType.INTEGER32
STR = DataType.VISIBLE_STRING
DOMAIN = DataType.DOMAIN

PDO_DISABLED = 1 << 31
PDO_RTR_NOT_ALLOWED = 1 << 30
MAX_PDO_ENTRIES = 8


_Entry = tuple[int, str, DataType, Access, int | None, int | None, int | None, bool, bool]


class _Builder:
    """Collects the objects of one table (`var`, `group`)."""

    def __init__(self) -> None:
        self.objects: list[ObjectSpec] = []
        self.groups: list[GroupSpec] = []

    def var(self, index: int, name: str, dtype: DataType, access: Access, default: int | str | None = None,
            low: int | None = None, high: int | None = None, pdo: bool = False, rel: bool = False) -> None:
        self.objects.append(ObjectSpec(index, 0, name, dtype, access, default, low, high, pdo, rel))

    def group(self, index: int, name: str, kind: Literal[8, 9], entries: list[_Entry]) -> None:
        self.groups.append(GroupSpec(index, name, kind))
        for sub, n, dt, acc, default, low, high, pdo, rel in entries:
            self.objects.append(ObjectSpec(index, sub, n, dt, acc, default, low, high, pdo, rel))


def _cia301(b: _Builder, *, device_name: str, product_code: int, rx_defaults: list[list[int]],
            rx_types: list[int], tx_defaults: list[list[int]], tx_types: list[int], max_entries: int,
            sync_period: tuple[int, int, int], v42: bool = True, empty_pdos_valid: bool = False) -> None:
    """The communication profile every simulated drive has (CiA 301). `v42`: with the objects CiA 301
    v4.2 added (time stamp 0x1012/0x1013, SYNC counter 0x1019, TPDO inhibit time / event timer / SYNC
    start value 0x18xx:03/05/06); without them a DS-301 v4.01 drive (seed 003). `empty_pdos_valid`: a
    PDO without default mapping still has a valid default COB-ID (seed 003: RPDO4 0x500 + node)."""
    var, group = b.var, b.group
    var(0x1000, "Device type", U32, "ro", 0x00020192)  # CiA 402 servo drive
    var(0x1001, "Error register", U8, "ro", 0, pdo=True)
    var(0x1005, "COB-ID SYNC", U32, "rw", 0x00000080)
    default, low, high = sync_period
    var(0x1006, "Communication cycle period", U32, "rw", default, low, high)  # us; 0 = not configured
    var(0x1008, "Manufacturer device name", STR, "const", device_name)
    # store / restore (CiA 301; seed 000 6.12 and seed 003: "save" 0x65766173, "load" 0x64616F6C); reading
    # sub 1 gives bit 0 = the device saves / restores on command
    group(0x1010, "Store parameters", 8, [
        (0, "Highest sub-index supported", U8, "ro", 1, None, None, False, False),
        (1, "Save all parameters", U32, "rw", 1, None, None, False, False),
    ])
    group(0x1011, "Restore default parameters", 8, [
        (0, "Highest sub-index supported", U8, "ro", 1, None, None, False, False),
        (1, "Restore all default parameters", U32, "rw", 1, None, None, False, False),
    ])
    if v42:
        # time stamp (seed 001 3.6.1-3.6.2): bit 31 = consume the TIME frame with this COB-ID; 0x1013 is
        # the master's high-resolution time stamp (us) of the last SYNC it sent
        var(0x1012, "COB-ID time stamp object", U32, "rw", 0x00000100)
        var(0x1013, "High resolution time stamp", U32, "rw", 0, pdo=True)
    var(0x1014, "COB-ID EMCY", U32, "ro", 0x80, rel=True)
    group(0x1016, "Consumer heartbeat time", 8, [
        (0, "Number of entries", U8, "ro", 1, None, None, False, False),
        (1, "Consumer heartbeat time 1", U32, "rw", 0, None, None, False, False),
    ])
    var(0x1017, "Producer heartbeat time", U16, "rw", 0)
    if v42:
        # CiA 301 SYNC counter: 0 = SYNC without counter; 2..240 = SYNC carries a counter 1..value
        var(0x1019, "Synchronous counter overflow value", U8, "rw", 0, 0, 240)
    group(0x1018, "Identity object", 9, [
        (0, "Number of entries", U8, "ro", 4, None, None, False, False),
        (1, "Vendor-ID", U32, "ro", 0x00000000, None, None, False, False),  # a simulation claims no vendor
        (2, "Product code", U32, "ro", product_code, None, None, False, False),
        (3, "Revision number", U32, "ro", 0x00010000, None, None, False, False),
        (4, "Serial number", U32, "ro", 0x00000000, None, None, False, True),
    ])
    # PDO communication and mapping: the family's factory defaults; the master remaps them
    for n in range(4):
        rx_cob = 0x200 + 0x100 * n
        tx_cob = 0x180 + 0x100 * n
        rx_enabled = bool(rx_defaults[n]) or empty_pdos_valid
        tx_enabled = bool(tx_defaults[n]) or empty_pdos_valid
        group(0x1400 + n, f"Receive PDO {n + 1} parameter", 9, [
            (0, "Highest sub-index supported", U8, "ro", 2, None, None, False, False),
            (1, "COB-ID used by RPDO", U32, "rw", rx_cob | (0 if rx_enabled else PDO_DISABLED), None, None,
             False, True),
            (2, "Transmission type", U8, "rw", rx_types[n], None, None, False, False),
        ])
        entries: list[_Entry] = [
            (0, "Number of mapped objects", U8, "rw", len(rx_defaults[n]), 0, max_entries, False, False)]
        for k in range(1, max_entries + 1):
            d = rx_defaults[n][k - 1] if k <= len(rx_defaults[n]) else 0
            entries.append((k, f"Mapped object {k}", U32, "rw", d, None, None, False, False))
        group(0x1600 + n, f"Receive PDO {n + 1} mapping", 9, entries)
        tx_comm: list[_Entry] = [
            (0, "Highest sub-index supported", U8, "ro", 6 if v42 else 2, None, None, False, False),
            (1, "COB-ID used by TPDO", U32, "rw", tx_cob | (0 if tx_enabled else PDO_DISABLED), None, None,
             False, True),
            (2, "Transmission type", U8, "rw", tx_types[n], None, None, False, False),
        ]
        if v42:
            tx_comm += [
                (3, "Inhibit time", U16, "rw", 0, None, None, False, False),  # 100 us units (event TPDOs)
                (5, "Event timer", U16, "rw", 0, None, None, False, False),  # ms (event TPDOs)
                (6, "SYNC start value", U8, "rw", 0, None, None, False, False),  # with a SYNC counter
            ]
        group(0x1800 + n, f"Transmit PDO {n + 1} parameter", 9, tx_comm)
        entries = [(0, "Number of mapped objects", U8, "rw", len(tx_defaults[n]), 0, max_entries, False, False)]
        for k in range(1, max_entries + 1):
            d = tx_defaults[n][k - 1] if k <= len(tx_defaults[n]) else 0
            entries.append((k, f"Mapped object {k}", U32, "rw", d, None, None, False, False))
        group(0x1A00 + n, f"Transmit PDO {n + 1} mapping", 9, entries)


def _cia402(b: _Builder, *, quick_stop: tuple[int, int, int], quick_stop_decel: int, max_velocity: int = 25000,
            profile_velocity: int = 1000, acceleration: int = 10000) -> None:
    """The CiA 402 objects of the EPOS and CSP families (seed 000 4.3.3-4.3.6); velocities and
    accelerations in the family's units (EPOS: rpm, rpm/s; CSP: counts/s, counts/s^2)."""
    var, group = b.var, b.group
    var(0x603F, "Error code", U16, "ro", 0, pdo=True)
    var(0x6040, "Controlword", U16, "rw", 0, pdo=True)
    var(0x6041, "Statusword", U16, "ro", 0, pdo=True)
    qs_default, qs_low, qs_high = quick_stop
    var(0x605A, "Quick stop option code", I16, "rw", qs_default, qs_low, qs_high)
    var(0x6060, "Modes of operation", I8, "rw", 0, pdo=True)
    var(0x6061, "Modes of operation display", I8, "ro", 0, pdo=True)
    var(0x6062, "Position demand value", I32, "ro", 0, pdo=True)
    var(0x6064, "Position actual value", I32, "ro", 0, pdo=True)
    var(0x6065, "Following error window", U32, "rw", 2000, pdo=True)
    var(0x6067, "Position window", U32, "rw", 100)
    var(0x606C, "Velocity actual value", I32, "ro", 0, pdo=True)
    var(0x6078, "Current actual value", I16, "ro", 0, pdo=True)
    group(0x607D, "Software position limit", 8, [
        (0, "Number of entries", U8, "ro", 2, None, None, False, False),
        (1, "Min position limit", I32, "rw", -(2**31), None, None, False, False),
        (2, "Max position limit", I32, "rw", 2**31 - 1, None, None, False, False),
    ])
    var(0x607F, "Max profile velocity", U32, "rw", max_velocity, pdo=True)
    var(0x6081, "Profile velocity", U32, "rw", profile_velocity, pdo=True)
    var(0x6083, "Profile acceleration", U32, "rw", acceleration, pdo=True)
    var(0x6084, "Profile deceleration", U32, "rw", acceleration, pdo=True)
    var(0x6085, "Quick stop deceleration", U32, "rw", quick_stop_decel, pdo=True)
    var(0x60C5, "Max acceleration", U32, "rw", 0xFFFFFFFF, pdo=True)
    var(0x60F4, "Following error actual value", I32, "ro", 0, pdo=True)


def _homing(b: _Builder, *, method: int, speeds: tuple[int, int], acceleration: int) -> None:
    """Homing mode's objects (CiA 402 / seed 003 "Homing Mode"): home offset 0x607C (position unit), method
    0x6098, speeds 0x6099 (switch search, zero search; velocity unit), acceleration 0x609A."""
    var, group = b.var, b.group
    var(0x607C, "Home offset", I32, "rw", 0)
    var(0x6098, "Homing method", I8, "rw", method)
    group(0x6099, "Homing speeds", 8, [
        (0, "Number of entries", U8, "ro", 2, None, None, False, False),
        (1, "Speed during search for switch", U32, "rw", speeds[0], None, None, False, False),
        (2, "Speed during search for zero", U32, "rw", speeds[1], None, None, False, False),
    ])
    var(0x609A, "Homing acceleration", U32, "rw", acceleration)


def _epos() -> _Builder:
    b = _Builder()
    _cia301(b, device_name="EPOS-IPM simulated drive", product_code=0x49504D31,  # "IPM1"
            # EPOS-like factory defaults (all event driven, statusword/controlword first)
            rx_defaults=[[0x60400010], [0x60400010, 0x60600008], [0x60400010], []], rx_types=[255] * 4,
            tx_defaults=[[0x60410010], [0x60410010, 0x60610008], [0x60410010, 0x60640020],
                         [0x60410010, 0x606C0020]], tx_types=[255] * 4,
            max_entries=MAX_PDO_ENTRIES, sync_period=(0, 0, 255_000))
    _cia402(b, quick_stop=(2, 0, 6), quick_stop_decel=10000)
    var, group = b.var, b.group
    # ---- manufacturer specific (seed 000 4.3.6)
    var(0x20C1, "Interpolation data record", U64, "wo", None, pdo=True)
    # data recorder (seed 004 "Object description"; seed 000 8.5.2; bus/sim/data_recorder.py): EPOS only (the
    # XtrapulsPac has its boot-up object at 0x2010)
    var(0x2010, "Data recorder control", U16, "rw", 0, 0, 3)
    var(0x2011, "Data recorder configuration", U16, "rw", 0, 0, 15)
    var(0x2012, "Data recorder sampling period", U16, "rw", 10)
    var(0x2013, "Data recorder number of preceding samples", U16, "rw", 0)
    var(0x2014, "Data recorder number of sampling variables", U16, "rw", 0, 0, 4)
    for index, what in ((0x2015, "index"), (0x2016, "sub index")):
        group(index, f"Data recorder {what} of variables", 8, [
            (0, "Number of entries", U8, "ro", 4, None, None, False, False),
            *((k, f"Data recorder {what} of variable {k}", U16, "rw", 0, None, None, False, False)
              for k in range(1, 5)),
        ])
    var(0x2017, "Data recorder status", U16, "ro", 0)
    var(0x2018, "Data recorder max number of samples", U16, "ro", 0)
    var(0x2019, "Data recorder offset of the recorded vector", U16, "ro", 0)
    var(0x201B, "Data recorder data buffer", DOMAIN, "ro")
    group(0x20C4, "Interpolation status", 9, [
        (0, "Number of entries", U8, "ro", 3, None, None, False, False),
        (1, "Interpolation buffer status", U16, "ro", 0, None, None, True, False),
        (2, "Interpolation buffer underflow warning", U16, "rw", 4, 0, 63, False, False),
        (3, "Interpolation buffer overflow warning", U16, "rw", 60, 1, 64, False, False),
    ])
    var(0x60C0, "Interpolation sub mode select", I16, "rw", -1, -1, -1)
    group(0x60C2, "Interpolation time period", 9, [
        (0, "Number of entries", U8, "ro", 2, None, None, False, False),
        (1, "Interpolation time period value", U8, "rw", 1, 1, 1, False, False),
        (2, "Interpolation time index", I8, "rw", -3, -3, -3, False, False),
    ])
    group(0x60C4, "Interpolation data configuration", 9, [
        (0, "Number of entries", U8, "ro", 6, None, None, False, False),
        (1, "Maximum buffer size", U32, "ro", 64, None, None, False, False),
        (2, "Actual buffer size", U32, "ro", 0, None, None, True, False),
        (3, "Buffer organization", U8, "rw", 0, 0, 0, False, False),
        (4, "Buffer position", U16, "rw", 0, 0, 64, False, False),
        (5, "Size of data record", U8, "wo", 8, 8, 8, False, False),
        (6, "Buffer clear", U8, "wo", 0, 0, 1, False, False),
    ])
    # homing (seed 000 6.3 states no defaults: CiA 402's method 0 "no homing", speeds in rpm, rpm/s)
    _homing(b, method=0, speeds=(100, 10), acceleration=1000)
    var(0x6502, "Supported drive modes", U32, "ro", 0x00000060)  # bits 5, 6: homing, interpolated position
    return b


def _xtrapuls() -> _Builder:
    """Infranor XtrapulsPac in interpolated position mode (seed 003, CANopen "-ak"; digest in
    ../shared/reference/). Only the objects the simulated drive models; positions in user units (0x6093),
    velocities in user units/s, accelerations in user units/s^2, 0x6080 in rpm (seed 003 3.2.2.7)."""
    b = _Builder()
    _cia301(b, device_name="XtrapulsPac IP simulated drive", product_code=0x58495031,  # "XIP1"
            # seed 003 3.1.1.5 PDO defaults: RPDO1 controlword (255), RPDO2 0x60FF (255), RPDO3 IP data
            # (type 1), RPDO4 nothing (type 0, COB-ID 0x500 + node); TPDO1 statusword and TPDO2 velocity RTR
            # only (253), TPDO3 position actual (type 1), TPDO4 nothing (type 0); up to 4 entries per PDO;
            # DS-301 v4.01: no time stamp, no SYNC counter, PDO parameters of 2 sub-indices
            rx_defaults=[[0x60400010], [0x60FF0020], [0x60C10120], []], rx_types=[255, 255, 1, 0],
            tx_defaults=[[0x60410010], [0x606C0020], [0x60640020], []], tx_types=[253, 253, 1, 0],
            max_entries=4, sync_period=(10_000, 0, 150_000), v42=False, empty_pdos_valid=True)
    var, group = b.var, b.group
    # dummy objects for multiplexed RPDOs: PDO-only (CiA 301 9.5.3; seed 003 "Multiplexed data")
    for index, name, dt in ((0x0002, "Dummy INTEGER8", I8), (0x0003, "Dummy INTEGER16", I16),
                            (0x0004, "Dummy INTEGER32", I32), (0x0005, "Dummy UNSIGNED8", U8),
                            (0x0006, "Dummy UNSIGNED16", U16), (0x0007, "Dummy UNSIGNED32", U32)):
        var(index, name, dt, "wo", None, pdo=True)
    # ---- manufacturer specific (seed 003 3.1)
    group(0x2006, "Sync control", 9, [  # the PLL; the header says "4 elements", the list has 5
        (0, "Number of entries", U8, "ro", 5, None, None, False, False),
        (1, "Sync phase", I16, "rw", 0, None, None, False, False),  # us
        (2, "Adjustment threshold", U16, "rw", 20, None, None, False, False),  # us
        (3, "Adjustment value", U16, "rw", 2, None, None, False, False),  # us
        (4, "Sync error limit", U16, "rw", 500, None, None, False, False),  # us: the PLL locks within it
        (5, "Sync filter", U16, "rw", 0, 0, 4, False, False),  # "0 disabled, 1.4" (stored only)
    ])
    var(0x2010, "CANopen boot-up configuration", U16, "rw", 0, 0, 1)  # 0: no boot-up message, 1: sent
    var(0x205F, "EMCY message behaviour", U16, "rw", 1, 0, 2)  # 0 none, 1 on error, 2 on error and reset
    var(0x30C1, "Interpolated data output", I32, "ro", 0, pdo=True)  # the interpolator's output
    group(0x3300, "Slow down ramp", 8, [  # quick stop options 1 and 5 (user units/s^2; no default printed)
        (0, "Number of entries", U8, "ro", 2, None, None, False, False),
        (1, "Slow down ramp 1", U32, "rw", 0x00200000, None, None, False, False),
        (2, "Slow down ramp 2", U32, "rw", 0x00200000, None, None, False, False),  # "reserved"
    ])
    group(0x3301, "Stop current limit", 8, [  # quick stop options 3 and 7 (per mille of rated current)
        (0, "Number of entries", U8, "ro", 2, None, None, False, False),
        (1, "Stop current limit 1", U16, "rw", 1000, 100, 6000, False, False),
        (2, "Stop current limit 2", U16, "rw", 1000, 100, 6000, False, False),  # "reserved"
    ])
    var(0x3350, "Absolute 16-bit position reference", U8, "rw", 0, 0, 1)
    # ---- device profile (seed 003 3.2)
    var(0x603F, "Error code", U16, "ro", 0, pdo=True)
    var(0x6040, "Controlword", U16, "rw", 0, pdo=True)
    var(0x6041, "Statusword", U16, "ro", 0, pdo=True)
    var(0x605A, "Quick stop option code", I16, "rw", 1, 0, 7)  # 4 is refused (no such option)
    var(0x6060, "Modes of operation", I8, "rw", 0, pdo=True)
    var(0x6061, "Modes of operation display", I8, "ro", 0, pdo=True)
    var(0x6062, "Position demand value", I32, "ro", 0, pdo=True)
    var(0x6064, "Position actual value", I32, "ro", 0, pdo=True)
    var(0x6065, "Following error window", U32, "rw", 2000, pdo=True)  # no default printed: a choice
    var(0x6067, "Position window", U32, "rw", 0)
    var(0x606C, "Velocity actual value", I32, "ro", 0, pdo=True)  # user units/s
    group(0x607D, "Software position limit", 8, [  # stored; enforced only with 0x3360 = 1 (not modelled)
        (0, "Number of entries", U8, "ro", 2, None, None, False, False),
        (1, "Min position limit", I32, "rw", -(2**31), None, None, False, False),
        (2, "Max position limit", I32, "rw", 2**31 - 1, None, None, False, False),
    ])
    var(0x607F, "Max profile velocity", U32, "rw", 0, pdo=True)  # limits PP/PV only
    var(0x6080, "Max motor speed", U32, "rw", 3000, 100, 60000)  # rpm
    var(0x6081, "Profile velocity", U32, "rw", 0x1000)
    var(0x6083, "Profile acceleration", U32, "rw", 0x10000)
    var(0x6084, "Profile deceleration", U32, "rw", 0x10000)
    var(0x6085, "Quick stop ramp", U32, "rw", 0x00200000)  # quick stop options 2 and 6
    group(0x6093, "Position factor", 8, [  # motor position = numerator / denominator * user position
        (0, "Number of entries", U8, "ro", 2, None, None, False, False),
        (1, "Numerator", U32, "rw", 4096, 4096, 4096, False, False),  # "must be set at 4096" increments/rev
        (2, "Denominator", U32, "rw", 4096, 1, None, False, False),  # user units per motor revolution
    ])
    var(0x60C0, "Interpolation sub mode select", I16, "rw", 0, -2, 0)  # 0 linear, -1 PV, -2 P3
    group(0x60C1, "Interpolation data record", 9, [
        (0, "Number of entries", U8, "ro", 2, None, None, False, False),
        (1, "Position", I32, "rw", 0, None, None, True, False),  # user units
        (2, "Velocity", I32, "rw", 0, None, None, True, False),  # user units/s, sub-mode PV only
    ])
    var(0x60F4, "Following error actual value", I32, "ro", 0, pdo=True)
    var(0x60FF, "Target velocity", I32, "rw", 0, pdo=True)  # profile velocity mode (not modelled)
    # seed 003 "Homing Mode" defaults: method 0x23 (35), speeds 0x19 / 0x0A, acceleration 0x00010000
    _homing(b, method=35, speeds=(0x19, 0x0A), acceleration=0x00010000)
    var(0x6502, "Supported drive modes", U32, "ro", 0x00000060)  # the simulation: homing and IP
    return b


def _csp() -> _Builder:
    """A CiA 402 drive in cyclic synchronous position mode (mode 8: 0x607A every SYNC; seed 000 2.6, 6.7)."""
    b = _Builder()
    _cia301(b, device_name="CiA 402 CSP simulated drive", product_code=0x43535031,  # "CSP1"
            rx_defaults=[[0x60400010], [0x607A0020], [], []], rx_types=[255, 1, 255, 255],
            tx_defaults=[[0x60410010], [0x60640020], [], []], tx_types=[255, 1, 255, 255],
            max_entries=MAX_PDO_ENTRIES, sync_period=(0, 0, 255_000))
    # counts, counts/s, counts/s^2 (the master writes them so: bus/families.py CIA402_CSP)
    _cia402(b, quick_stop=(2, 0, 6), quick_stop_decel=10_000_000, max_velocity=1_000_000,
            profile_velocity=100_000, acceleration=1_000_000)
    var, group = b.var, b.group
    var(0x607A, "Target position", I32, "rw", 0, pdo=True)
    group(0x60C2, "Interpolation time period", 9, [  # in CSP: the set point cycle (= the SYNC period)
        (0, "Number of entries", U8, "ro", 2, None, None, False, False),
        (1, "Interpolation time period value", U8, "rw", 10, 1, 255, False, False),
        (2, "Interpolation time index", I8, "rw", -3, -3, -3, False, False),
    ])
    _homing(b, method=0, speeds=(100_000, 10_000), acceleration=1_000_000)  # counts/s, counts/s^2
    var(0x6502, "Supported drive modes", U32, "ro", 0x000000A0)  # bits 5, 7: homing, cyclic synchronous position
    return b


@dataclass(frozen=True)
class ObjectTable:
    """One family's object dictionary: the single definition its drive, its EDS and the PDO checks use."""

    name: str
    eds_name: str
    objects: MappingProxyType[Key, ObjectSpec]
    groups: MappingProxyType[int, GroupSpec]
    indices: frozenset[int]

    @classmethod
    def build(cls, name: str, eds_name: str, b: _Builder) -> ObjectTable:
        return cls(name, eds_name, MappingProxyType({s.key: s for s in b.objects}),
                   MappingProxyType({gr.index: gr for gr in b.groups}), frozenset(s.index for s in b.objects))

    def spec(self, index: int, sub: int) -> ObjectSpec:
        """The spec of (index, sub). Raises SdoAbort with the CiA 301 code for a missing object/sub-index."""
        s = self.objects.get((index, sub))
        if s is None:
            if index in self.indices:
                raise SdoAbort(ABORT_NO_SUBINDEX, f"0x{index:04X} has no sub-index {sub}")
            raise SdoAbort(ABORT_NO_OBJECT, f"object 0x{index:04X} does not exist")
        if index < 0x1000:
            raise SdoAbort(ABORT_NO_OBJECT, f"0x{index:04X} is a dummy object (PDO mapping only)")
        return s

    def defaults(self, node_id: int) -> dict[Key, int]:
        """Power-on values of every integer object for `node_id`."""
        return {k: s.default_for(node_id) for k, s in self.objects.items() if isinstance(s.default, int)}


EPOS_TABLE = ObjectTable.build("epos-ipm", "epos-ipm.eds", _epos())
XTRAPULS_TABLE = ObjectTable.build("xtrapuls-ip", "xtrapuls-ip.eds", _xtrapuls())
CSP_TABLE = ObjectTable.build("cia402-csp", "cia402-csp.eds", _csp())
TABLES: MappingProxyType[str, ObjectTable] = MappingProxyType(
    {t.name: t for t in (EPOS_TABLE, XTRAPULS_TABLE, CSP_TABLE)})


def check_value(s: ObjectSpec, value: int) -> None:
    """Type and EDS range checks of a value written to `s` (raises SdoAbort)."""
    lo, hi = s.dtype.value_range()
    if s.low is not None:
        lo = max(lo, s.low)
    if s.high is not None:
        hi = min(hi, s.high)
    if value > hi:
        raise SdoAbort(ABORT_VALUE_TOO_HIGH, f"0x{s.index:04X}:{s.sub:02X} value {value} above {hi}")
    if value < lo:
        raise SdoAbort(ABORT_VALUE_TOO_LOW, f"0x{s.index:04X}:{s.sub:02X} value {value} below {lo}")


def decode_value(s: ObjectSpec, data: bytes) -> int:
    """Little-endian bytes of `s`'s type to an int. Raises SdoAbort on a length mismatch."""
    if len(data) * 8 != s.dtype.bits:
        raise SdoAbort(ABORT_TYPE_LENGTH, f"0x{s.index:04X}:{s.sub:02X} needs {s.dtype.bits // 8} bytes, "
                       f"got {len(data)}")
    return int.from_bytes(data, "little", signed=s.dtype.signed)


def encode_value(s: ObjectSpec, value: int) -> bytes:
    return int(value).to_bytes(s.dtype.bits // 8, "little", signed=s.dtype.signed)
