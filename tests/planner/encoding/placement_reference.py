"""The PVT encoder's knot placement as NumPy had it (planner/encoding/encoder.py at 60b5382, before it was compiled):
the reference the compiled placement must reproduce (tests/planner/encoding/test_placement.py). Kept only as
that reference; the encoder never calls it."""

from __future__ import annotations

import bisect

import numpy as np
from encoder_reference import _hermite_basis
from numpy.typing import NDArray

from planner.encoding.encoder import (
    _LADDER,
    _PROX,
    ACC_PLACEMENT_SHARE,
    MANDATORY_GAP,
    SECTION_MS,
    STEP_SHARE,
    AxisScales,
    drive_round,
)
from planner.motion.reference import FloatArray, IntArray, Reference


def _placement_errors(
    ref: Reference,
    starts: IntArray,
    lengths: IntArray,
    acc_axis: FloatArray,
    min_seg: int = 0,
    acc_share: float = ACC_PLACEMENT_SHARE,
) -> FloatArray:
    """Candidate segments' error: max over axes of the position error (counts, at sample ticks) of the
    Hermite through the exact knot values, or a large value where its end accelerations already miss
    the plan's by more than `ACC_PLACEMENT_SHARE` of the axis limit (the linear Hermite acceleration
    cannot follow a jerk kink inside a long segment; quantisation needs the rest of the budget)."""
    tt = lengths.astype(np.float64)[:, None]
    off = np.clip(np.round(_PROX[None, :] * tt), 1.0, np.maximum(tt - 1.0, 1.0))
    h00, h10, h01, h11 = _hermite_basis(off, tt)
    ends = starts + lengths
    tick = starts[:, None] + off.astype(np.int64)
    p, v = ref.positions, ref.velocities
    pa, pb, va, vb = p[:, starts], p[:, ends], v[:, starts], v[:, ends]
    h = pa[:, :, None] * h00 + va[:, :, None] * h10 + pb[:, :, None] * h01 + vb[:, :, None] * h11
    err = np.abs(h - p[:, tick]).max(axis=(0, 2))
    t1 = lengths.astype(np.float64)
    dp = pb - pa
    acc_s = (6.0 * dp - 2.0 * t1 * vb - 4.0 * t1 * va) / (t1 * t1)
    acc_e = (-6.0 * dp + 4.0 * t1 * vb + 2.0 * t1 * va) / (t1 * t1)
    miss = np.maximum(np.abs(acc_s - ref.acc_right[:, starts]), np.abs(acc_e - ref.acc_left[:, ends]))
    # shorter segments only make the quantisation noise worse: the check applies above min_seg
    acc_bad = (miss > acc_share * acc_axis[:, None]).any(axis=0) & (lengths > min_seg)
    out: FloatArray = np.where(acc_bad, np.inf, err)
    return out


def _exact_errors(ref: Reference, starts: IntArray, lengths: IntArray) -> FloatArray:
    """As `_placement_errors`, at every tick (used for the few rebalancing checks)."""
    total = int(lengths.sum())
    seg = np.repeat(np.arange(starts.size), lengths)
    first = np.cumsum(lengths) - lengths
    off = (np.arange(total) - first[seg] + 1).astype(np.float64)
    h00, h10, h01, h11 = _hermite_basis(off, lengths[seg].astype(np.float64))
    ends = starts + lengths
    p, v = ref.positions, ref.velocities
    tick = starts[seg] + off.astype(np.int64)
    h = p[:, starts[seg]] * h00 + v[:, starts[seg]] * h10 + p[:, ends[seg]] * h01 + v[:, ends[seg]] * h11
    err = np.abs(h - p[:, tick]).max(axis=0)
    out: FloatArray = np.maximum.reduceat(err, first)
    return out


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
    kept: list[int] = []
    for j in order:
        t = int(cand[j])
        if t < min_gap or m - t < min_gap:
            continue
        if all(abs(t - k) >= min_gap for k in kept):
            kept.append(t)
    return np.array(sorted([0, m, *kept]), dtype=np.int64)


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
    cuts: list[int] = []
    for a, b in zip(bounds[:-1].tolist(), bounds[1:].tolist(), strict=True):
        parts = -(-(b - a) // piece)  # equal parts, none longer than `piece`
        cuts.extend(a + (j * (b - a)) // parts for j in range(parts))
    cuts.append(m)
    sec_start = np.array(cuts[:-1], dtype=np.int64)
    sec_end = np.array(cuts[1:], dtype=np.int64)
    cur = sec_start.copy()
    prev = np.minimum(sec_end - sec_start, min(max_seg, 2 * min_seg)).astype(np.int64)
    found: list[IntArray] = [sec_start.copy()]
    while True:
        act = np.nonzero(cur < sec_end)[0]
        if act.size == 0:
            break
        c = cur[act]
        room = sec_end[act] - c
        lim = np.minimum(room, max_seg)
        lens = np.concatenate(
            [
                np.round(prev[act][:, None] * _LADDER[None, :]),
                lim[:, None],
                np.ceil(room / 2.0)[:, None],
                np.ceil(room / 3.0)[:, None],
            ],
            axis=1,
        )
        lens = np.clip(lens, 1, lim[:, None]).astype(np.int64)
        k = lens.shape[1]
        err = _placement_errors(
            ref, np.repeat(c, k), lens.ravel(), scales.acceleration_axis, min_seg, acc_share
        ).reshape(-1, k)
        ok = err <= budget
        rem = room[:, None] - lens
        half = lens == np.ceil(room / 2.0)[:, None]
        # preference: finish the section; else the longest that leaves at least min_seg; else split
        # the rest in two halves; else the longest that passes (a short remainder is the last resort)
        score = np.where(ok, lens + 4096 * (rem == 0) + 2048 * (rem >= min_seg) + 1024 * half, 0)
        best = score.max(axis=1) % 1024
        adv = best > 0
        go = act[adv]
        cur[go] += best[adv]
        prev[go] = best[adv]
        found.append(cur[go].copy())
        stay = act[~adv]
        prev[stay] = np.maximum(1, lens[~adv].min(axis=1) // 3)  # length 1 always passes, eventually
    times = np.unique(np.concatenate([*found, np.array([m], dtype=np.int64)]))
    times = _rebalance(ref, times, mand, budget, min_seg, max_seg, scales.acceleration_axis, acc_share)
    return _coarsen(ref, times, mand, budget, min_seg, max_seg, scales.acceleration_axis, acc_share)


def _structure(
    ref: Reference, mand: IntArray, gap: int, max_seg: int, keep_kinks: bool = True
) -> tuple[IntArray, int]:
    """Section boundaries and the longest section: the plan's own structure where it has one.

    With `hints` (a ruckig profile's phases, a user's rows, a path chain's knots) the plan is one cubic
    between two of them: they become section boundaries (those closer than `gap` to a kept one are
    dropped, a short phase is better crossed than isolated, unless the acceleration may step there or
    the conservative variant keeps them all) and sections are at most `max_seg` long, so a section that a
    single segment reproduces becomes exactly one. Without hints (toppra's profiles) sections are the
    stretches between the mandatory knots, cut at `SECTION_MS` for the lockstep placement.
    """
    if ref.hints.size == 0:
        return mand, SECTION_MS
    kept = sorted(mand.tolist())
    kinks = set(ref.breaks.tolist()) if keep_kinks else set()
    for h in ref.hints.tolist():
        # a hint where the acceleration may step (a chain's knot, a pvt row) is kept however close: a
        # segment across it cannot follow the plan
        i = bisect.bisect_left(kept, h)
        nearest = min(abs(h - kept[j]) for j in (i - 1, i) if 0 <= j < len(kept))
        if h in kinks or nearest >= gap:
            kept.insert(i, h)
    return np.array(kept, dtype=np.int64), max_seg


def _acc_misses(
    ref: Reference, starts: IntArray, lengths: IntArray, acc_axis: FloatArray, min_seg: int, acc_share: float
) -> NDArray[np.bool_]:
    """Segments (longer than `min_seg`) whose exact-value Hermite misses the plan's end accelerations by
    more than `acc_share` of an axis limit (see `_placement_errors`)."""
    ends = starts + lengths
    t1 = lengths.astype(np.float64)
    p, v = ref.positions, ref.velocities
    dp = p[:, ends] - p[:, starts]
    acc_s = (6.0 * dp - 2.0 * t1 * v[:, ends] - 4.0 * t1 * v[:, starts]) / (t1 * t1)
    acc_e = (-6.0 * dp + 4.0 * t1 * v[:, ends] + 2.0 * t1 * v[:, starts]) / (t1 * t1)
    miss = np.maximum(np.abs(acc_s - ref.acc_right[:, starts]), np.abs(acc_e - ref.acc_left[:, ends]))
    out: NDArray[np.bool_] = (miss > acc_share * acc_axis[:, None]).any(axis=0) & (lengths > min_seg)
    return out


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
    t = times
    for _round in range(64):
        dropped = False
        for parity in (1, 2):
            k = np.arange(parity, t.size - 1, 2)
            k = k[~np.isin(t[k], mand)]
            if k.size == 0:
                continue
            starts, lengths = t[k - 1], t[k + 1] - t[k - 1]
            short = lengths <= max_seg
            k, starts, lengths = k[short], starts[short], lengths[short]
            if k.size == 0:
                continue
            err = _exact_errors(ref, starts, lengths)
            ok = (err <= budget) & ~_acc_misses(ref, starts, lengths, acc_axis, min_seg, acc_share)
            if ok.any():
                t = np.delete(t, k[ok])
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
    segments checked in one vectorised evaluation)."""
    t = times
    dt = np.diff(t)
    short = np.nonzero(dt < min_seg)[0]
    if short.size == 0:
        return t
    fixed = np.isin(t, mand)
    last = t.size - 1
    # options: (segment k, kind, new knot value or -1 to drop, knot index, [(start, length), ...])
    options: list[tuple[int, int, int, list[tuple[int, int]]]] = []
    for k in short.tolist():
        a, b = int(t[k]), int(t[k + 1])
        if k + 1 < last and not fixed[k + 1] and int(t[k + 2]) - a <= max_seg:  # drop the right knot
            options.append((k, k + 1, -1, [(a, int(t[k + 2]) - a)]))
        if k >= 1 and not fixed[k] and b - int(t[k - 1]) <= max_seg:  # drop the left knot
            options.append((k, k, -1, [(int(t[k - 1]), b - int(t[k - 1]))]))
        if k + 1 < last and not fixed[k + 1]:  # move the right knot to the middle
            mid = (a + int(t[k + 2])) // 2
            if mid - a >= min_seg and int(t[k + 2]) - mid >= min_seg:
                options.append((k, k + 1, mid, [(a, mid - a), (mid, int(t[k + 2]) - mid)]))
        if k >= 1 and not fixed[k]:  # move the left knot to the middle
            mid = (int(t[k - 1]) + b) // 2
            if mid - int(t[k - 1]) >= min_seg and b - mid >= min_seg:
                options.append((k, k, mid, [(int(t[k - 1]), mid - int(t[k - 1])), (mid, b - mid)]))
    if not options:
        return t
    segs = [seg for opt in options for seg in opt[3]]
    st = np.array([x[0] for x in segs], dtype=np.int64)
    ln = np.array([x[1] for x in segs], dtype=np.int64)
    errs = np.where(_acc_misses(ref, st, ln, acc_axis, min_seg, acc_share), np.inf, _exact_errors(ref, st, ln))
    ok: list[bool] = []
    pos = 0
    for opt in options:
        ok.append(bool(errs[pos : pos + len(opt[3])].max() <= budget))
        pos += len(opt[3])
    new_t = t.copy()
    keep = np.ones(t.size, dtype=bool)
    touched: set[int] = set()
    done: set[int] = set()
    for (k, idx, value, _segs), good in zip(options, ok, strict=True):
        if not good or k in done or touched & {idx - 1, idx, idx + 1}:
            continue
        if value < 0:
            keep[idx] = False
        else:
            new_t[idx] = value
        touched.add(idx)
        done.add(k)
    out: IntArray = np.unique(new_t[keep])
    return out


# ----------------------------------------------------------------------------------------------------
# value choice (Viterbi over the knots, per axis)


def _quick_misses(
    ref: Reference,
    grids: list[IntArray],
    want: IntArray,
    tol: float,
    scales: AxisScales,
    first_last: tuple[IntArray, IntArray, IntArray],
    fractions: tuple[float, ...],
) -> NDArray[np.bool_]:
    """For each uniform grid (knot values: the planned demand and the rpm nearest the plan's velocity;
    knot 0 and the last velocity fixed): does the drive's reconstruction miss the planned demand at these
    `fractions` of some segment? All grids in one vectorised pass."""
    p_first, v_first, v_last = first_last
    conv = scales.counts_per_ms_per_rpm[:, None]
    starts = np.concatenate([g[:-1] for g in grids])
    stops = np.concatenate([g[1:] for g in grids])
    owner = np.repeat(np.arange(len(grids)), [g.size - 1 for g in grids])
    is_first = np.concatenate([[True], owner[1:] != owner[:-1]])
    is_last = np.concatenate([owner[1:] != owner[:-1], [True]])
    pa = want[:, starts].astype(np.float64)
    pb = want[:, stops].astype(np.float64)
    va = np.round(ref.velocities[:, starts] / conv)
    vb = np.round(ref.velocities[:, stops] / conv)
    pa[:, is_first] = p_first[:, None]
    va[:, is_first] = v_first[:, None]
    vb[:, is_last] = v_last[:, None]
    dt = (stops - starts).astype(np.float64)
    off = np.clip(np.round(np.array(fractions)[None, :] * dt[:, None]), 1.0, np.maximum(dt[:, None] - 1, 1))
    h00, h10, h01, h11 = _hermite_basis(off, dt[:, None])
    h = pa[:, :, None] * h00 + (va * conv)[:, :, None] * h10 + pb[:, :, None] * h01 + (vb * conv)[:, :, None] * h11
    tick = (starts[:, None] + off).astype(np.int64)
    seg_miss = (np.abs(drive_round(h, scales.toward_zero) - want[:, tick]) > tol).any(axis=(0, 2))
    out: NDArray[np.bool_] = np.bincount(owner, weights=seg_miss, minlength=len(grids)) > 0
    return out
