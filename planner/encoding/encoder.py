"""PVT encoder: a `Reference` (the planned motion at every ms) -> knots on one shared integer-ms grid.

Theory of operation. The drive rebuilds each axis from PVT knots with seed 000 4.2.3's cubic
(planner/encoding/hermite.py) every 1 ms, rounded to whole counts. Contract, checked at every ms of every
axis on the quantised values: |drive demand - planned demand| <= tolerance, both in whole counts (the
planned demand is the plan rounded as the drive rounds; docs/formats.md, section 3, says why integer).

1. Knot times, shared by all axes (`place_knots`): greedily the longest segment whose exact-value Hermite
   stays within `PLACEMENT_SHARE` of the tolerance and `ACC_PLACEMENT_SHARE` of the acceleration limit,
   with sections ending at the plan's acceleration steps and `hints`; `min_segment` / `max_segment`
   bound the lengths (quantisation is acceleration noise on short segments, position error on long ones).
   The coarsest valid uniform grid competes (`_uniform_alternative`), so no encoding needs more records.
2. Knot values (`_choose_values`): per axis a Viterbi pass over each knot's candidates (planned demand
   +-1 count, the two rpm around the plan) keeping the tolerance and minimising the acceleration excess.
3. Verification at every ms; failing segments are refined, then split. Limits or `ACC_EXCESS_LIMIT`
   exceeded raise `EncodingNeedsTime`: other placements (`variant`), then a slower replay.

Knot 0 is the start state exactly, the last knot the end in counts at rest (or cruising, open-ended).
Steps 2 and 3 are compiled (quantise.py); `Knots` and the reconstruction are reconstruction.py.
"""

from __future__ import annotations

import bisect
import contextlib

import numpy as np
from numpy.typing import NDArray

from planner.encoding import hermite, quantise
from planner.encoding.reconstruction import (  # the callers' and tests' `encoder.X` for these still work
    AxisScales,
    Knots,
    Reconstruction,
    acceleration_excess,
    planned_demand,
    reconstruct,
    segment_envelope,
)
from planner.encoding.reconstruction import drive_round as drive_round  # tests/planner/encoding/placement_reference.py
from planner.encoding.reconstruction import toward_zero_flags as _toward_zero
from planner.encoding.record import POSITION_MAX, POSITION_MIN, SEGMENT_TIME_MAX_MS
from planner.jit import kernel
from planner.motion.reference import FloatArray, IntArray, Reference

PLACEMENT_SHARE = 0.7  # share of the tolerance the exact-value Hermite may use (the rest: quantisation)
SECTION_MS = 250  # a plan without hints is placed in sections of at most this length
ACC_EXCESS_LIMIT = 0.05  # reconstruction acceleration over the plan, as a share of the axis limit
VELOCITY_SLACK = 0.005  # reconstruction velocity over the axis limit allowed (0.5 %)
MAX_ROUNDS = 6  # verify/refine/split rounds before giving up
ACC_PLACEMENT_SHARE = 0.02  # end-acceleration miss of exact-value segments, share of the axis limit
STEP_SHARE = 0.15  # acceleration steps above this share of the axis limit get a knot of their own
MANDATORY_GAP = 4  # ms: acceleration steps closer than this share one knot
DP_VELOCITIES = (0, 1)  # first pass: the two rpm values around the plan (refinement: 7)
_DP_POSITIONS = (-1.0, 0.0, 1.0)  # counts around the planned demand
_PROX = np.array([1 / 6, 1 / 3, 1 / 2, 2 / 3, 5 / 6, 0.93])  # sample ticks (fractions of a segment)
_LADDER = np.array([0.55, 0.75, 0.9, 1.0, 1.12, 1.3, 1.6, 2.0])


class EncodingNeedsTime(Exception):
    """Internal: the motion is too fast for the quantisation (slow it down by `factor` and retry)."""

    def __init__(self, message: str, factor: float, axis: int = -1):
        super().__init__(message)
        self.message = message
        self.factor = factor
        self.axis = axis


class EncodingFailed(Exception):
    """Internal: the reference cannot be encoded within tolerance (the caller raises a PlanningError)."""

    def __init__(self, message: str, axis: int = -1, tick: int = -1):
        super().__init__(message)
        self.message = message
        self.axis = axis
        self.tick = tick


# ----------------------------------------------------------------------------------------------------
# knot placement


def _segment_errors(
    ref: Reference,
    starts: IntArray,
    lengths: IntArray,
    acc_axis: FloatArray,
    min_seg: int = 0,
    acc_share: float = ACC_PLACEMENT_SHARE,
    every_tick: bool = False,
) -> FloatArray:
    """Candidate segments' error: max over axes of the position error (counts) of the Hermite through the
    exact knot values, at the sample ticks `_PROX` (or at every tick), or inf where its end accelerations
    already miss the plan's by more than `acc_share` of the axis limit (the linear Hermite acceleration
    cannot follow a jerk kink inside a long segment; quantisation needs the rest of the budget). Shorter
    segments than `min_seg` only make the quantisation noise worse: the acceleration check applies above."""
    return _segment_errors_kernel(
        ref.positions, ref.velocities, ref.acc_left, ref.acc_right, np.ascontiguousarray(starts, dtype=np.int64),
        np.ascontiguousarray(lengths, dtype=np.int64), acc_share * acc_axis, min_seg, every_tick, _PROX)


@kernel
def _basis(x: float, t1: float) -> tuple[float, float, float, float]:
    """The cubic Hermite's weights at x = tau / T of a segment of T = t1 ms: position = h00 p0 + h01 p1 +
    h10 v0 + h11 v1 (velocities per ms)."""
    x2 = x * x
    h00 = 1.0 - 3.0 * x2 + 2.0 * x2 * x
    return h00, 1.0 - h00, (x - 2.0 * x2 + x2 * x) * t1, (x2 * x - x2) * t1


@kernel
def _segment_error(
    p: FloatArray, v: FloatArray, acc_left: FloatArray, acc_right: FloatArray, a: int, length: int,
    acc_limit: FloatArray, min_seg: int, every_tick: bool, prox: FloatArray,
) -> float:
    """One segment of `_segment_errors` (the same arithmetic as the NumPy reconstruction, term by term)."""
    b = a + length
    t1 = float(length)
    n = p.shape[0]
    if length > min_seg:
        for i in range(n):
            dp = p[i, b] - p[i, a]
            acc_s = (6.0 * dp - 2.0 * t1 * v[i, b] - 4.0 * t1 * v[i, a]) / (t1 * t1)
            acc_e = (-6.0 * dp + 4.0 * t1 * v[i, b] + 2.0 * t1 * v[i, a]) / (t1 * t1)
            if max(abs(acc_s - acc_right[i, a]), abs(acc_e - acc_left[i, b])) > acc_limit[i]:
                return np.inf
    count = length if every_tick else prox.size
    err = 0.0
    for j in range(count):
        off = float(j + 1) if every_tick else min(max(np.rint(prox[j] * t1), 1.0), max(t1 - 1.0, 1.0))
        h00, h01, h10, h11 = _basis(off / t1, t1)
        tick = a + int(off)
        for i in range(n):
            h = p[i, a] * h00 + v[i, a] * h10 + p[i, b] * h01 + v[i, b] * h11
            err = max(err, abs(h - p[i, tick]))
    return err


@kernel
def _segment_errors_kernel(
    p: FloatArray, v: FloatArray, acc_left: FloatArray, acc_right: FloatArray, starts: IntArray,
    lengths: IntArray, acc_limit: FloatArray, min_seg: int, every_tick: bool, prox: FloatArray,
) -> FloatArray:
    out = np.empty(starts.size)
    for k in range(starts.size):
        out[k] = _segment_error(p, v, acc_left, acc_right, starts[k], lengths[k], acc_limit, min_seg, every_tick,
                                prox)
    return out


def load_kernels(ref: Reference) -> None:
    """Compile (or load) the kernels a small plan may not reach (planner.plan.warm_up): the error of
    candidate segments at every tick (`_rebalance`, where the placement left short segments)."""
    _segment_errors(ref, np.array([0]), np.array([ref.duration_ms]), np.ones(ref.n_axes), 0, every_tick=True)


def segment_bounds(scales: AxisScales, tolerance: float) -> tuple[int, int]:
    """(min_segment, max_segment) in ms for these axes (see the module docstring)."""
    conv = float(np.max(scales.counts_per_ms_per_rpm))
    a_min = float(np.min(scales.acceleration_axis))
    # one rpm error over a segment of T ms peaks at T * conv * 4/27 counts; keep that near the tolerance
    max_seg = int(np.clip(np.floor(tolerance * 27.0 / (2.0 * conv)), 16, SEGMENT_TIME_MAX_MS))
    # 0.6 rpm of velocity error moves an end acceleration by 4 * 0.6 * conv / T: keep that under 5 %
    min_seg = int(np.clip(np.ceil(2.4 * conv / (ACC_EXCESS_LIMIT * a_min)), 4, 40))
    if scales.max_segment_ms is not None:  # a job's bound, never below what the acceleration budget allows
        max_seg = min(max_seg, max(scales.max_segment_ms, min_seg))
    return min(min_seg, max_seg), max_seg


def segment_cap(scales: AxisScales, tolerance: float) -> int | None:
    """The longest segment the job's `max_segment_ms` allows these axes (None: no bound asked): the bound,
    raised to the shortest segment the acceleration budget allows where it is below it."""
    return None if scales.max_segment_ms is None else segment_bounds(scales, tolerance)[1]


def _mandatory_knots(ref: Reference, scales: AxisScales, min_gap: int) -> IntArray:
    """Start, end, and the plan's acceleration steps above `STEP_SHARE` of an axis' limit.

    A Hermite segment has a linear acceleration: one that spans a step misses it on both sides (an
    acceleration excess over the plan, even when the positions stay within the tolerance). Steps closer
    than `min_gap` ms share the knot of the larger one.
    """
    m = ref.duration_ms
    b = ref.breaks
    if b.size == 0 or m <= 2 * min_gap:
        return np.array([0, m], dtype=np.int64)
    step = np.abs(ref.acc_right[:, b] - ref.acc_left[:, b])
    rel = (step / scales.acceleration_axis[:, None]).max(axis=0)
    big = rel > STEP_SHARE
    cand = b[big]
    order = np.argsort(-rel[big], kind="stable")
    kept: list[int] = []  # sorted
    for t in cand[order].tolist():
        if t < min_gap or m - t < min_gap:
            continue
        i = bisect.bisect_left(kept, t)  # the nearest kept steps are its neighbours in the sorted list
        if (i == 0 or t - kept[i - 1] >= min_gap) and (i == len(kept) or kept[i] - t >= min_gap):
            kept.insert(i, t)
    return np.array([0, *kept, m], dtype=np.int64)


def place_knots(
    ref: Reference,
    scales: AxisScales,
    budget: float,
    min_seg: int,
    max_seg: int,
    acc_share: float = ACC_PLACEMENT_SHARE,
    hint_gap: int = 0,
    keep_kinks: bool = True,
) -> IntArray:
    """Greedy shared knot times 0..M (see the module docstring); hints closer than `hint_gap` (default
    `min_seg`) to a kept one are no section boundary, unless the acceleration may step there and
    `keep_kinks`."""
    m = ref.duration_ms
    if m <= 0:
        return np.array([0], dtype=np.int64)
    mand = _mandatory_knots(ref, scales, MANDATORY_GAP)
    bounds, piece = _structure(ref, mand, hint_gap or min_seg, max_seg, keep_kinks)
    # each section in equal parts, none longer than `piece`
    span = np.diff(bounds)
    parts = -(-span // piece)
    first = np.repeat(np.cumsum(parts) - parts, parts)
    j = np.arange(int(parts.sum())) - first
    cuts = np.append(np.repeat(bounds[:-1], parts) + (j * np.repeat(span, parts)) // np.repeat(parts, parts), m)
    found = _greedy_knots(
        ref.positions, ref.velocities, ref.acc_left, ref.acc_right, cuts.astype(np.int64),
        acc_share * scales.acceleration_axis, budget, min_seg, max_seg, _PROX, _LADDER)
    times = np.unique(found)
    times = _rebalance(ref, times, mand, budget, min_seg, max_seg, scales.acceleration_axis, acc_share)
    return _coarsen(ref, times, mand, budget, min_seg, max_seg, scales.acceleration_axis, acc_share)


@kernel
def _greedy_knots(
    p: FloatArray, v: FloatArray, acc_left: FloatArray, acc_right: FloatArray, cuts: IntArray,
    acc_limit: FloatArray, budget: float, min_seg: int, max_seg: int, prox: FloatArray, ladder: FloatArray,
) -> IntArray:
    """The greedy placement of `place_knots` in every section [cuts[j], cuts[j+1]]: the knots it visits,
    the cuts included (unsorted where sections interleave nothing: each section's knots in order)."""
    out = np.empty(cuts[-1] + cuts.size + 1, dtype=np.int64)
    count = 0
    lens = np.empty(ladder.size + 3, dtype=np.int64)
    for j in range(cuts.size - 1):
        a, b = cuts[j], cuts[j + 1]
        out[count] = a
        count += 1
        cur = a
        prev = min(b - a, min(max_seg, 2 * min_seg))
        while cur < b:
            room = b - cur
            lim = min(room, max_seg)
            half = np.ceil(room / 2.0)
            for k in range(ladder.size):
                lens[k] = np.rint(prev * ladder[k])
            lens[ladder.size] = lim
            lens[ladder.size + 1] = half
            lens[ladder.size + 2] = np.ceil(room / 3.0)
            best_score = 0
            shortest = lim
            for k in range(lens.size):
                length = min(max(lens[k], 1), lim)
                lens[k] = length
                shortest = min(shortest, length)
                if _segment_error(p, v, acc_left, acc_right, cur, length, acc_limit, min_seg, False, prox) > budget:
                    continue
                rem = room - length
                score = length + 4096 * (rem == 0) + 2048 * (rem >= min_seg) + 1024 * (length == half)
                best_score = max(best_score, score)
            best = best_score % 1024
            if best > 0:
                cur += best
                prev = best
                out[count] = cur
                count += 1
            else:
                prev = max(1, shortest // 3)  # length 1 always passes, eventually
    out[count] = cuts[-1]
    return out[: count + 1]


def _structure(
    ref: Reference, mand: IntArray, gap: int, max_seg: int, keep_kinks: bool = True
) -> tuple[IntArray, int]:
    """Section boundaries and the longest section: the plan's own structure where it has one.

    With `hints` (a ruckig profile's phases, a user's rows, a path chain's knots) the plan is one cubic
    between two of them: they become section boundaries (those closer than `gap` to a kept one are
    dropped, a short phase is better crossed than isolated, unless the acceleration may step there or
    the conservative variant keeps them all) and sections are at most `max_seg` long, so a section that a
    single segment reproduces becomes exactly one. Without hints (time-optimal path profiles) sections are the
    stretches between the mandatory knots, cut at `SECTION_MS`.
    """
    if ref.hints.size == 0:
        return mand, SECTION_MS
    kinks = np.zeros(ref.duration_ms + 1, dtype=np.bool_)
    if keep_kinks:
        kinks[ref.breaks] = True
    return _keep_hints(np.sort(mand), ref.hints, kinks, gap), max_seg


@kernel
def _keep_hints(mand: IntArray, hints: IntArray, kinks: NDArray[np.bool_], gap: int) -> IntArray:
    """`_structure`'s boundaries: `mand` and the sorted `hints` at least `gap` from every boundary kept
    before them, or where the acceleration may step (`kinks`: a chain's knot, a pvt row is kept however
    close: a segment across it cannot follow the plan)."""
    kept = np.empty(mand.size + hints.size, dtype=np.int64)
    kept[: mand.size] = mand
    size = mand.size
    for h in hints:
        i = np.searchsorted(kept[:size], h)  # bisect_left
        nearest = np.iinfo(np.int64).max
        if i > 0:
            nearest = abs(h - kept[i - 1])
        if i < size:
            nearest = min(nearest, abs(h - kept[i]))
        if kinks[h] or nearest >= gap:
            kept[i + 1 : size + 1] = kept[i:size].copy()
            kept[i] = h
            size += 1
    return kept[:size].copy()


def _coarsen(
    ref: Reference,
    times: IntArray,
    mand: IntArray,
    budget: float,
    min_seg: int,
    max_seg: int,
    acc_axis: FloatArray,
    acc_share: float,
) -> IntArray:
    """Drop every knot whose two segments one segment reproduces as well (error at every tick within
    `budget`, end accelerations within `acc_share`, at most `max_seg` long). Dense user rows and the
    sections' cuts otherwise cost points that a uniform grid would not spend. Knots at even and odd
    positions alternate, so no two neighbours are dropped at once; rounds repeat while any is."""
    fixed = np.zeros(ref.duration_ms + 1, dtype=np.bool_)
    fixed[mand] = True
    return _coarsen_kernel(ref.positions, ref.velocities, ref.acc_left, ref.acc_right, times, fixed, budget, min_seg,
                           max_seg, acc_share * acc_axis, _PROX)


@kernel
def _coarsen_kernel(
    p: FloatArray, v: FloatArray, acc_left: FloatArray, acc_right: FloatArray, times: IntArray,
    fixed: NDArray[np.bool_], budget: float, min_seg: int, max_seg: int, acc_limit: FloatArray, prox: FloatArray,
) -> IntArray:
    t = times.copy()
    for _round in range(64):
        dropped = False
        for parity in (1, 2):
            keep = np.ones(t.size, dtype=np.bool_)
            for k in range(parity, t.size - 1, 2):
                length = t[k + 1] - t[k - 1]
                if fixed[t[k]] or length > max_seg:
                    continue
                err = _segment_error(p, v, acc_left, acc_right, t[k - 1], length, acc_limit, min_seg, True, prox)
                if err <= budget:
                    keep[k] = False
            if not keep.all():
                t = t[keep]
                dropped = True
        if not dropped:
            break
    return t


def _rebalance(
    ref: Reference,
    times: IntArray,
    mand: IntArray,
    budget: float,
    min_seg: int,
    max_seg: int,
    acc_axis: FloatArray,
    acc_share: float,
) -> IntArray:
    """Remove or move knots next to segments shorter than `min_seg` where the plan allows it: position
    within `budget` at every tick and end accelerations within `acc_share` (one pass, all candidate
    segments checked at every tick)."""
    if not (np.diff(times) < min_seg).any():
        return times
    fixed = np.zeros(ref.duration_ms + 1, dtype=np.bool_)
    fixed[mand] = True
    return _rebalance_kernel(ref.positions, ref.velocities, ref.acc_left, ref.acc_right, times, fixed, budget,
                             min_seg, max_seg, acc_share * acc_axis, _PROX)


@kernel
def _rebalance_kernel(
    p: FloatArray, v: FloatArray, acc_left: FloatArray, acc_right: FloatArray, t: IntArray,
    fixed: NDArray[np.bool_], budget: float, min_seg: int, max_seg: int, acc_limit: FloatArray, prox: FloatArray,
) -> IntArray:
    """`_rebalance`: for each short segment k, in order, the options (drop the right knot, drop the left
    one, move the right one to the middle of its two segments, move the left one there), each passing
    when all the segments it makes do; the first passing option of each short segment whose knot is not
    next to one already changed is taken."""
    last = t.size - 1
    new_t = t.copy()
    keep = np.ones(t.size, dtype=np.bool_)
    touched = np.zeros(t.size + 1, dtype=np.bool_)
    for k in range(t.size - 1):
        a, b = t[k], t[k + 1]
        if b - a >= min_seg:
            continue
        for option in range(4):
            right = option % 2 == 0
            idx = k + 1 if right else k
            if (right and not (k + 1 < last)) or (not right and k < 1) or fixed[t[idx]]:
                continue
            lo, hi = (a, t[k + 2]) if right else (t[k - 1], b)
            if option < 2:  # drop the knot: one segment across both
                if hi - lo > max_seg:
                    continue
                good = _segment_error(p, v, acc_left, acc_right, lo, hi - lo, acc_limit, min_seg, True,
                                      prox) <= budget
                value = -1
            else:  # move it to the middle
                value = (lo + hi) // 2
                if value - lo < min_seg or hi - value < min_seg:
                    continue
                e1 = _segment_error(p, v, acc_left, acc_right, lo, value - lo, acc_limit, min_seg, True, prox)
                e2 = _segment_error(p, v, acc_left, acc_right, value, hi - value, acc_limit, min_seg, True, prox)
                good = max(e1, e2) <= budget
            if not good:
                continue
            if (idx >= 1 and touched[idx - 1]) or touched[idx] or touched[idx + 1]:
                continue  # next to a knot already changed
            if value < 0:
                keep[idx] = False
            else:
                new_t[idx] = value
            touched[idx] = True
            break
    return np.unique(new_t[keep])


# ----------------------------------------------------------------------------------------------------
# value choice (Viterbi over the knots, per axis)


def _axis_terms(scales: AxisScales) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
    """Per axis, as the compiled value search takes them: counts/ms per rpm, the acceleration-excess
    budget (counts/ms^2), 0x60C5, 0x607F, and which drives truncate."""
    return (
        np.ascontiguousarray(scales.counts_per_ms_per_rpm, dtype=np.float64),
        np.ascontiguousarray(ACC_EXCESS_LIMIT * scales.acceleration_axis, dtype=np.float64),
        np.ascontiguousarray(scales.drive_acceleration, dtype=np.float64),
        np.ascontiguousarray(scales.drive_velocity, dtype=np.float64),
        _toward_zero(scales),
    )


def _choose_values(
    ref: Reference,
    times: IntArray,
    scales: AxisScales,
    tolerance: float,
    ends: tuple[IntArray, IntArray, IntArray, IntArray],
    envelope: FloatArray,
) -> tuple[IntArray, IntArray]:
    """Quantised positions (counts) and velocities (rpm) for every knot, chosen jointly at the sample
    ticks; knot 0 and the last knot are `ends` (first positions, velocities, last positions, velocities);
    `envelope`: `segment_envelope(ref, times)`.

    Candidates per knot: the planned demand and one count either side (all within the tolerance at the
    knot; the side counts let a slow axis keep its motion smooth on a grid set by faster ones), and the
    two rpm values that bracket the plan's velocity (`DP_VELOCITIES`)."""
    conv, budget, drive_acc, drive_vel, tz = _axis_terms(scales)
    p_first, v_first, p_last, v_last = (np.ascontiguousarray(e, dtype=np.int64) for e in ends)
    return quantise.choose_values(
        ref.positions, ref.velocities, envelope, np.ascontiguousarray(times, dtype=np.int64), conv, budget,
        drive_acc, drive_vel, tz, tolerance, _PROX, np.array(_DP_POSITIONS), np.array(DP_VELOCITIES, dtype=np.int64),
        DP_VELOCITIES == (0, 1), (p_first, v_first), (p_last, v_last),
    )


def _refine(
    ref: Reference,
    knots: Knots,
    scales: AxisScales,
    tolerance: float,
    bad: NDArray[np.bool_],
    fixed_knots: set[int],
    envelope: FloatArray,
) -> Knots:
    """Choose the values again around failing segments, with more candidates and an exact check.

    `bad` (n_axes, N) marks the failing segments of each axis; a window of two knots either side of
    them is chosen again on the axes that fail inside it (the others keep their values, which pass),
    with 7 velocity candidates and every tick checked (`quantise.refine`). `envelope`:
    `segment_envelope(ref, knots.times_ms)`.
    """
    times = knots.times_ms
    pinned = np.zeros(times.size, dtype=bool)
    pinned[sorted(fixed_knots)] = True
    conv, budget, drive_acc, drive_vel, tz = _axis_terms(scales)
    pos, vel = quantise.refine(
        ref.positions, ref.velocities, envelope, np.ascontiguousarray(times, dtype=np.int64),
        np.ascontiguousarray(knots.positions, dtype=np.int64),
        np.ascontiguousarray(knots.velocities_rpm, dtype=np.int64), np.ascontiguousarray(bad), pinned,
        conv, budget, drive_acc, drive_vel, tz, tolerance, _PROX, np.array(_DP_POSITIONS),
        np.arange(-3, 4, dtype=np.int64),
    )
    return Knots(times, pos, vel)


# ----------------------------------------------------------------------------------------------------
# the encoder


def encode(
    ref: Reference,
    scales: AxisScales,
    *,
    tolerance: float,
    start_positions: IntArray | None = None,
    start_velocities_rpm: IntArray | None = None,
    times_ms: IntArray | None = None,
    variant: int = 0,
    uniform_fallback: bool = False,
    end_velocities_rpm: IntArray | None = None,
) -> tuple[Knots, Reconstruction]:
    """Knots for `ref` whose drive reconstruction is within `tolerance` counts of it at every ms.

    `start_positions`/`start_velocities_rpm` fix knot 0 (default: the plan's start rounded, at rest);
    `end_velocities_rpm` the last knot's velocity (default 0: an open-ended velocity move ends cruising);
    `times_ms` gives the knot times instead of placing them (raw PVT jobs pass their own rows through);
    a segment whose quantised values cannot meet the tolerance is still split in two. `variant` 1 and 2
    are the retries when the quantisation noise exceeded the budget (see the module docstring).
    `uniform_fallback`: also try the coarsest uniform grid with fewer knots (`_uniform_alternative`;
    the planner asks for it).
    Raises EncodingNeedsTime or EncodingFailed (internal; the planner turns them into PlanningError).
    """
    n = ref.n_axes
    m = ref.duration_ms
    tol = float(np.floor(tolerance + 1e-9))
    if m <= 0:
        raise EncodingFailed("a motion needs at least 1 ms")
    p_first = (
        np.asarray(start_positions, dtype=np.int64)
        if start_positions is not None
        else hermite.round_counts_array(ref.positions[:, 0])
    )
    v_first = (
        np.asarray(start_velocities_rpm, dtype=np.int64)
        if start_velocities_rpm is not None
        else np.zeros(n, dtype=np.int64)
    )
    p_last = hermite.round_counts_array(ref.positions[:, m])
    v_last = np.zeros(n, dtype=np.int64) if end_velocities_rpm is None else np.asarray(end_velocities_rpm, np.int64)
    for a in (p_first, p_last):
        if a.min() < POSITION_MIN or a.max() > POSITION_MAX:
            i = int(np.argmax((a < POSITION_MIN) | (a > POSITION_MAX)))
            raise EncodingFailed(f"position {int(a[i])} counts does not fit int32", axis=i)
    min_seg, max_seg = segment_bounds(scales, tol)
    share, acc_share = PLACEMENT_SHARE, ACC_PLACEMENT_SHARE
    if variant == 1:  # conservative: shorter maximum segments leave the value search more room
        max_seg = max(16, int(0.6 * max_seg))
        share = 0.5
        min_seg = min(min_seg, max_seg)
    elif variant >= 2:  # long: fewer short segments, where slow axes on the shared grid need them
        min_seg = min(int(1.6 * min_seg), max_seg)
        acc_share = 2.0 * ACC_PLACEMENT_SHARE
    cap = segment_cap(scales, tol)
    if cap is not None:  # the job's bound holds in every variant
        max_seg = min(max_seg, cap)
        min_seg = min(min_seg, max_seg)
    if times_ms is None:
        # the long variant also crosses close kinks: a few ms between two knots shake the acceleration
        # more than a segment across a small acceleration step
        times = place_knots(
            ref, scales, share * tol, min_seg, max_seg, acc_share, 1 if variant == 1 else 0, variant < 2
        )
    else:
        times = _split_long(np.asarray(times_ms, dtype=np.int64), max_seg)
    ends = (p_first, v_first, p_last, v_last)
    if not (times_ms is None and uniform_fallback):
        return _quantise(ref, times, scales, tol, ends)
    # a plan made of whole cubics (a jerk-limited profile's phases, a user's rows, a path's chain)
    # often allows segments beyond `max_seg` (a worst case of the velocity quantisation), and a uniform
    # grid may beat the greedy placement: try them too, keep the fewest knots that pass. A retry
    # (variant 1, 2) keeps its own placement, and is compared with the uniform grids too: the coarsest
    # uniform grid that keeps every promise bounds every encoding (a small path slowed down for its
    # acceleration budget had 4 knots where 3 on a uniform grid passed)
    grids = [times]
    if variant == 0:
        longest = segment_cap(scales, tol) or SEGMENT_TIME_MAX_MS
        grids.append(place_knots(ref, scales, share * tol, min_seg, longest, acc_share))
    failure: EncodingNeedsTime | EncodingFailed | None = None
    found: tuple[Knots, Reconstruction] | None = None
    # fewest knots first: where that placement passes, the other (more knots) is not quantised at all
    for grid in sorted(grids, key=len):
        if found is not None and grid.size >= found[0].times_ms.size:
            continue
        try:
            other = _quantise(ref, grid, scales, tol, ends)
        except (EncodingNeedsTime, EncodingFailed) as e:
            failure = failure or e
            continue
        if found is None or other[0].times_ms.size < found[0].times_ms.size:
            found = other
    found = _uniform_alternative(ref, scales, tol, ends, found, times.size)
    if found is None:
        assert failure is not None
        raise failure
    return found


def _uniform_alternative(
    ref: Reference,
    scales: AxisScales,
    tol: float,
    ends: tuple[IntArray, IntArray, IntArray, IntArray],
    best: tuple[Knots, Reconstruction] | None,
    placed: int,
) -> tuple[Knots, Reconstruction] | None:
    """The coarsest uniform grid's number of knots, if fewer than `best`'s (or, when no other placement
    passed, than the `placed` knots of the greedy placement) and they pass everything `encode` checks
    (the grid's plain values, or values chosen jointly on it; a grid that meets the tolerance but not
    the acceleration budget gives way to the next finer one).

    An encoding should never need more knots than the coarsest plain uniform grid that meets the
    tolerance (planner/encoding/uniform.py: rounded values, the tolerance at every ms). Where that grid has fewer
    knots than `best`, the same number spread evenly (no short last segment, which the acceleration
    budget would not allow) and the uniform grid itself have their values chosen and verified like any
    other placement, and the one with the fewest knots replaces `best`. Only grids with fewer knots
    than `best` are looked at, each first at three ticks per segment (`_uniform_misses`), so this costs
    little where the adaptive placement is far below the uniform grid (paths).
    """
    m = ref.duration_ms
    count = best[0].times_ms.size if best is not None else placed
    p_first, v_first, _p_last, v_last = ends
    want = planned_demand(ref, scales.toward_zero)
    conv = scales.counts_per_ms_per_rpm[:, None]
    longest = min(segment_cap(scales, tol) or SEGMENT_TIME_MAX_MS, m)
    lengths = np.arange(longest, 0, -1)
    lengths = lengths[-(-m // lengths) + 1 < count]  # only grids with fewer knots than `best`
    if lengths.size == 0:
        return best
    # the cheap check of every grid first (three ticks per segment, the middle one first), then the full one
    # in order
    tz = np.zeros(ref.n_axes, dtype=bool) if scales.toward_zero is None else scales.toward_zero
    missed = _uniform_misses(want, ref.velocities, scales.counts_per_ms_per_rpm, tz, tol, p_first, v_first, v_last,
                             lengths, np.array([0.5, 0.25, 0.75]))
    survivors = [np.unique(np.concatenate([np.arange(0, m, dt), [m]])).astype(np.int64)
                 for dt in lengths[~missed].tolist()]
    for times in survivors:
        pos = want[:, times].copy()
        vel = np.round(ref.velocities[:, times] / conv).astype(np.int64)
        pos[:, 0], vel[:, 0], vel[:, -1] = p_first, v_first, v_last
        plain = Knots(times, pos, vel)
        if (np.abs(reconstruct(plain, scales).demand - want) > tol).any():
            continue
        points = times.size
        even = np.unique(np.round(np.linspace(0.0, m, points))).astype(np.int64)
        found = False
        for grid in (even, times):
            with contextlib.suppress(EncodingNeedsTime, EncodingFailed):
                other = _quantise(ref, grid, scales, tol, ends)  # may split segments: count again
                if best is None or other[0].times_ms.size < best[0].times_ms.size:
                    best, found = other, True
        # the grid's own values (what uniform.py measures) where they keep every promise and the
        # joint choice on the same grid did not (it may trade the acceleration budget differently)
        if (best is None or points < best[0].times_ms.size) and within_contract(ref, plain, scales, tol):
            best, found = (plain, reconstruct(plain, scales)), True
        if found:
            break
        # this grid meets the tolerance but not the rest of the contract: a finer one still may
    return best


@kernel
def _uniform_misses(
    want: IntArray, vel: FloatArray, conv: FloatArray, toward_zero: NDArray[np.bool_], tol: float,
    p_first: IntArray, v_first: IntArray, v_last: IntArray, lengths: IntArray, fractions: FloatArray,
) -> NDArray[np.bool_]:
    """For the uniform grid of each segment length (knots 0, dt, 2 dt, ... and the end; values: the planned
    demand and the rpm nearest the plan's velocity; knot 0 and the last velocity fixed): does the drive's
    reconstruction miss the planned demand at these `fractions` of some segment?"""
    n, total = want.shape[0], want.shape[1] - 1
    out = np.zeros(lengths.size, dtype=np.bool_)
    for g in range(lengths.size):
        dt = lengths[g]
        a = 0
        while a < total and not out[g]:
            b = min(a + dt, total)
            t1 = float(b - a)
            for f in fractions:
                off = min(max(np.rint(f * t1), 1.0), max(t1 - 1.0, 1.0))
                h00, h01, h10, h11 = _basis(off / t1, t1)
                tick = a + int(off)
                for i in range(n):
                    pa = float(p_first[i]) if a == 0 else float(want[i, a])
                    va = float(v_first[i]) if a == 0 else np.rint(vel[i, a] / conv[i])
                    vb = float(v_last[i]) if b == total else np.rint(vel[i, b] / conv[i])
                    h = pa * h00 + va * conv[i] * h10 + float(want[i, b]) * h01 + vb * conv[i] * h11
                    r = np.trunc(h) if toward_zero[i] else np.trunc(h + np.copysign(0.5, h))
                    if abs(r - want[i, tick]) > tol:
                        out[g] = True
                        break
                if out[g]:
                    break
            a = b
    return out


def _quantise(
    ref: Reference,
    times: IntArray,
    scales: AxisScales,
    tol: float,
    ends: tuple[IntArray, IntArray, IntArray, IntArray],
) -> tuple[Knots, Reconstruction]:
    """Knot values for the knot times (joint choice, local refinement, verification), splitting the
    segments that still fail the tolerance (see `encode`).

    After a split only the new knots need values: the other segments passed and keep theirs, the new
    knots start at the plan (rounded) and the refinement fixes what fails around them."""
    want = planned_demand(ref, scales.toward_zero)
    conv = scales.counts_per_ms_per_rpm[:, None]
    knots: Knots | None = None
    for _round in range(MAX_ROUNDS):
        env = segment_envelope(ref, times)
        if knots is None:
            pos, vel = _choose_values(ref, times, scales, tol, ends, env)
        else:
            # the knots kept (both sorted): np.isin's answer, without its sorting (a sixth of the time)
            at = np.minimum(np.searchsorted(knots.times_ms, times), knots.times_ms.size - 1)
            old = knots.times_ms[at] == times
            pos = want[:, times].copy()
            vel = np.round(ref.velocities[:, times] / conv).astype(np.int64)
            pos[:, old], vel[:, old] = knots.positions, knots.velocities_rpm
        knots = Knots(times, pos, vel)
        off_tol, off_budget = _misses(knots, scales, tol, want, env)
        if off_tol.any() or off_budget.any():
            refined = _refine(ref, knots, scales, tol, off_tol | off_budget, {0, times.size - 1}, env)
            off_tol, off_budget = _misses(refined, scales, tol, want, env, (knots, off_tol, off_budget))
            knots = refined
        bad = np.nonzero((off_tol | off_budget).any(axis=0))[0]
        if bad.size == 0:
            rec = reconstruct(knots, scales)
            _check_dynamics(ref, knots, rec, scales)
            return knots, rec
        if off_tol.any():
            # split every segment that still holds a failing tick
            seg = np.nonzero(off_tol.any(axis=0))[0]
            a, b = times[seg], times[seg + 1]
            split = b - a >= 2
        else:
            # only the acceleration budget fails: typically a short segment between long ones, whose
            # end values the long neighbours pin down (their middles must stay within the tolerance
            # too). Splitting the failing segments and their neighbours, where both halves stay at
            # least `min_segment` long, leaves the values at the failing ends more freedom.
            seg = np.unique(np.concatenate([bad - 1, bad, bad + 1]))
            seg = seg[(seg >= 0) & (seg < times.size - 1)]
            a, b = times[seg], times[seg + 1]
            split = b - a >= 2 * segment_bounds(scales, tol)[0]
        if not split.any():
            break
        times = np.unique(np.concatenate([times, (a[split] + b[split]) // 2]))
    assert knots is not None  # MAX_ROUNDS >= 1
    rec = reconstruct(knots, scales)
    dev = np.abs(rec.demand - want)
    if (dev > tol).any():
        i, tick = (int(x) for x in np.unravel_index(int(np.argmax(dev)), dev.shape))
        raise EncodingFailed(
            f"the drive's reconstruction misses the planned demand by {int(dev[i, tick])} counts at "
            f"t = {int(tick)} ms (tolerance {tol:g})",
            axis=int(i),
            tick=int(tick),
        )
    _check_dynamics(ref, knots, rec, scales)
    return knots, rec


def _split_long(times: IntArray, max_seg: int) -> IntArray:
    """Given knot times with segments longer than `max_seg` split into equal parts (extra knots lie on
    the plan; long segments cannot be quantised within the tolerance, see `segment_bounds`)."""
    dt = np.diff(times)
    if dt.size == 0 or dt.max() <= max_seg:
        return times
    extra = [
        times[k] + np.round(np.arange(1, parts) * dt[k] / parts).astype(np.int64)
        for k in np.nonzero(dt > max_seg)[0]
        for parts in [int(np.ceil(dt[k] / max_seg))]
    ]
    return np.unique(np.concatenate([times, *extra]))


def _misses(
    knots: Knots,
    scales: AxisScales,
    tol: float,
    want: IntArray,
    envelope: FloatArray,
    before: tuple[Knots, NDArray[np.bool_], NDArray[np.bool_]] | None = None,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """(n_axes, N) twice: which axis misses the tolerance on which segment (the drive's reconstruction
    checked as it is computed), and which misses 0x60C5 or the acceleration-excess budget (0x607F is
    `_check_dynamics`'); `envelope`: the plan's `segment_envelope` on the knots' times. With `before`
    (other values on the same times and their misses) only the segments whose values changed are
    checked again."""
    pos = np.ascontiguousarray(knots.positions, dtype=np.float64)
    vel = np.ascontiguousarray(knots.velocities_rpm, dtype=np.float64)
    if before is None:
        check = np.ones((pos.shape[0], pos.shape[1] - 1), dtype=bool)
    else:
        changed = (pos != before[0].positions) | (vel != before[0].velocities_rpm)
        check = changed[:, :-1] | changed[:, 1:]
    off_tol, off_budget = quantise.failing_segments(
        pos, vel, np.ascontiguousarray(knots.times_ms, dtype=np.int64),
        np.ascontiguousarray(scales.counts_per_ms_per_rpm, dtype=np.float64), _toward_zero(scales), want, tol,
        envelope, ACC_EXCESS_LIMIT * scales.acceleration_axis,
        np.ascontiguousarray(scales.drive_acceleration, dtype=np.float64), check,
    )
    if before is not None:
        off_tol = np.where(check, off_tol, before[1])
        off_budget = np.where(check, off_budget, before[2])
    return off_tol, off_budget


def within_contract(ref: Reference, knots: Knots, scales: AxisScales, tol: float) -> bool:
    """Does this encoding keep everything `encode` guarantees (tolerance at every ms, velocity and
    acceleration limits, the acceleration-excess budget)? For baselines (planner/encoding/uniform.py)."""
    want = planned_demand(ref, scales.toward_zero)
    off_tol, off_budget = _misses(knots, scales, tol, want, segment_envelope(ref, knots.times_ms))
    if off_tol.any() or off_budget.any():
        return False
    try:
        _check_dynamics(ref, knots, reconstruct(knots, scales), scales)
    except EncodingNeedsTime:
        return False
    return True


def _check_dynamics(ref: Reference, knots: Knots, rec: Reconstruction, scales: AxisScales) -> None:
    """Velocity and acceleration of the reconstruction against the drive and axis limits."""
    vpeak = np.abs(rec.velocity).max(axis=1)
    quantum = scales.counts_per_ms_per_rpm
    vlim = np.minimum(
        scales.drive_velocity,
        np.maximum(scales.velocity_limit * (1.0 + VELOCITY_SLACK), scales.velocity_limit + quantum),
    )
    peak = np.maximum(np.abs(rec.acc_start), np.abs(rec.acc_end))
    excess = acceleration_excess(ref, knots, rec)
    for i in range(ref.n_axes):
        if vpeak[i] > vlim[i] + 1e-12:
            raise EncodingNeedsTime(
                f"reconstructed velocity {vpeak[i]:.4f} counts/ms is above the limit {vlim[i]:.4f}",
                factor=float(vpeak[i] / vlim[i]) * 1.002,
                axis=i,
            )
        if peak.size == 0:
            continue
        apk = float(peak[i].max())
        if apk > scales.drive_acceleration[i]:
            raise EncodingNeedsTime(
                f"reconstructed acceleration {apk * 1e6:.0f} counts/s^2 is above the drive's 0x60C5 "
                f"({scales.drive_acceleration[i] * 1e6:.0f} counts/s^2)",
                factor=float(np.sqrt(apk / scales.drive_acceleration[i])) * 1.05,
                axis=i,
            )
        ex = float(excess[i].max())
        if ex > ACC_EXCESS_LIMIT * scales.acceleration_axis[i]:
            raise EncodingNeedsTime(
                f"reconstructed acceleration exceeds the plan by {ex * 1e6:.0f} counts/s^2 "
                f"({100 * ex / scales.acceleration_axis[i]:.1f} % of the axis limit)",
                factor=1.1,
                axis=i,
            )
