"""Homing mode (CiA 402 mode 6) of the simulated drives: the inputs, the methods, the search trajectories.

The pure part of bus/sim/homing_mode.py (seed 003 "Homing Mode"). `Inputs`: home and limit switches at
machine positions, `word(x)` the functionality word (CiA 402's 0x60FD bits). `phases(method, inputs, x)`:
the method as searches ("move this way at this speed until this input is in this state"), chosen from the
inputs at the start as CiA 402's methods do; cam methods 23 and 27 reverse on a limit switch. `search`:
one search's demand per tick, ramping at 0x609A, failing beyond the machine's travel. `move_to`: back to
the home position (0x309D = 1).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

HOMING_MODE = 6
SW_HOMING_ATTAINED = 1 << 12  # "Homing attained" (seed 003: bits 12, 13 in homing mode)
SW_HOMING_ERROR = 1 << 13  # "Homing error"
# the inputs' functionality bits (seed 000 table 3-11)
INPUT_NEGATIVE_LIMIT = 1 << 0
INPUT_POSITIVE_LIMIT = 1 << 1
INPUT_HOME = 1 << 2
CURRENT_POSITION_METHODS = frozenset({35, 37})  # CiA 402: 35, renumbered 37 in its later edition
SIMULATED_METHODS = frozenset({17, 18, 19, 20, 21, 22, 23, 27, 35, 37})
STANDSTILL_COUNTS_PER_MS = 0.05  # below this the motor "velocity is 0" (statusword bit 10 in homing mode)
MAX_SEARCH_TICKS = 3_600_000  # one hour of drive time: a search longer than this is a homing error

Signal = str  # "home", "negative", "positive"


@dataclass(frozen=True)
class Inputs:
    """The switches in counts of the machine frame (see the module docstring)."""

    home: tuple[float, float] | None = None
    limits: tuple[float, float] | None = None

    @classmethod
    def of(cls, home: tuple[float, ...] | None, limits: tuple[float, ...] | None, counts_per_unit: float) -> Inputs:
        """From the sim options (user units of an axis with `counts_per_unit`)."""
        h = None if home is None else (home[0] * counts_per_unit, home[1] * counts_per_unit)
        lim = None if limits is None else (limits[0] * counts_per_unit, limits[1] * counts_per_unit)
        return cls(h, lim)

    def state(self, signal: Signal, x: float) -> bool:
        if signal == "home":
            return self.home is not None and self.home[0] <= x <= self.home[1]
        if self.limits is None:
            return False
        return x <= self.limits[0] if signal == "negative" else x >= self.limits[1]

    def word(self, x: float) -> int:
        return ((INPUT_NEGATIVE_LIMIT if self.state("negative", x) else 0)
                | (INPUT_POSITIVE_LIMIT if self.state("positive", x) else 0)
                | (INPUT_HOME if self.state("home", x) else 0))


@dataclass(frozen=True)
class Phase:
    """Move in `direction` (+1/-1) at the `speed` ("search" 0x6099:01 / "zero" 0x6099:02) until `signal` is
    `until`; `on_limit`: the phases that follow when the limit switch in `direction` is met first (else that
    is a homing error)."""

    direction: int
    speed: str
    signal: Signal
    until: bool
    on_limit: tuple[Phase, ...] | None = None


def _p(direction: int, speed: str, signal: Signal, until: bool, on_limit: tuple[Phase, ...] | None = None) -> Phase:
    return Phase(direction, speed, signal, until, on_limit)


def phases(method: int, inputs: Inputs, x: float) -> tuple[Phase, ...] | None:
    """The searches of `method` from machine position `x` (None: a method this simulation does not perform;
    () for the current position methods)."""
    if method in CURRENT_POSITION_METHODS:
        return ()
    home = inputs.state("home", x)
    if method == 17:  # negative limit switch: home where it goes inactive, approached moving positive
        first = () if inputs.state("negative", x) else (_p(-1, "search", "negative", True),)
        return (*first, _p(+1, "zero", "negative", False))
    if method == 18:
        first = () if inputs.state("positive", x) else (_p(+1, "search", "positive", True),)
        return (*first, _p(-1, "zero", "positive", False))
    if method == 19:  # positive home switch (active above its edge): the edge, leaving the switch moving negative
        return (_p(-1, "zero", "home", False),) if home else (_p(+1, "search", "home", True),
                                                              _p(-1, "zero", "home", False))
    if method == 20:  # the same edge, entering the switch moving positive
        return (_p(-1, "search", "home", False), _p(+1, "zero", "home", True)) if home else (
            _p(+1, "zero", "home", True),)
    if method == 21:  # negative home switch (active below its edge): leaving it moving positive
        return (_p(+1, "zero", "home", False),) if home else (_p(-1, "search", "home", True),
                                                              _p(+1, "zero", "home", False))
    if method == 22:
        return (_p(+1, "search", "home", False), _p(-1, "zero", "home", True)) if home else (
            _p(-1, "zero", "home", True),)
    if method in (23, 27):
        # the cam: towards it in the initial direction d at the search speed, then away from it (-d) at the
        # zero speed until it goes inactive: its edge on the side it was met (method 23: the negative edge,
        # positive initial move; 27: the positive edge, negative initial move). Met the limit switch first:
        # reverse, cross the cam, and leave it on the far side, then come back to that edge
        d = +1 if method == 23 else -1
        leave = _p(-d, "zero", "home", False)
        if home:
            return (leave,)
        back = (_p(-d, "search", "home", True), _p(-d, "search", "home", False), _p(d, "search", "home", True),
                leave)
        return (_p(d, "search", "home", True, on_limit=back), leave)
    return None


@dataclass(frozen=True)
class Search:
    """One search's demand (counts, one per 1 ms tick) and how it ended: "found" (the last tick is the first
    with the input in its state), "limit" (a limit switch not searched for), "travel" (too far)."""

    demands: list[int]
    outcome: str
    velocity: float  # counts/ms at the end


def search(p0: float, v0: float, velocity: float, acceleration: float, done: Callable[[float], bool],
           limit: Callable[[float], bool], travel: float, rnd: Callable[[float], int]) -> Search:
    """Ticks from position p0 (counts) and velocity v0 (counts/ms) towards `velocity` (signed) at
    `acceleration` (counts/ms^2) until `done(x)` (found), `limit(x)` (a limit switch met) or |x - p0| >
    `travel`. Positions are checked once the motion heads the search's way (a reversal first runs down)."""
    out: list[int] = []
    p, v = p0, v0
    a = max(acceleration, 1e-12)
    sign = 1.0 if velocity > 0 else -1.0
    for _ in range(MAX_SEARCH_TICKS):
        dv = velocity - v
        step = max(-a, min(a, dv))
        v_next = v + step
        p += (v + v_next) / 2.0
        v = v_next
        d = rnd(p)
        out.append(d)
        if v * sign > 0.0:
            if done(d):
                return Search(out, "found", v)
            if limit(d):
                return Search(out, "limit", v)
        if abs(p - p0) > travel:
            return Search(out, "travel", v)
    return Search(out, "travel", v)


def stop(p0: float, v0: float, acceleration: float, rnd: Callable[[float], int]) -> list[int]:
    """Decelerate from v0 to standstill at `acceleration` (counts/ms^2)."""
    out: list[int] = []
    p, v = p0, v0
    a = max(acceleration, 1e-12)
    while v != 0.0:
        v_next = v - math.copysign(min(a, abs(v)), v)
        p += (v + v_next) / 2.0
        v = v_next
        out.append(rnd(p))
    return out


def move_to(p0: float, target: int, vmax: float, acceleration: float) -> list[int]:
    """From standstill at p0 to `target` (counts) and stand: a trapezoid (triangle) at `vmax` (counts/ms) and
    `acceleration` (counts/ms^2), the last tick exactly at the target."""
    dist = target - p0
    if dist == 0.0:
        return []
    s = 1.0 if dist > 0 else -1.0
    dist = abs(dist)
    a = max(acceleration, 1e-12)
    v = min(vmax, math.sqrt(dist * a))
    t_acc = v / a
    d_acc = v * t_acc / 2.0
    t_flat = (dist - 2.0 * d_acc) / v
    total = 2.0 * t_acc + t_flat
    n = max(1, math.ceil(total))
    out: list[int] = []
    for k in range(1, n + 1):
        t = min(float(k), total)
        if t <= t_acc:
            x = a * t * t / 2.0
        elif t <= t_acc + t_flat:
            x = d_acc + v * (t - t_acc)
        else:
            r = total - t
            x = dist - a * r * r / 2.0
        out.append(round(p0 + s * x))
    out[-1] = target
    return out
