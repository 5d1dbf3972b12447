"""CiA 301 on the simulated drive: the entry points, NMT, the object dictionary, SDO and SYNC.

The bottom layer of the simulated drive (bus/sim/device.py lists the others). A pure state machine:
every entry point takes `t` (seconds) and returns the frames the drive sends, after first bringing the
drive up to `t`. `power_on`, `on_frame` (NMT, SYNC, RPDOs, monitored heartbeats, time stamp; SDO is served
through `sdo_read`/`sdo_write` by bus/sim/node.py or a virtual-time runtime), `on_sync` (a SYNC-locked
drive runs the period's ticks, applies synchronous RPDOs, lets the family act, sends its TPDOs),
`advance` (heartbeat production and consumption, SYNC loss, held and event TPDOs, the own clock) and
`next_deadline`. Writes go through `_write`'s handlers, else are stored; `_refresh_caches` keeps the
per-tick values as attributes.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, field

from bus import codec
from bus.codec import Frame, NmtCommand, NmtState
from bus.errors import ProtocolError
from bus.profile import DriveProfile, FeedbackSchedule, SetpointSlot
from bus.sim import od as odm
from bus.sim.clock import MotionClock
from bus.sim.od import Key, SdoAbort
from planner.config import AxisConfig, DriveSettings
from planner.readings import SimDriveOptions

SAVE_SIGNATURE = 0x65766173  # "save" (seed 000 6.12; CiA 301 0x1010)
LOAD_SIGNATURE = 0x64616F6C  # "load" (seed 000 6.12; CiA 301 0x1011)
# what 0x1010 "save all parameters" never keeps (a family adds its commands and buffers)
_NOT_STORED = frozenset({(0x6040, 0), (0x1010, 1), (0x1011, 1), (0x1013, 0)})


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


# the PDO tables the node routes frames by (built from the mapping by bus/sim/pdo.py)
@dataclass
class RxPdo:
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
class TxPdo:
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


class Cia301Node:
    """Entry points, NMT, object dictionary, SDO and SYNC of one simulated drive. See the module docstring."""

    # what a family sets (bus/sim/device.py lists the family's class attributes)
    not_stored: frozenset[tuple[int, int]]
    # what the layers above provide (bus/sim/pdo.py, plant.py, cia402.py, device.py)
    _on_rpdo: Callable[[RxPdo, bytes, float], None]
    _apply_pdo_pairs: Callable[[list[tuple[Key, int, int]]], None]
    _sample_sync_tpdos: Callable[[int | None], list[Frame]]
    _send_sync_tpdos: Callable[[list[Frame], float], None]
    _release_held: Callable[[float], None]
    _flush_event_tpdos: Callable[[], None]
    _event_deadline: Callable[[], float | None]
    _rebuild_pdos: Callable[[], None]
    _fault: Callable[[int, int, float], None]
    _run_ticks: Callable[[int, float], None]
    _clock_deadline: Callable[[], float | None]
    _reset_application: Callable[..., None]
    _ip_active: bool
    # the state, set in DriveDevice.__init__
    node_id: int
    axis: AxisConfig | None
    settings: DriveSettings
    profile: DriveProfile
    objects: odm.ObjectTable
    counts_per_rev: int
    sync_gap_factor: float
    receive_slack_s: float
    options: SimDriveOptions
    counters: DriveCounters
    _sample_before: bool
    _clock: MotionClock | None
    _held: list[tuple[float, Frame]]
    _absent: frozenset[int]
    _stored: dict[Key, int]
    _rpm_to_cpms: float
    _nmt: NmtState
    _pending_sync: dict[int, list[tuple[Key, int, int]]]
    _od: dict[Key, int]
    _rx_by_cob: dict[int, RxPdo]
    _tx_sync: list[TxPdo]
    _tx_event: list[TxPdo]
    _t_now: float
    _t_last_sync: float | None
    _tick_acc_us: int
    _hb_next: float | None
    _hb_rx_last: float | None
    _out: list[Frame]
    _dynamic: dict[Key, Callable[[], int]]
    _handlers: dict[Key, Callable[[int], None]]

    # ============================================================================================
    # public entry points

    def power_on(self, t: float) -> list[Frame]:
        """Boot: send the boot-up message and enter NMT pre-operational."""
        self._t_now = t
        self._out = []
        if self._nmt == NmtState.BOOTUP:
            self._boot(t)
        return self._out

    def _start_entry(self, t: float) -> bool:
        """What every entry point after `power_on` does first: the frames out start empty and a booted
        drive runs up to `t` (TPDOs held for their latency, then its ticks). False before the boot."""
        self._t_now = t
        self._out = []
        if self._nmt == NmtState.BOOTUP:
            return False
        self._release_held(t)
        self._catch_up(t)
        return True

    def on_frame(self, cob_id: int, data: bytes, t: float) -> list[Frame]:
        """A frame seen on the bus. Returns the frames the drive sends in response."""
        if not self._start_entry(t):
            return self._out
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
        if self._start_entry(t):
            self._sync(t, data)
            self._flush_event_tpdos()
        return self._out

    def advance(self, t: float) -> list[Frame]:
        """Timers up to time `t`: heartbeat producer, SYNC loss, heartbeat consumer, the own clock's
        ticks, TPDOs held for their latency, event TPDO timers."""
        if not self._start_entry(t):
            return self._out
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

    def read_domain(self, index: int, sub: int) -> bytes:
        """SDO upload of a domain object: its bytes (EPOS: 0x201B, the data recorder's memory). A family
        without domain objects has none to serve."""
        self._spec(index, sub)  # a missing object answers as such
        raise SdoAbort(odm.ABORT_UNSUPPORTED_ACCESS, f"0x{index:04X}:{sub:02X} is not a domain")

    # ---- introspection ---------------------------------------------------------------------------
    @property
    def nmt_state(self) -> NmtState:
        return self._nmt

    @property
    def sync_cob_id(self) -> int:
        return self._sync_cob

    @property
    def clock(self) -> MotionClock | None:
        """The drive's own motion clock (None: locked to SYNC)."""
        return self._clock

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

    def _store(self, key: Key, value: int) -> None:
        self._od[key] = value
        self._refresh_caches()

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

    # ============================================================================================
    # what a family adds to CiA 301 (the defaults: CiA 301 as written)

    def _sends_bootup(self) -> bool:
        """Boot-up message on entering pre-operational after power-on / reset (CiA 301: yes)."""
        return True

    def _after_sync_rpdos(self, t: float) -> None:
        """At a SYNC, after its synchronous RPDOs were applied and before its TPDOs are sent."""

    def _check_write(self, key: Key, via_sdo: bool) -> None:
        """Refuse a write the family's state does not allow (raise SdoAbort)."""

    def _refresh_family(self, od: dict[Key, int]) -> None:
        """An object changed: the family's caches of object values."""
