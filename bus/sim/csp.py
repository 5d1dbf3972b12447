"""The cyclic synchronous position family (CiA 402 mode 8, seed 000 2.6 and 6.7), on the shared drive
(bus/sim/device.py) and the cyclic part (bus/sim/cyclic_drive.py).

In operation enabled with mode 8 the drive follows 0x607A: at each SYNC k it latches x_k, faults if it is
beyond 0x6065 of the actual position (EMCY 0x8611), and moves the demand linearly from x_{k-1} to x_k over
the coming period (CiA 402 leaves the interpolation open: linear is the sim's reading), so x_k is the
demand at SYNC k+1. No new target holds the last; following starts at the current demand, so enabling
with 0x607A at the drive's position moves nothing. SYNC loss while following is EMCY 0x8780.
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
