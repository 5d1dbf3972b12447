"""Feedback attribution: which SYNC a drive's synchronous TPDO answers, decided by what it contains.

A drive answers every SYNC once, in order, but may answer after the next SYNC, so arrival is no key;
content is (a running axis' demand, the possible fill and ip state are predictable per SYNC). Candidates:
after the last SYNC this PDO (and for TPDO1 its TPDO2) answered, not after the newest SYNC on the wire at
arrival, not before the measured reach, and for a staggered TPDO2 only SYNCs that carry the node. The
earliest candidate is taken if the content fits it, else the earliest that fits, else the earliest (and
the check reports the fault); this never attributes an answer too late while the drive is right. Pure.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from streamer.core.spool import Column, StoreFactory

REACH = 3  # the least reach: an answer can reach the master this many SYNCs after the newest on the wire

Fits = Callable[[int], bool | None]  # does the TPDO's content fit SYNC m? None: content has no say


def candidates(upper: int, after: int, *, reach: int = REACH,
               scheduled: Callable[[int], bool] | None = None) -> list[int]:
    """The SYNCs a TPDO can answer, earliest first: in (after, upper], not before upper - reach, and only
    those `scheduled` says carry it (TPDO2 every n-th SYNC)."""
    lo = max(after + 1, upper - reach)
    return [m for m in range(lo, upper + 1) if scheduled is None or scheduled(m)]


def choose(options: Sequence[int], fits: Fits) -> int | None:
    """The SYNC a TPDO answers among `options` (earliest first): the earliest if its content fits there or
    content has no say, else the earliest it fits, else the earliest (None: no SYNC it can answer)."""
    if not options:
        return None
    order = options[0]
    ok = fits(order)
    if ok is None or ok:
        return order
    return next((m for m in options[1:] if fits(m)), order)


def attribute(upper: int, after: int, fits: Fits, *, reach: int = REACH,
              scheduled: Callable[[int], bool] | None = None, schedule_reach: int = 0) -> int | None:
    """The SYNC a TPDO answers (see the module docstring). `after`: the last SYNC it cannot answer (the
    last one this PDO of the node answered; for TPDO1 also its TPDO2's). `reach`: how many SYNCs before
    `upper` it may answer. `scheduled`/`schedule_reach`: a PDO sent every n-th SYNC, with how far back its
    schedule looks (2n - 1)."""
    reach = max(reach, REACH)
    if scheduled is not None:
        return choose(candidates(upper, after, reach=max(schedule_reach, reach), scheduled=scheduled), fits)
    # `choose` over `candidates`, without building the list (this runs for every TPDO)
    first = max(after + 1, upper - reach)
    if first > upper:
        return None
    ok = fits(first)
    if ok is None or ok:
        return first
    return next((m for m in range(first + 1, upper + 1) if fits(m)), first)


class FeedbackLog:
    """What one node's drive reported, per SYNC it answered (as attributed): position demand and actual from
    TPDO2 and how long after that SYNC the answer left (us: a drive with its own clock may have sampled as
    late as that, streamer/core/drive_time.py), and the last SYNC whose TPDO1 showed ip mode active. Kept by
    the coordinator; the job report measures the deviation from it (never from arrival order). Compact
    columns (streamer/core/spool.py): one job of minutes holds a few ten thousand samples per axis in memory;
    given a `store` (an endless job), the columns keep one block each in memory and the rest in the store, and
    still read whole."""

    __slots__ = ("actual", "demand", "last_active_sync", "late", "sync")

    def __init__(self, store: StoreFactory | None = None) -> None:
        self.sync = Column("q", store)
        self.demand = Column("q", store)
        self.actual = Column("q", store)
        self.late = Column("q", store)
        self.last_active_sync: int | None = None

    @property
    def held(self) -> int:
        """Samples held in memory (all of them without a store)."""
        return self.sync.held + self.demand.held + self.actual.held + self.late.held

    def position(self, sync: int, demand: int, actual: int, late_us: int = 0) -> None:
        self.sync.append(sync)
        self.demand.append(demand)
        self.actual.append(actual)
        self.late.append(late_us)

    def active(self, sync: int) -> None:
        if self.last_active_sync is None or sync > self.last_active_sync:
            self.last_active_sync = sync
