"""What the simulated drives fed one set point per SYNC share (bus/sim/xtrapuls.py, bus/sim/csp.py), on the
shared CiA 402 drive (bus/sim/device.py).

Theory of operation. No FIFO: at each SYNC k the family latches the set point x_k and builds the
polynomial p(s), s in [0, 1], from x_{k-1} to x_k; `_play` turns it into the demands of the coming
period's 1 ms ticks (tick j at s_j = (1000 j - r) / 0x1006, r the offset of the last tick before SYNC
k), so x_k is the demand at SYNC k+1. Positions in user units (`scale` counts per unit), the demand
rounded to whole counts (planner/readings.py). The family adds when a set point is latched, which
polynomial, when interpolation is active, and its own checks and objects.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from bus.sim.device import DriveDevice, Source
from bus.sim.od import Key
from planner.encoding import hermite

Poly = tuple[float, float, float, float]  # p(s) = a0 + a1 s + a2 s^2 + a3 s^3


def evaluate(poly: Poly, s: float) -> float:
    a0, a1, a2, a3 = poly
    return ((a3 * s + a2) * s + a1) * s + a0


def derivative(poly: Poly, s: float) -> float:
    """dp/ds at s."""
    _, a1, a2, a3 = poly
    return (3.0 * a3 * s + 2.0 * a2) * s + a1


def linear(x0: float, x1: float) -> Poly:
    """Linear interpolation from x0 to x1."""
    return (x0, x1 - x0, 0.0, 0.0)


def hermite_pv(x0: float, v0: float, x1: float, v1: float, period_s: float) -> Poly:
    """The cubic Hermite from (x0, v0) to (x1, v1) over one period (velocities in units/s)."""
    d0, d1 = v0 * period_s, v1 * period_s  # dp/ds = period * velocity
    return (x0, d0, -3.0 * x0 - 2.0 * d0 + 3.0 * x1 - d1, 2.0 * x0 + d0 - 2.0 * x1 + d1)


def parabola_p3(x_m2: float, x_m1: float, x0: float) -> Poly:
    """The parabola through x_{k-2}, x_{k-1}, x_k at SYNC k-2, k-1, k, on [k-1, k] (s = 0 at k-1)."""
    return (x_m1, (x0 - x_m2) / 2.0, (x0 - 2.0 * x_m1 + x_m2) / 2.0, 0.0)


def tick_positions(since_last_tick_us: int, period_us: int) -> list[float]:
    """s of each 1 ms tick of the period after a SYNC whose last tick was `since_last_tick_us` before it."""
    if period_us <= 0:
        return []
    n = (since_last_tick_us + period_us) // 1000
    return [(1000 * j - since_last_tick_us) / period_us for j in range(1, n + 1)]


class CyclicDrive(DriveDevice):
    """A drive that takes one set point per SYNC (see the module docstring). Not used on its own."""

    _poly: Poly = (0.0, 0.0, 0.0, 0.0)
    _poly_s: list[float]  # s of each tick of the current period (`_reset_interpolator`, `_play`)
    _poly_playing = False  # the demand follows `_poly` this period
    _poly_period_us = 0  # the period `_poly` spans
    _scale = 1.0  # motor counts per user unit
    _unit = True  # scale == 1

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if self._clock is not None:
            # the interpolator's cycle is locked to SYNC (seed 003: a PLL); a free-running clock would
            # start each period's polynomial at whatever tick the last one had reached
            raise ValueError(f"drive {self.node_id} ({self.family}): sim.clock = \"own\" is not a reading of "
                             "a drive fed one set point per SYNC (its cycle is locked to SYNC)")

    # ---- units
    def _set_scale(self, counts_per_user_unit: float) -> None:
        self._scale = counts_per_user_unit
        self._unit = counts_per_user_unit == 1.0

    def _to_user(self, counts: float) -> int:
        return hermite.round_counts(counts if self._unit else counts / self._scale)

    def _acc_limit(self, key: Key) -> float:
        """An acceleration object (user units/s^2) as counts/ms^2 (no limit when the drive lacks it)."""
        if key[0] in self._absent or key not in self._od:
            return math.inf
        return self._od[key] * self._scale / 1e6

    def _velocity_cpms(self, value: int) -> float:
        return value * self._scale / 1000.0  # user units/s

    def _position_counts(self, value: int) -> float:
        return value * self._scale  # user units

    def _family_dynamic(self) -> dict[Key, Callable[[], int]]:
        return {
            (0x6062, 0): lambda: self._demand if self._unit else self._to_user(self._demand),
            (0x6064, 0): lambda: self._to_user(self._pos),
            (0x60F4, 0): lambda: self._to_user(self._demand) - self._to_user(self._pos),
            (0x606C, 0): lambda: self._to_user(self._vel * 1000.0),
        }

    # ---- the interpolator
    def _reset_interpolator(self) -> None:
        """Power-on / reset node: no polynomial (a family's `_reset_family` calls it)."""
        self._poly = (0.0, 0.0, 0.0, 0.0)
        self._poly_s = []
        self._poly_playing = False
        self._poly_period_us = 0

    def _play(self, poly: Poly, end: float, active: bool, period_us: int | None = None) -> None:
        """The interpolator's polynomial for the period that starts at this SYNC (p(1) = `end`, the set
        point) over `period_us` (default 0x1006); with `active` the position demand follows it at each
        tick, rounded to counts. The tick at s = 1 (the last of a whole-ms period) is `end` itself, not
        p(1) with its float rounding."""
        period = self._period_us if period_us is None else period_us
        s_list = tick_positions(self._tick_acc_us, period)
        self._poly_period_us = period
        self._poly = poly
        self._poly_s = s_list
        self._poly_playing = active
        if not active:
            return
        scale, rnd = self._scale, self._round
        demands = [rnd(evaluate(poly, s) * scale) for s in s_list]
        if s_list and s_list[-1] == 1.0:
            demands[-1] = rnd(end * scale)
        self._set_source(demands, Source.SEGMENT)

    def _poly_position(self) -> float:
        """s at the last tick run of the current period (0 right after its SYNC)."""
        if self._poly_playing and self._src is not None and self._src_kind == Source.SEGMENT and self._src_i:
            return self._poly_s[self._src_i - 1]
        return 0.0

    @property
    def interpolator_output(self) -> float:
        """The interpolator's output now, user units (0x30C1 rounds it)."""
        return evaluate(self._poly, self._poly_position())

    def _demand_velocity(self) -> float:
        """counts/ms: the polynomial's slope while it drives the demand (a stop ramps from it)."""
        if self._src is not None and self._src_kind == Source.SEGMENT:
            if not self._poly_playing or self._poly_period_us <= 0:
                return 0.0
            ds_per_ms = 1000.0 / self._poly_period_us
            return derivative(self._poly, self._poly_position()) * ds_per_ms * self._scale
        return super()._demand_velocity()

    def _stop_interpolation(self) -> None:
        super()._stop_interpolation()
        self._poly_playing = False
