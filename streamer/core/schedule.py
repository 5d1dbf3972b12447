"""The fill model: which records a drive has consumed at a given time, and how far to keep ahead.

Pure functions over the shared timing of a record stream: `ends[i]` is when record i's segment completes
(the end record with the last segment). A SYNC-locked drive has interpolated j * period ms by SYNC s + j,
so the core knows every fill without asking and uses the reported free size only to verify it.
`target_prefix` is the top-up rule: the lockstep prefix K rises to
    max( consumed at next SYNC + R periods + U,     fill stays >= U for R more SYNCs with no arrivals
         consumed at next SYNC + lead_ms + 1 )      the lead time, in motion
capped by consumed-now + O and the stream length. In steady state that sends what the last period
consumed: the smallest batch, which is what makes losses repairable (fifo_feeder.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from streamer.core.window import bisect_right


def segment_ends(segment_ms: Sequence[int]) -> list[int]:
    """ends[i] for N segment records followed by the end record."""
    ends: list[int] = []
    t = 0
    for dt in segment_ms:
        t += dt
        ends.append(t)
    ends.append(t)
    return ends


def consumed_at(ends: Sequence[int], elapsed_ms: int) -> int:
    """Records popped after `elapsed_ms` of interpolation (`ends` may be a `Window`: stream indices)."""
    return bisect_right(ends, elapsed_ms)


@dataclass(frozen=True)
class FillPolicy:
    sync_period_ms: int
    underflow_watermark: int
    overflow_watermark: int
    lead_ms: int
    repair_syncs: int


def target_prefix(ends: Sequence[int], elapsed_now_ms: int, elapsed_next_ms: int, policy: FillPolicy) -> int:
    """Records to have sent by the next SYNC (see the module docstring)."""
    total = len(ends)
    need_count = (
        consumed_at(ends, elapsed_next_ms + policy.repair_syncs * policy.sync_period_ms)
        + policy.underflow_watermark
    )
    need_time = consumed_at(ends, elapsed_next_ms + policy.lead_ms) + 1
    cap = consumed_at(ends, elapsed_now_ms) + policy.overflow_watermark
    return min(total, max(need_count, need_time), cap)


def priming_level(ends: Sequence[int], policy: FillPolicy) -> int:
    """Records in every FIFO before the start: what the first cycle needs, >= 2, <= the overflow watermark."""
    total = len(ends)
    return min(total, policy.overflow_watermark, max(2, target_prefix(ends, 0, 0, policy)))


def needed_fill(underflow_watermark: int, remaining: int) -> int:
    """The lowest acceptable fill at a SYNC with `remaining` records not yet consumed."""
    return min(max(underflow_watermark, 1), remaining)


@dataclass(frozen=True)
class Shortfall:
    """Where a nominal run (no losses) would leave a FIFO below min(U, records left)."""

    elapsed_ms: int
    fill: int
    needed: int


def dry_run(
    ends: Sequence[int], policy: FillPolicy, step_per_sync: int, prefix: int, elapsed_ms: int
) -> Shortfall | None:
    """Simulate the lockstep top-up from (`prefix` records sent, `elapsed_ms` interpolated), sending at
    most `step_per_sync` new records per axis per cycle; the first shortfall, or None when it holds."""
    total = len(ends)
    period = policy.sync_period_ms
    e = elapsed_ms
    k = prefix
    while consumed_at(ends, e) < total:
        want = target_prefix(ends, e, e + period, policy)
        if want > k:
            k = min(want, k + step_per_sync)
        e += period
        c = consumed_at(ends, e)
        needed = needed_fill(policy.underflow_watermark, total - c)
        if k - c < needed:
            return Shortfall(elapsed_ms=e, fill=k - c, needed=needed)
    return None
