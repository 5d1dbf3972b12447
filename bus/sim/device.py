"""A simulated CiA 402 servo drive as a pure state machine: frames and time in, frames out.

The part every family shares; a family (epos.py, xtrapuls.py, csp.py) adds its mode, objects and SYNC
behaviour through hooks. No sleeps, wall clock, canopen or threads: every entry point takes `t` and
returns the frames sent. Layers, each a class on the one below: cia301.py, pdo.py, plant.py,
recorder_ticks.py, homing_mode.py, cia402.py, and here `DriveDevice` (the family's settings, the state,
write handlers, reset node). A lower layer declares what it needs from a higher one in its class body.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable

from bus import codec
from bus.codec import Frame, Internal, NmtState
from bus.families import EPOS_IPM
from bus.profile import DriveProfile
from bus.sim import homing as hm
from bus.sim import od as odm
from bus.sim.cia301 import LOAD_SIGNATURE, SAVE_SIGNATURE, DriveCounters, RxPdo, TxPdo
from bus.sim.cia402 import QUICK_STOP_OPTIONS, Cia402Drive, FaultRecord
from bus.sim.clock import MotionClock
from bus.sim.data_recorder import DataRecorder
from bus.sim.motor import DEFAULT_MOTOR, LoopConstants, MotorParams
from bus.sim.od import Key
from bus.sim.plant import COAST_STOP_COUNTS_PER_MS, MAX_RAMP_TICKS, ST, Source, SubSteps, first_violation
from planner.config import AxisConfig, DriveSettings
from planner.encoding import hermite
from planner.readings import SimDriveOptions

__all__ = [
    "COAST_STOP_COUNTS_PER_MS", "LOAD_SIGNATURE", "MAX_RAMP_TICKS", "QUICK_STOP_OPTIONS", "SAVE_SIGNATURE",
    "DriveCounters", "DriveDevice", "FaultRecord", "Source", "first_violation",
]


class DriveDevice(Cia402Drive):
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
        # the family's data recorder (None: it has none; EPOS sets it at each reset) and the plant's sub-steps
        # while it samples finer than the 1 ms tick (bus/sim/recorder_ticks.py)
        self.recorder: DataRecorder | None = None
        self._fine: SubSteps | None = None
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
        self._rx_by_cob: dict[int, RxPdo] = {}
        self._tx_sync: list[TxPdo] = []
        self._tx_event: list[TxPdo] = []
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
    # NMT reset node and the object write handlers

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

    # ============================================================================================
    # what a family adds (the defaults: a CiA 402 drive with no interpolation of its own)

    def _object_table(self) -> odm.ObjectTable:
        return odm.EPOS_TABLE

    def _family_dynamic(self) -> dict[Key, Callable[[], int]]:
        return {}

    def _family_handlers(self) -> dict[Key, Callable[[int], None]]:
        return {}

    def _reset_family(self) -> None:
        """Power-on / reset node: the family's own state back to its power-on values."""
