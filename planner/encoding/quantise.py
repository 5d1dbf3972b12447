"""The PVT encoder's value search and verification, compiled (planner/encoding/encoder.py, steps 2 and 3).

One axis at a time, without temporaries. Both searches (`choose_values`, `refine`) check every tick
lazily: the costs at the sample ticks bound those at every tick from below; `_exact_path` checks the best
path's pairs at every tick and runs again until no bound is left on it, which gives the full check's
result, ties included. The loops are shaped to vectorise (rows of candidates or ticks, padded; maxima as
integer bit patterns; unsigned offsets; one array per per-pair kernel). Results are bit for bit the NumPy
reference's (tests/planner/encoding/encoder_reference.py).
"""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from planner.encoding.record import VELOCITY_MAX, VELOCITY_MIN
from planner.jit import kernel
from planner.motion.reference import FloatArray, IntArray

BoolArray = NDArray[np.bool_]
Float32Array = NDArray[np.float32]

HARD = 1.0e6  # cost of a pair that misses the tolerance, 0x60C5 or 0x607F: only chosen where all do
_ROUNDS = 32  # passes of the lazy exact Viterbi before every bound left is replaced by its cost
_VMIN = float(VELOCITY_MIN)
_VMAX = float(VELOCITY_MAX)


@kernel
def drive_round(x: float, toward_zero: bool) -> float:
    """`x` rounded as the drive rounds its demand, as planner/encoding/hermite.py computes it: half away from zero
    (`round_counts_array`: trunc(x +- 0.5)) or toward zero (`truncate_counts_array`)."""
    if toward_zero:
        return float(np.trunc(x))
    return float(np.trunc(x + np.copysign(0.5, x)))


# ----------------------------------------------------------------------------------------------------
# verification


@kernel
def _segment(p0: float, v0: float, p1: float, v1: float, t: float) -> tuple[float, float, float, float]:
    """One segment's a and b (planner/encoding/hermite.py's polynomial, anchored at its end) and its start and
    end accelerations; velocities in counts/ms, t in ms (t * t * t is t**3 exactly: whole ms)."""
    dp = p1 - p0
    a = (-2.0 * dp + t * (v1 + v0)) / (t * t * t)
    b = (-3.0 * dp + t * (2.0 * v1 + v0)) / (t * t)
    acc_s = (6.0 * dp - 2.0 * t * v1 - 4.0 * t * v0) / (t * t)
    acc_e = (-6.0 * dp + 4.0 * t * v1 + 2.0 * t * v0) / (t * t)
    return a, b, acc_s, acc_e


@kernel
def reconstruct(
    positions: FloatArray, velocities_rpm: FloatArray, times: IntArray, conv: FloatArray, toward_zero: BoolArray
) -> tuple[IntArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """The drive's rounded demand, unrounded position and velocity at every ms 0..times[-1], and every
    segment's start and end acceleration, of every axis: planner.encoding.hermite.reconstruct, evaluated in the
    same order (tau in [-T + 1, 0] from the segment's end)."""
    n, nk = positions.shape
    total = times[-1]
    demand = np.empty((n, total + 1), np.int64)
    pos = np.empty((n, total + 1))
    vel = np.empty((n, total + 1))
    acc_s = np.zeros((n, nk - 1))
    acc_e = np.zeros((n, nk - 1))
    for i in range(n):
        pos[i, 0] = positions[i, 0]
        vel[i, 0] = velocities_rpm[i, 0] * conv[i]
        for k in range(nk - 1):
            v1 = velocities_rpm[i, k + 1] * conv[i]
            p1 = positions[i, k + 1]
            a, b, acc_s[i, k], acc_e[i, k] = _segment(
                positions[i, k], velocities_rpm[i, k] * conv[i], p1, v1, float(times[k + 1] - times[k])
            )
            for tick in range(times[k] + 1, times[k + 1] + 1):
                tau = float(tick - times[k + 1])
                pos[i, tick] = ((a * tau + b) * tau + v1) * tau + p1
                vel[i, tick] = (3.0 * a * tau + 2.0 * b) * tau + v1
        for tick in range(total + 1):
            demand[i, tick] = int(drive_round(pos[i, tick], toward_zero[i]))
    return demand, pos, vel, acc_s, acc_e


@kernel
def segment_envelope(acc_left: FloatArray, acc_right: FloatArray, times: IntArray) -> FloatArray:
    """max(|acc_left|, |acc_right|) over each segment's ticks, both ends included, (n_axes, N).

    The last segment's runs to the end of the plan, not to times[-1] (numpy's `maximum.reduceat`, which
    the encoder used: the same where the times end at the plan's end, as an encoding's do)."""
    n, m1 = acc_left.shape
    nseg = times.size - 1
    out = np.empty((n, max(nseg, 0)))
    env = np.empty(m1 + 1)  # and one more, to read a peak back as float
    # non-negative floats order as their bit patterns (nan above inf, as np.maximum propagates it), and
    # an integer maximum vectorises where a nan-aware float one does not
    bits = env.view(np.int64)
    for i in range(n):
        for t in range(m1):
            env[t] = np.maximum(abs(acc_left[i, t]), abs(acc_right[i, t]))
        for k in range(nseg):
            a = times[k]
            run = bits[a : m1 if k == nseg - 1 else max(times[k + 1], a + 1)]
            top = bits[times[k + 1]]
            for t in range(run.size):
                top = run[t] if run[t] > top else top
            bits[m1] = top
            out[i, k] = env[m1]
    return out


@kernel
def failing_segments(
    positions: FloatArray,
    velocities_rpm: FloatArray,
    times: IntArray,
    conv: FloatArray,
    toward_zero: BoolArray,
    want: IntArray,
    tol: float,
    envelope: FloatArray,
    excess_limit: FloatArray,
    drive_acc: FloatArray,
    check: BoolArray,
) -> tuple[BoolArray, BoolArray]:
    """(n_axes, N) twice, for the segments `check` marks (the others False): does the drive demand
    (`reconstruct`'s, checked as it is computed) miss `want` by more than `tol` at a tick of the segment
    (tick 0 counts to segment 0, a knot's tick to the segment it ends); does its peak acceleration exceed
    the plan's `envelope` by more than `excess_limit`, or `drive_acc`."""
    n, nk = positions.shape
    off_tol = np.zeros((n, nk - 1), np.bool_)
    off_budget = np.zeros((n, nk - 1), np.bool_)
    for i in range(n):
        tz = toward_zero[i]
        for k in range(nk - 1):
            if not check[i, k]:
                continue
            v1 = velocities_rpm[i, k + 1] * conv[i]
            p1 = positions[i, k + 1]
            p0 = positions[i, k]
            nt = times[k + 1] - times[k]
            a, b, acc_s, acc_e = _segment(p0, velocities_rpm[i, k] * conv[i], p1, v1, float(nt))
            peak = np.maximum(abs(acc_s), abs(acc_e))
            off_budget[i, k] = peak - envelope[i, k] > excess_limit[i] or peak > drive_acc[i]
            w = want[i, times[k] + 1 : times[k + 1] + 1]
            miss = k == 0 and abs(int(drive_round(p0, tz)) - want[i, 0]) > tol
            # every tick, without stopping at the first miss: a loop that vectorises
            if tz:
                for u in range(nt):
                    tau = float(u + 1 - nt)
                    miss |= abs(int(drive_round(((a * tau + b) * tau + v1) * tau + p1, True)) - w[u]) > tol
            else:
                for u in range(nt):
                    tau = float(u + 1 - nt)
                    miss |= abs(int(drive_round(((a * tau + b) * tau + v1) * tau + p1, False)) - w[u]) > tol
            off_tol[i, k] = miss
    return off_tol, off_budget


# ----------------------------------------------------------------------------------------------------
# value search


@kernel
def axis_candidates(
    p_plan: FloatArray,
    v_plan: FloatArray,
    times: IntArray,
    conv: float,
    dp: FloatArray,
    dv: IntArray,
    bracket: bool,
    pinned: BoolArray,
    pin_p: IntArray,
    pin_v: IntArray,
) -> tuple[FloatArray, FloatArray]:
    """One axis' candidate (position counts, velocity rpm) at every knot, (K, C) each, C = dv x dp:
    the planned demand (rounded to nearest) plus `dp`, the rpm nearest the plan's velocity plus `dv`
    (`bracket`: the rpm below instead, so dv = (0, 1) brackets it); at a `pinned` knot all C are
    (pin_p, pin_v). Velocities clipped to int24."""
    nk = times.size
    c = dp.size * dv.size
    cand_p = np.empty((nk, c))
    cand_v = np.empty((nk, c))
    for k in range(nk):
        if pinned[k]:
            for j in range(c):
                cand_p[k, j] = float(pin_p[k])
                cand_v[k, j] = min(max(float(pin_v[k]), _VMIN), _VMAX)
            continue
        x = p_plan[times[k]]
        rp = float(int(np.trunc(x + np.copysign(0.5, x))))
        v_rpm = v_plan[times[k]] / conv
        vr = np.floor(v_rpm) if bracket else np.round(v_rpm)
        j = 0
        for jv in dv:
            for jp in dp:
                cand_p[k, j] = rp + jp
                cand_v[k, j] = min(max(vr + jv, _VMIN), _VMAX)
                j += 1
    return cand_p, cand_v


@kernel
def _limits(
    pa: float, va: float, pb: float, vb: float, dt: float, envelope: float, excess_scale: float, drive_acc: float,
    drive_vel: float,
) -> tuple[float, float, float]:
    """A pair's costs that do not depend on the ticks: HARD above 0x60C5 or (at the ends) 0x607F, 1e3 where
    the end accelerations' excess over the plan's `envelope` is above 0.9 of `excess_scale`, its square.

    The larger end acceleration is divided once: a rounded quotient by dt * dt > 0 keeps the order of the
    numerators and their sign, so max(|a| / d, |b| / d) is max(|a|, |b|) / d to the bit (nan too)."""
    dp = pb - pa
    peak = np.maximum(abs(6.0 * dp - 2.0 * dt * vb - 4.0 * dt * va), abs(-6.0 * dp + 4.0 * dt * vb + 2.0 * dt * va))
    peak = peak / (dt * dt)
    excess = np.maximum(peak - envelope, 0.0) / excess_scale
    over = peak > drive_acc or np.maximum(abs(va), abs(vb)) > drive_vel
    return HARD if over else 0.0, 1.0e3 if excess > 0.9 else 0.0, excess * excess


@kernel
def padded(c: int) -> int:
    """`c` rounded up to whole vectors of 8 lanes (the widest numba's loops here use)."""
    return (c + 7) // 8 * 8


@kernel
def sample_misses(
    p_plan: FloatArray,
    times: IntArray,
    cand_p: FloatArray,
    cand_v: FloatArray,
    pinned: BoolArray,
    envelope: FloatArray,
    conv: float,
    excess_scale: float,
    drive_acc: float,
    drive_vel: float,
    toward_zero: bool,
    tol: float,
    prox: FloatArray,
    dev: Float32Array,
    feasible: BoolArray,
) -> None:
    """dev (K-1, C, W): for every pair of one axis' candidates (K, C: positions, velocities in rpm, `conv`
    counts/ms per rpm) on every segment, the largest miss of the drive's rounded demand at the sample
    ticks `prox` (fractions of each segment, rounded, within 1..T-1), as `_exact_cost` computes a miss and
    np.maximum keeps it (a nan stays; which nan does not matter, it only fails comparisons): what
    `sample_bounds` makes lower bounds of. W: C rounded up to whole vectors (`padded`), scratch beyond C;
    a loop over a few more lanes costs less than its scalar remainder would (C is 6 or 21).

    And into `feasible` (unless it is empty) whether the pair passes at the sample ticks: what NumPy's
    sample cost decided (below HARD; its deviation term was half the squared float error, a tie-breaker).
    That cost is HARD plus non-negative terms (at least HARD, or nan) wherever the pair misses `tol`, so
    only the start candidates with a pair that meets it (3 in 8) need their float errors and limits.

    A pinned knot's candidates are all the same values: computed once, copied to the others."""
    nk, c = cand_p.shape
    nq = prox.size
    wide = dev.shape[2]
    # each share relative to the whole count below the plan: small numbers, float32 will do
    ea = np.empty((nq, c), np.float32)
    eb = np.zeros((nq, wide), np.float32)
    want = np.empty(nq, np.float32)  # the planned demand
    frac = np.empty(nq, np.float32)  # the plan
    below = np.empty(nq)  # the whole count below the plan
    whole = np.empty(nq)  # the plan's truncation
    row = np.empty(wide, np.float32)  # a start candidate's misses
    row_bits = row.view(np.int32)
    half = np.float32(0.5)
    tol32 = np.float32(tol)
    checked = feasible.size > 0
    for k in range(nk - 1):
        ca = 1 if pinned[k] else c
        cb = 1 if pinned[k + 1] else c
        t0 = times[k]
        dt = float(times[k + 1] - t0)
        top = max(dt - 1.0, 1.0)
        for q in range(nq):
            off = min(max(np.round(prox[q] * dt), 1.0), top)
            s = off / dt
            s2 = s * s
            h00 = 1.0 - 3.0 * s2 + 2.0 * s2 * s
            h01 = 1.0 - h00
            h10 = (s - 2.0 * s2 + s2 * s) * dt
            h11 = (s2 * s - s2) * dt
            p = p_plan[t0 + int(off)]
            base = np.floor(p)
            for i in range(ca):
                ea[q, i] = np.float32((cand_p[k, i] - base) * h00 + cand_v[k, i] * conv * h10)
            for j in range(cb):
                eb[q, j] = np.float32((cand_p[k + 1, j] - base) * h01 + cand_v[k + 1, j] * conv * h11)
            want[q] = np.float32(float(int(np.trunc(p + np.copysign(0.5, p)))) - base)
            frac[q] = np.float32(p - base)
            below[q] = base
            whole[q] = np.trunc(p)
        for i in range(ca):
            # the largest miss, as np.maximum keeps it: non-negative floats order as their bit patterns
            # (nan above inf), and an integer maximum is stored whole, where a float one is a masked store
            # that the next tick's load waits for
            for j in range(wide):
                row_bits[j] = 0
            for q in range(nq):
                a = ea[q, i]
                if toward_zero:
                    for j in range(wide):
                        miss = np.float32(abs(np.trunc(np.float64(a + eb[q, j]) + below[q]) - whole[q]))
                        row_bits[j] = max(row_bits[j], miss.view(np.int32))
                else:
                    for j in range(wide):
                        miss = np.float32(abs(np.floor(a + eb[q, j] + half) - want[q]))
                        row_bits[j] = max(row_bits[j], miss.view(np.int32))
            for j in range(wide):
                dev[k, i, j] = row[j]
            if not checked:
                continue
            # a start candidate none of whose pairs meets `tol` (5 in 8 in the refinement of 30 random
            # paths) is settled; the others are scored whole (a branch per pair would go either way)
            near = False
            for j in range(cb):
                near |= not dev[k, i, j] > tol32
            if not near:
                for j in range(cb):
                    feasible[k, i, j] = False
                continue
            for j in range(wide):
                row_bits[j] = 0
            for q in range(nq):
                a = ea[q, i]
                for j in range(wide):
                    e = np.float32(abs(a + eb[q, j] - frac[q]))  # the float error, kept as the misses are
                    row_bits[j] = max(row_bits[j], e.view(np.int32))
            va = cand_v[k, i] * conv
            for j in range(cb):
                hard, budget, excess2 = _limits(cand_p[k, i], va, cand_p[k + 1, j], cand_v[k + 1, j] * conv, dt,
                                                envelope[k], excess_scale, drive_acc, drive_vel)
                e32 = row[j] / tol32
                cost = 0.0 + np.float64(half * (e32 * e32)) + hard + budget + excess2
                feasible[k, i, j] = (not dev[k, i, j] > tol32) & (hard == 0.0) & (cost < HARD)
        _replicate(dev, k, ca, cb)
        if checked:
            _replicate(feasible, k, ca, cb)


@kernel
def sample_bounds(
    dev: Float32Array,
    times: IntArray,
    cand_p: FloatArray,
    cand_v: FloatArray,
    pinned: BoolArray,
    envelope: FloatArray,
    conv: float,
    excess_scale: float,
    drive_acc: float,
    drive_vel: float,
    tol: float,
    bounds: FloatArray,
) -> None:
    """bounds (K-1, C, C): one axis' pair costs (`exact_costs`) with the misses at the sample ticks `dev`
    (`sample_misses`) in place of the deviation. Where no cost is nan they bound the costs from below:
    the sample ticks are some of the ticks (the same misses), so their largest miss is at most the
    deviation. Apart from the misses, only for the candidates the search keeps (the refinement prunes)."""
    nk, c = cand_p.shape
    tol32 = np.float32(tol)
    for k in range(nk - 1):
        ca = 1 if pinned[k] else c
        cb = 1 if pinned[k + 1] else c
        dt = float(times[k + 1] - times[k])
        for i in range(ca):
            pa = cand_p[k, i]
            va = cand_v[k, i] * conv
            for j in range(cb):
                hard, budget, excess2 = _limits(pa, va, cand_p[k + 1, j], cand_v[k + 1, j] * conv, dt, envelope[k],
                                                excess_scale, drive_acc, drive_vel)
                miss = dev[k, i, j]
                q32 = miss / tol32
                bounds[k, i, j] = (HARD if miss > tol32 else 0.0) + np.float64(q32 * q32) + hard + budget + excess2
        _replicate(bounds, k, ca, cb)


@kernel
def _segment_ticks(p_plan: FloatArray, t0: int, t1: int, terms: FloatArray, at: int) -> None:
    """For the ticks 1..T of the segment t0..t1, columns at..at+T-1 of terms: the Hermite basis h00, h01,
    h10, h11 (the formulas of encoder._basis), the whole count below the plan, the planned demand
    (rounded to nearest) relative to that whole count (a float32, exact as a float64), the plan's
    truncation."""
    nt = t1 - t0
    dt = float(nt)
    # unsigned offsets: numba wraps negative indices around, and a wrapped index does not vectorise
    col = np.uint64(at)
    tick = np.uint64(t0 + 1)
    for t in range(nt):
        s = float(t + 1) / dt
        s2 = s * s
        h00 = 1.0 - 3.0 * s2 + 2.0 * s2 * s
        u = col + np.uint64(t)
        terms[0, u] = h00
        terms[1, u] = 1.0 - h00
        terms[2, u] = (s - 2.0 * s2 + s2 * s) * dt
        terms[3, u] = (s2 * s - s2) * dt
        p = p_plan[tick + np.uint64(t)]
        base = np.floor(p)
        terms[4, u] = base
        terms[5, u] = np.float32(float(int(np.trunc(p + np.copysign(0.5, p)))) - base)
        terms[6, u] = np.trunc(p)


@kernel
def _exact_cost(
    terms: FloatArray,
    at: int,
    nt: int,
    pa: float,
    va: float,
    pb: float,
    vb: float,
    toward_zero: bool,
    tol: float,
    limits: tuple[float, float, float],
) -> float:
    """One pair's cost at every tick of a segment (`_segment_ticks`' terms from column `at`; `_limits`);
    velocities in counts/ms."""
    half = np.float32(0.5)
    col = np.uint64(at)  # unsigned: see `_segment_ticks`
    # the largest miss: non-negative floats order as their bit patterns (nan above inf, as np.maximum
    # propagates it), and an integer maximum vectorises where a nan-aware float one does not
    top = np.int32(0)
    # each share relative to the whole count below the plan: small numbers, float32 will do
    if toward_zero:
        for t in range(nt):
            u = col + np.uint64(t)
            a = np.float32((pa - terms[4, u]) * terms[0, u] + va * terms[2, u])
            b = np.float32((pb - terms[4, u]) * terms[1, u] + vb * terms[3, u])
            miss = np.float32(abs(np.trunc(np.float64(a + b) + terms[4, u]) - terms[6, u]))
            top = max(top, miss.view(np.int32))
    else:
        for t in range(nt):
            u = col + np.uint64(t)
            a = np.float32((pa - terms[4, u]) * terms[0, u] + va * terms[2, u])
            b = np.float32((pb - terms[4, u]) * terms[1, u] + vb * terms[3, u])
            miss = np.float32(abs(np.floor(a + b + half) - np.float32(terms[5, u])))
            top = max(top, miss.view(np.int32))
    dev = np.int32(top).view(np.float32)
    tol32 = np.float32(tol)
    q32 = dev / tol32
    hard, budget, excess2 = limits
    return (HARD if dev > tol32 else 0.0) + np.float64(q32 * q32) + hard + budget + excess2


@kernel
def exact_costs(
    p_plan: FloatArray,
    times: IntArray,
    cand_p: FloatArray,
    cand_v: FloatArray,
    pinned: BoolArray,
    envelope: FloatArray,
    conv: float,
    excess_scale: float,
    drive_acc: float,
    drive_vel: float,
    toward_zero: bool,
    tol: float,
    costs: FloatArray,
) -> None:
    """costs[k, i, j]: the cost of segment k of one axis from candidate i of knot k to candidate j of knot
    k + 1 (cand_p, cand_v (K, C): positions, velocities in rpm, `conv` counts/ms per rpm).

    Deviation: the drive's rounded demand against the planned demand at every tick; beyond `tol` it costs
    HARD, below it (dev / tol)^2. Plus `_limits`. A pinned knot's candidates are all the same values:
    computed once, copied to the others."""
    nk, c = cand_p.shape
    span = times[-1] - times[0]
    terms = np.empty((7, span))
    for k in range(nk - 1):
        ca = 1 if pinned[k] else c
        cb = 1 if pinned[k + 1] else c
        t0, t1 = times[k], times[k + 1]
        at = t0 - times[0]
        _segment_ticks(p_plan, t0, t1, terms, at)
        for i in range(ca):
            va = cand_v[k, i] * conv
            for j in range(cb):
                vb = cand_v[k + 1, j] * conv
                limits = _limits(cand_p[k, i], va, cand_p[k + 1, j], vb, float(t1 - t0), envelope[k], excess_scale,
                                 drive_acc, drive_vel)
                costs[k, i, j] = _exact_cost(terms, at, t1 - t0, cand_p[k, i], va, cand_p[k + 1, j], vb, toward_zero,
                                             tol, limits)
        _replicate(costs, k, ca, cb)


@kernel
def _first_min(x: FloatArray) -> int:
    """numpy's argmin: the first minimum, or the first nan."""
    best = 0
    for i in range(1, x.size):
        if np.isnan(x[best]):
            break
        if x[i] < x[best] or np.isnan(x[i]):
            best = i
    return best


@kernel
def _forward(costs: FloatArray, pinned: BoolArray, totals: FloatArray, back: IntArray, start: int) -> None:
    """NumPy's Viterbi pass over the pair costs (K-1, C, C) from segment `start` on: totals[k] the cheapest
    path to each candidate of knot k (totals[0] set: candidate 0 at 0, the others inf), back[k] its
    candidate at knot k (the first minimum, as argmin; a nan is a minimum). A pinned knot's columns are
    all the same: the first stands for all.

    The minimum runs over the rows with the columns inner (totals[k + 1] and back[k] the running
    minimum): a loop over the columns vectorises, one over the rows would not. Row by row it is argmin's
    scan: a row replaces the minimum where it is lower or nan, unless the minimum is nan already."""
    nseg, c, _ = costs.shape
    for k in range(start, nseg):
        cj = 1 if pinned[k + 1] else c
        first = totals[k, 0]
        for j in range(cj):
            totals[k + 1, j] = first + costs[k, 0, j]
            back[k, j] = 0
        for i in range(1, c):
            here = totals[k, i]
            for j in range(cj):
                x = here + costs[k, i, j]
                low = totals[k + 1, j]
                take = not np.isnan(low) and (x < low or np.isnan(x))
                totals[k + 1, j] = x if take else low
                back[k, j] = i if take else back[k, j]
        if pinned[k + 1]:
            back[k, 1:] = back[k, 0]
            totals[k + 1, 1:] = totals[k + 1, 0]


@kernel
def _best_path(costs: FloatArray, pinned: BoolArray, totals: FloatArray, back: IntArray, start: int) -> IntArray:
    """The minimum-cost path through the pair costs from candidate 0 of knot 0, as NumPy's Viterbi chose
    it (`_forward` from segment `start`: totals and back before it are kept; the first minimum at the
    last knot)."""
    nseg = costs.shape[0]
    if start == 0:
        totals[0, :] = np.inf
        totals[0, 0] = 0.0
    _forward(costs, pinned, totals, back, start)
    choice = np.empty(nseg + 1, np.int64)
    choice[nseg] = _first_min(totals[nseg])
    for k in range(nseg - 1, -1, -1):
        choice[k] = back[k, choice[k + 1]]
    return choice


@kernel
def viterbi(
    cand_p: FloatArray,
    cand_v: FloatArray,
    pinned: BoolArray,
    p_plan: FloatArray,
    times: IntArray,
    envelope: FloatArray,
    conv: float,
    excess_scale: float,
    drive_acc: float,
    drive_vel: float,
    toward_zero: bool,
    tol: float,
) -> IntArray:
    """One axis' minimum-cost candidate path through the knots (`exact_costs` of every segment), from
    candidate 0 of knot 0. A `pinned` knot's candidates are all the same values: their costs are computed
    once, and the path takes the first, as numpy's argmin did."""
    nk, c = cand_p.shape
    costs = np.empty((nk - 1, c, c))
    exact_costs(p_plan, times, cand_p, cand_v, pinned, envelope, conv, excess_scale, drive_acc, drive_vel, toward_zero,
                tol, costs)
    return _best_path(costs, pinned, np.empty((nk, c)), np.empty((nk - 1, c), np.int64), 0)


@kernel
def _exact_path(
    cand_p: FloatArray,
    cand_v: FloatArray,
    pinned: BoolArray,
    costs: FloatArray,
    p_plan: FloatArray,
    times: IntArray,
    envelope: FloatArray,
    conv: float,
    excess_scale: float,
    drive_acc: float,
    drive_vel: float,
    toward_zero: bool,
    tol: float,
) -> IntArray:
    """`viterbi`, from lower bounds of the costs (K-1, C, C: `sample_bounds`, replaced by the costs where
    they are computed): while the best path passes pairs whose cost is only bounded, their costs replace
    the bounds and the path is found again (after `_ROUNDS`, all of them). A path without bounds is the
    one the costs give, ties included: its cost is exact, no other path costs less (bounds are below
    costs), and at each of its columns and at its end the candidates that tie for the minimum are the
    same with the bounds as with the costs (a bound ties only where it is the cost). No cost is nan (the
    caller's conditions)."""
    nk, c = cand_p.shape
    lower = np.ones((nk - 1, c, c), np.bool_)
    span = times[-1] - times[0]
    terms = np.empty((7, span))  # `_segment_ticks` of each segment, where a pair needs them
    ready = np.zeros(nk - 1, np.bool_)
    totals = np.empty((nk, c))
    back = np.empty((nk - 1, c), np.int64)
    start = 0
    for _round in range(_ROUNDS + 1):
        choice = _best_path(costs, pinned, totals, back, start)
        start = nk
        everyone = _round == _ROUNDS
        for k in range(nk - 1):
            # the pair on the path; after `_ROUNDS`, every one still bounded. A pinned knot's candidates are
            # all the same values: its first stands for all, and its cost is every one's
            ca = 1 if pinned[k] else c
            cb = 1 if pinned[k + 1] else c
            i0 = 0 if everyone else min(choice[k], ca - 1)
            j0 = 0 if everyone else min(choice[k + 1], cb - 1)
            for i in range(i0, ca if everyone else i0 + 1):
                for j in range(j0, cb if everyone else j0 + 1):
                    if not lower[k, i, j]:
                        continue
                    t0, t1 = times[k], times[k + 1]
                    at = t0 - times[0]
                    if not ready[k]:
                        _segment_ticks(p_plan, t0, t1, terms, at)
                        ready[k] = True
                    va, vb = cand_v[k, i] * conv, cand_v[k + 1, j] * conv
                    limits = _limits(cand_p[k, i], va, cand_p[k + 1, j], vb, float(t1 - t0), envelope[k],
                                     excess_scale, drive_acc, drive_vel)
                    cost = _exact_cost(terms, at, t1 - t0, cand_p[k, i], va, cand_p[k + 1, j], vb, toward_zero, tol,
                                       limits)
                    if cost != costs[k, i, j]:  # a bound that is the cost changes no total: no pass again for it
                        start = min(start, k)
                    for r in range(c) if ca == 1 else range(i, i + 1):
                        for s in range(c) if cb == 1 else range(j, j + 1):
                            costs[k, r, s] = cost
                            lower[k, r, s] = False
        if start == nk:
            return choice
    return _best_path(costs, pinned, totals, back, start)


@kernel
def _replicate(values: NDArray[np.generic], k: int, ca: int, cb: int) -> None:
    """In values[k], rows ca.. as row 0 and columns cb.. as column 0 (the candidates of a pinned knot)."""
    for i in range(ca, values.shape[1]):
        for j in range(cb):
            values[k, i, j] = values[k, 0, j]
    for j in range(cb, values.shape[2]):
        for i in range(values.shape[1]):
            values[k, i, j] = values[k, i, 0]


@kernel
def _largest(x: FloatArray) -> float:
    """np.abs(x).max(), or a nan where x holds one (which one does not matter: it only fails comparisons).
    Non-negative floats order as their bit patterns (nan above inf), and an integer maximum vectorises
    where a nan-aware float one does not: |x| is copied in chunks to be read as integers."""
    flat = x.ravel()
    chunk = np.empty(256)
    bits = chunk.view(np.int64)
    top = np.int64(0)
    for s in range(0, flat.size, chunk.size):
        part = flat[s : s + chunk.size]
        for t in range(part.size):
            chunk[t] = abs(part[t])
        for t in range(part.size):
            top = bits[t] if bits[t] > top else top
    bits[0] = top
    return float(chunk[0])


@kernel
def alive_candidates(feasible: BoolArray, pinned: BoolArray) -> BoolArray:
    """(K, C): the candidates of one axis that lie on at least one path of feasible pairs through every
    knot (`feasible` (K-1, C, C)), by forward and backward passes; at a `pinned` knot (all candidates the
    same values) only the first. A knot where none would be left keeps all its candidates (then no path
    passes, and the choice is the least bad one of all). Whole rows of `feasible` at a time, with no early
    exit: loops that vectorise."""
    nseg, c, _ = feasible.shape
    alive = np.ones((nseg + 1, c), np.bool_)
    for k in range(nseg + 1):
        if pinned[k]:
            alive[k, 1:] = False
    reach = np.empty(c, np.bool_)
    for k in range(nseg):  # reachable from the start
        for j in range(c):
            reach[j] = False
        for i in range(c):
            if alive[k, i]:
                for j in range(c):
                    reach[j] |= feasible[k, i, j]
        for j in range(c):
            alive[k + 1, j] &= reach[j]
    for k in range(nseg - 1, -1, -1):  # and reaching the end
        for i in range(c):
            if alive[k, i]:
                hit = False
                for j in range(c):
                    hit |= feasible[k, i, j] & alive[k + 1, j]
                alive[k, i] = hit
    for k in range(nseg + 1):
        if not alive[k].any():
            alive[k, :] = True
    return alive


@kernel
def _every_tick_path(
    cand_p: FloatArray,
    cand_v: FloatArray,
    pinned: BoolArray,
    p_plan: FloatArray,
    times: IntArray,
    envelope: FloatArray,
    conv: float,
    excess_scale: float,
    drive_acc: float,
    drive_vel: float,
    toward_zero: bool,
    tol: float,
    prox: FloatArray,
) -> IntArray:
    """One axis' minimum-cost candidate path with the costs at every tick (`viterbi`), found lazily from the
    costs at the sample ticks as lower bounds (`_exact_path`) where no cost can be nan (as the refinement
    decides it)."""
    nk, c = cand_p.shape
    reach = _largest(cand_p) + _largest(p_plan) + _largest(cand_v) * conv * (times[-1] - times[0])
    if not (tol > 0.0 and excess_scale > 0.0 and reach < 1.0e30):
        return viterbi(cand_p, cand_v, pinned, p_plan, times, envelope, conv, excess_scale, drive_acc, drive_vel,
                       toward_zero, tol)
    dev = np.empty((nk - 1, c, padded(c)), np.float32)
    sample_misses(p_plan, times, cand_p, cand_v, pinned, envelope, conv, excess_scale, drive_acc, drive_vel,
                  toward_zero, tol, prox, dev, np.empty((0, 0, 0), np.bool_))
    bounds = np.empty((nk - 1, c, c))
    sample_bounds(dev, times, cand_p, cand_v, pinned, envelope, conv, excess_scale, drive_acc, drive_vel, tol, bounds)
    return _exact_path(cand_p, cand_v, pinned, bounds, p_plan, times, envelope, conv, excess_scale, drive_acc,
                       drive_vel, toward_zero, tol)


@kernel
def choose_values(
    positions: FloatArray,
    velocities: FloatArray,
    envelope: FloatArray,
    times: IntArray,
    conv: FloatArray,
    excess_scale: FloatArray,
    drive_acc: FloatArray,
    drive_vel: FloatArray,
    toward_zero: BoolArray,
    tol: float,
    prox: FloatArray,
    dp: FloatArray,
    dv: IntArray,
    bracket: bool,
    first: tuple[IntArray, IntArray],
    last: tuple[IntArray, IntArray],
) -> tuple[IntArray, IntArray]:
    """Every axis' knot values (counts, rpm) chosen jointly, every tick checked (`_every_tick_path`), knot 0
    at `first` and the last knot at `last` (positions, velocities per axis); `envelope` the plan's
    acceleration peak per segment (`segment_envelope`)."""
    n = positions.shape[0]
    nk = times.size
    pinned = np.zeros(nk, np.bool_)
    pinned[0] = True
    pinned[nk - 1] = True
    out_p = np.empty((n, nk), np.int64)
    out_v = np.empty((n, nk), np.int64)
    pin_p = np.zeros(nk, np.int64)
    pin_v = np.zeros(nk, np.int64)
    for a in range(n):
        pin_p[0], pin_v[0] = first[0][a], first[1][a]
        pin_p[nk - 1], pin_v[nk - 1] = last[0][a], last[1][a]
        cand_p, cand_v = axis_candidates(positions[a], velocities[a], times, conv[a], dp, dv, bracket, pinned,
                                         pin_p, pin_v)
        if nk == 1:
            choice = np.zeros(1, np.int64)
        else:
            choice = _every_tick_path(cand_p, cand_v, pinned, positions[a], times, envelope[a], conv[a],
                                      excess_scale[a], drive_acc[a], drive_vel[a], toward_zero[a], tol, prox)
        for k in range(nk):
            out_p[a, k] = int(cand_p[k, choice[k]])
            out_v[a, k] = int(cand_v[k, choice[k]])
    return out_p, out_v


@kernel
def refine(
    positions: FloatArray,
    velocities: FloatArray,
    envelope: FloatArray,
    times: IntArray,
    knot_p: IntArray,
    knot_v: IntArray,
    bad: BoolArray,
    pinned: BoolArray,
    conv: FloatArray,
    excess_scale: FloatArray,
    drive_acc: FloatArray,
    drive_vel: FloatArray,
    toward_zero: BoolArray,
    tol: float,
    prox: FloatArray,
    dp: FloatArray,
    dv: IntArray,
) -> tuple[IntArray, IntArray]:
    """The knot values (counts, rpm) chosen again, every tick checked, in a window of two knots either
    side of the segments `bad` (n_axes, N) marks, on the axes that fail in the window (the others keep
    theirs, which pass); the window's ends and the `pinned` knots keep their values.

    Candidates: positions `dp`, velocities `dv` around the plan. Only those on a path of pairs that pass
    at the sample ticks get the check at every tick (a pair that fails there fails at every tick too),
    padded with the first others up to the window's widest knot. The check at every tick starts from
    the costs at the sample ticks as lower bounds (`_exact_path`): most pairs are never checked at
    every tick. A window's last segment is weighed against the plan's acceleration peak (`envelope`
    per segment) from its start to the plan's end, as numpy's reduceat on the window's times had it."""
    nk = knot_p.shape[1]
    out_p = knot_p.copy()
    out_v = knot_v.copy()
    lows = np.empty(nk, np.int64)
    highs = np.empty(nk, np.int64)
    nw = 0
    for s in range(nk - 1):
        if bad[:, s].any():
            lo, hi = max(0, s - 2), min(nk - 1, s + 3)
            if nw > 0 and lo <= highs[nw - 1]:
                highs[nw - 1] = hi
            else:
                lows[nw], highs[nw] = lo, hi
                nw += 1
    c = dp.size * dv.size
    farthest = np.empty(positions.shape[0])  # the plan's largest |position| per axis, where one is needed
    known = np.zeros(positions.shape[0], np.bool_)
    for w in range(nw):
        lo, hi = lows[w], highs[w]
        kw = hi - lo + 1
        sub = times[lo : hi + 1]
        pin = pinned[lo : hi + 1].copy()
        pin[0] = True
        pin[kw - 1] = True
        axes = np.nonzero(bad[:, lo:hi].sum(axis=1) > 0)[0]
        na = axes.size
        cands_p = np.empty((na, kw, c))
        cands_v = np.empty((na, kw, c))
        alive = np.empty((na, kw, c), np.bool_)
        env = np.empty((na, kw - 1))
        feasible = np.empty((kw - 1, c, c), np.bool_)
        dev = np.empty((na, kw - 1, c, padded(c)), np.float32)
        lazy = np.empty(na, np.bool_)
        for ai in range(na):
            a = axes[ai]
            env[ai, : kw - 2] = envelope[a, lo : hi - 1]
            env[ai, kw - 2] = envelope[a, hi - 1 :].max()
            cands_p[ai], cands_v[ai] = axis_candidates(positions[a], velocities[a], sub, conv[a], dp, dv, False,
                                                       pin, out_p[a, lo : hi + 1], out_v[a, lo : hi + 1])
            sample_misses(positions[a], sub, cands_p[ai], cands_v[ai], pin, env[ai], conv[a], excess_scale[a],
                          drive_acc[a], drive_vel[a], toward_zero[a], tol, prox, dev[ai], feasible)
            alive[ai] = alive_candidates(feasible, pin)
            # bounds only where no cost can be nan: tol and the budget above 0, and every share far below
            # float32's range (|share| <= |p| + |plan| + 1 + |v| T), so that no miss is nan
            if not known[a]:
                farthest[a] = _largest(positions[a])
                known[a] = True
            reach = _largest(cands_p[ai]) + farthest[a] + _largest(cands_v[ai]) * conv[a] * (sub[-1] - sub[0])
            lazy[ai] = tol > 0.0 and excess_scale[a] > 0.0 and reach < 1.0e30
        width = 1
        for ai in range(na):
            for k in range(kw):
                width = max(width, int(alive[ai, k].sum()))
        for ai in range(na):
            a = axes[ai]
            order = np.empty((kw, width), np.int64)
            for k in range(kw):
                j = 0
                for keep in (True, False):  # the live candidates first, each group in its order
                    for i in range(c):
                        if alive[ai, k, i] == keep and j < width:
                            order[k, j] = i
                            j += 1
            cp = np.empty((kw, width))
            cv = np.empty((kw, width))
            for k in range(kw):
                for j in range(width):
                    cp[k, j], cv[k, j] = cands_p[ai, k, order[k, j]], cands_v[ai, k, order[k, j]]
            if lazy[ai]:
                sub_dev = np.empty((kw - 1, width, width), np.float32)
                for k in range(kw - 1):
                    for i in range(width):
                        for j in range(width):
                            sub_dev[k, i, j] = dev[ai, k, order[k, i], order[k + 1, j]]
                sub_bounds = np.empty((kw - 1, width, width))
                sample_bounds(sub_dev, sub, cp, cv, pin, env[ai], conv[a], excess_scale[a], drive_acc[a], drive_vel[a],
                              tol, sub_bounds)
                choice = _exact_path(cp, cv, pin, sub_bounds, positions[a], sub, env[ai], conv[a], excess_scale[a],
                                     drive_acc[a], drive_vel[a], toward_zero[a], tol)
            else:
                choice = viterbi(cp, cv, pin, positions[a], sub, env[ai], conv[a], excess_scale[a], drive_acc[a],
                                 drive_vel[a], toward_zero[a], tol)
            for k in range(kw):
                out_p[a, lo + k] = int(cp[k, choice[k]])
                out_v[a, lo + k] = int(cv[k, choice[k]])
    return out_p, out_v
