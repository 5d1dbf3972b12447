"""Drive profiles: what one drive family needs from the master, as data (no I/O).

A `DriveProfile` names a family's objects, PDO layout, EMCY codes and how it takes motion (a PVT FIFO,
or one set point per SYNC), and produces the ordered SDO writes that configure an axis (`configuration`):
the master writes and reads them back (bus.network), the simulated drive applies them directly. The
streamer asks only for data (`kind`, COB-IDs, set point slots, `frame_to_event`). Families are
bus/families.py. Cyclic set points travel in RPDO3 (type 1), own or shared by a multiplexed group
(XtrapulsPac 0x3350 = 1: 16-bit entries at each member's offset under the lowest node's COB-ID, dummy
objects over the others); `bus.families.setpoint_slots` lays the slots out for master, sim and streamer.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Literal

from bus import cob, codec
from bus.events import Bootup, BufferStatus, Emcy, Event, PositionFeedback, StatusWord
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
    shared_cob_id: int | None = None  # a multiplexed RPDO: every member uses this COB-ID

    def __post_init__(self) -> None:
        if not 1 <= self.number <= 4:
            raise ValueError(f"PDO number must be 1..4, got {self.number}")
        if sum(e.bits for e in self.entries) > 64:
            raise ValueError(f"{self.direction}PDO{self.number} maps more than 64 bits")
        if not (0 <= self.transmission_type <= 240 or self.transmission_type in (254, 255)):
            raise ValueError(f"transmission type {self.transmission_type} not supported")

    def cob_id(self, node: int) -> int:
        return self.shared_cob_id if self.shared_cob_id is not None else self.cob_base + node

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


def rpm_per_s(axis: AxisConfig, user_per_s2: float) -> float:
    """User units/s^2 -> the drive's acceleration unit, rpm/s of the motor shaft (seed 000 1.7)."""
    return user_per_s2 * axis.counts_per_unit * 60.0 / axis.counts_per_rev


def u32(x: float) -> int:
    return max(0, min(0xFFFFFFFF, math.ceil(x)))


# ---- set point slots (cyclic families) -----------------------------------------------------------------
Kind = Literal["fifo", "cyclic"]
MAX_GROUP_BITS = 64  # one CAN frame
MAX_GROUP_AXES = 4  # seed 003: "4 axis demand values (16 bit absolute) with one RPDO"


@dataclass(frozen=True)
class SetpointSlot:
    """Where one cyclic axis' set point travels: the frame's COB-ID and length, the byte offset of the
    axis' position (`position_bits` 32, or 16 in a multiplexed group), then its velocity (`velocity_bits`:
    0 unless PV; 32, or 16 in a group). `members`: the group's node ids in frame order (just this node
    when the axis has an RPDO3 of its own)."""

    node: int
    cob_id: int
    offset: int
    position_bits: int
    velocity_bits: int
    frame_bytes: int
    members: tuple[int, ...]

    @property
    def multiplexed(self) -> bool:
        return len(self.members) > 1 or self.position_bits == 16

    @property
    def size_bytes(self) -> int:
        return (self.position_bits + self.velocity_bits) // 8

    def entries(self, position: PdoEntry, velocity: PdoEntry | None) -> tuple[PdoEntry, ...]:
        """This axis' RPDO3 mapping: dummies over the bytes before its slot, its own objects, dummies
        over the bytes after it (so that every member's mapping is as long as the frame: seed 003's prose;
        its example leaves the trailing dummies out, which a drive that accepts a longer frame also takes)."""
        before = _dummies(self.offset * 8)
        own = (position,) + ((velocity,) if velocity is not None and self.velocity_bits else ())
        after = _dummies((self.frame_bytes - self.offset - self.size_bytes) * 8)
        return before + own + after


def _dummies(bits: int) -> tuple[PdoEntry, ...]:
    """Dummy entries covering `bits` (CiA 301 0x0007 UNSIGNED32 / 0x0006 UNSIGNED16)."""
    out: list[PdoEntry] = []
    while bits >= 32:
        out.append(PdoEntry(0x0007, 0, 32))
        bits -= 32
    while bits >= 16:
        out.append(PdoEntry(0x0006, 0, 16))
        bits -= 16
    if bits:
        raise ValueError(f"slot boundaries must be whole 16-bit words, {bits} bits left")
    return tuple(out)


def pack_setpoints(slot: SetpointSlot, frame: bytearray, position: int, velocity: int = 0) -> None:
    """Write one axis' set point into its group's frame (little-endian; 16-bit slots carry the low word
    of the position, the drive rebuilds the upper one; a 16-bit velocity must fit, the planner checks)."""
    o = slot.offset
    if slot.position_bits == 32:
        frame[o:o + 4] = (position & 0xFFFFFFFF).to_bytes(4, "little")
        o += 4
    else:
        frame[o:o + 2] = (position & 0xFFFF).to_bytes(2, "little")
        o += 2
    if slot.velocity_bits == 32:
        frame[o:o + 4] = (velocity & 0xFFFFFFFF).to_bytes(4, "little")
    elif slot.velocity_bits == 16:
        frame[o:o + 2] = (velocity & 0xFFFF).to_bytes(2, "little")


HOMING_MODE = 6  # CiA 402 modes of operation: homing


# ---- the profile ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DriveProfile:
    """Everything the master needs to know about one drive family (see the module docstring). The
    family's own part is in the hooks `_mode_writes` (mode, sub-mode and the family's own objects) and
    `pdo_layouts`; bus/families.py subclasses it once per family."""

    name: str
    eds_name: str
    kind: Kind
    ip_mode: int  # 7 interpolated position, 8 cyclic synchronous position
    objects: Mapping[str, ObjectRef]
    fifo_depth: int = 0  # 64 for EPOS; 0 = no FIFO (one set point per SYNC)
    tick_ms: int = 1  # the interpolation tick (the simulated drives' internal cycle)
    emcy: EmcyCodes = field(default_factory=EmcyCodes)
    # what the drive needs before a job, after operation enabled (EPOS: buffer clear, then enable)
    after_enable: tuple[tuple[str, int], ...] = ()
    # the set point object(s) written with the drive's position before operation is enabled, so that the
    # drive does not move to a stale set point (cyclic families)
    hold_objects: tuple[str, ...] = ()
    # controlword bit 4 starts the interpolation (IP); False: the drive follows set points once enabled (CSP)
    starts_with_bit4: bool = True
    # how long SYNC must have run before the drive accepts bit 4 (its PLL locks on SYNC: XtrapulsPac 180 ms)
    sync_lock_ms: int = 0
    # halt (controlword bit 8) is available in this mode
    halt_in_mode: bool = True

    def obj(self, name: str) -> ObjectRef:
        try:
            return self.objects[name]
        except KeyError:
            raise KeyError(f"profile {self.name!r} has no object {name!r} "
                           f"(has {sorted(self.objects)})") from None

    def has(self, name: str) -> bool:
        return name in self.objects

    @property
    def eds_path(self) -> str:
        """Path of the family's EDS (configs/drives/ of the source tree)."""
        from pathlib import Path

        return str(Path(__file__).resolve().parent.parent / "configs" / "drives" / self.eds_name)

    # ---- family hooks
    def velocity_in_setpoint(self, axis: AxisConfig) -> bool:
        """Does the axis' set point carry a velocity (XtrapulsPac sub-mode PV)?"""
        return False

    def submode(self, axis: AxisConfig) -> str:
        """The interpolation the drive applies to the stream (planner/encoding/cyclic.py): "pvt" for the EPOS
        FIFO, "linear", "pv" or "p3" for one set point per SYNC."""
        from planner.encoding.cyclic import interpolation_of

        return interpolation_of(axis) or "pvt"

    def pdo_layouts(self, axis: AxisConfig, slot: SetpointSlot | None) -> tuple[PdoLayout, ...]:
        raise NotImplementedError

    def _mode_writes(self, axis: AxisConfig, settings: DriveSettings, sync_period_ms: int,
                     slot: SetpointSlot | None) -> list[SdoWrite]:
        raise NotImplementedError

    def _limit_writes(self, axis: AxisConfig, settings: DriveSettings) -> list[SdoWrite]:
        """The drive's own limits and ramps, in its units."""
        raise NotImplementedError

    # ---- COB-IDs the streamer uses
    def record_cob_id(self, node: int) -> int:
        return cob.rpdo2_id(node)

    def controlword_cob_id(self, node: int) -> int:
        return cob.rpdo1_id(node)

    # ---- configuration
    def _w(self, name: str, value: int, what: str, why: str = "", essential: bool = True) -> SdoWrite:
        ref = self.obj(name)
        return SdoWrite(ref.index, ref.sub, value, what, essential=essential, why=why)

    def configuration(
        self,
        axis: AxisConfig,
        settings: DriveSettings,
        sync_period_ms: int,
        *,
        feedback: FeedbackSchedule | None = None,
        time_stamp: bool = False,
        slot: SetpointSlot | None = None,
    ) -> tuple[SdoWrite, ...]:
        """Ordered SDO writes that put one axis into the family's mode with the product's PDO layout.

        Limits in the family's units (EPOS: rpm, rpm/s; cyclic families: counts/s, counts/s^2) are
        rounded up, so a plan inside the axis limits never trips the drive's own checks on rounding
        alone. `feedback`: TPDO2 every n-th SYNC from a SYNC counter value (None: every SYNC).
        `time_stamp`: consume the master's 0x1013 time stamps. `slot`: where a cyclic axis' set point
        travels (`setpoint_slots`; required for a cyclic family).
        """
        if self.kind == "cyclic" and slot is None:
            raise ValueError(f"axis {axis.name!r} ({self.name}) needs its set point slot (setpoint_slots)")
        w = self._w
        writes: list[SdoWrite] = [
            w("sync_period", sync_period_ms * 1000, "communication cycle period (us)",
              essential=self.kind == "cyclic",
              why="the drive's interpolation period is the SYNC period (seed 003: 0x1006 is also the IP period)"),
            w("heartbeat_producer", heartbeat_producer_ms(settings.heartbeat_ms, axis.node_id),
              "producer heartbeat time (ms)", "the master detects a lost drive by its heartbeat"),
        ]
        writes += self._mode_writes(axis, settings, sync_period_ms, slot)
        writes.append(w("following_error_window", settings.following_error_counts, "following error window",
                        "the drive stops itself on a following error"))
        writes += self._limit_writes(axis, settings)
        if time_stamp and self.has("time_stamp_cob_id"):
            writes.append(w("time_stamp_cob_id", TIME_STAMP_CONSUME | cob.TIME_STAMP_COB_ID,
                            "consume the high-resolution time stamp 0x1013", essential=False))
        if feedback is not None and feedback.every > 1 and self.has("sync_counter_overflow"):
            writes.append(w("sync_counter_overflow", feedback.counter_overflow,
                            "SYNC counter overflow value", essential=False))
        writes += self.pdo_configuration(axis.node_id, self.pdo_layouts(axis, slot), feedback)
        return tuple(writes)

    def pdo_configuration(self, node: int, layouts: Sequence[PdoLayout],
                          feedback: FeedbackSchedule | None = None) -> list[SdoWrite]:
        """CiA 301 remapping sequence for every PDO 1..4 of both directions (unused ones disabled).
        With `feedback`, TPDO2 goes every `feedback.every` SYNCs from the counter value `start_value`."""
        writes: list[SdoWrite] = []
        directions: tuple[Direction, Direction] = ("rx", "tx")
        for direction in directions:
            base_comm = 0x1400 if direction == "rx" else 0x1800
            for number in range(1, 5):
                comm = base_comm + number - 1
                layout = next((p for p in layouts if p.direction == direction and p.number == number), None)
                if layout is None:
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

    def mode_writes(self, axis: AxisConfig, settings: DriveSettings, sync_period_ms: int,
                    slot: SetpointSlot | None) -> tuple[SdoWrite, ...]:
        """The family's mode writes of `configuration` (back to the streaming mode after homing)."""
        return tuple(self._mode_writes(axis, settings, sync_period_ms, slot))

    def homing_writes(self, axis: AxisConfig, method: int, search_speed: float, zero_speed: float,
                      acceleration: float, offset: float) -> tuple[SdoWrite, ...]:
        """Homing mode's parameters in the family's units (user units in): method 0x6098, speeds 0x6099:01/02
        (EPOS rpm, cyclic families counts/s), acceleration 0x609A (rpm/s, counts/s^2), home offset 0x607C
        (counts), then modes of operation = 6."""
        if self.kind == "fifo":
            def vel(v: float) -> int:
                return max(1, round(axis.velocity_rpm(v)))

            def acc(a: float) -> int:
                return max(1, round(rpm_per_s(axis, a)))
        else:
            def vel(v: float) -> int:
                return max(1, round(v * axis.counts_per_unit))

            def acc(a: float) -> int:
                return max(1, round(a * axis.counts_per_unit))
        return (
            SdoWrite(0x6098, 0, method, "homing method"),
            SdoWrite(0x6099, 1, vel(search_speed), "homing speed: search for switch"),
            SdoWrite(0x6099, 2, vel(zero_speed), "homing speed: search for zero"),
            SdoWrite(0x609A, 0, acc(acceleration), "homing acceleration"),
            SdoWrite(0x607C, 0, round(offset * axis.counts_per_unit), "home offset (counts)"),
            SdoWrite(0x6060, 0, HOMING_MODE, "modes of operation = homing"),
        )

    def hold_writes(self, position: int) -> tuple[SdoWrite, ...]:
        """Before operation is enabled: the set point objects = the drive's position (cyclic families)."""
        out = []
        for name in self.hold_objects:
            value = 0 if name.endswith("velocity") else position
            out.append(self._w(name, value, f"{name} = {value} (hold where the drive is)"))
        return tuple(out)

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
            if self.kind == "cyclic":
                return StatusWord(node, codec.decode_statusword(data), t, sync_count)
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


def frame_to_event(profiles: Mapping[int, DriveProfile], cob_id: int, data: bytes, t: float,
                   nodes: frozenset[int] | set[int], sync_count: int | None = None) -> Event | None:
    """`DriveProfile.frame_to_event` with the profile of the node that sent the frame (a mixed cell)."""
    node = cob.classify(cob_id).node
    profile = profiles.get(node)
    if profile is None:
        return None
    return profile.frame_to_event(cob_id, data, t, nodes, sync_count)
