"""A simulated drive's own motion clock: a 1 kHz tick grid with a drift, corrected by 0x1013 time stamps.

Whose clock times the interpolation is an open point (docs/drive-model.md, "Variants"). A SYNC-locked drive
needs nothing here. An own-clock drive ticks at 1 kHz of an oscillator `drift_ppm` off true time, the grid
re-anchored at the enabling SYNC. Seed 001 (3.6.1-3.6.2) corrects it with the 0x1013 time stamp of each
SYNC without saying how; here master time is estimated as a line through the (latched local time, master
stamp) pairs, slope from the oldest and newest of the last `PAIRS` (about 1 s at 10 ms SYNC: ~1 ppm),
anchored at the newest. Pure: true time `t` in, tick counts out.
"""

from __future__ import annotations

import math
from collections import deque

PAIRS = 100
_WRAP_US = 1 << 32


class MotionClock:
    """Ticks due at true time t for one drive with its own clock."""

    def __init__(self, drift_ppm: float, t0: float = 0.0):
        self.rate = 1.0 + drift_ppm * 1e-6  # local seconds per true second
        self._t_ref = t0
        self._pairs: deque[tuple[float, float]] = deque(maxlen=PAIRS)  # (local s, master s)
        self._last_stamp_us: int | None = None
        self._master_unwrapped = 0.0
        self._latched_local: float | None = None
        self._origin = 0.0  # estimated master time (s) of tick 0
        self.done = 0  # ticks run since the origin
        self.stamps = 0

    # ---- clocks
    def local(self, t: float) -> float:
        """The drive's own clock reading (s) at true time t."""
        return (t - self._t_ref) * self.rate

    def master_estimate(self, t: float) -> float:
        """What the drive believes master time is at true time t (its own clock until corrected)."""
        loc = self.local(t)
        if not self._pairs:
            return loc
        l1, m1 = self._pairs[-1]
        return m1 + (loc - l1) * self._slope()

    def _slope(self) -> float:
        if len(self._pairs) < 2:
            return 1.0
        l0, m0 = self._pairs[0]
        l1, m1 = self._pairs[-1]
        return (m1 - m0) / (l1 - l0) if l1 > l0 else 1.0

    @property
    def corrected(self) -> bool:
        return bool(self._pairs)

    # ---- events
    def anchor(self, t: float) -> None:
        """Start the tick grid at true time t (the enabling SYNC): tick k comes k ms of drive time later."""
        self._origin = self.master_estimate(t)
        self.done = 0

    def latch_sync(self, t: float) -> None:
        """A SYNC arrived: latch the motion clock (the time stamp that follows refers to this SYNC)."""
        self._latched_local = self.local(t)

    def time_stamp(self, stamp_us: int) -> None:
        """0x1013 written (the master's send time of the last SYNC, us, mod 2^32)."""
        if self._latched_local is None:
            return
        if self._last_stamp_us is None:
            self._master_unwrapped = stamp_us / 1e6
        else:
            step = (stamp_us - self._last_stamp_us) % _WRAP_US
            self._master_unwrapped += step / 1e6
        self._last_stamp_us = stamp_us
        if not self._pairs:
            # the first pair: re-express the grid origin in master time so running ticks do not jump
            offset = self._master_unwrapped - self._latched_local
            self._origin += offset
        self._pairs.append((self._latched_local, self._master_unwrapped))
        self._latched_local = None
        self.stamps += 1

    def due(self, t: float) -> int:
        """Ticks that should have run by true time t, minus those already run (never negative)."""
        ms = (self.master_estimate(t) - self._origin) * 1000.0
        return max(0, math.floor(ms + 1e-9) - self.done)

    def time_of_tick(self, k: int) -> float:
        """True time at which tick `done + k` falls due (k >= 1)."""
        target_master = self._origin + (self.done + k) / 1000.0
        if self._pairs:
            l1, m1 = self._pairs[-1]
            loc = l1 + (target_master - m1) / self._slope()
        else:
            loc = target_master
        return self._t_ref + loc / self.rate
