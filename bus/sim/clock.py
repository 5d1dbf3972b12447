"""A simulated drive's own motion clock: a 1 kHz tick grid with a drift, corrected by 0x1013 time stamps.

The manuals leave open whose clock times the interpolation (docs/drive-model.md, "Variants"). A drive
locked to SYNC needs nothing here (each SYNC is one period of ticks, `DriveDevice._sync`). A drive with
its own clock ticks at 1 kHz of its own oscillator, which runs `drift_ppm` fast (or slow) against true
time; the grid is re-anchored when interpolation starts, so the first tick comes 1 ms of drive time after
the enabling SYNC ("the drive's own 1 kHz clock, started at the enabling SYNC").

Seed 001 (3.6.1-3.6.2, "Synchronization"): the master latches the time it sent each SYNC and sends it
afterwards as the high-resolution time stamp 0x1013 (us); the drive latches its own motion clock when
the SYNC arrives; "after a write access to this object the EPOS2 calculates the difference between the
received timestamp and the internal latched timestamp of the SYNC object. This time difference is used
as correction for the IPM time calculations." The seed does not say how; the choice here: the drive
estimates master time as a line through its (latched local time, master stamp) pairs, the slope from
the oldest and newest of the last `PAIRS` pairs (about 1 s at 10 ms SYNC: 1 us stamps then give the
rate to ~1 ppm), anchored at the newest pair, and times the interpolation by that estimate.

Pure: times in, tick counts out. `t` is true time in seconds (the simulation's clock).
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
