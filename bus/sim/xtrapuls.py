"""The XtrapulsPac family: Infranor's interpolated position mode, one set point per SYNC (seed 003 3.2.3.5),
on the shared CiA 402 drive (bus/sim/device.py) and the cyclic part (bus/sim/cyclic_drive.py).

Per SYNC k (`_after_sync_rpdos`): the PLL (0x2006) locks after 180 ms of steady SYNC (`sim.sync_lock_ms`),
and while interpolating a jitter of half a period, a period off by 0.4 % or SYNC loss is error 49 (limits
scaled by `sync_gap_factor`: in-process runtimes pass 3.0, their SYNC stamps carry Python's scheduling); a
set point missing since SYNC k-1 is error 50; the interpolator latches 0x60C1:01 (and :02); interpolation
starts with controlword bit 4 once the PLL is locked (before that the request is refused until bit 4 is
seen low, or held until the lock: `sim.early_bit4`), from the current demand; the period's polynomial
follows sub-mode 0x60C0. Set points in RPDO3, optionally 16-bit multiplexed (0x3350 = 1).
docs/drive-model.md has every reading and its seed sentence.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from collections.abc import Callable

from bus import codec
from bus.codec import Cia402State, Internal
from bus.families import XTRAPULS_IP
from bus.sim import od as odm
from bus.sim.cyclic_drive import CyclicDrive, Poly, hermite_pv, linear, parabola_p3
from bus.sim.homing import HOMING_MODE
from bus.sim.od import Key, SdoAbort
from planner.config import HOMING_METHODS

IP_MODE = 7
SUBMODE_LINEAR, SUBMODE_PV, SUBMODE_P3 = 0, -1, -2
PLL_WINDOW_S = 0.180  # "At least 180 ms are necessary for the servo-drive to start the synchronisation"
PERIOD_TOLERANCE = 0.004  # error 49: "period accuracy is not within the tolerance (>=0.4%)"
SETPOINT_LEAD_S = 100e-6  # error 50: "this RPDO must precede the SYNC signal at least of 100 us"
PERIOD_STEP_US = 500  # 0x1006: "only the values multiples of 500 are supported"
MOTOR_INCREMENTS = 4096  # 0x6093:01 "must be set at 4096" increments per motor revolution
_EPS_S = 1e-9  # float slack on times compared with thresholds
# DS-402 code (0x603F, EMCY bytes 0-1) -> Infranor error code (0x3023:04, EMCY byte 3), seed 003's table
INFRANOR_CODES = {
    codec.EMCY_FOLLOWING_ERROR: 35,  # position following error
    0x8680: 36,  # software position limit
    codec.EMCY_SYNC_LOST: 49,  # fieldbus SYNC cycle error
    codec.EMCY_IP_BUFFER: 50,  # fieldbus IP reference underflow/overflow
    codec.EMCY_HEARTBEAT: 51,  # fieldbus guarding error
}
SET_POINT: Key = (0x60C1, 1)
SET_VELOCITY: Key = (0x60C1, 2)
# objects that may be mapped 16 bits in an RPDO: the set point (0x3350 = 1) and the velocities (the
# manual's multiplexed example maps 0x60FF with 16 bits)
_SHORT_MAPPABLE = frozenset({SET_POINT, SET_VELOCITY, (0x60FF, 0)})


class XtrapulsDrive(CyclicDrive):
    """A simulated Infranor XtrapulsPac in interpolated position mode (see the module docstring)."""

    family = "xtrapuls-ip"
    supported_modes = frozenset({0, HOMING_MODE, IP_MODE})
    homing_methods = HOMING_METHODS["xtrapuls-ip"]
    interpolation_mode = IP_MODE
    default_profile = XTRAPULS_IP
    quick_stop_options = frozenset({0, 1, 2, 3, 5, 6, 7})  # seed 003 0x605A
    rtr_tpdo_types = frozenset({253})  # seed 003: TPDO1/2 default to "RTR only"
    accepts_longer_rpdo = True  # the manual's multiplexed example: drive 1 maps 2 bytes of an 8-byte frame
    not_stored = frozenset({SET_POINT, SET_VELOCITY})

    # interpolator history: x_{k-2}, x_{k-1}, x_k (user units) and v_{k-1}, v_k (user units/s)
    _x: tuple[float, float, float] = (0.0, 0.0, 0.0)
    _v: tuple[float, float] = (0.0, 0.0)
    _sp_arrival: float | None = None  # when the last set point RPDO arrived (since the previous SYNC)
    _prev_sync: float | None = None
    # the PLL: the SYNC intervals of the last 180 ms (arrival order, and sorted), when the run began, locked
    _pll_intervals: deque[float]
    _pll_sorted: list[float]
    _pll_since: float | None = None
    _locked = False
    _ip_refused = False  # bit 4 came before the PLL locked: ignored until it falls
    ip_refusals = 0  # requests (bit 4 rising, operation enabled, mode 7) refused for want of the lock
    setpoints_received = 0
    setpoints_late = 0  # error 50 at a SYNC (missing or less than 100 us before it)

    # ---- hooks of the shared drive
    def _object_table(self) -> odm.ObjectTable:
        return odm.XTRAPULS_TABLE

    def _family_dynamic(self) -> dict[Key, Callable[[], int]]:
        return {**super()._family_dynamic(), (0x30C1, 0): lambda: self._round(self.interpolator_output)}

    def _family_handlers(self) -> dict[Key, Callable[[int], None]]:
        def store(key: Key) -> Callable[[int], None]:
            def write(value: int) -> None:
                self._od[key] = value  # no cached value depends on it (per-SYNC path)

            return write

        return {
            (0x1006, 0): self._write_period,
            SET_POINT: store(SET_POINT),
            SET_VELOCITY: store(SET_VELOCITY),
        }

    def _reset_family(self) -> None:
        self._x = (0.0, 0.0, 0.0)
        self._v = (0.0, 0.0)
        self._reset_interpolator()
        self._sp_arrival = None
        self._prev_sync = None
        self._ip_refused = False
        self._pll_reset()

    def _refresh_family(self, od: dict[Key, int]) -> None:
        # motor position = numerator / denominator * user position, in increments of 4096 per revolution
        counts = od[(0x6093, 1)] / od[(0x6093, 2)] * self.counts_per_rev / MOTOR_INCREMENTS
        self._set_scale(counts)
        few = od[(0x6065, 0)]
        self._fe_window = math.inf if few == 0xFFFFFFFF else few * counts
        self._submode = od[(0x60C0, 0)]
        self._ip16 = od[(0x3350, 0)] == 1
        self._sync_error_limit_s = od[(0x2006, 4)] * 1e-6
        self._emcy_mode = od[(0x205F, 0)]

    def _write_period(self, value: int) -> None:
        if value % PERIOD_STEP_US:
            raise SdoAbort(odm.ABORT_INVALID_VALUE, f"0x1006 = {value} us: only multiples of {PERIOD_STEP_US} "
                           "are supported")
        self._store((0x1006, 0), value)
        self._pll_reset()  # a new period: the PLL locks again

    def _may_map_short(self, key: Key, bits: int, direction: str) -> bool:
        if direction != "rx" or bits != 16 or key not in _SHORT_MAPPABLE:
            return False
        # "When in 16-bit mode (object 3350h = 1), the position reference ... is set at 16 bits"
        return key != SET_POINT or self._ip16

    def _widen(self, key: Key, value: int, bits: int) -> int:
        if key == SET_POINT and self._ip16:
            # "the drive calculates the upper word": the value nearest the previous set point (the last
            # one, or what 0x60C1:01 was last written over SDO)
            ref = self._od[SET_POINT]
            delta = ((value - ref + 0x8000) & 0xFFFF) - 0x8000
            return ref + delta
        return value  # a 16-bit velocity (or a 16-bit set point with 0x3350 = 0): sign-extended

    def _rpdo_received(self, keys: tuple[Key, ...], t: float) -> None:
        if SET_POINT in keys:
            self._sp_arrival = t
            self.setpoints_received += 1

    def _sends_bootup(self) -> bool:
        return self._od.get((0x2010, 0), 0) == 1  # "0 No Bootup message" (the default)

    def _emcy_enabled(self, code: int) -> bool:
        mode = self._emcy_mode  # 0x205F: 0 none, 1 on error, 2 on error and on reset (code 0)
        return mode == 2 or (mode == 1 and code != codec.EMCY_ERROR_RESET)

    def _emcy_status(self) -> int:
        # EMCY byte 3: the Infranor code ("error code is error bit number+1"), byte 4 zero
        return INFRANOR_CODES.get(self._error_code, 0)

    def _quick_stop_deceleration(self) -> float:
        option = self._qs_option
        if option in (1, 5):
            return self._acc_limit((0x3300, 1))  # "Stopped on Slow down speed ramp"
        if option in (3, 7):
            return self._current_limit_deceleration()  # "Stopped on current limit"
        return self._acc_limit((0x6085, 0))  # 2, 6: "Stopped on Quick Stop speed ramp"

    def _current_limit_deceleration(self) -> float:
        """counts/ms^2 the unloaded motor reaches at the stop current 0x3301:01 (per mille of the rated
        current, which the motor model takes as half its current limit)."""
        m = self.motor
        amps = self._od[(0x3301, 1)] / 1000.0 * m.current_limit_a / 2.0
        rad_per_s2 = m.torque_constant_nm_per_a * amps / m.inertia_kgm2
        return rad_per_s2 * self.counts_per_rev / (2.0 * math.pi) / 1e6

    def _fault_reaction(self) -> None:
        # "a Stop 0 is executed (power stage switched off and motor brake activated). This is the default"
        self._transition(Internal.FAULT_REACTION_DONE)

    def _mode_control(self, cw: int, prev: int) -> None:
        # bit 4 is a level ("bit 4 of the control word must also be set ... to be fully operational"):
        # interpolation starts at a SYNC while it is set (`_after_sync_rpdos`) and ends when it falls;
        # halt (bit 8) acts "only in PV, PT, AS, AT"
        if not cw & codec.CW_ENABLE_IP and self._ip_active:
            self._stop_interpolation()

    def _get_statusword(self) -> int:
        # seed 003 "Correct sequence to enable the drive": 0x0240 / 0x0221 / 0x0223 / 0x0227 (state bits and
        # bit 9 remote); bit 12 "Ip-Mode active"
        sw = self._state.statusword_bits | codec.SW_REMOTE
        if self._ip_active:
            sw |= codec.SW_IP_ACTIVE
        if self._mode == HOMING_MODE:  # bits 13 / 12 / 10 of the homing table ("velocity is 0": bit 10)
            sw |= self._homing_status() | (codec.SW_TARGET_REACHED if self._target_reached() else 0)
        return sw

    @property
    def ready_for_job(self) -> bool:
        return (self._state == Cia402State.OPERATION_ENABLED and self._mode == IP_MODE and not self._ip_active)

    @property
    def pll_locked(self) -> bool:
        """The PLL is locked on SYNC: interpolation can start."""
        return self._locked

    # ---- the SYNC
    def _after_sync_rpdos(self, t: float) -> None:
        prev, self._prev_sync = self._prev_sync, t
        was_active = self._ip_active
        self._pll_sync(t, prev)
        if was_active and self._ip_active:
            arrived = self._sp_arrival
            if arrived is None or t - arrived < SETPOINT_LEAD_S - _EPS_S:
                self.setpoints_late += 1
                self._fault(codec.EMCY_IP_BUFFER, 0, t)
        self._sp_arrival = None
        # the interpolator runs in any mode: it latches the set point at every SYNC
        x = float(self._od[SET_POINT])
        self._x = (self._x[1], self._x[2], x)
        self._v = (self._v[1], float(self._od[SET_VELOCITY]))
        wanted = bool(self._cw & codec.CW_ENABLE_IP) and self._state == Cia402State.OPERATION_ENABLED and \
            self._mode == IP_MODE
        if not wanted:
            self._ip_refused = False  # bit 4 low (or not enabled in mode 7): the next request is a new one
        elif not self._ip_active and not self._ip_refused and not self._locked:
            # bit 4 before the lock: refused, bit 12 stays low until bit 4 falls and rises again (the "held"
            # reading keeps the request and starts at the lock)
            if self.options.early_bit4 == "refused":
                self._ip_refused = True
                self.ip_refusals += 1
        elif not self._ip_active and not self._ip_refused:
            self._ip_active = True
            self.counters.activations += 1
            here = self._demand if self._unit else self._demand / self._scale
            self._x = (self._x[0], float(here), x)  # from the current demand: enabling moves nothing
        self._play(self._polynomial(), x, self._ip_active)

    def _polynomial(self) -> Poly:
        x_m2, x_m1, x0 = self._x
        if self._submode == SUBMODE_PV:
            return hermite_pv(x_m1, self._v[0], x0, self._v[1], self._period_us * 1e-6)
        if self._submode == SUBMODE_P3:
            return parabola_p3(x_m2, x_m1, x0)
        return linear(x_m1, x0)

    # ---- the PLL (0x2006)
    @property
    def _period_tolerance(self) -> float:
        """Error 49's period accuracy, scaled with the jitter limit (0.4 % at the default factor 1.5)."""
        return PERIOD_TOLERANCE * (self.sync_gap_factor - 1.0) / 0.5

    def _pll_reset(self) -> None:
        self._pll_intervals = deque()
        self._pll_sorted = []
        self._pll_since = None
        self._locked = False

    def _pll_sync(self, t: float, prev: float | None) -> None:
        period_us = self._period_us
        if not period_us:  # "When the value of this object is reset at 0, the synchronisation is no more operative"
            self._pll_reset()
            return
        period_s = period_us * 1e-6
        if prev is not None and self._pll_since is not None:
            interval = t - prev
            if abs(interval - period_s) >= (self.sync_gap_factor - 1.0) * period_s - _EPS_S:
                if self._ip_active:
                    self.counters.sync_gaps += 1
                    self._fault(codec.EMCY_SYNC_LOST, 0, t)  # error 49: "great jitter (>=half-period)"
                self._pll_reset()
            else:
                # the window: the intervals of the last 180 ms, in arrival order and sorted (for the median)
                window = max(1, math.ceil(PLL_WINDOW_S / period_s - _EPS_S))
                fifo, ordered = self._pll_intervals, self._pll_sorted
                fifo.append(interval)
                bisect.insort(ordered, interval)
                while len(fifo) > window:
                    del ordered[bisect.bisect_left(ordered, fifo.popleft())]
                # the measured period: the median interval (one late SYNC, within the jitter limit, makes one
                # long and one short interval and leaves it alone; a master whose clock runs off does not)
                error = abs(ordered[len(ordered) // 2] - period_s)
                if self._ip_active and len(fifo) == window and error >= self._period_tolerance * period_s - _EPS_S:
                    self._fault(codec.EMCY_SYNC_LOST, 0, t)  # error 49: "period accuracy ... (>=0.4%)"
                lock_s = self.options.sync_lock_ms / 1000.0
                self._locked = t - self._pll_since >= lock_s - _EPS_S and error < self._sync_error_limit_s
                return
        if self._pll_since is None:
            self._pll_since = t  # the first SYNC of a run
        self._locked = False
