"""The PVT encoder's value search and verification, compiled (planner/encoder.py, steps 2 and 3).

Theory of operation: encoder.py's module docstring; this module is its arithmetic, in loops compiled with
numba (planner/jit.py). The value search scores every (start candidate, end candidate) pair of every
segment, and the refinement checks every tick of every pair: as NumPy that took (n, N, C, C, ticks)
temporaries and tens of array operations per window (15-90 ms per plan, most of the encoder's time).
Here the Viterbi pass computes each segment's (C, C) costs where it needs them, and the verification
reconstructs the drive's demand in one pass over the ticks.

The results are bit for bit those of the NumPy formulation the encoder had (tests/planner/
test_planner_value_search.py keeps it as the reference): the drive's interpolation and rounding as
planner/hermite.py writes them, operation for operation; the deviation near the plan in float32 (whole
counts subtracted first, so the numbers are small), cast where NumPy cast; ties to the first candidate,
as numpy's argmin.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from planner.jit import kernel
from planner.record import VELOCITY_MAX, VELOCITY_MIN
from planner.reference import FloatArray, IntArray

BoolArray = NDArray[np.bool_]

HARD = 1.0e6  # cost of a pair that misses the tolerance, 0x60C5 or 0x607F: only chosen where all do
_VMIN = float(VELOCITY_MIN)
_VMAX = float(VELOCITY_MAX)


@kernel
def drive_round(x: float, toward_zero: bool) -> float:
    """`x` rounded as the drive rounds its demand, as planner/hermite.py computes it: half away from zero
    (`round_counts_array`: trunc(x +- 0.5)) or toward zero (`truncate_counts_array`)."""
    if toward_zero:
        return float(np.trunc(x))
    return float(np.trunc(x + np.copysign(0.5, x)))


# ----------------------------------------------------------------------------------------------------
# verification


@kernel
def reconstruct(
    positions: IntArray, velocities_rpm: IntArray, times: IntArray, conv: FloatArray, toward_zero: BoolArray
) -> tuple[IntArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """The drive's rounded demand, unrounded position and velocity at every ms 0..times[-1], and every
    segment's start and end acceleration, of every axis: planner.hermite.reconstruct's polynomial
    (anchored at the segment's end, tau in [-T + 1, 0]), evaluated in the same order."""
    n, nk = positions.shape
    total = times[-1]
    demand = np.empty((n, total + 1), np.int64)
    pos = np.empty((n, total + 1))
    vel = np.empty((n, total + 1))
    acc_s = np.zeros((n, nk - 1))
    acc_e = np.zeros((n, nk - 1))
    for i in range(n):
        pos[i, 0] = float(positions[i, 0])
        vel[i, 0] = float(velocities_rpm[i, 0]) * conv[i]
        for k in range(nk - 1):
            p0 = float(positions[i, k])
            p1 = float(positions[i, k + 1])
            v0 = float(velocities_rpm[i, k]) * conv[i]
            v1 = float(velocities_rpm[i, k + 1]) * conv[i]
            t = float(times[k + 1] - times[k])
            dp = p1 - p0
            # t * t * t is t**3 exactly: whole ms, far below 2**17
            a = (-2.0 * dp + t * (v1 + v0)) / (t * t * t)
            b = (-3.0 * dp + t * (2.0 * v1 + v0)) / (t * t)
            for tick in range(times[k] + 1, times[k + 1] + 1):
                tau = float(tick - times[k + 1])
                pos[i, tick] = ((a * tau + b) * tau + v1) * tau + p1
                vel[i, tick] = (3.0 * a * tau + 2.0 * b) * tau + v1
            acc_s[i, k] = (6.0 * dp - 2.0 * t * v1 - 4.0 * t * v0) / (t * t)
            acc_e[i, k] = (-6.0 * dp + 4.0 * t * v1 + 2.0 * t * v0) / (t * t)
        for tick in range(total + 1):
            demand[i, tick] = int(drive_round(pos[i, tick], toward_zero[i]))
    return demand, pos, vel, acc_s, acc_e


@kernel
def segment_envelope(acc_left: FloatArray, acc_right: FloatArray, times: IntArray) -> FloatArray:
    """max(|acc_left|, |acc_right|) over each segment's ticks, both ends included, (n_axes, N).

    The last segment's runs to the end of the plan, not to times[-1] (numpy's `maximum.reduceat`, which
    the encoder used: the same where times end at the plan's end, as an encoding's do; the refinement's
    windows inherit it, see `refine`)."""
    n, m1 = acc_left.shape
    nseg = times.size - 1
    out = np.empty((n, max(nseg, 0)))
    for i in range(n):
        for k in range(nseg):
            a = times[k]
            stop = m1 if k == nseg - 1 else max(times[k + 1], a + 1)
            peak = np.maximum(abs(acc_left[i, a]), abs(acc_right[i, a]))
            for t in range(a + 1, stop):
                peak = np.maximum(peak, np.maximum(abs(acc_left[i, t]), abs(acc_right[i, t])))
            b = times[k + 1]
            out[i, k] = np.maximum(peak, np.maximum(abs(acc_left[i, b]), abs(acc_right[i, b])))
    return out


@kernel
def failing_segments(
    demand: IntArray,
    want: IntArray,
    times: IntArray,
    tol: float,
    acc_start: FloatArray,
    acc_end: FloatArray,
    envelope: FloatArray,
    excess_limit: FloatArray,
    drive_acc: FloatArray,
) -> BoolArray:
    """(n_axes, N): the segments of each axis whose demand misses `want` by more than `tol` at a tick
    (tick 0 counts to segment 0, a knot's tick to the segment it ends), or whose peak acceleration
    exceeds the plan's `envelope` by more than `excess_limit` or is above `drive_acc`."""
    n = demand.shape[0]
    nseg = times.size - 1
    bad = np.zeros((n, nseg), np.bool_)
    for i in range(n):
        for k in range(nseg):
            for tick in range(times[k] + 1 if k > 0 else 0, times[k + 1] + 1):
                if abs(demand[i, tick] - want[i, tick]) > tol:
                    bad[i, k] = True
                    break
            peak = np.maximum(abs(acc_start[i, k]), abs(acc_end[i, k]))
            if peak - envelope[i, k] > excess_limit[i] or peak > drive_acc[i]:
                bad[i, k] = True
    return bad


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
def pair_costs(
    p_plan: FloatArray,
    t0: int,
    t1: int,
    pa: FloatArray,
    va_rpm: FloatArray,
    pb: FloatArray,
    vb_rpm: FloatArray,
    conv: float,
    envelope: float,
    excess_scale: float,
    drive_acc: float,
    drive_vel: float,
    toward_zero: bool,
    tol: float,
    exact: bool,
    prox: FloatArray,
    out: FloatArray,
) -> None:
    """out[i, j]: the cost of the segment t0..t1 of one axis from candidate (pa[i], va_rpm[i]) to
    (pb[j], vb_rpm[j]) (velocities in rpm, `conv` counts/ms per rpm).

    Deviation: the drive's rounded demand against the planned demand, at every tick (`exact`) or at the
    sample ticks `prox` (fractions of the segment, rounded, within 1..T-1); beyond `tol` it costs HARD,
    below it (dev / tol)^2 (exact) or half the squared float error (a tie-breaker: smaller is more robust
    at the ticks in between). Plus HARD above 0x60C5 (`drive_acc`) or, at the ends, 0x607F
    (`drive_vel`), and the squared excess of the end accelerations over the plan's `envelope` in units
    of `excess_scale` (1e3 more above 0.9 of it).
    """
    ca = pa.size
    cb = pb.size
    dt = float(t1 - t0)
    va = va_rpm * conv
    vb = vb_rpm * conv
    if exact:
        offsets = np.arange(1, t1 - t0 + 1).astype(np.float64)
    else:
        offsets = np.empty(prox.size)
        top = max(dt - 1.0, 1.0)
        for q in range(prox.size):
            offsets[q] = min(max(np.round(prox[q] * dt), 1.0), top)
    dev = np.zeros((ca, cb), np.float32)
    err = np.zeros((ca, cb), np.float32)
    ea = np.empty(ca, np.float32)
    eb = np.empty(cb, np.float32)
    half = np.float32(0.5)
    for off in offsets:
        s = off / dt
        s2 = s * s
        h00 = 1.0 - 3.0 * s2 + 2.0 * s2 * s
        h01 = 1.0 - h00
        h10 = (s - 2.0 * s2 + s2 * s) * dt
        h11 = (s2 * s - s2) * dt
        p = p_plan[t0 + int(off)]
        # relative to the whole count below the plan: small numbers, float32 will do
        base = np.floor(p)
        for i in range(ca):
            ea[i] = np.float32((pa[i] - base) * h00 + va[i] * h10)
        for j in range(cb):
            eb[j] = np.float32((pb[j] - base) * h01 + vb[j] * h11)
        if toward_zero:
            target = np.trunc(p)
            for i in range(ca):
                for j in range(cb):
                    miss = np.float32(abs(np.trunc(np.float64(ea[i] + eb[j]) + base) - target))
                    if miss > dev[i, j]:
                        dev[i, j] = miss
        else:
            want = np.float32(float(int(np.trunc(p + np.copysign(0.5, p)))) - base)
            for i in range(ca):
                a = ea[i]
                for j in range(cb):
                    miss = abs(np.floor(a + eb[j] + half) - want)
                    if miss > dev[i, j]:
                        dev[i, j] = miss
        if not exact:
            frac = np.float32(p - base)
            for i in range(ca):
                a = ea[i]
                for j in range(cb):
                    e = abs(a + eb[j] - frac)
                    if e > err[i, j]:
                        err[i, j] = e
    tol32 = np.float32(tol)
    for i in range(ca):
        for j in range(cb):
            hard = HARD if dev[i, j] > tol32 else 0.0
            if exact:
                q = dev[i, j] / tol32
                dev_cost = hard + np.float64(q * q)
            else:
                q = err[i, j] / tol32
                dev_cost = hard + np.float64(half * (q * q))
            dp = pb[j] - pa[i]
            acc_s = (6.0 * dp - 2.0 * dt * vb[j] - 4.0 * dt * va[i]) / (dt * dt)
            acc_e = (-6.0 * dp + 4.0 * dt * vb[j] + 2.0 * dt * va[i]) / (dt * dt)
            peak = np.maximum(abs(acc_s), abs(acc_e))
            excess = np.maximum(peak - envelope, 0.0) / excess_scale
            over = peak > drive_acc or np.maximum(abs(va[i]), abs(vb[j])) > drive_vel
            out[i, j] = dev_cost + (HARD if over else 0.0) + (1.0e3 if excess > 0.9 else 0.0) + excess * excess


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
def viterbi(
    cand_p: FloatArray,
    cand_v: FloatArray,
    p_plan: FloatArray,
    times: IntArray,
    envelope: FloatArray,
    conv: float,
    excess_scale: float,
    drive_acc: float,
    drive_vel: float,
    toward_zero: bool,
    tol: float,
    exact: bool,
    prox: FloatArray,
    pin_last: bool,
) -> IntArray:
    """One axis' minimum-cost candidate path through the knots (`pair_costs` of each segment, computed
    where the pass reaches it); knot 0 is candidate 0, and with `pin_last` the last knot too."""
    nk, c = cand_p.shape
    total = np.full(c, np.inf)
    total[0] = 0.0
    back = np.empty((nk - 1, c), np.int64)
    cost = np.empty((c, c))
    tot = np.empty(c)
    nxt = np.empty(c)
    for k in range(nk - 1):
        pair_costs(p_plan, times[k], times[k + 1], cand_p[k], cand_v[k], cand_p[k + 1], cand_v[k + 1], conv,
                   envelope[k], excess_scale, drive_acc, drive_vel, toward_zero, tol, exact, prox, cost)
        if pin_last and k == nk - 2:
            cost[:, 1:] = np.inf
        for j in range(c):
            for i in range(c):
                tot[i] = total[i] + cost[i, j]
            best = _first_min(tot)
            back[k, j] = best
            nxt[j] = tot[best]
        total[:] = nxt
    choice = np.empty(nk, np.int64)
    choice[nk - 1] = _first_min(total)
    for k in range(nk - 2, -1, -1):
        choice[k] = back[k, choice[k + 1]]
    return choice


@kernel
def alive_candidates(feasible: BoolArray, pinned: BoolArray) -> BoolArray:
    """(K, C): the candidates of one axis that lie on at least one path of feasible pairs through every
    knot (`feasible` (K-1, C, C)), by forward and backward passes; at a `pinned` knot (all candidates the
    same values) only the first. A knot where none would be left keeps all its candidates (then no path
    passes, and the choice is the least bad one of all)."""
    nseg, c, _ = feasible.shape
    alive = np.ones((nseg + 1, c), np.bool_)
    for k in range(nseg + 1):
        if pinned[k]:
            alive[k, 1:] = False
    for k in range(nseg):  # reachable from the start
        for j in range(c):
            if alive[k + 1, j]:
                reach = False
                for i in range(c):
                    if feasible[k, i, j] and alive[k, i]:
                        reach = True
                        break
                alive[k + 1, j] = reach
    for k in range(nseg - 1, -1, -1):  # and reaching the end
        for i in range(c):
            if alive[k, i]:
                reach = False
                for j in range(c):
                    if feasible[k, i, j] and alive[k + 1, j]:
                        reach = True
                        break
                alive[k, i] = reach
    for k in range(nseg + 1):
        if not alive[k].any():
            alive[k, :] = True
    return alive


@kernel
def choose_values(
    positions: FloatArray,
    velocities: FloatArray,
    acc_left: FloatArray,
    acc_right: FloatArray,
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
    """Every axis' knot values (counts, rpm) chosen jointly at the sample ticks (`viterbi`), knot 0 at
    `first` and the last knot at `last` (positions, velocities per axis)."""
    n = positions.shape[0]
    nk = times.size
    envelope = segment_envelope(acc_left, acc_right, times)
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
            choice = viterbi(cand_p, cand_v, positions[a], times, envelope[a], conv[a], excess_scale[a],
                             drive_acc[a], drive_vel[a], toward_zero[a], tol, False, prox, False)
        for k in range(nk):
            out_p[a, k] = int(cand_p[k, choice[k]])
            out_v[a, k] = int(cand_v[k, choice[k]])
    return out_p, out_v


@kernel
def refine(
    positions: FloatArray,
    velocities: FloatArray,
    acc_left: FloatArray,
    acc_right: FloatArray,
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
    padded with the first others up to the window's widest knot. The window's last segment is weighed
    against the plan's acceleration up to the plan's end (`segment_envelope` on the window's times)."""
    n, nk = knot_p.shape
    m1 = positions.shape[1]
    out_p = knot_p.copy()
    out_v = knot_v.copy()
    envelope = segment_envelope(acc_left, acc_right, times)
    suffix = np.empty((n, m1))  # planned |acceleration| peak from each tick to the plan's end
    for a in range(n):
        run = np.maximum(abs(acc_left[a, m1 - 1]), abs(acc_right[a, m1 - 1]))
        suffix[a, m1 - 1] = run
        for t in range(m1 - 2, -1, -1):
            run = np.maximum(np.maximum(abs(acc_left[a, t]), abs(acc_right[a, t])), run)
            suffix[a, t] = run
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
    cost = np.empty((c, c))
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
        for ai in range(na):
            a = axes[ai]
            env[ai, : kw - 2] = envelope[a, lo : hi - 1]
            env[ai, kw - 2] = suffix[a, times[hi - 1]]
            cands_p[ai], cands_v[ai] = axis_candidates(positions[a], velocities[a], sub, conv[a], dp, dv, False,
                                                       pin, out_p[a, lo : hi + 1], out_v[a, lo : hi + 1])
            for k in range(kw - 1):
                pair_costs(positions[a], sub[k], sub[k + 1], cands_p[ai, k], cands_v[ai, k], cands_p[ai, k + 1],
                           cands_v[ai, k + 1], conv[a], env[ai, k], excess_scale[a], drive_acc[a], drive_vel[a],
                           toward_zero[a], tol, False, prox, cost)
                feasible[k] = cost < HARD
            alive[ai] = alive_candidates(feasible, pin)
        width = 1
        for ai in range(na):
            for k in range(kw):
                width = max(width, int(alive[ai, k].sum()))
        for ai in range(na):
            a = axes[ai]
            cp = np.empty((kw, width))
            cv = np.empty((kw, width))
            for k in range(kw):
                j = 0
                for keep in (True, False):  # the live candidates first, each group in its order
                    for i in range(c):
                        if alive[ai, k, i] == keep and j < width:
                            cp[k, j], cv[k, j] = cands_p[ai, k, i], cands_v[ai, k, i]
                            j += 1
            choice = viterbi(cp, cv, positions[a], sub, env[ai], conv[a], excess_scale[a], drive_acc[a],
                             drive_vel[a], toward_zero[a], tol, True, prox, True)
            for k in range(kw):
                out_p[a, lo + k] = int(cp[k, choice[k]])
                out_v[a, lo + k] = int(cv[k, choice[k]])
    return out_p, out_v
