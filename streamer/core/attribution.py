"""Feedback attribution: which SYNC a drive's synchronous TPDO answers, decided by what it contains.

Owns the one rule every consumer of feedback uses (the coordinator's start, fill and demand checks, and
through the coordinator's `FeedbackLog` the job report's deviation): it is given the bounds the protocol
sets and a `fits(sync)` test of the TPDO's content, and returns the SYNC. No I/O, no clock.

Why content, not arrival. A drive answers every SYNC once, in order (CiA 301), but how soon is open: an
EPOS may answer up to 0.9 period late, and a loaded bus or host adds to that, so the answer to SYNC k can
reach the master after SYNC k + 1 (reordered with it). When it arrived (its bus stamp `t`) is then no key:
a late stamp made the master take the answer to k for the answer to k + 1 (a false PROTOCOL one SYNC of
travel off, or a false "record arrived twice"). What the answer says is a key: a running axis' position
demand is known in advance for every SYNC (the coordinator predicts it from the queued records with
planner.encoding.hermite), and so are the fill the FIFO can show and whether ip mode can be active.

The candidates for one TPDO of one node are the SYNCs it can answer:
- not after `upper`, the newest SYNC on the wire when it arrived (the runtime's tag: an answer never comes
  before its SYNC);
- after `after`, the last SYNC this PDO of the node answered (once, in order), and for TPDO1 also after the
  last SYNC its TPDO2 answered (a drive sends a SYNC's TPDOs in PDO order, TPDO1 first);
- not before `upper - reach`: the SYNCs whose answers may still be on their way. The caller measures it on
  the wire (streamer/core/feedback.py `_reach`): at least REACH, and every SYNC sent within the TPDO timeout
  before the newest, so a sender that stalled and then put the SYNCs it owed on the wire back to back (or a
  host that held the drives' answers up as long as the timeout allows) leaves the answers in reach. A reach
  counted in SYNCs alone would take the answer to SYNC k, arriving after a burst up to k + 4, for k + 1's:
  content that fits both (a FIFO's fill) would be one SYNC off, content that does not a false PROTOCOL;
- TPDO2 every n-th SYNC: only SYNCs whose counter carries the node (the feedback schedule, 0x1019).
The order's choice is the earliest of them: with no answer lost it is the one (the drive answers every
SYNC, in order). If the content fits it (or content has no say: the axis at rest, a state with nothing to
check), it is taken; else the earliest candidate the content fits (an answer was lost: this one answers a
later SYNC); if none fits, the order's choice, and the check that follows reports the fault (a lost,
duplicated or swapped record fits no SYNC, so it is caught at once, as before). Taking the earliest never
attributes an answer to a SYNC after the one it answers while the drive is right, so the bounds the next
TPDO gets stay true; after a lost answer with nothing to tell the SYNCs apart (at rest) the attribution may
lag by a SYNC until the content differs, which no check minds (they all fit).
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
    TPDO2, and the last SYNC whose TPDO1 showed ip mode active. Kept by the coordinator; the job report
    measures the deviation from it (never from arrival order). Compact columns (streamer/core/spool.py): one
    job of minutes holds a few ten thousand samples per axis in memory; given a `store` (an endless job), the
    columns keep one block each in memory and the rest in the store, and still read whole."""

    __slots__ = ("actual", "demand", "last_active_sync", "sync")

    def __init__(self, store: StoreFactory | None = None) -> None:
        self.sync = Column("q", store)
        self.demand = Column("q", store)
        self.actual = Column("q", store)
        self.last_active_sync: int | None = None

    @property
    def held(self) -> int:
        """Samples held in memory (all of them without a store)."""
        return self.sync.held + self.demand.held + self.actual.held

    def position(self, sync: int, demand: int, actual: int) -> None:
        self.sync.append(sync)
        self.demand.append(demand)
        self.actual.append(actual)

    def active(self, sync: int) -> None:
        if self.last_active_sync is None or sync > self.last_active_sync:
            self.last_active_sync = sync
