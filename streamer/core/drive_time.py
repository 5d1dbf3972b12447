"""Drive time: how far each drive has interpolated at a SYNC, as the master can know it.

A SYNC-locked drive has interpolated exactly j * period ms by SYNC s + j. A drive with its own clock runs
its 1 kHz grid at 1 + e of true time (|e| <= `clock_ppm_max`; with 0x1013 time stamps it follows the
master's clock to a small residual), so the master knows its interpolation time tau only as an interval:
propagated with the SYNCs' own stamps and narrowed by every reported position demand (the ticks whose
predicted demand matches bound tau to [min k, max k + 1)). It starts a tick wide on either side of the start
SYNC, as the grid's phase against that SYNC is the drive's own (`_GRID_PHASE_MS`). In motion the demands pin
tau to about a tick; at standstill it grows by the drift. Everything downstream is computed from [lo, hi];
for a SYNC-locked drive lo == hi. Pure: SYNC counts and times in, intervals out.

When such a drive samples what it reports is its own affair: at the SYNC, or as late as its answer leaves
(a busy drive, a reading of TPDO latency). The answer's own time on the wire (`sampled_by`) bounds it: the
ticks an answer may show run from the interval's low end at the SYNC to its high end at that time, and what
it shows narrows tau at the SYNC by no more than the ticks between the two. Judged at the SYNC alone, a drive
that sampled 2 ms after it (measured here: the simulated drives' process on a loaded machine) showed 2
ticks "too many", and the master failed a job that was right (PROTOCOL, `bench_realtime --only epos`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable

from planner.readings import DriveReadings

# the master's time stamp of the enabling SYNC differs from the drive's reception by bus and processing delays
_ANCHOR_SLACK_MS = 0.25
# where the drive's 1 ms grid stands against the enabling SYNC is the drive's affair (the manuals leave it
# open): anchored there (the own clocks simulated here), running on with its first tick anywhere within a
# tick after it (a drive timed by the SYNCs it receives keeps the remainder of the SYNC intervals before the
# job), or beginning the segment at its first tick after it (a tick behind). The interval starts with all of
# these; the first demands in motion narrow it to the drive's own. Started at +-0.25 ms (anchored alone), a
# drive timed by the SYNCs whose remainder was 0.9 ms was a tick "ahead" as soon as a SYNC left later than
# the enabling one: PROTOCOL in 3 of 4 virtual-time jobs with 60 us of SYNC send delay, and a false fault in
# bench_realtime --only epos (optional_objects_absent)
_GRID_PHASE_MS = 1.0
# a drive timed by the SYNCs it receives (no 0x1006): no drift, only its receive delay against the SYNC's
# time on the wire (tens of us) over the time since the last demand that pinned it
SYNC_TIMED_PPM = 100.0


class DriveTime:
    """Interpolation time of one drive since the start SYNC (ms), exact or as an interval."""

    def __init__(self, period_ms: int, *, own_clock: bool, ppm_max: float, time_stamped: bool) -> None:
        self.period_ms = period_ms
        self.exact = not own_clock
        # with time stamps the drive follows master time; what is left is its estimator's error
        self.rho = (min(ppm_max, 50.0) if time_stamped else ppm_max) * 1e-6
        self._start: int | None = None
        self._t_start = 0.0
        self._ref_sync = 0
        self._ref_t = 0.0
        self._lo = 0.0
        self._hi = 0.0
        self.narrowings = 0

    @classmethod
    def of_reading(cls, r: DriveReadings, period_ms: int, *, cyclic: bool, time_stamped: bool) -> DriveTime:
        """The clock of a drive with readings `r`: locked to SYNC, its own (`clock = "own"`), or timed by the
        SYNCs it receives (0x1006, the cycle period, absent: like its own clock with no drift of its own, the
        SYNC's time on the wire its time base). A cyclic drive takes a set point per SYNC: locked."""
        by_sync_time = 0x1006 in (r.absent or ())
        own = r.clock == "own"
        return cls(period_ms, own_clock=(own or by_sync_time) and not cyclic,
                   ppm_max=r.clock_ppm_max if own else SYNC_TIMED_PPM, time_stamped=time_stamped)

    def plan_window(self, k: float, late_us: int, last_ms: int) -> tuple[int, int]:
        """The plan's ms [lo, hi] a demand answering the SYNC at plan ms `k` may show, known from the start
        alone (the report's check, after the job, without the narrowings): `bounds`' rule in whole ms, a tick
        off the grid's phase plus what the drift added since the start, and ahead by the ticks the drive may
        have run before its answer left `late_us` after the SYNC. A drive not locked to the SYNC count runs on
        time: its `k` is the ms since the start SYNC by the SYNCs' times, which need not be whole. A SYNC-locked
        drive: k."""
        lo_k, hi_k = math.floor(k), math.ceil(k)
        if self.exact:
            return lo_k, hi_k
        ahead = math.ceil(late_us * 1e-3 * (1.0 + self.rho))
        return (max(0, lo_k - 1 - math.ceil(self.rho * lo_k)),
                min(last_ms, hi_k + 1 + math.ceil(self.rho * hi_k) + ahead))

    def start(self, sync: int, t: float) -> None:
        """Interpolation began at SYNC `sync`, sent at time `t` (s)."""
        self._start = sync
        self._t_start = t
        self._ref_sync, self._ref_t = sync, t
        self._lo, self._hi = -_GRID_PHASE_MS - _ANCHOR_SLACK_MS, _GRID_PHASE_MS + _ANCHOR_SLACK_MS

    @property
    def started(self) -> bool:
        return self._start is not None

    def bounds(self, sync: int, t: float, sampled_by: float | None = None) -> tuple[float, float]:
        """[lo, hi] of the drive's interpolation time (ms) at SYNC `sync` sent at time `t`; with `sampled_by`
        (the time its answer left), of what the answer may show: hi runs on to that time."""
        s = self._start
        if s is None or sync <= s:
            return 0.0, 0.0
        if self.exact:
            e = float((sync - s) * self.period_ms)
            return e, e
        dt_ms = max(0.0, (t - self._ref_t) * 1000.0)
        lo = max(0.0, self._lo + dt_ms * (1.0 - self.rho))
        if sampled_by is not None:
            dt_ms = max(dt_ms, (sampled_by - self._ref_t) * 1000.0)
        hi = max(lo, self._hi + dt_ms * (1.0 + self.rho))
        return lo, hi

    def ticks(self, sync: int, t: float, sampled_by: float | None = None) -> tuple[int, int]:
        """The whole ticks the drive may have run by SYNC `sync` (by `sampled_by`: see `bounds`):
        [floor(lo), floor(hi)]."""
        lo, hi = self.bounds(sync, t, sampled_by)
        return math.floor(lo + 1e-9), math.floor(hi + 1e-9)

    def observe(self, sync: int, t: float, matching_ticks: Iterable[int], sampled_by: float | None = None) -> None:
        """The drive's report at SYNC `sync` (sampled by `sampled_by` at the latest) is explained by these tick
        counts only: narrow tau at the SYNC (by the ticks it may have run since, less at the low end)."""
        if self.exact or self._start is None:
            return
        ks = list(matching_ticks)
        if not ks:
            return
        lo, hi = self.bounds(sync, t)
        late_ms = 0.0 if sampled_by is None else max(0.0, (sampled_by - t) * 1000.0) * (1.0 + self.rho)
        new_lo = max(lo, float(min(ks)) - late_ms)
        new_hi = min(hi, float(max(ks) + 1) - 1e-6)
        if new_lo > new_hi:  # numerical edge: keep the observation, it is the stronger statement
            new_lo, new_hi = float(min(ks)) - late_ms, float(max(ks) + 1) - 1e-6
        if new_hi - new_lo < hi - lo:
            self.narrowings += 1
        self._ref_sync, self._ref_t = sync, t
        self._lo, self._hi = new_lo, new_hi

    def matching(self, sync: int, t: float, predict: Callable[[int], Iterable[int]], demand: int,
                 tolerance: int, sampled_by: float | None = None) -> tuple[list[int], int]:
        """Ticks k in the current interval (to `sampled_by`: see `bounds`) whose predicted demands (one per
        rounding reading) hit `demand` exactly, and the smallest |demand - prediction| over the interval (for
        the tolerance check)."""
        k_lo, k_hi = self.ticks(sync, t, sampled_by)
        exact: list[int] = []
        best = math.inf
        for k in range(k_lo, k_hi + 1):
            for p in predict(k):
                err = abs(demand - p)
                if err < best:
                    best = err
                if err == 0:
                    exact.append(k)
        if not exact and best <= tolerance:
            for k in range(k_lo, k_hi + 1):
                if any(abs(demand - p) <= tolerance for p in predict(k)):
                    exact.append(k)
        return exact, int(best) if math.isfinite(best) else 2**31
