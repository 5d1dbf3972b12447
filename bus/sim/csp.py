"""The cyclic synchronous position family (CiA 402 mode 8: the target 0x607A every SYNC; seed 000 2.6 and
6.7 for EPOS3 over EtherCAT), on the shared CiA 402 drive (bus/sim/device.py) and the cyclic part
(bus/sim/cyclic_drive.py).

Theory of operation. In operation enabled with mode 8 the drive follows the command value (statusword
bit 12; no controlword bit starts it). At each SYNC k (after the period's ticks and the synchronous
RPDOs) it latches x_k = 0x607A, checks it against the actual position ("If the difference between
actual and new position is greater than 'Max Following Error', an emergency procedure will be
launched": |x_k - 0x6064| > 0x6065 -> EMCY 0x8611 and the fault reaction) and moves the demand from
x_{k-1} to x_k along a straight line over the coming period's 1 ms ticks, so x_k is the demand at SYNC
k+1. CiA 402 leaves the interpolation between set points to the manufacturer; seed 000 says only "the
axis moves to the new absolute position": linear is the sim's reading. A SYNC without a new target
holds the last one (no error: CiA 402 defines none). Following begins at the current demand, so
enabling moves nothing when 0x607A holds the drive's position (the master writes it first). SYNC loss
while following is EMCY 0x8780 (device.py's SYNC monitoring). Units: counts, counts/s, counts/s^2.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from bus import codec
from bus.codec import Cia402State
from bus.families import CIA402_CSP
from bus.sim import od as odm
from bus.sim.cyclic_drive import CyclicDrive, linear
from bus.sim.homing import HOMING_MODE
from bus.sim.od import Key
from planner.config import HOMING_METHODS

CSP_MODE = 8
TARGET: Key = (0x607A, 0)


class CspDrive(CyclicDrive):
    """A simulated CiA 402 drive in cyclic synchronous position mode (see the module docstring)."""

    family = "cia402-csp"
    supported_modes = frozenset({0, HOMING_MODE, CSP_MODE})
    homing_methods = HOMING_METHODS["cia402-csp"]
    interpolation_mode = CSP_MODE
    default_profile = CIA402_CSP

    _x_prev = 0.0  # x_{k-1}: where this period's line starts (counts)

    def _object_table(self) -> odm.ObjectTable:
        return odm.CSP_TABLE

    def _family_handlers(self) -> dict[Key, Callable[[int], None]]:
        def write_target(value: int) -> None:
            self._od[TARGET] = value  # no cached value depends on it (per-SYNC path)

        return {TARGET: write_target}

    def _reset_family(self) -> None:
        self._x_prev = 0.0
        self._reset_interpolator()

    def _refresh_family(self, od: dict[Key, int]) -> None:
        few = od[(0x6065, 0)]
        self._fe_window = math.inf if few == 0xFFFFFFFF else float(few)

    def _mode_changed(self, old: int, new: int) -> None:
        if new == CSP_MODE and self._state == Cia402State.OPERATION_ENABLED:
            self._follow()

    def _mode_control(self, cw: int, prev: int) -> None:
        if not self._ip_active:
            self._follow()  # operation enabled in mode 8 (transition 4 or 16): the drive follows

    def _follow(self) -> None:
        self._ip_active = True
        self.counters.activations += 1
        self._x_prev = float(self._demand)

    @property
    def ready_for_job(self) -> bool:
        return self._state == Cia402State.OPERATION_ENABLED and self._mode == CSP_MODE

    def _after_sync_rpdos(self, t: float) -> None:
        x = float(self._od[TARGET])
        if self._ip_active and abs(x - self._pos) > self._fe_window:
            self._fault(codec.EMCY_FOLLOWING_ERROR, 0, t)  # seed 000 6.7: the new target vs the actual position
        active = self._ip_active
        start = self._x_prev if active else x
        self._play(linear(start, x), x, active, self._period_us or self._ip_period_us())
        self._x_prev = x

    def _ip_period_us(self) -> int:
        """0x60C2 (value x 10^index s) in us: the set point cycle when 0x1006 is not set."""
        value, index = self._od[(0x60C2, 1)], self._od[(0x60C2, 2)]
        return round(value * 10.0 ** index * 1e6)
