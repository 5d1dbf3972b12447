"""Drive profiles: what one drive family needs from the master, as data (no I/O).

A `DriveProfile` names a family's object indices, its PDO layout, its EMCY codes, its buffer (a FIFO
of PVT records with watermarks, or one point per SYNC), and produces the ordered list of SDO writes
that configures one axis (`configuration`). The master adapter (`bus.network`) writes that list over
SDO and reads it back; the simulated drive (`bus.sim.device.DriveDevice.configure`) applies the
same list directly in virtual time. The streamer only asks the profile (`fifo_depth`,
`points_per_sync`, `encode_point`, the COB-IDs, `frame_to_event`), so a second family can be added by
writing a second profile.

EPOS_IPM is maxon's interpolated position mode (seed 000 chapter 4, seed 001): PVT records 0x20C1 into
a 64-entry FIFO, buffer status 0x20C4:01, watermarks 0x20C4:02/03, free size 0x60C4:02, cubic Hermite
interpolation every 1 ms. The PDO layout is bus/cob.py's (the wire contract).

How an XtrapulsPac profile (seed 003) would differ: mode 7 with sub-mode -1 (PV) on 0x60C0, one
point per SYNC (`fifo_depth=0`, `points_per_sync=1`) in 0x60C1:01 (position) and 0x60C1:02
(velocity) mapped in a synchronous RPDO (type 1) instead of an asynchronous 0x20C1 record, no buffer
status (the streamer then feeds exactly one point per SYNC and watches EMCY 0x8782 for a late point),
its EMCY codes (0x8611, 0x8780, 0x8782, 0x8130 are already shared) and its SYNC window object 0x2006.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Literal

from bus import cob, codec
from bus.events import Bootup, BufferStatus, Emcy, Event, PositionFeedback
from planner import record
from planner.config import AxisConfig, DriveSettings

Direction = Literal["rx", "tx"]


@dataclass(frozen=True)
class ObjectRef:
    """(index, sub-index) of one object; unpacks as a pair: `read(node, *ref)`."""

    index: int
    sub: int = 0

    def __iter__(self) -> Iterator[int]:
        return iter((self.index, self.sub))

    def __str__(self) -> str:
        return f"0x{self.index:04X}:{self.sub:02X}"


@dataclass(frozen=True)
class PdoEntry:
    """One mapped object: index, sub-index, length in bits (the mapping word is index<<16|sub<<8|bits)."""

    index: int
    sub: int
    bits: int

    def __post_init__(self) -> None:
        if self.bits not in (8, 16, 32, 64):
            raise ValueError(f"PDO entry 0x{self.index:04X}:{self.sub:02X} length {self.bits} "
                             "is not 8/16/32/64")

    @property
    def word(self) -> int:
        return (self.index << 16) | (self.sub << 8) | self.bits

    @classmethod
    def from_word(cls, word: int) -> PdoEntry:
        return cls(word >> 16, (word >> 8) & 0xFF, word & 0xFF)


@dataclass(frozen=True)
class PdoLayout:
    """One PDO of the product layout: direction, number 1..4, COB-ID base (+ node id), type, entries."""

    direction: Direction
    number: int
    cob_base: int
    transmission_type: int
    entries: tuple[PdoEntry, ...]

    def __post_init__(self) -> None:
        if not 1 <= self.number <= 4:
            raise ValueError(f"PDO number must be 1..4, got {self.number}")
        if sum(e.bits for e in self.entries) > 64:
            raise ValueError(f"{self.direction}PDO{self.number} maps more than 64 bits")
        if not (0 <= self.transmission_type <= 240 or self.transmission_type in (254, 255)):
            raise ValueError(f"transmission type {self.transmission_type} not supported")

    def cob_id(self, node: int) -> int:
        return self.cob_base + node

    @property
    def comm_index(self) -> int:
        return (0x1400 if self.direction == "rx" else 0x1800) + self.number - 1

    @property
    def mapping_index(self) -> int:
        return (0x1600 if self.direction == "rx" else 0x1A00) + self.number - 1

    @property
    def size_bytes(self) -> int:
        return sum(e.bits for e in self.entries) // 8

    @property
    def synchronous(self) -> bool:
        return self.transmission_type <= 240


@dataclass(frozen=True)
class SdoWrite:
    """One configuration write: the master sends it over SDO (and verifies it if `verify`).

    `essential`: the product cannot run the drive without this object (a drive that lacks it fails
    configuration with `why`); a non-essential object the drive lacks is skipped (bus/readings.py's
    optional objects)."""

    index: int
    sub: int
    value: int
    what: str
    verify: bool = True
    essential: bool = True
    why: str = ""

    @property
    def ref(self) -> ObjectRef:
        return ObjectRef(self.index, self.sub)


@dataclass(frozen=True)
class EmcyCodes:
    following_error: int = codec.EMCY_FOLLOWING_ERROR
    ip_buffer: int = codec.EMCY_IP_BUFFER
    sync_lost: int = codec.EMCY_SYNC_LOST
    heartbeat: int = codec.EMCY_HEARTBEAT
    pdo_too_short: int = codec.EMCY_PDO_LENGTH
    pdo_too_long: int = codec.EMCY_PDO_LENGTH_EXCEEDED
    ip_velocity: int = codec.EMCY_IP_VELOCITY
    ip_acceleration: int = codec.EMCY_IP_ACCELERATION
    error_reset: int = codec.EMCY_ERROR_RESET

    def name_of(self, code: int) -> str:
        return codec.EMCY_NAMES.get(code, f"0x{code:04X}")


FEEDBACK_TPDO = 2  # TPDO2 carries the position feedback (0x6064, 0x6062)
HEARTBEAT_SPREAD_MS = 11  # producer times heartbeat_ms + (node id mod 11): the drives' heartbeats drift
# apart instead of all landing in one SYNC cycle (24 of them are 1560 bits, 16 % of a 10 ms cycle)


def heartbeat_producer_ms(heartbeat_ms: int, node: int) -> int:
    """0x1017 for `node`: the cell's heartbeat time, spread by node id (see HEARTBEAT_SPREAD_MS)."""
    return heartbeat_ms + node % HEARTBEAT_SPREAD_MS if heartbeat_ms > 0 else 0
TIME_STAMP_CONSUME = 1 << 31  # 0x1012 bit 31: the node consumes the time stamp


@dataclass(frozen=True)
class FeedbackSchedule:
    """Position feedback (TPDO2) every `every` SYNCs, staggered over the axes with the CiA 301 SYNC counter:
    the SYNC carries a counter 1..`counter_overflow` (0x1019), and axis k's TPDO2 goes first at the counter
    value 1 + k mod `every` (0x18xx:06), then every `every` SYNCs. `counter_overflow` is a multiple of
    `every`, so the phase holds across the counter's wrap. `phases` maps node id -> start value."""

    every: int
    phases: Mapping[int, int]

    @property
    def counter_overflow(self) -> int:
        return self.every * (240 // self.every) if self.every > 1 else 0

    def start_value(self, node: int) -> int:
        return self.phases[node]

    def carries(self, node: int, counter: int | None) -> bool:
        """Does the SYNC with this counter value carry the node's TPDO2?"""
        if self.every <= 1:
            return True
        if counter is None:
            return False
        return (counter - self.phases[node]) % self.every == 0

    @classmethod
    def staggered(cls, nodes: Sequence[int], every: int) -> FeedbackSchedule:
        return cls(every, MappingProxyType({n: 1 + k % every for k, n in enumerate(nodes)}))


def feedback_schedule(nodes: Sequence[int], every: int, counter_everywhere: bool) -> FeedbackSchedule | None:
    """The cell's TPDO2 schedule: staggered every `every` SYNCs when every drive has the SYNC counter
    (0x1019), else None (TPDO2 every SYNC: without the counter the phases could not be set)."""
    if every <= 1 or not counter_everywhere:
        return None
    return FeedbackSchedule.staggered(nodes, every)


def _pack_pvt(position: int, velocity_rpm: int, time_ms: int) -> bytes:
    return record.pack((position, velocity_rpm, time_ms))


def rpm_per_s(axis: AxisConfig, user_per_s2: float) -> float:
    """User units/s^2 -> the drive's acceleration unit, rpm/s of the motor shaft (seed 000 1.7)."""
    return user_per_s2 * axis.counts_per_unit * 60.0 / axis.counts_per_rev


def _u32(x: float) -> int:
    return max(0, min(0xFFFFFFFF, math.ceil(x)))


@dataclass(frozen=True)
class DriveProfile:
    """Everything the master needs to know about one drive family (see the module docstring)."""

    name: str
    eds_name: str
    ip_mode: int
    ip_submode: int
    fifo_depth: int  # 64 for EPOS; 0 = no FIFO (one point per SYNC)
    points_per_sync: int | None  # None = asynchronous records into the FIFO
    tick_ms: int  # the drive's interpolation tick
    pdos: tuple[PdoLayout, ...]
    objects: Mapping[str, ObjectRef]
    emcy: EmcyCodes = field(default_factory=EmcyCodes)
    default_underflow_warning: int = 4
    default_overflow_warning: int = 60
    # writes after the drive is operation enabled, before a job (EPOS: buffer clear, then enable)
    after_enable: tuple[tuple[str, int], ...] = ()
    encode_point: Callable[[int, int, int], bytes] = field(default=lambda p, v, t: _pack_pvt(p, v, t))

    def obj(self, name: str) -> ObjectRef:
        try:
            return self.objects[name]
        except KeyError:
            raise KeyError(f"profile {self.name!r} has no object {name!r} "
                           f"(has {sorted(self.objects)})") from None

    def pdo(self, direction: Direction, number: int) -> PdoLayout:
        for p in self.pdos:
            if p.direction == direction and p.number == number:
                return p
        raise KeyError(f"profile {self.name!r} has no {direction}PDO{number}")

    @property
    def eds_path(self) -> str:
        """Path of the family's EDS (configs/drives/ of the source tree)."""
        from pathlib import Path

        return str(Path(__file__).resolve().parent.parent / "configs" / "drives" / self.eds_name)

    # ---- COB-IDs the streamer uses
    def record_cob_id(self, node: int) -> int:
        return self.pdo("rx", 2).cob_id(node)

    def controlword_cob_id(self, node: int) -> int:
        return self.pdo("rx", 1).cob_id(node)

    # ---- configuration
    def configuration(
        self,
        axis: AxisConfig,
        settings: DriveSettings,
        sync_period_ms: int,
        *,
        feedback: FeedbackSchedule | None = None,
        time_stamp: bool = False,
    ) -> tuple[SdoWrite, ...]:
        """Ordered SDO writes that put one axis into ip mode with the product's PDO layout.

        Limits in drive units (rpm, rpm/s) are rounded up so that a plan inside the axis limits never
        trips the drive's own checks on rounding alone. `feedback`: TPDO2 every n-th SYNC from a SYNC
        counter value (None: every SYNC). `time_stamp`: consume the master's 0x1013 time stamps.
        """
        o = self.objects
        decel = settings.profile_deceleration if settings.profile_deceleration > 0 else axis.acceleration

        def w(name: str, value: int, what: str, why: str = "", essential: bool = True) -> SdoWrite:
            ref = o[name]
            return SdoWrite(ref.index, ref.sub, value, what, essential=essential, why=why)

        writes: list[SdoWrite] = [
            w("sync_period", sync_period_ms * 1000, "communication cycle period (us)", essential=False),
            w("heartbeat_producer", heartbeat_producer_ms(settings.heartbeat_ms, axis.node_id),
              "producer heartbeat time (ms)", "the master detects a lost drive by its heartbeat"),
            w("mode", self.ip_mode, "modes of operation = interpolated position", "selects the PVT mode"),
            w("ip_submode", self.ip_submode, "interpolation sub mode", "cubic PVT interpolation"),
            w("underflow_warning", settings.underflow_warning, "buffer underflow warning level",
              "the FIFO's low watermark"),
            w("overflow_warning", settings.overflow_warning, "buffer overflow warning level",
              "the FIFO's high watermark"),
            w("following_error_window", settings.following_error_counts, "following error window",
              "the drive stops itself on a following error"),
            w("max_profile_velocity", _u32(axis.max_profile_velocity_rpm),
              "max profile velocity (rpm)", "the drive's own velocity limit"),
            w("profile_velocity", _u32(axis.velocity_rpm(axis.velocity)),
              "profile velocity (rpm)", essential=False),
            w("profile_acceleration", _u32(rpm_per_s(axis, axis.acceleration)),
              "profile acceleration (rpm/s)", essential=False),
            w("max_acceleration", _u32(rpm_per_s(axis, axis.max_acceleration)),
              "max acceleration (rpm/s)", "the drive's own acceleration limit"),
            w("profile_deceleration", _u32(rpm_per_s(axis, decel)),
              "profile deceleration (rpm/s)", "halt decelerates with it"),
            w("quick_stop_deceleration", _u32(rpm_per_s(axis, axis.max_acceleration)),
              "quick stop deceleration (rpm/s)", essential=False),
        ]
        if time_stamp:
            writes.append(w("time_stamp_cob_id", TIME_STAMP_CONSUME | cob.TIME_STAMP_COB_ID,
                            "consume the high-resolution time stamp 0x1013", essential=False))
        if feedback is not None and feedback.every > 1:
            writes.append(w("sync_counter_overflow", feedback.counter_overflow,
                            "SYNC counter overflow value", essential=False))
        writes += self.pdo_configuration(axis.node_id, feedback)
        return tuple(writes)

    def pdo_configuration(self, node: int, feedback: FeedbackSchedule | None = None) -> list[SdoWrite]:
        """CiA 301 remapping sequence for every PDO 1..4 of both directions (unused ones disabled).
        With `feedback`, TPDO2 goes every `feedback.every` SYNCs from the counter value `start_value`."""
        writes: list[SdoWrite] = []
        directions: tuple[Direction, Direction] = ("rx", "tx")
        for direction in directions:
            base_comm = 0x1400 if direction == "rx" else 0x1800
            for number in range(1, 5):
                comm = base_comm + number - 1
                try:
                    layout = self.pdo(direction, number)
                except KeyError:
                    default_base = (0x200 if direction == "rx" else 0x180) + 0x100 * (number - 1)
                    writes.append(SdoWrite(comm, 1, 0x80000000 | (default_base + node),
                                           f"{direction}PDO{number} disabled"))
                    continue
                cob_id = layout.cob_id(node)
                tag = f"{direction}PDO{number}"
                writes.append(SdoWrite(comm, 1, 0x80000000 | cob_id, f"{tag} invalid while remapping", False))
                ttype = layout.transmission_type
                staggered = (feedback is not None and feedback.every > 1 and direction == "tx"
                             and number == FEEDBACK_TPDO)
                if staggered:
                    assert feedback is not None
                    ttype = feedback.every
                writes.append(SdoWrite(comm, 2, ttype, f"{tag} transmission type"))
                if staggered:
                    assert feedback is not None
                    writes.append(SdoWrite(comm, 6, feedback.start_value(node), f"{tag} SYNC start value"))
                writes.append(SdoWrite(layout.mapping_index, 0, 0, f"{tag} clear mapping", False))
                for k, entry in enumerate(layout.entries, start=1):
                    writes.append(SdoWrite(layout.mapping_index, k, entry.word,
                                           f"{tag} entry {k} = 0x{entry.index:04X}:{entry.sub:02X}"))
                writes.append(SdoWrite(layout.mapping_index, 0, len(layout.entries),
                                       f"{tag} number of entries"))
                writes.append(SdoWrite(comm, 1, cob_id, f"{tag} COB-ID (valid)"))
        return writes

    # ---- frames -> streamer events (pure)
    def frame_to_event(self, cob_id: int, data: bytes, t: float, nodes: frozenset[int] | set[int],
                       sync_count: int | None = None) -> Event | None:
        """The event a received frame means, for the cell's `nodes`; None for frames that mean none
        (SYNC, NMT, SDO, RPDOs, frames of other nodes, heartbeats other than boot-up). TPDO events
        carry `sync_count`, the SYNC they answer. Raises ProtocolError for a malformed
        TPDO/EMCY/heartbeat of one of `nodes`."""
        kind, node = cob.classify(cob_id)
        if node not in nodes:
            return None
        if kind == "TPDO1":
            t1 = codec.decode_tpdo1(data)
            return BufferStatus(node, t1.statusword, t1.buffer_status, t1.free_size, t, sync_count)
        if kind == "TPDO2":
            t2 = codec.decode_tpdo2(data)
            return PositionFeedback(node, t2.position_actual, t2.position_demand, t, sync_count)
        if kind == "EMCY":
            e = codec.decode_emcy(data)
            return Emcy(node, e.code, e.register, e.manufacturer, t)
        if kind == "HEARTBEAT":
            if codec.decode_heartbeat(data) == codec.NmtState.BOOTUP:
                return Bootup(node, t)
            return None
        return None


_EPOS_OBJECTS: dict[str, ObjectRef] = {
    "device_type": ObjectRef(0x1000),
    "error_register": ObjectRef(0x1001),
    "sync_cob_id": ObjectRef(0x1005),
    "sync_period": ObjectRef(0x1006),
    "store_parameters": ObjectRef(0x1010, 1),
    "restore_defaults": ObjectRef(0x1011, 1),
    "time_stamp_cob_id": ObjectRef(0x1012),
    "high_resolution_time_stamp": ObjectRef(0x1013),
    "identity_vendor": ObjectRef(0x1018, 1),
    "identity_product": ObjectRef(0x1018, 2),
    "identity_revision": ObjectRef(0x1018, 3),
    "identity_serial": ObjectRef(0x1018, 4),
    "sync_counter_overflow": ObjectRef(0x1019),
    "heartbeat_consumer": ObjectRef(0x1016, 1),
    "heartbeat_producer": ObjectRef(0x1017),
    "record": ObjectRef(0x20C1),
    "buffer_status": ObjectRef(0x20C4, 1),
    "underflow_warning": ObjectRef(0x20C4, 2),
    "overflow_warning": ObjectRef(0x20C4, 3),
    "error_code": ObjectRef(0x603F),
    "controlword": ObjectRef(0x6040),
    "statusword": ObjectRef(0x6041),
    "quick_stop_option": ObjectRef(0x605A),
    "mode": ObjectRef(0x6060),
    "mode_display": ObjectRef(0x6061),
    "position_demand": ObjectRef(0x6062),
    "position_actual": ObjectRef(0x6064),
    "following_error_window": ObjectRef(0x6065),
    "position_window": ObjectRef(0x6067),
    "velocity_actual": ObjectRef(0x606C),
    "current_actual": ObjectRef(0x6078),
    "position_limit_min": ObjectRef(0x607D, 1),
    "position_limit_max": ObjectRef(0x607D, 2),
    "max_profile_velocity": ObjectRef(0x607F),
    "profile_velocity": ObjectRef(0x6081),
    "profile_acceleration": ObjectRef(0x6083),
    "profile_deceleration": ObjectRef(0x6084),
    "quick_stop_deceleration": ObjectRef(0x6085),
    "ip_submode": ObjectRef(0x60C0),
    "ip_time_value": ObjectRef(0x60C2, 1),
    "ip_time_index": ObjectRef(0x60C2, 2),
    "max_buffer_size": ObjectRef(0x60C4, 1),
    "free_size": ObjectRef(0x60C4, 2),
    "buffer_organization": ObjectRef(0x60C4, 3),
    "buffer_position": ObjectRef(0x60C4, 4),
    "record_size": ObjectRef(0x60C4, 5),
    "buffer_clear": ObjectRef(0x60C4, 6),
    "max_acceleration": ObjectRef(0x60C5),
    "following_error_actual": ObjectRef(0x60F4),
    "supported_modes": ObjectRef(0x6502),
}

EPOS_IPM = DriveProfile(
    name="epos-ipm",
    eds_name="epos-ipm.eds",
    ip_mode=7,
    ip_submode=-1,
    fifo_depth=64,
    points_per_sync=None,
    tick_ms=1,
    pdos=(
        PdoLayout("rx", 1, cob.RPDO1_BASE, 1, (PdoEntry(0x6040, 0, 16),)),
        PdoLayout("rx", 2, cob.RPDO2_BASE, 255, (PdoEntry(0x20C1, 0, 64),)),
        PdoLayout("tx", 1, cob.TPDO1_BASE, 1, (PdoEntry(0x6041, 0, 16), PdoEntry(0x60C4, 2, 32))),
        PdoLayout("tx", 2, cob.TPDO2_BASE, 1, (PdoEntry(0x6064, 0, 32), PdoEntry(0x6062, 0, 32))),
    ),
    objects=MappingProxyType(_EPOS_OBJECTS),
    after_enable=(("buffer_clear", 0), ("buffer_clear", 1)),
)

PROFILES: Mapping[str, DriveProfile] = MappingProxyType({EPOS_IPM.name: EPOS_IPM})
