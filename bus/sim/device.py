"""A simulated CiA 402 servo drive as a pure state machine: frames and time in, frames out.

This is the part every drive family shares; a family (bus/sim/epos.py: maxon's IPM FIFO;
bus/sim/xtrapuls.py: one set point per SYNC; bus/sim/csp.py: cyclic synchronous position) adds its
mode, its objects and what it does at each SYNC through the hooks below. No sleeps, no wall clock, no
canopen, no threads: every entry point takes the time `t` (seconds, any monotonic origin) and returns the
frames the drive sends in response.

What it owns: the object dictionary (`objects`: the family's table, bus/sim/od.py), NMT state and
heartbeat producer/consumer, the CiA 402 power state machine (bus.codec.TRANSITIONS), the position
controller and motor (bus/sim/motor.py), the demand sources (an interpolation segment: a cubic over n
ticks, or a stop ramp), PDOs (CiA 301 mapping rules, synchronous and event TPDOs with inhibit time and
event timer, TPDO latency, the SYNC counter), EMCYs, store/restore, the drive's clock (locked to SYNC,
or its own: bus/sim/clock.py) and the readings of the manuals' open points (planner/readings.py).

What it is fed:
- `power_on(t)`: boot (boot-up message, NMT pre-operational; a family may stay silent).
- `on_frame(cob_id, data, t)`: NMT, SYNC, RPDOs (checked against the current mapping), heartbeats
  of a monitored producer (0x1016), the time stamp. SDO frames are not handled here: the canopen
  LocalNode adapter (bus/sim/node.py) serves SDO through `sdo_read`/`sdo_write`, and a virtual-time
  runtime calls those (or `configure`) directly.
- `on_sync(t)`: the drive clock. A drive locked to SYNC on each SYNC (1) runs the control ticks of the
  period that just ended (0x1006 / 1 ms ticks), (2) applies what synchronous RPDOs delivered since the
  last SYNC, (3) lets the family act (`_after_sync_rpdos`), (4) sends its synchronous TPDOs in
  PDO-number order, so they report the state after 1-3 (or before 2, reading `tpdo_sampling`).
- `advance(t)`: timers between frames: heartbeat production, SYNC loss while interpolating, heartbeat
  consumer timeout (EMCY 0x8130), TPDOs held for their latency, event TPDO timers, the own clock's ticks.
  `next_deadline()` says when it next has something to do.

The per-tick loop (`_integrate`) is the hot spot: it runs on locals, and work that does not need to be
per tick is done per segment (the demand list of a segment is computed once; limit crossings are found
once per segment and scheduled as events).

A family with a data recorder (EPOS, seed 004: bus/sim/recorder.py, its objects in bus/sim/epos.py) sets
`recorder`; while it runs, `_run_ticks_recorded` replaces the loop above so that every sample instant is
hit (sub-stepping the plant when the period is not whole ticks), and the error and halt-end triggers
fire here. Without a recorder (None, or stopped) the loop is the plain one.

Homing mode (6, every family; bus/sim/homing.py has the inputs and the methods): controlword bit 4 rising in
operation enabled starts the family's method 0x6098 (`homing_methods`; another one is homing error, bit 13)
with 0x6099 / 0x609A in the family's units; each search is a demand source (`Source.HOMING`) that ends at
the tick its input changes; at the end the drive returns to the edge and its position becomes 0x607C
(`_home_shift`: the counts between the machine's frame, in which the switches stand, and the position it
reports). Statusword bits 12 (attained, while bit 4 is set) / 13 (error) / 10 per seed 003's table.
`referenced` is true from a successful homing until a reset or power-on.
"""

from __future__ import annotations

import itertools
import math
import random
import struct
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from enum import Enum

from bus import codec
from bus.codec import (
    CW_FAULT_RESET,
    Cia402State,
    Command,
    Frame,
    Internal,
    InvalidTransition,
    NmtCommand,
    NmtState,
)
from bus.errors import ProtocolError
from bus.families import EPOS_IPM
from bus.profile import DriveProfile, FeedbackSchedule, SetpointSlot
from bus.sim import homing as hm
from bus.sim import od as odm
from bus.sim.clock import MotionClock
from bus.sim.motor import DEFAULT_MOTOR, LoopConstants, MotorParams, plant_constants
from bus.sim.od import Key, SdoAbort
from bus.sim.recorder import TICK_UNITS, TRIGGER_END, TRIGGER_ERROR, UNIT_S, DataRecorder, RecorderConfig, substep_units
from planner import hermite
from planner.config import AxisConfig, DriveSettings
from planner.readings import SimDriveOptions

ST = Cia402State
QUICK_STOP_OPTIONS = frozenset({0, 1, 2, 5, 6})
MAX_RAMP_TICKS = 600_000  # a stop ramp longer than 10 min of drive time ends with an abrupt stop
SAVE_SIGNATURE = 0x65766173  # "save" (seed 000 6.12; CiA 301 0x1010)
LOAD_SIGNATURE = 0x64616F6C  # "load" (seed 000 6.12; CiA 301 0x1011)
# what 0x1010 "save all parameters" never keeps (a family adds its commands and buffers)
_NOT_STORED = frozenset({(0x6040, 0), (0x1010, 1), (0x1011, 1), (0x1013, 0)})
COAST_STOP_COUNTS_PER_MS = 1e-4  # below this a coasting motor is taken as standing still

_EMCY_REGISTER = {
    codec.EMCY_FOLLOWING_ERROR: codec.ER_GENERIC | codec.ER_DEVICE_PROFILE,
    codec.EMCY_IP_BUFFER: codec.ER_GENERIC | codec.ER_DEVICE_PROFILE,
    codec.EMCY_SYNC_LOST: codec.ER_GENERIC | codec.ER_COMMUNICATION,
    codec.EMCY_HEARTBEAT: codec.ER_GENERIC | codec.ER_COMMUNICATION,
    codec.EMCY_PDO_LENGTH: codec.ER_GENERIC | codec.ER_COMMUNICATION,
    codec.EMCY_PDO_LENGTH_EXCEEDED: codec.ER_GENERIC | codec.ER_COMMUNICATION,
    codec.EMCY_IP_VELOCITY: codec.ER_GENERIC | codec.ER_MANUFACTURER,
    codec.EMCY_IP_ACCELERATION: codec.ER_GENERIC | codec.ER_MANUFACTURER,
}


class Source(Enum):
    """Where the position demand comes from while a demand list is being played."""

    SEGMENT = "ip segment"
    HALT = "halt ramp"
    QUICK_STOP = "quick stop ramp"
    FAULT = "fault reaction ramp"
    HOMING = "homing"


@dataclass
class DriveCounters:
    """Introspection for tests and reports (not part of the drive's object dictionary)."""

    syncs: int = 0
    ticks: int = 0
    records_received: int = 0
    records_rejected: int = 0
    segments_completed: int = 0
    activations: int = 0
    underflow_warnings: int = 0  # rising edges of 0x20C4:01 bit 0 seen at SYNC
    overflow_warnings: int = 0  # rising edges of bit 1 seen at SYNC
    velocity_warnings: int = 0  # segments whose velocity exceeded 0x6081
    acceleration_warnings: int = 0  # segments whose acceleration exceeded 0x6083
    emcy_sent: int = 0
    faults: int = 0
    sync_gaps: int = 0
    pdo_length_errors: int = 0
    ignored_commands: int = 0
    pdo_writes_rejected: int = 0


@dataclass(frozen=True)
class FaultRecord:
    t: float
    code: int
    name: str
    buffer_status: int
    state: Cia402State


@dataclass
class _RxPdo:
    number: int
    cob_id: int
    synchronous: bool
    length: int
    keys: tuple[Key, ...]
    unpacker: struct.Struct
    is_record: bool
    bits: tuple[int, ...] = ()  # mapped length of each entry (shorter than its object: `_widen`)
    short: bool = False  # some entry is mapped shorter than its object


@dataclass
class _TxPdo:
    number: int
    cob_id: int
    trans_type: int
    build: Callable[[], bytes]
    sync_count: int = 0
    last: bytes | None = field(default=None)
    inhibit_s: float = 0.0  # event TPDOs: at least this long between two transmissions (0x18xx:03)
    event_timer_s: float = 0.0  # event TPDOs: sent at least this often, changed or not (0x18xx:05)
    start_value: int = 0  # synchronous TPDOs with a SYNC counter: first sent at this counter (0x18xx:06)
    started: bool = True
    sent_at: float | None = None
    pending: bool = False  # changed during the inhibit time: sent when it ends


def _builder(packer: struct.Struct, getters: tuple[Callable[[], int], ...]) -> Callable[[], bytes]:
    """payload = packer.pack(getter values), unrolled for the usual 1-3 entries (per-SYNC hot path)."""
    pack = packer.pack
    if len(getters) == 1:
        (g0,) = getters
        return lambda: pack(g0())
    if len(getters) == 2:
        g0, g1 = getters
        return lambda: pack(g0(), g1())
    if len(getters) == 3:
        g0, g1, g2 = getters
        return lambda: pack(g0(), g1(), g2())
    return lambda: pack(*[g() for g in getters])


def _first_violation(
    values: Callable[[int], float], ticks: int, limit: float, candidates: Iterable[int]
) -> int:
    """First tick k in 1..ticks with |values(k)| > limit, or 0. `candidates` contain the maximiser."""
    if max(abs(values(k)) for k in candidates) <= limit:
        return 0
    for k in range(1, ticks + 1):
        if abs(values(k)) > limit:
            return k
    return 0  # pragma: no cover - the candidates found one


class DriveDevice:
    """One simulated drive of some family (a subclass). See the module docstring."""

    # ---- what a family sets
    family = "cia402"
    supported_modes: frozenset[int] = frozenset({0})
    interpolation_mode = 7  # the mode whose interpolation the family implements
    not_stored: frozenset[tuple[int, int]] = frozenset()
    default_profile: DriveProfile = EPOS_IPM  # the family's profile (bus/families.py)
    quick_stop_options: frozenset[int] = QUICK_STOP_OPTIONS  # 0x605A values the drive accepts (5.. stay in QS)
    rtr_tpdo_types: frozenset[int] = frozenset()  # RTR-only TPDO types accepted (never sent: no RTR here)
    accepts_longer_rpdo = False  # an RPDO longer than its mapping: use its first bytes (else EMCY 0x8220)
    homing_methods: frozenset[int] = frozenset()  # 0x6098 values it performs (planner.config.HOMING_METHODS)

    def __init__(
        self,
        node_id: int,
        axis: AxisConfig | None = None,
        settings: DriveSettings | None = None,
        *,
        counts_per_rev: int | None = None,
        motor: MotorParams = DEFAULT_MOTOR,
        initial_position: float = 0.0,
        sync_gap_factor: float = 1.5,
        profile: DriveProfile | None = None,
        options: SimDriveOptions | None = None,
        receive_slack_s: float = 0.0,
    ):
        if not 1 <= node_id <= 127:
            raise ValueError(f"node id must be 1..127, got {node_id}")
        if axis is not None and axis.node_id != node_id:
            raise ValueError(f"axis {axis.name!r} has node id {axis.node_id}, not {node_id}")
        if not (math.isfinite(sync_gap_factor) and sync_gap_factor > 1.0):
            raise ValueError(f"sync_gap_factor must be > 1, got {sync_gap_factor}")
        self.node_id = node_id
        self.axis = axis
        self.settings = settings or DriveSettings()
        self.profile = profile if profile is not None else self.default_profile
        self.objects: odm.ObjectTable = self._object_table()
        self.motor = motor
        self.counts_per_rev = int(counts_per_rev or (axis.counts_per_rev if axis else 8192))
        self.sync_gap_factor = float(sync_gap_factor)
        # a SYNC or heartbeat that does not come is noticed by the timer this much after its deadline (the
        # real-time adapter's own receive delay, so that a frame on the bus in time but not yet handed to the
        # model is not taken for a lost one); a SYNC that comes late is judged by its time stamp at once
        self.receive_slack_s = float(receive_slack_s)
        # the reading of every point the manuals leave open (planner/readings.py, docs/drive-model.md)
        self.options = o = options if options is not None else (axis.sim if axis is not None else SimDriveOptions())
        self._sample_before = o.tpdo_sampling == "before_rpdo"
        self._count_started = o.fifo_count == "until_segment_start"
        self._first_is_origin = o.first_record == "time_zero"
        self._toward_zero = o.rounding == "toward_zero"
        self._round = hermite.truncate_counts if self._toward_zero else hermite.round_counts
        self._tick_underflow = o.underflow_check == "every_tick"
        self._clock = MotionClock(o.clock_drift_ppm) if o.clock == "own" else None
        self._tpdo_latency_s = o.tpdo_latency_ms / 1000.0
        self._tpdo_jitter_s = o.tpdo_jitter_ms / 1000.0
        self._latency_rng = random.Random(o.seed * 1000 + node_id)
        self._held: list[tuple[float, Frame]] = []  # TPDOs answering a SYNC, sent after the latency
        self._absent = frozenset(o.absent)
        self._stored: dict[Key, int] = {}  # 0x1010 "save": survives NMT reset node
        self._c = LoopConstants.build(motor, self.counts_per_rev)
        self._rpm_to_cpms = self.counts_per_rev / hermite.MS_PER_MINUTE
        self.counters = DriveCounters()
        self.fault_log: list[FaultRecord] = []
        self.disturbance_current_a = 0.0  # external load, as motor current (tests: a blocked axis)
        # homing (bus/sim/homing.py): the switches in the machine's frame, counts
        cpu = axis.counts_per_unit if axis is not None else 1.0
        self.inputs = hm.Inputs.of(o.home_switch, o.limit_switches, cpu)
        travel = o.homing_travel or ((axis.position_max - axis.position_min) if axis is not None else 0.0)
        self._homing_travel = travel * cpu if travel > 0.0 else float(self.counts_per_rev) * 1000.0
        self._home_shift = 0  # reported position - machine position, counts
        self.referenced = False
        self._hm_state = "idle"  # idle, running, attained, error, interrupted
        self._hm_phases: list[hm.Phase] = []
        self._hm_phase: hm.Phase | None = None
        self._hm_stage = ""  # search, return, failing, stopping
        self._hm_outcome = ""
        self._hm_v = 0.0  # counts/ms at the end of the current source
        self._hm_speeds = (0.0, 0.0, 0.0)  # search, zero (counts/ms), acceleration (counts/ms^2)
        self._hm_edge = 0
        self.homing_error_reason = ""
        # the family's data recorder (None: it has none; EPOS sets it at each reset) and the plant's sub-step
        # while it samples finer than the 1 ms tick: (plant constants, sub-steps per tick, units per sub-step)
        self.recorder: DataRecorder | None = None
        self._fine: tuple[tuple[float, float, float, float], int, int] | None = None
        # plant and controller state
        self._pos = float(initial_position)
        self._vel = 0.0
        self._integ = 0.0
        self._dterm = 0.0
        self._eprev = 0.0
        self._current = 0.0
        self._demand = hermite.round_counts(self._pos)
        self._powered = False
        self._fe_tripped = False
        # demand source
        self._src: list[int] | None = None
        self._src_i = 0
        self._src_kind = Source.SEGMENT
        self._next_event = 0
        self._seg_events: list[tuple[int, int]] = []
        self._seg_coeffs = (0.0, 0.0, 0.0, 0.0)
        self._ramp_v0 = 0.0
        self._ramp_dec = 0.0
        # drive state
        self._nmt = NmtState.BOOTUP  # = not powered yet
        self._state = ST.NOT_READY_TO_SWITCH_ON
        self._cw = 0
        self._ip_active = False
        self._error_code = 0
        self._error_register = 0
        self._pending_sync: dict[int, list[tuple[Key, int, int]]] = {}
        self._od: dict[Key, int] = {}
        self._rx_by_cob: dict[int, _RxPdo] = {}
        self._tx_sync: list[_TxPdo] = []
        self._tx_event: list[_TxPdo] = []
        self.pdo_config_version = 0
        # timers
        self._t_now = 0.0
        self._t_last_sync: float | None = None
        self._tick_acc_us = 0
        self._hb_next: float | None = None
        self._hb_rx_last: float | None = None
        self._out: list[Frame] = []
        self._dynamic: dict[Key, Callable[[], int]] = {
            (0x1001, 0): lambda: self._error_register,
            (0x603F, 0): lambda: self._error_code,
            (0x6041, 0): self._get_statusword,
            (0x6061, 0): lambda: self._mode,
            (0x6062, 0): lambda: self._demand,
            (0x6064, 0): self._get_position_actual,
            (0x606C, 0): lambda: self.velocity_actual_rpm_int,
            (0x6078, 0): lambda: max(-32768, min(32767, round(self._current * 1000.0))),
            (0x60F4, 0): lambda: self._demand - self._get_position_actual(),
            (0x6040, 0): lambda: self._cw,
            **self._family_dynamic(),
        }
        self._handlers: dict[Key, Callable[[int], None]] = {**self._build_handlers(), **self._family_handlers()}
        self._reset_application(first=True)

    # ============================================================================================
    # public entry points

    def power_on(self, t: float) -> list[Frame]:
        """Boot: send the boot-up message and enter NMT pre-operational."""
        self._t_now = t
        self._out = []
        if self._nmt == NmtState.BOOTUP:
            self._boot(t)
        return self._out

    def on_frame(self, cob_id: int, data: bytes, t: float) -> list[Frame]:
        """A frame seen on the bus. Returns the frames the drive sends in response."""
        self._t_now = t
        self._out = []
        if self._nmt == NmtState.BOOTUP:
            return self._out
        self._release_held(t)
        self._catch_up(t)
        if cob_id == 0:
            self._on_nmt(data, t)
        elif cob_id == self._sync_cob:
            self._sync(t, data)
        elif cob_id in self._rx_by_cob:
            if self._nmt == NmtState.OPERATIONAL:
                self._on_rpdo(self._rx_by_cob[cob_id], bytes(data), t)
        elif cob_id == self._hb_consumer_cob and len(data) >= 1:
            self._hb_rx_last = t
        elif cob_id == self._ts_cob and self._clock is not None and len(data) >= 4:
            self._clock.time_stamp(int.from_bytes(bytes(data[:4]), "little"))  # 0x1013 as a TIME frame
        self._flush_event_tpdos()
        return self._out

    def on_sync(self, t: float, data: bytes = b"") -> list[Frame]:
        """A SYNC: run the period's ticks, apply synchronous RPDOs, send synchronous TPDOs."""
        self._t_now = t
        self._out = []
        if self._nmt != NmtState.BOOTUP:
            self._release_held(t)
            self._catch_up(t)
            self._sync(t, data)
            self._flush_event_tpdos()
        return self._out

    def advance(self, t: float) -> list[Frame]:
        """Timers up to time `t`: heartbeat producer, SYNC loss, heartbeat consumer, the own clock's
        ticks, TPDOs held for their latency, event TPDO timers."""
        self._t_now = t
        self._out = []
        if self._nmt == NmtState.BOOTUP:
            return self._out
        self._release_held(t)
        self._catch_up(t)
        if self._hb_next is not None and t >= self._hb_next:
            self._out.append(codec.heartbeat_frame(self.node_id, self._nmt))
            period = self._od[(0x1017, 0)] / 1000.0
            self._hb_next += period
            if self._hb_next <= t:
                self._hb_next = t + period
        sync_deadline = self._sync_deadline()
        if sync_deadline is not None and t > sync_deadline + self.receive_slack_s:
            self.counters.sync_gaps += 1
            self._fault(codec.EMCY_SYNC_LOST, 0, t)
        hb_deadline = self._hb_consumer_deadline()
        if hb_deadline is not None and t > hb_deadline + self.receive_slack_s:
            self._hb_rx_last = None
            self._fault(codec.EMCY_HEARTBEAT, 0, t)
        self._flush_event_tpdos()
        return self._out

    def next_deadline(self) -> float | None:
        """The earliest time `advance` has something to do, or None."""
        if self._nmt == NmtState.BOOTUP:
            return None
        slack = self.receive_slack_s
        sync_deadline, hb_deadline = self._sync_deadline(), self._hb_consumer_deadline()
        candidates = (self._hb_next, None if sync_deadline is None else sync_deadline + slack,
                      None if hb_deadline is None else hb_deadline + slack,
                      self._held[0][0] if self._held else None, self._clock_deadline(), self._event_deadline())
        times = [x for x in candidates if x is not None]
        return min(times) if times else None

    def _spec(self, index: int, sub: int) -> odm.ObjectSpec:
        if index in self._absent:
            raise SdoAbort(odm.ABORT_NO_OBJECT, f"object 0x{index:04X} does not exist on this drive")
        return self.objects.spec(index, sub)

    def has_object(self, index: int) -> bool:
        return index not in self._absent and index in self.objects.indices

    def sdo_read(self, index: int, sub: int) -> int:
        """SDO upload of an integer object (raises SdoAbort like the drive's SDO server)."""
        s = self._spec(index, sub)
        if not s.readable:
            raise SdoAbort(odm.ABORT_WRITE_ONLY, f"0x{index:04X}:{sub:02X} is write-only")
        if s.dtype == odm.DataType.VISIBLE_STRING:
            raise SdoAbort(odm.ABORT_UNSUPPORTED_ACCESS,
                           f"0x{index:04X}:{sub:02X} is a string (served by the EDS)")
        if s.dtype == odm.DataType.DOMAIN:
            raise SdoAbort(odm.ABORT_UNSUPPORTED_ACCESS,
                           f"0x{index:04X}:{sub:02X} is a domain (read it with read_domain)")
        getter = self._dynamic.get((index, sub))
        return getter() if getter is not None else self._od[(index, sub)]

    def sdo_write(self, index: int, sub: int, value: int, t: float | None = None) -> list[Frame]:
        """SDO download of an integer object: access, range and device-state checks, then its effect.
        Raises SdoAbort with the CiA 301 code the drive would answer with."""
        if t is not None:
            self._t_now = t
        s = self._spec(index, sub)
        if not s.writable:
            raise SdoAbort(odm.ABORT_READ_ONLY, f"0x{index:04X}:{sub:02X} is read-only")
        if isinstance(value, bool) or not isinstance(value, int):
            raise SdoAbort(odm.ABORT_TYPE_LENGTH, f"0x{index:04X}:{sub:02X} takes an integer, got {value!r}")
        odm.check_value(s, value)
        self._out = []
        self._write(s.key, value, via_sdo=True)
        self._flush_event_tpdos()
        return self._out

    def configure(
        self,
        sync_period_ms: int,
        axis: AxisConfig | None = None,
        settings: DriveSettings | None = None,
        *,
        start: bool = True,
        t: float | None = None,
        feedback: FeedbackSchedule | None = None,
        time_stamp: bool = False,
        slot: SetpointSlot | None = None,
    ) -> list[Frame]:
        """Apply the very writes the master sends over SDO (`profile.configuration`), then NMT start.
        `slot`: a cyclic axis' set point slot (bus.families.setpoint_slots of the cell).

        For virtual-time runtimes that bypass SDO. Boots the drive first if it was not powered on. Like
        the master, it skips the optional objects the drive lacks and refuses a missing essential one.
        """
        axis = axis or self.axis
        if axis is None:
            raise ValueError("configure needs an AxisConfig (constructor or argument)")
        settings = settings or self.settings
        if t is not None:
            self._t_now = t
        out: list[Frame] = []
        if self._nmt == NmtState.BOOTUP:
            out += self.power_on(self._t_now)
        for w in self.profile.configuration(axis, settings, sync_period_ms, feedback=feedback,
                                            time_stamp=time_stamp, slot=slot):
            if not self.has_object(w.index):
                if w.essential:
                    raise SdoAbort(odm.ABORT_NO_OBJECT, f"0x{w.index:04X} ({w.what}) is missing")
                continue  # what the master does: configure what the drive has
            out += self.sdo_write(w.index, w.sub, w.value)
        if start:
            out += self.on_frame(0, bytes((NmtCommand.START, self.node_id)), self._t_now)
        return out

    # ---- introspection ---------------------------------------------------------------------------
    @property
    def state(self) -> Cia402State:
        return self._state

    @property
    def nmt_state(self) -> NmtState:
        return self._nmt

    @property
    def controlword(self) -> int:
        return self._cw

    @property
    def mode(self) -> int:
        return self._mode

    @property
    def ip_active(self) -> bool:
        return self._ip_active

    @property
    def position_demand(self) -> int:
        return self._demand

    @property
    def position_actual(self) -> int:
        return self._get_position_actual()

    @property
    def position_actual_exact(self) -> float:
        return self._pos

    @property
    def velocity_actual_rpm(self) -> float:
        return self._vel / self._rpm_to_cpms

    @property
    def velocity_actual_rpm_int(self) -> int:
        return round(self._vel / self._rpm_to_cpms)

    @property
    def demand_velocity_rpm(self) -> float:
        return self._demand_velocity() / self._rpm_to_cpms

    @property
    def current_a(self) -> float:
        return self._current

    @property
    def following_error(self) -> int:
        return self._demand - self.position_actual

    @property
    def error_code(self) -> int:
        return self._error_code

    @property
    def drive_time_ms(self) -> int:
        return self.counters.ticks

    @property
    def sync_cob_id(self) -> int:
        return self._sync_cob

    @property
    def clock(self) -> MotionClock | None:
        """The drive's own motion clock (None: locked to SYNC)."""
        return self._clock

    @property
    def statusword(self) -> int:
        return self._get_statusword()

    @property
    def ready_for_job(self) -> bool:
        """Operation enabled and whatever else the family needs before a job (EPOS: the buffer enabled)."""
        return self._state == ST.OPERATION_ENABLED

    def _get_position_actual(self) -> int:
        x = self._pos
        return math.floor(x + 0.5) if x >= 0 else -math.floor(-x + 0.5)

    def _get_statusword(self) -> int:
        sw = self._state.statusword_bits | codec.SW_REMOTE
        if self._powered:
            sw |= codec.SW_VOLTAGE_ENABLED
        if self._ip_active:
            sw |= codec.SW_IP_ACTIVE
        if self._target_reached():
            sw |= codec.SW_TARGET_REACHED
        return sw | self._homing_status()

    def rx_cob_ids(self) -> frozenset[int]:
        """COB-IDs this drive consumes (NMT, SYNC, enabled RPDOs, monitored heartbeat, time stamp)."""
        ids = {0, self._sync_cob, *self._rx_by_cob}
        if self._hb_consumer_cob:
            ids.add(self._hb_consumer_cob)
        if self._ts_cob:
            ids.add(self._ts_cob)
        return frozenset(ids)

    # ============================================================================================
    # NMT and resets

    def _boot(self, t: float) -> None:
        if self._sends_bootup():
            self._out.append(codec.heartbeat_frame(self.node_id, NmtState.BOOTUP))
        self._nmt = NmtState.PRE_OPERATIONAL
        self._restart_heartbeat(t)

    def _on_nmt(self, data: bytes, t: float) -> None:
        try:
            command, node = codec.decode_nmt(data)
        except ProtocolError:
            return
        if node not in (0, self.node_id):
            return
        if command == NmtCommand.START:
            self._nmt = NmtState.OPERATIONAL
        elif command == NmtCommand.STOP:
            self._nmt = NmtState.STOPPED
        elif command == NmtCommand.ENTER_PRE_OPERATIONAL:
            self._nmt = NmtState.PRE_OPERATIONAL
        elif command == NmtCommand.RESET_NODE:
            self._reset_application()
            self._boot(t)
        elif command == NmtCommand.RESET_COMMUNICATION:
            self._reset_communication()
            self._boot(t)
        for p in self._tx_event:
            p.last = None  # an event TPDO is sent again once operational

    def _reset_application(self, first: bool = False) -> None:
        """Power-on / NMT reset node: every object to its default (or to what 0x1010 stored), the drive to
        switch on disabled."""
        self._od = self.objects.defaults(self.node_id)
        self._od.update(self._stored)
        self._reset_family()
        self.referenced = False  # seed 003 0x3218: "it is cleared when drive is switched on"
        self._hm_state = "idle"
        self._ip_active = False
        self._error_code = 0
        self._error_register = 0
        self._cw = 0
        self._pending_sync.clear()
        self._power_off()
        self._state = ST.NOT_READY_TO_SWITCH_ON
        self._state = codec.next_state(self._state, Internal.INIT_DONE)
        self._t_last_sync = None
        self._tick_acc_us = 0
        self._hb_rx_last = None
        self._refresh_caches()
        self._rebuild_pdos()
        if not first:
            self._nmt = NmtState.BOOTUP

    def _reset_communication(self) -> None:
        defaults = self.objects.defaults(self.node_id)
        for key, value in defaults.items():
            if 0x1000 <= key[0] < 0x2000:
                self._od[key] = value
        for key, value in self._stored.items():
            if 0x1000 <= key[0] < 0x2000:
                self._od[key] = value
        self._pending_sync.clear()
        self._t_last_sync = None
        self._hb_rx_last = None
        self._refresh_caches()
        self._rebuild_pdos()
        self._nmt = NmtState.BOOTUP

    def _restart_heartbeat(self, t: float) -> None:
        period_ms = self._od[(0x1017, 0)]
        self._hb_next = t + period_ms / 1000.0 if period_ms else None

    def _sync_deadline(self) -> float | None:
        if not self._ip_active or not self._period_us or self._t_last_sync is None:
            return None
        return self._t_last_sync + self.sync_gap_factor * self._period_us * 1e-6

    def _hb_consumer_deadline(self) -> float | None:
        if not self._hb_consumer_cob or self._hb_rx_last is None:
            return None
        return self._hb_rx_last + self._hb_consumer_timeout_s

    # ============================================================================================
    # object dictionary writes

    def _refresh_caches(self) -> None:
        od = self._od
        few = od[(0x6065, 0)]
        self._fe_window = math.inf if few == 0xFFFFFFFF else float(few)
        pw = od[(0x6067, 0)]
        self._pos_window = math.inf if pw == 0xFFFFFFFF else float(pw)
        self._mode = od[(0x6060, 0)]
        self._period_us = od[(0x1006, 0)] if 0x1006 not in self._absent else 0
        self._sync_cob = od[(0x1005, 0)] & 0x7FF
        # a family's table may lack the CiA 301 v4.2 objects (0x1012, 0x1013, 0x1019): as if absent
        ts = od.get((0x1012, 0), 0)
        has_ts = 0x1012 not in self._absent and 0x1013 not in self._absent
        self._ts_cob = ts & 0x7FF if has_ts and ts & (1 << 31) else 0
        self._sync_counter_max = od.get((0x1019, 0), 0) if 0x1019 not in self._absent else 0
        self._qs_dec_key: Key = (0x6085, 0) if 0x6085 not in self._absent else (0x6084, 0)
        self._emcy_cob = od[(0x1014, 0)]
        hb = od[(0x1016, 1)]
        hb_node = (hb >> 16) & 0x7F
        hb_ms = hb & 0xFFFF
        self._hb_consumer_cob = 0x700 + hb_node if hb_node and hb_ms else 0
        self._hb_consumer_timeout_s = hb_ms / 1000.0
        self._qs_option = od[(0x605A, 0)]
        self._v_limit_min = min(self._rpm_limit((0x6081, 0)), self._rpm_limit((0x607F, 0)))
        self._a_limit_min = min(self._acc_limit((0x6083, 0)), self._acc_limit((0x60C5, 0)))
        self._refresh_family(od)  # last: a family may rescale what was set above (its units)

    def _rpm_limit(self, key: Key) -> float:
        """A velocity object (rpm) as counts/ms (no limit when the drive lacks the object)."""
        if key[0] in self._absent or key not in self._od:
            return math.inf
        return self._od[key] * self._rpm_to_cpms

    def _acc_limit(self, key: Key) -> float:
        """An acceleration object (rpm/s) as counts/ms^2 (no limit when the drive lacks the object)."""
        if key[0] in self._absent or key not in self._od:
            return math.inf
        return self._od[key] * self._rpm_to_cpms / 1000.0

    def _write(self, key: Key, value: int, via_sdo: bool) -> None:
        handler = self._handlers.get(key)
        if handler is not None:
            self._check_write(key, via_sdo)
            handler(value)
        else:
            self._od[key] = value
            self._refresh_caches()

    def _build_handlers(self) -> dict[Key, Callable[[int], None]]:
        h: dict[Key, Callable[[int], None]] = {
            (0x6040, 0): self._apply_controlword,
            (0x6060, 0): self._write_mode,
            (0x1017, 0): self._write_heartbeat_producer,
            (0x1005, 0): self._write_sync_cob,
            (0x605A, 0): self._write_quick_stop_option,
            (0x1016, 1): self._write_heartbeat_consumer,
            (0x1010, 1): self._write_store,
            (0x1011, 1): self._write_restore,
            (0x1013, 0): self._write_time_stamp,
        }
        for n in range(4):
            for base, direction in ((0x1400, "rx"), (0x1800, "tx")):
                h[(base + n, 1)] = self._pdo_cob_writer(base + n)
                h[(base + n, 2)] = self._pdo_type_writer(base + n, direction)
            for sub in (3, 5):  # inhibit time, event timer: the running TPDO takes them at once
                if (0x1800 + n, sub) in self.objects.objects:
                    h[(0x1800 + n, sub)] = self._tpdo_timing_writer(0x1800 + n, sub)
            for base, direction in ((0x1600, "rx"), (0x1A00, "tx")):
                comm = (0x1400 if direction == "rx" else 0x1800) + n
                h[(base + n, 0)] = self._pdo_count_writer(base + n, comm, direction)
                for k in range(1, odm.MAX_PDO_ENTRIES + 1):
                    h[(base + n, k)] = self._pdo_entry_writer(base + n, k, comm, direction)
        return h

    def _store(self, key: Key, value: int) -> None:
        self._od[key] = value
        self._refresh_caches()

    def _write_mode(self, value: int) -> None:
        if value not in self.supported_modes:
            raise SdoAbort(odm.ABORT_INVALID_VALUE, f"mode of operation {value} is not supported (0x6502)")
        old = self._mode
        if old == hm.HOMING_MODE and value != old:
            self._homing_abort()
        self._store((0x6060, 0), value)
        if value != old:
            self._mode_changed(old, value)
        if old == self.interpolation_mode and value != old:
            self._stop_interpolation()  # the demand holds where it is (seed 000 table 4-26 II)

    def _write_heartbeat_producer(self, value: int) -> None:
        self._store((0x1017, 0), value)
        self._restart_heartbeat(self._t_now)

    def _write_heartbeat_consumer(self, value: int) -> None:
        self._store((0x1016, 1), value)
        self._hb_rx_last = None

    def _write_sync_cob(self, value: int) -> None:
        if value & (1 << 30):
            raise SdoAbort(odm.ABORT_INVALID_VALUE, "the drive cannot produce SYNC (0x1005 bit 30)")
        if value & (1 << 29):
            raise SdoAbort(odm.ABORT_INVALID_VALUE, "29-bit COB-IDs are not supported")
        self._store((0x1005, 0), value)

    def _write_store(self, value: int) -> None:
        if value != SAVE_SIGNATURE:
            raise SdoAbort(odm.ABORT_CANNOT_STORE, f"0x1010:01 needs the signature \"save\" (0x{SAVE_SIGNATURE:08X}), "
                           f"got 0x{value:08X}")
        self._stored = {k: v for k, v in self._od.items()
                        if k not in _NOT_STORED and k not in self.not_stored and self.objects.objects[k].writable}

    def _write_restore(self, value: int) -> None:
        if value != LOAD_SIGNATURE:
            raise SdoAbort(odm.ABORT_CANNOT_STORE, f"0x1011:01 needs the signature \"load\" (0x{LOAD_SIGNATURE:08X}), "
                           f"got 0x{value:08X}")
        self._stored = {}  # defaults again from the next reset node / power-on (CiA 301)

    def _write_time_stamp(self, value: int) -> None:
        self._od[(0x1013, 0)] = value
        if self._clock is not None:
            self._clock.time_stamp(value)

    def _write_quick_stop_option(self, value: int) -> None:
        if value not in self.quick_stop_options:
            raise SdoAbort(odm.ABORT_INVALID_VALUE, f"quick stop option code {value} not supported")
        self._store((0x605A, 0), value)

    # ---- PDO configuration (CiA 301 7.5.2.35-38)
    def _pdo_cob_writer(self, comm: int) -> Callable[[int], None]:
        def write(value: int) -> None:
            old = self._od[(comm, 1)]
            if value & (1 << 29):
                raise SdoAbort(odm.ABORT_INVALID_VALUE, "29-bit COB-IDs are not supported")
            if not old & odm.PDO_DISABLED and not value & odm.PDO_DISABLED and (old ^ value) & 0x7FF:
                raise SdoAbort(odm.ABORT_INVALID_VALUE,
                               f"0x{comm:04X}:01 cannot change the COB-ID of a valid PDO")
            self._od[(comm, 1)] = value
            self._rebuild_pdos()

        return write

    def _pdo_type_writer(self, comm: int, direction: str) -> Callable[[int], None]:
        def write(value: int) -> None:
            rtr = direction == "tx" and value in self.rtr_tpdo_types
            if not (value <= 240 or value in (254, 255) or rtr):
                raise SdoAbort(odm.ABORT_INVALID_VALUE,
                               f"{direction}PDO transmission type {value} not supported")
            self._od[(comm, 2)] = value
            self._rebuild_pdos()

        return write

    def _tpdo_timing_writer(self, comm: int, sub: int) -> Callable[[int], None]:
        """0x18xx:03 (inhibit time, 100 us) and 0x18xx:05 (event timer, ms): stored and applied to the TPDO
        as it runs, keeping when it was last sent (CiA 301 lets a master change the event timer of a valid
        PDO; a rebuild would only pick it up at the next remapping)."""
        number = comm - 0x1800 + 1

        def write(value: int) -> None:
            self._od[(comm, sub)] = value
            for p in (*self._tx_event, *self._tx_sync):
                if p.number == number:
                    if sub == 5:
                        p.event_timer_s = value * 1e-3
                    else:
                        p.inhibit_s = value * 1e-4

        return write

    def _check_mapping_editable(self, mapping: int, comm: int) -> None:
        if not self._od[(comm, 1)] & odm.PDO_DISABLED:
            raise SdoAbort(odm.ABORT_PARAMETER_INCOMPATIBLE,
                           f"0x{mapping:04X}: set 0x{comm:04X}:01 bit 31 (PDO invalid) before remapping")

    def _check_entry(self, word: int, direction: str) -> int:
        if word == 0:
            return 0
        index, sub, bits = word >> 16, (word >> 8) & 0xFF, word & 0xFF
        s = self.objects.objects.get((index, sub))
        if s is None or index in self._absent or not s.pdo or (
                bits != s.dtype.bits and not self._may_map_short((index, sub), bits, direction)):
            raise SdoAbort(odm.ABORT_CANNOT_MAP, f"0x{index:04X}:{sub:02X} ({bits} bits) cannot be mapped")
        if (direction == "rx" and not s.writable) or (direction == "tx" and not s.readable):
            raise SdoAbort(odm.ABORT_CANNOT_MAP,
                           f"0x{index:04X}:{sub:02X} cannot be mapped into a {direction}PDO")
        return bits

    def _pdo_count_writer(self, mapping: int, comm: int, direction: str) -> Callable[[int], None]:
        def write(value: int) -> None:
            self._check_mapping_editable(mapping, comm)
            total = 0
            for k in range(1, value + 1):
                word = self._od[(mapping, k)]
                if word == 0:
                    raise SdoAbort(odm.ABORT_CANNOT_MAP, f"0x{mapping:04X}:{k:02X} is empty")
                total += self._check_entry(word, direction)
            if total > 64:
                raise SdoAbort(odm.ABORT_PDO_LENGTH, f"0x{mapping:04X}: {total} bits exceed 64")
            self._od[(mapping, 0)] = value
            self._rebuild_pdos()

        return write

    def _pdo_entry_writer(self, mapping: int, k: int, comm: int, direction: str) -> Callable[[int], None]:
        def write(value: int) -> None:
            self._check_mapping_editable(mapping, comm)
            if self._od[(mapping, 0)] != 0:
                raise SdoAbort(odm.ABORT_PARAMETER_INCOMPATIBLE,
                               f"0x{mapping:04X}:00 must be 0 while entries are written")
            self._check_entry(value, direction)
            self._od[(mapping, k)] = value

        return write

    def _getter(self, key: Key) -> Callable[[], int]:
        dyn = self._dynamic.get(key)
        if dyn is not None:
            return dyn
        od = self._od
        return lambda: od[key]

    def _rebuild_pdos(self) -> None:
        od = self._od
        rx: dict[int, _RxPdo] = {}
        tx_sync: list[_TxPdo] = []
        tx_event: list[_TxPdo] = []
        for n in range(4):
            cob = od[(0x1400 + n, 1)]
            count = od[(0x1600 + n, 0)]
            if not cob & odm.PDO_DISABLED and count:
                words = [od[(0x1600 + n, k)] for k in range(1, count + 1)]
                keys = tuple((w >> 16, (w >> 8) & 0xFF) for w in words)
                bits = tuple(w & 0xFF for w in words)
                fmt = "<" + "".join(self._entry_code(k, b) for k, b in zip(keys, bits, strict=True))
                st = struct.Struct(fmt)
                short = any(b != self.objects.objects[k].dtype.bits for k, b in zip(keys, bits, strict=True))
                rx[cob & 0x7FF] = _RxPdo(n + 1, cob & 0x7FF, od[(0x1400 + n, 2)] <= 240, st.size, keys, st,
                                         self._is_record_pdo(keys), bits, short)
            cob = od[(0x1800 + n, 1)]
            count = od[(0x1A00 + n, 0)]
            if not cob & odm.PDO_DISABLED and count:
                words = [od[(0x1A00 + n, k)] for k in range(1, count + 1)]
                keys = tuple((w >> 16, (w >> 8) & 0xFF) for w in words)
                fmt = "<" + "".join(self._struct_code(k) for k in keys)
                ttype = od[(0x1800 + n, 2)]
                if ttype in (252, 253):
                    continue  # RTR only: this simulation serves no remote requests, so it is never sent
                # a family's table may lack the optional sub-indices 3/5/6 (seed 003: TPDO parameters 1-2)
                pdo = _TxPdo(n + 1, cob & 0x7FF, ttype,
                             _builder(struct.Struct(fmt), tuple(self._getter(k) for k in keys)),
                             inhibit_s=od.get((0x1800 + n, 3), 0) * 1e-4,
                             event_timer_s=od.get((0x1800 + n, 5), 0) * 1e-3,
                             start_value=od.get((0x1800 + n, 6), 0))
                pdo.started = not (pdo.start_value and self._sync_counter_max)
                (tx_sync if ttype <= 240 else tx_event).append(pdo)
        self._rx_by_cob = rx
        self._tx_sync = tx_sync
        self._tx_event = tx_event
        self.pdo_config_version += 1

    # ============================================================================================
    # PDO traffic

    def _on_rpdo(self, pdo: _RxPdo, data: bytes, t: float) -> None:
        if len(data) != pdo.length:
            if len(data) > pdo.length and self.accepts_longer_rpdo:
                data = data[:pdo.length]
            else:
                self.counters.pdo_length_errors += 1
                code = codec.EMCY_PDO_LENGTH if len(data) < pdo.length else codec.EMCY_PDO_LENGTH_EXCEEDED
                self._fault(code, 0, t)
                return
        if pdo.is_record and not pdo.synchronous:
            self._on_record(data)
            return
        values = pdo.unpacker.unpack(data)
        # dummy entries (index < 0x1000, CiA 301 dummy mapping) only hold the place of other data
        pairs = [(k, v, b) for k, v, b in zip(pdo.keys, values, pdo.bits, strict=True) if k[0] >= 0x1000]
        self._rpdo_received(pdo.keys, t)
        if pdo.synchronous:
            self._pending_sync[pdo.number] = pairs
        else:
            self._apply_pdo_pairs(pairs)

    def _apply_pdo_pairs(self, pairs: list[tuple[Key, int, int]]) -> None:
        objects = self.objects.objects
        for key, value, bits in pairs:
            try:
                spec = objects[key]
                if bits != spec.dtype.bits:
                    value = self._widen(key, value, bits)
                odm.check_value(spec, value)
                self._write(key, value, via_sdo=False)
            except SdoAbort:
                self.counters.pdo_writes_rejected += 1

    def _sample_sync_tpdos(self, counter: int | None) -> list[Frame]:
        """The synchronous TPDOs due at this SYNC, sampled now (CiA 301: type n = every n-th SYNC; with a
        SYNC counter and a start value, first at the SYNC whose counter equals the start value)."""
        out: list[Frame] = []
        for p in self._tx_sync:
            if not p.started:
                if counter is None or counter != p.start_value:
                    continue
                p.started = True
                p.sync_count = p.trans_type - 1
            p.sync_count += 1
            if p.trans_type == 0:
                payload = p.build()
                if payload != p.last:
                    p.last = payload
                    out.append(Frame(p.cob_id, payload))
            elif p.sync_count >= p.trans_type:
                p.sync_count = 0
                out.append(Frame(p.cob_id, p.build()))
        return out

    def _send_sync_tpdos(self, frames: list[Frame], t: float) -> None:
        """Now, or after this SYNC's latency draw (the `tpdo_latency_ms` option, plus the `tpdo_jitter_ms`
        draw; all of a SYNC's TPDOs go together, in PDO order, never before the previous SYNC's)."""
        if not frames:
            return
        if self._tpdo_latency_s <= 0.0 and self._tpdo_jitter_s <= 0.0:
            self._out.extend(frames)
            return
        at = t + self._latency_rng.uniform(0.0, self._tpdo_latency_s)
        if self._tpdo_jitter_s > 0.0:
            at += self._latency_rng.uniform(0.0, self._tpdo_jitter_s)
        # in order: a SYNC's answers never overtake the previous SYNC's (a later draw waits behind them)
        if self._held:
            at = max(at, self._held[-1][0])
        self._held.extend((at, f) for f in frames)

    def _release_held(self, t: float) -> None:
        """TPDOs whose latency ran out by t go out (in order), before anything the drive does at t."""
        held = self._held
        while held and held[0][0] <= t:
            self._out.append(held.pop(0)[1])

    def _flush_event_tpdos(self) -> None:
        """Event-driven TPDOs (types 254/255): sent when their payload changed, no sooner than the inhibit
        time after the previous one (a change inside it is sent when it ends), and at least every event
        timer period (CiA 301 0x18xx:03 / 0x18xx:05)."""
        if not self._tx_event or self._nmt != NmtState.OPERATIONAL:
            return
        t = self._t_now
        for p in self._tx_event:
            payload = p.build()
            changed = payload != p.last
            timer_due = p.event_timer_s > 0.0 and p.sent_at is not None and t >= p.sent_at + p.event_timer_s
            if not (changed or timer_due or p.pending):
                continue
            if p.sent_at is not None and t < p.sent_at + p.inhibit_s - 1e-9:
                p.pending = True
                continue
            p.last = payload
            p.sent_at = t
            p.pending = False
            self._out.append(Frame(p.cob_id, payload))

    def _event_deadline(self) -> float | None:
        if self._nmt != NmtState.OPERATIONAL:
            return None
        times: list[float] = []
        for p in self._tx_event:
            if p.sent_at is None:
                continue
            if p.pending:
                times.append(p.sent_at + p.inhibit_s)
            if p.event_timer_s > 0.0:
                times.append(p.sent_at + p.event_timer_s)
        return min(times) if times else None

    # ============================================================================================
    # SYNC: the drive clock

    def _sync(self, t: float, data: bytes = b"") -> None:
        self.counters.syncs += 1
        last = self._t_last_sync
        period_us = self._period_us
        if last is not None:
            if period_us and self._ip_active and t - last > self.sync_gap_factor * period_us * 1e-6:
                self.counters.sync_gaps += 1
                self._fault(codec.EMCY_SYNC_LOST, 0, t)
            self._tick_acc_us += period_us if period_us else max(0, round((t - last) * 1e6))
        else:
            self._tick_acc_us += period_us
        self._t_last_sync = t
        n, self._tick_acc_us = divmod(self._tick_acc_us, 1000)
        if self._clock is not None:
            self._clock.latch_sync(t)  # the own clock already ran to t (_catch_up); latch it for 0x1013
        elif n:
            self._run_ticks(n, t)
        counter = data[0] if self._sync_counter_max and len(data) >= 1 else None
        sampled = self._sample_sync_tpdos(counter) if self._sample_before else None
        if self._pending_sync:
            pending = self._pending_sync
            self._pending_sync = {}
            for number in sorted(pending):
                self._apply_pdo_pairs(pending[number])
        self._after_sync_rpdos(t)
        if self._nmt == NmtState.OPERATIONAL:
            self._send_sync_tpdos(sampled if sampled is not None else self._sample_sync_tpdos(counter), t)

    # ---- the own clock (option clock = "own"; bus/sim/clock.py)
    def _catch_up(self, t: float) -> None:
        """Run the ticks the own clock has due by t (a drive locked to SYNC ticks in `_sync` only)."""
        clock = self._clock
        if clock is None:
            return
        n = clock.due(t)
        if n:
            clock.done += n
            self._run_ticks(n, t)

    def _clock_deadline(self) -> float | None:
        """With an own clock, the time of the next tick at which the active source has an event
        (segment end, limit event), so underflows and pops happen at their tick, not at the next frame."""
        clock = self._clock
        if clock is None or self._src is None:
            return None
        return clock.time_of_tick(max(1, self._next_event - self._src_i))

    def _run_ticks(self, n: int, t: float) -> None:
        rec = self.recorder
        if rec is not None and rec.active:
            self._run_ticks_recorded(n, t)  # the data recorder samples: see "data recorder ticks" below
            return
        while n > 0:
            src = self._src
            if src is None:
                if self._powered:
                    done = self._integrate(itertools.repeat(self._demand, n))
                elif self._vel != 0.0:
                    done = self._coast(n)
                else:
                    self.counters.ticks += n
                    return
            else:
                i = self._src_i
                m = min(n, self._next_event - i)
                if m <= 0:
                    self._on_source_event(t)
                    continue
                done = self._integrate(src[i:i + m])
                self._src_i = i + done
            n -= done
            if self._fe_tripped:
                self._fe_tripped = False
                self._fault(codec.EMCY_FOLLOWING_ERROR, 0, t)
                continue
            if self._src is not None and self._src_i == self._next_event:
                self._on_source_event(t)

    def _integrate(self, demands: Iterable[int]) -> int:
        """Run one tick of position control + plant per demand. Stops after a tick whose following
        error exceeds 0x6065 (sets _fe_tripped). Returns the ticks run."""
        c = self._c
        kp, ki, kdf, kdg, imax = c.kp, c.ki, c.kd_f, c.kd_g, c.i_max
        cou, phi, gam, psi, eta = c.coulomb_a, c.phi, c.gam, c.psi, c.eta
        dist = self.disturbance_current_a
        pos, vel, integ, dterm, ep = self._pos, self._vel, self._integ, self._dterm, self._eprev
        few = self._fe_window if self._state is not ST.FAULT_REACTION_ACTIVE else math.inf
        i = self._current
        d = self._demand
        done = 0
        for d in demands:
            e = d - pos
            integ += ki * e
            if integ > imax:
                integ = imax
            elif integ < -imax:
                integ = -imax
            dterm = kdf * dterm + kdg * (e - ep)
            ep = e
            i = kp * e + integ + dterm
            if i > imax:
                i = imax
            elif i < -imax:
                i = -imax
            ie = i - dist
            if vel > 0.0:
                ie -= cou
            elif vel < 0.0:
                ie += cou
            elif ie > cou:
                ie -= cou
            elif ie < -cou:
                ie += cou
            else:
                ie = 0.0
            nv = phi * vel + gam * ie
            pos += psi * vel + eta * ie
            if cou and ((vel > 0.0 and nv < 0.0) or (vel < 0.0 and nv > 0.0)):
                nv = 0.0
            vel = nv
            done += 1
            if e > few or e < -few:
                self._fe_tripped = True
                break
        self._pos, self._vel, self._integ, self._dterm, self._eprev = pos, vel, integ, dterm, ep
        self._current = i
        self._demand = d
        self.counters.ticks += done
        return done

    def _coast(self, n: int) -> int:
        """Power stage off: the motor runs down on friction; the demand follows the actual position."""
        c = self._c
        cou, phi, gam, psi, eta = c.coulomb_a, c.phi, c.gam, c.psi, c.eta
        dist = self.disturbance_current_a
        pos, vel = self._pos, self._vel
        done = 0
        while done < n:
            ie = -dist - (cou if vel > 0.0 else -cou)
            nv = phi * vel + gam * ie
            pos += psi * vel + eta * ie
            done += 1
            if (vel > 0.0 and nv <= 0.0) or (vel < 0.0 and nv >= 0.0) or abs(nv) < COAST_STOP_COUNTS_PER_MS:
                vel = 0.0
                break
            vel = nv
        self._pos, self._vel = pos, vel
        self._current = 0.0
        self._demand = hermite.round_counts(pos)
        self.counters.ticks += done
        return done

    # ============================================================================================
    # data recorder ticks (seed 004; bus/sim/recorder.py, its objects in the family: bus/sim/epos.py): while
    # the recorder runs, `_run_ticks_recorded` cuts the ticks into chunks that end at sample instants; a
    # period that is not whole ticks sub-steps the plant, the position controller staying at 1 ms
    # (`_integrate_fine`, `_coast_fine`).

    def _recorder_read(self, index: int, sub: int) -> int:
        """A sampled variable's value now (the recorder checked it is a readable integer object)."""
        getter = self._dynamic.get((index, sub))
        return getter() if getter is not None else self._od[(index, sub)]

    def _prepare_recording(self, config: RecorderConfig) -> None:
        """The recorder is about to start with `config`: the plant keeps its 1 ms step when the sampling
        period is whole ticks, else it runs at the sub-step that hits every sample instant."""
        units = substep_units(config.period_units)
        if units == TICK_UNITS:
            self._fine = None
        else:
            self._fine = plant_constants(self.motor, self.counts_per_rev, units * UNIT_S), TICK_UNITS // units, units

    def _run_ticks_recorded(self, n: int, t: float) -> None:
        """`_run_ticks` while the recorder runs: the same loop, in chunks that end at sample instants
        (`_recorder_chunk`), sampling after each chunk, or inside each tick while sub-stepping. Kept apart
        so the loop without a recorder pays nothing for it (benchmarks/bench_sim.py)."""
        rec = self.recorder
        assert rec is not None
        fine = self._fine is not None
        integrate = self._integrate_fine if fine else self._integrate
        while n > 0:
            k = self._recorder_chunk(n)
            src = self._src
            sampled = fine  # the fine integrators sample inside the tick
            if src is None:
                if self._powered:
                    done = integrate(itertools.repeat(self._demand, k))
                elif self._vel != 0.0:
                    done = self._coast_fine(k) if fine else self._coast(k)
                else:
                    self.counters.ticks += k
                    done = k
                    self._recorder_idle(k)
                    sampled = True
            else:
                i = self._src_i
                m = min(k, self._next_event - i)
                if m <= 0:
                    self._on_source_event(t)
                    continue
                done = integrate(src[i:i + m])
                self._src_i = i + done
            n -= done
            if not sampled:
                rec.advance(done * TICK_UNITS, self._recorder_read)
            if self._fe_tripped:
                self._fe_tripped = False
                self._fault(codec.EMCY_FOLLOWING_ERROR, 0, t)
                continue
            if self._src is not None and self._src_i == self._next_event:
                self._on_source_event(t)

    def _recorder_chunk(self, n: int) -> int:
        """Ticks to run before the next sample instant (at most n; 1 while sub-stepping)."""
        rec = self.recorder
        if rec is None or not rec.active:
            return n
        if self._fine is not None:
            return 1
        return max(1, min(n, rec.units_to_sample() // TICK_UNITS))

    def _recorder_idle(self, ticks: int) -> None:
        """Ticks in which nothing moves (power off, standing): the samples due see the same state."""
        rec = self.recorder
        assert rec is not None
        units = ticks * TICK_UNITS
        while units > 0 and rec.active:
            step = min(units, rec.units_to_sample())
            rec.advance(step, self._recorder_read)
            units -= step

    def _integrate_fine(self, demands: Iterable[int]) -> int:
        """`_integrate` with the plant sub-stepped at the recorder's period (the position controller
        still runs once per 1 ms tick, its current held over the sub-steps); samples at every instant."""
        assert self._fine is not None and self.recorder is not None
        (phi, gam, psi, eta), steps, units = self._fine
        c = self._c
        cou, imax = c.coulomb_a, c.i_max
        rec, read = self.recorder, self._recorder_read
        few = self._fe_window if self._state is not ST.FAULT_REACTION_ACTIVE else math.inf
        done = 0
        for d in demands:
            e = d - self._pos
            integ = min(imax, max(-imax, self._integ + c.ki * e))
            dterm = c.kd_f * self._dterm + c.kd_g * (e - self._eprev)
            i = min(imax, max(-imax, c.kp * e + integ + dterm))
            self._integ, self._dterm, self._eprev, self._current, self._demand = integ, dterm, e, i, d
            for _ in range(steps):
                vel = self._vel
                ie = i - self.disturbance_current_a
                if vel > 0.0:
                    ie -= cou
                elif vel < 0.0:
                    ie += cou
                elif ie > cou:
                    ie -= cou
                elif ie < -cou:
                    ie += cou
                else:
                    ie = 0.0
                nv = phi * vel + gam * ie
                self._pos += psi * vel + eta * ie
                if cou and ((vel > 0.0 and nv < 0.0) or (vel < 0.0 and nv > 0.0)):
                    nv = 0.0
                self._vel = nv
                rec.advance(units, read)
            done += 1
            if e > few or e < -few:
                self._fe_tripped = True
                break
        self.counters.ticks += done
        return done

    def _coast_fine(self, n: int) -> int:
        """`_coast` with the plant sub-stepped at the recorder's period; samples at every instant."""
        assert self._fine is not None and self.recorder is not None
        (phi, gam, psi, eta), steps, units = self._fine
        cou = self._c.coulomb_a
        rec, read = self.recorder, self._recorder_read
        self._current = 0.0
        for _ in range(n):
            for _ in range(steps):
                vel = self._vel
                if vel != 0.0:
                    ie = -self.disturbance_current_a - (cou if vel > 0.0 else -cou)
                    nv = phi * vel + gam * ie
                    self._pos += psi * vel + eta * ie
                    stopped = (vel > 0.0 and nv <= 0.0) or (vel < 0.0 and nv >= 0.0)
                    self._vel = 0.0 if stopped or abs(nv) < COAST_STOP_COUNTS_PER_MS else nv
                    self._demand = hermite.round_counts(self._pos)
                rec.advance(units, read)
        self.counters.ticks += n
        return n

    # ============================================================================================
    # demand sources: ip segments and stop ramps

    def _set_source(self, demands: list[int], kind: Source) -> None:
        self._src = demands
        self._src_i = 0
        self._src_kind = kind
        self._seg_events = []
        self._next_event = len(demands)

    def _on_source_event(self, t: float) -> None:
        """The tick `_next_event` was just run: fire its limit events and/or complete the source."""
        src = self._src
        assert src is not None
        k = self._src_i
        while self._seg_events and self._seg_events[0][0] == k:
            _, bit = self._seg_events.pop(0)
            self._limit_event(bit, t)
            if self._src is not src:
                return  # an error aborted the trajectory
        if k >= len(src):
            self._source_done(t)
        else:
            self._next_event = self._seg_events[0][0] if self._seg_events else len(src)

    def _source_done(self, t: float) -> None:
        kind = self._src_kind
        self._src = None
        if kind == Source.HOMING:
            self._homing_next()
        elif kind == Source.SEGMENT:
            self.counters.segments_completed += 1
            self._segment_done(t)
        elif kind == Source.QUICK_STOP:
            if self._qs_option < 5:  # CiA 402: 1-3 then switch on disabled, 5-8 stay in quick stop
                self._transition(Internal.QUICK_STOP_DONE)
        elif kind == Source.FAULT:
            self._transition(Internal.FAULT_REACTION_DONE)
        elif kind == Source.HALT and self.recorder is not None:
            self.recorder.trigger(TRIGGER_END, "end of profile (halt)", self._t_now)

    def _start_segment(self, coeffs: tuple[float, float, float, float], n_ms: int) -> None:
        """Interpolate the demand along the seed's cubic (planner.hermite) over the next n_ms ticks,
        rounded as the drive rounds; the family's limit checks become events at their ticks."""
        self._set_source(hermite.demand_from_coefficients(coeffs, n_ms, self._toward_zero), Source.SEGMENT)
        self._seg_coeffs = coeffs
        self._seg_events = self._segment_limit_events(coeffs, n_ms)
        if self._seg_events:
            self._next_event = self._seg_events[0][0]

    def _segment_limit_events(self, coeffs: tuple[float, float, float, float], n_ms: int) -> list[tuple[int, int]]:
        """(tick, status bit) at which the segment first crosses a limit the family checks."""
        return []

    def _limit_event(self, bit: int, t: float) -> None:
        """A limit crossing of `_segment_limit_events` came due."""

    def _demand_velocity(self) -> float:
        """The interpolator's current velocity demand, counts/ms."""
        if self._src is None:
            return 0.0
        if self._src_kind == Source.SEGMENT:
            return hermite.evaluate(self._seg_coeffs, float(self._src_i - len(self._src)))[1]
        if self._src_kind == Source.HOMING:
            i, src = self._src_i, self._src
            return float(src[i - 1] - src[i - 2]) if i >= 2 else float(src[0] - self._demand) if i == 0 else 0.0
        v = abs(self._ramp_v0) - self._ramp_dec * self._src_i
        return math.copysign(max(0.0, v), self._ramp_v0)

    def _start_ramp(self, kind: Source, dec_key: Key) -> None:
        """Decelerate from the current demand velocity to standstill with `dec_key` (rpm/s)."""
        self._ramp(kind, self._acc_limit(dec_key))

    def _ramp(self, kind: Source, deceleration: float) -> None:
        """Decelerate from the current demand velocity to standstill at `deceleration` counts/ms^2."""
        v0 = self._demand_velocity()
        dec = max(deceleration, 1e-9)
        self._ip_active = False
        p0 = float(self._demand)
        demands: list[int] = []
        if v0 != 0.0:
            t_stop = abs(v0) / dec
            steps = min(MAX_RAMP_TICKS, math.ceil(t_stop))
            s = 1.0 if v0 > 0 else -1.0
            rnd = self._round
            for k in range(1, steps + 1):
                tk = min(float(k), t_stop)
                demands.append(rnd(p0 + v0 * tk - s * dec * tk * tk / 2.0))
        self._ramp_v0 = v0
        self._ramp_dec = dec
        self._set_source(demands, kind)
        if not demands:
            self._src = None
            self._on_ramp_done_immediately(kind)

    def _on_ramp_done_immediately(self, kind: Source) -> None:
        if kind == Source.QUICK_STOP and self._qs_option < 5:
            self._transition(Internal.QUICK_STOP_DONE)
        elif kind == Source.FAULT:
            self._transition(Internal.FAULT_REACTION_DONE)

    def _stop_interpolation(self) -> None:
        """ip mode disabled (bit 4 falling, mode change): the demand stays where it is."""
        self._ip_active = False
        if self._src is not None and self._src_kind == Source.SEGMENT:
            self._src = None

    # ============================================================================================
    # FIFO

    # ============================================================================================
    # CiA 402 device control

    def _apply_controlword(self, cw: int) -> None:
        prev = self._cw
        self._cw = cw
        command = codec.decode_command(cw)
        if command == Command.FAULT_RESET:
            if not prev & CW_FAULT_RESET and self._state == ST.FAULT:
                self._fault_reset()
            return
        state = self._state
        try:
            new = codec.next_state(state, command)
        except InvalidTransition:
            self.counters.ignored_commands += 1
            new = state
        if state == ST.QUICK_STOP_ACTIVE and new == ST.OPERATION_ENABLED and self._qs_option < 5:
            self.counters.ignored_commands += 1
            new = state
        if new != state:
            self._enter(new)
        if self._mode == hm.HOMING_MODE:
            self._homing_control(cw, prev)
            return
        if self._state != ST.OPERATION_ENABLED or self._mode != self.interpolation_mode:
            return
        self._mode_control(cw, prev)

    def _transition(self, trigger: Internal) -> None:
        self._enter(codec.next_state(self._state, trigger))

    def _enter(self, new: Cia402State) -> None:
        old = self._state
        self._state = new
        if old == ST.OPERATION_ENABLED and new != old and self._hm_state == "running":
            self._hm_state = "interrupted"  # the state machine's stop (quick stop, fault, disable) takes over
        if new.power_enabled and not old.power_enabled:
            self._power_on_stage()
        elif not new.power_enabled and old.power_enabled:
            self._power_off()
        if old == ST.OPERATION_ENABLED and new == ST.QUICK_STOP_ACTIVE:
            if self._qs_option == 0:
                self._transition(Internal.QUICK_STOP_DONE)
            else:
                self._ramp(Source.QUICK_STOP, self._quick_stop_deceleration())
        elif old == ST.QUICK_STOP_ACTIVE and new == ST.OPERATION_ENABLED:
            self._src = None
            self._ip_active = False

    def _power_on_stage(self) -> None:
        self._powered = True
        self._demand = hermite.round_counts(self._pos)
        self._integ = 0.0
        self._dterm = 0.0
        self._eprev = 0.0
        self._src = None
        self._ip_active = False

    def _power_off(self) -> None:
        self._powered = False
        self._src = None
        self._ip_active = False
        self._current = 0.0
        self._demand = hermite.round_counts(self._pos)

    def _fault(self, code: int, bit: int, t: float) -> None:
        """An error: latch its status bit (a family's buffer status), send EMCY, start the fault reaction."""
        self._latch(bit)
        if self._state in (ST.FAULT_REACTION_ACTIVE, ST.FAULT):
            return
        self.counters.faults += 1
        self._error_code = code
        self._error_register |= _EMCY_REGISTER.get(code, codec.ER_GENERIC)
        before = self._state
        self._state = codec.next_state(self._state, Internal.FAULT_DETECTED)
        self._ip_active = False  # the EMCY reports the status of the aborted trajectory
        bs = self._emcy_status()
        self.fault_log.append(FaultRecord(t, code, codec.EMCY_NAMES.get(code, hex(code)), bs, before))
        if self.recorder is not None:
            self.recorder.trigger(TRIGGER_ERROR, f"error 0x{code:04X}", t)
        self._emit_emcy(code, bs)
        if self._powered:
            self._fault_reaction()
        else:
            self._transition(Internal.FAULT_REACTION_DONE)

    def _fault_reset(self) -> None:
        if self._hm_state == "error":
            self._hm_state = "idle"  # bit 13 "is reset ... on rising edge of bit 7 of the Control Word"
        self._enter(codec.next_state(self._state, Command.FAULT_RESET))
        self._clear_latched()
        self._error_code = 0
        self._error_register = 0
        self._emit_emcy(codec.EMCY_ERROR_RESET, self._emcy_status())

    def _emit_emcy(self, code: int, status: int) -> None:
        if self._nmt not in (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL) or not self._emcy_enabled(code):
            return
        if self._emcy_cob & odm.PDO_DISABLED:
            return
        self.counters.emcy_sent += 1
        self._out.append(Frame(self._emcy_cob & 0x7FF, codec.encode_emcy(
            code, self._error_register, codec.emcy_manufacturer_bytes(status))))

    def _target_reached(self) -> bool:
        state = self._state
        if state == ST.OPERATION_ENABLED and self._mode == hm.HOMING_MODE:
            # seed 003's homing table: "If Bit 10 is set, this indicates that the velocity is 0"
            return self._src is None and abs(self._vel) < hm.STANDSTILL_COUNTS_PER_MS
        if state == ST.OPERATION_ENABLED:
            if self._cw & codec.CW_HALT:
                return self._src is None
            if self._ip_active or self._src is not None:
                return False
            return abs(self._demand - self._pos) <= self._pos_window
        if state == ST.QUICK_STOP_ACTIVE:
            return self._src is None
        return False

    # ============================================================================================
    # homing mode (6): bus/sim/homing.py

    @property
    def homing_state(self) -> str:
        """idle, running, attained, error or interrupted."""
        return self._hm_state

    @property
    def machine_position(self) -> float:
        """The actual position in the machine's frame (where the switches are), counts."""
        return self._pos - self._home_shift

    @property
    def inputs_word(self) -> int:
        """The home and limit switch inputs now (seed 000 table 3-11 bits), read at the position demand."""
        return self.inputs.word(self._demand - self._home_shift)

    def _homing_status(self) -> int:
        if self._mode != hm.HOMING_MODE:
            return 0
        if self._hm_state == "error":
            return hm.SW_HOMING_ERROR
        # "Bit 12 is reset at 0 ... when bit 4 of the Control Word is at 0"
        return hm.SW_HOMING_ATTAINED if self._hm_state == "attained" and self._cw & codec.CW_ENABLE_IP else 0

    def _homing_control(self, cw: int, prev: int) -> None:
        """A controlword in homing mode: bit 4 rising starts, falling (or halt, bit 8) interrupts."""
        rising = cw & ~prev
        running = self._hm_state == "running"
        if running and (not cw & codec.CW_ENABLE_IP or cw & codec.CW_HALT):
            self._hm_state = "interrupted"  # "can be interrupted when clear"; seed 000: 0x011F halt homing
            self._homing_stop_motion("stopping")
            return
        if not rising & codec.CW_ENABLE_IP or cw & codec.CW_HALT:
            return
        method = self._od.get((0x6098, 0), 0)
        if self._state != ST.OPERATION_ENABLED and method not in hm.CURRENT_POSITION_METHODS:
            # "homing launched whereas the drive is not in 'operation enabled' (except for homing method 35)"
            self._homing_fail(f"homing started in {self._state.value}")
            return
        self._homing_start(method)

    def _homing_start(self, method: int) -> None:
        self.homing_error_reason = ""
        self._hm_state = "running"
        plan = hm.phases(method, self.inputs, self._demand - self._home_shift) \
            if method in self.homing_methods else None
        if plan is None:
            self._homing_fail(f"method {method} is not implemented")  # "an unimplemented selected method"
            return
        od = self._od
        self._hm_speeds = (self._velocity_cpms(od[(0x6099, 1)]), self._velocity_cpms(od[(0x6099, 2)]),
                           self._acc_limit((0x609A, 0)))
        self._hm_phases = list(plan)
        self._hm_v = 0.0
        if not plan:
            self._homing_reference(self._demand)  # 35/37: the current position is the home position
            return
        self._homing_phase()

    def _homing_phase(self) -> None:
        ph = self._hm_phases.pop(0)
        self._hm_phase = ph
        search_v, zero_v, acc = self._hm_speeds
        v = ph.direction * (search_v if ph.speed == "search" else zero_v)
        shift, inputs = self._home_shift, self.inputs
        limit_signal = "positive" if ph.direction > 0 else "negative"

        def done(d: float) -> bool:
            return inputs.state(ph.signal, d - shift) == ph.until

        def limit(d: float) -> bool:
            return ph.signal != limit_signal and inputs.state(limit_signal, d - shift)

        s = hm.search(float(self._demand), self._hm_v, v, acc, done, limit, self._homing_travel, self._round)
        self._hm_stage, self._hm_outcome, self._hm_v = "search", s.outcome, s.velocity
        self._set_source(s.demands, Source.HOMING)

    def _homing_next(self) -> None:
        """A homing source ran to its end."""
        stage = self._hm_stage
        if stage == "failing":
            self._hm_v = 0.0
            self._hm_state = "error"
            return
        if stage == "stopping":
            self._hm_v = 0.0
            return
        if stage == "return":
            self._homing_reference(self._hm_edge)
            return
        ph = self._hm_phase
        assert ph is not None
        outcome = self._hm_outcome
        if outcome == "limit" and ph.on_limit is not None:
            self._hm_phases = list(ph.on_limit)
            self._homing_phase()
        elif outcome != "found":
            what = "a limit switch" if outcome == "limit" else f"no {ph.signal} switch edge within the travel"
            self._homing_fail(f"{what} (method {self._od.get((0x6098, 0), 0)})")
        elif self._hm_phases:
            self._homing_phase()
        else:
            # the home position: the edge just found; stop and come back to it at the zero speed
            self._hm_edge = self._demand
            _, zero_v, acc = self._hm_speeds
            ramp = hm.stop(float(self._demand), self._hm_v, acc, self._round)
            end = ramp[-1] if ramp else self._demand
            back = hm.move_to(float(end), self._hm_edge, zero_v, acc)
            self._hm_stage, self._hm_v = "return", 0.0
            if ramp or back:
                self._set_source(ramp + back, Source.HOMING)
            else:
                self._homing_reference(self._hm_edge)

    def _homing_reference(self, at: int) -> None:
        """The drive stands at the home position `at` (counts, reported frame): it becomes 0x607C."""
        offset = round(self._position_counts(self._od.get((0x607C, 0), 0)))
        delta = offset - at
        self._pos += delta
        self._demand += delta
        self._home_shift += delta
        self.referenced = True
        self._hm_state = "attained"

    def _homing_fail(self, reason: str) -> None:
        self.homing_error_reason = reason
        self._hm_state = "error"
        self._homing_stop_motion("failing")

    def _homing_stop_motion(self, stage: str) -> None:
        """Ramp down at 0x609A from the current homing motion (the state is already set)."""
        if self._src is None or self._src_kind != Source.HOMING:
            return
        v = self._demand_velocity()
        ramp = hm.stop(float(self._demand), v, self._hm_speeds[2] or self._acc_limit((0x609A, 0)), self._round)
        self._hm_stage = stage  # bit 13 with bit 10 clear while it ramps down: "error occurred, velocity is not 0"
        self._set_source(ramp, Source.HOMING)
        if not ramp:
            self._src = None
            self._homing_next()

    def _homing_abort(self) -> None:
        """Mode changed away from homing: the demand holds where it is."""
        if self._src is not None and self._src_kind == Source.HOMING:
            self._src = None
        if self._hm_state == "running":
            self._hm_state = "interrupted"

    def _velocity_cpms(self, value: int) -> float:
        """A velocity object's value (the family's unit: rpm here) as counts/ms."""
        return value * self._rpm_to_cpms

    def _position_counts(self, value: int) -> float:
        """A position object's value (the family's unit: counts here) as counts."""
        return float(value)

    # ============================================================================================
    # what a family adds (the defaults: a CiA 402 drive with no interpolation of its own)

    def _object_table(self) -> odm.ObjectTable:
        return odm.EPOS_TABLE

    def _struct_code(self, key: Key) -> str:
        return self.objects.objects[key].dtype.struct_code

    def _entry_code(self, key: Key, bits: int) -> str:
        """The struct code of a mapped entry: its object's type, or that signedness at the mapped length."""
        dtype = self.objects.objects[key].dtype
        if bits == dtype.bits:
            return self._struct_code(key)
        code = {8: "b", 16: "h", 32: "i", 64: "q"}[bits]
        return code if dtype.signed else code.upper()

    def _may_map_short(self, key: Key, bits: int, direction: str) -> bool:
        """May `key` be mapped with fewer bits than its type (seed 003: 16-bit set points)? Default no."""
        return False

    def _widen(self, key: Key, value: int, bits: int) -> int:
        """The object value an entry mapped with `bits` (< its type) carries; default: as received
        (sign-extended for a signed object)."""
        return value

    def _rpdo_received(self, keys: tuple[Key, ...], t: float) -> None:
        """An RPDO mapping `keys` arrived at `t` (accepted; synchronous ones are applied at the next SYNC)."""

    def _sends_bootup(self) -> bool:
        """Boot-up message on entering pre-operational after power-on / reset (CiA 301: yes)."""
        return True

    def _emcy_enabled(self, code: int) -> bool:
        """Is the EMCY with `code` sent (0x0000 = error reset)? Default: all."""
        return True

    def _quick_stop_deceleration(self) -> float:
        """The quick stop ramp for the option code 0x605A, counts/ms^2 (CiA 402: 1/5 slow down ramp =
        0x6084, 2/6 quick stop ramp 0x6085)."""
        return self._acc_limit((0x6084, 0) if self._qs_option in (1, 5) else self._qs_dec_key)

    def _fault_reaction(self) -> None:
        """The power stage is on and a fault was detected: ramp down with the quick stop deceleration,
        then fault (a family may switch off at once: `_transition(Internal.FAULT_REACTION_DONE)`)."""
        self._start_ramp(Source.FAULT, self._qs_dec_key)

    def _family_dynamic(self) -> dict[Key, Callable[[], int]]:
        return {}

    def _family_handlers(self) -> dict[Key, Callable[[int], None]]:
        return {}

    def _reset_family(self) -> None:
        """Power-on / reset node: the family's own state back to its power-on values."""

    def _refresh_family(self, od: dict[Key, int]) -> None:
        """An object changed: the family's caches of object values."""

    def _check_write(self, key: Key, via_sdo: bool) -> None:
        """Refuse a write the family's state does not allow (raise SdoAbort)."""

    def _mode_changed(self, old: int, new: int) -> None:
        """Modes of operation changed."""

    def _is_record_pdo(self, keys: tuple[Key, ...]) -> bool:
        """An RPDO whose payload goes to `_on_record` as it is (a FIFO record)."""
        return False

    def _on_record(self, data: bytes) -> None:
        raise NotImplementedError(f"{self.family} drives take no records")  # pragma: no cover

    def _after_sync_rpdos(self, t: float) -> None:
        """At a SYNC, after its synchronous RPDOs were applied and before its TPDOs are sent."""

    def _segment_done(self, t: float) -> None:
        """An interpolation segment (`_start_segment`) ran to its end."""

    def _mode_control(self, cw: int, prev: int) -> None:
        """A controlword in operation enabled, in the interpolation mode: the mode-specific bits."""

    def _latch(self, bit: int) -> None:
        """An error's status bit (the EPOS buffer status' error bits)."""

    def _clear_latched(self) -> None:
        """Fault reset: the latched status bits are cleared."""

    def _emcy_status(self) -> int:
        """The 16 bits an EMCY carries in its manufacturer bytes 0-1 (EPOS: the buffer status)."""
        return 0

    def read_domain(self, index: int, sub: int) -> bytes:
        """SDO upload of a domain object: its bytes (EPOS: 0x201B, the data recorder's memory). A family
        without domain objects has none to serve."""
        self._spec(index, sub)  # a missing object answers as such
        raise SdoAbort(odm.ABORT_UNSUPPORTED_ACCESS, f"0x{index:04X}:{sub:02X} is not a domain")
