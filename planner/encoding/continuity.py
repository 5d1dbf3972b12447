"""Knot values that keep the drive's acceleration continuous: the encoder's values re-chosen for a
jerk-limited plan (planner/motion/jerkpath.py, `jerk_limited` path jobs).

Theory of operation. A cubic Hermite chain is C2 only where its knot velocities make it so: at a knot,
the acceleration the drive ends one segment with and the one it starts the next with both depend on the
knot's position and velocity and on its two neighbours'. The encoder (planner/encoding/encoder.py) rounds each
knot to whole counts and whole rpm choosing values that keep the drive within the tolerance and the
acceleration-excess budget, pair of knots by pair of knots (a Viterbi pass over the segments); the
steps of acceleration that rounding leaves at the knots are a jerk over the 1 ms tick, typically 10-20
times what a jerk limit allows. Here, per axis, a second-order Viterbi pass chooses the values again on
the same knot times: its states are the candidate pairs of two consecutive knots, so that the step at
every knot (three knots' values) is a cost of one transition. Candidates per knot: the planned demand
and the counts either side within the tolerance (two at most), the rpm value nearest the plan and one
more either side, and the
encoder's own choice (so the encoder's encoding is always one of the paths). A pair is admissible when
its segment keeps the encoder's promises at every ms (the drive's rounded demand within the tolerance of
the planned demand, velocity within the limits, acceleration within 0x60C5 and the excess budget) and
its in-segment jerk within JERK_SLACK of the limit or, on an axis where the encoder's own values already
exceed that, within the encoder's largest there (a bound per axis, not per segment: a segment a little
above the limit can buy a much smaller step at a knot); its
cost penalises an in-segment jerk above the limit; a knot's cost is its acceleration step over the
tick against the jerk limit (squared, and heavily beyond the limit). The result is checked with the
encoder's own verification (`encoder.within_contract`); an encoding that does not pass is not used.
The pass is a compiled kernel (`_viterbi`, planner/jit.py): up to 16 candidates per knot make 4,000
transitions per knot, which in NumPy cost most of a jerk-limited plan's time.

The knot times are shared by every axis (every drive gets the same record times), so values alone cannot
always meet the bound: a knot between a short and a long segment moves its step by 6/T^2 per count of the
short one's neighbour. `refine_times` then moves such knots a few ms, one at a time, worst first, and
re-chooses every axis' values in a window around each by the same pass, keeping a move that lowers the
window's worst step or jerk over all axes.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from planner.encoding.encoder import ACC_EXCESS_LIMIT, VELOCITY_SLACK, segment_cap, within_contract
from planner.encoding.reconstruction import AxisScales, Knots, planned_demand, segment_envelope
from planner.encoding.record import SEGMENT_TIME_MAX_MS
from planner.jit import kernel
from planner.motion.reference import FloatArray, IntArray, Reference

JERK_SLACK = 0.05  # in-segment jerk allowed above the limit (the issue's +5 %)
OVER = 1.0e4  # weight of a step or jerk beyond the limit (against 1 for a step at the limit)
_VELOCITIES = (-1, 0, 1)  # rpm around the plan's rounded velocity (+-2 measured no better)
MAX_OFFSET = 2  # counts around the planned demand: up to the tolerance, at most this many


def knot_steps(knots: Knots, scales: AxisScales) -> tuple[FloatArray, FloatArray]:
    """Per axis and segment the constant jerk (counts/ms^3) and per interior knot the acceleration step
    (counts/ms^2) of the drive's reconstruction of `knots`."""
    conv = scales.counts_per_ms_per_rpm[:, None]
    t = np.diff(knots.times_ms).astype(np.float64)[None, :]
    p = knots.positions.astype(np.float64)
    v = knots.velocities_rpm.astype(np.float64) * conv
    dp = p[:, 1:] - p[:, :-1]
    b = (-3.0 * dp + t * (2.0 * v[:, 1:] + v[:, :-1])) / (t * t)
    a = (-2.0 * dp + t * (v[:, 1:] + v[:, :-1])) / (t * t * t)
    acc_start, acc_end = -6.0 * a * t + 2.0 * b, 2.0 * b
    out: tuple[FloatArray, FloatArray] = (6.0 * a, acc_start[:, 1:] - acc_end[:, :-1])
    return out


def _candidates(
    want: IntArray, v_plan: FloatArray, times: IntArray, p_orig: IntArray, v_orig: IntArray, conv: float,
    tol: float, held: int = 1, moved: int = -1,
) -> tuple[FloatArray, FloatArray, IntArray]:
    """Every knot's candidate values (positions, rpm), sorted, padded to one width: (n+1, C) each, and the
    count per knot. The `held` knots at each end keep their values (the start is where the drive stands;
    `refine_times` holds two to cost the steps at its window's edges). Positions within the tolerance of
    the planned demand (at most `MAX_OFFSET` counts either side: at a tolerance of 2 counts, +-2 left the
    demo path's worst step at 2.1 x the bound where +-1 left 2.7), and the knot's own values but at the
    knot `moved` (whose time changed)."""
    n = times.size - 1
    offsets = range(-min(int(tol), MAX_OFFSET), min(int(tol), MAX_OFFSET) + 1)
    width = len(offsets) * len(_VELOCITIES) + 1
    cp = np.zeros((n + 1, width))
    cv = np.zeros((n + 1, width))
    count = np.ones(n + 1, dtype=np.int64)
    for k in range(n + 1):
        if k < held or k > n - held:
            cp[k, 0], cv[k, 0] = float(p_orig[k]), float(v_orig[k])
            continue
        w = float(want[times[k]])
        r = float(np.round(v_plan[times[k]] / conv))
        pairs = {(w + dp, r + dv) for dp in offsets for dv in _VELOCITIES}
        if k != moved:
            pairs.add((float(p_orig[k]), float(v_orig[k])))
        arr = np.array(sorted(pairs))
        count[k] = arr.shape[0]
        cp[k, : count[k]], cv[k, : count[k]] = arr[:, 0], arr[:, 1]
    return cp, cv, count


@kernel
def _viterbi(
    cp: FloatArray, cv: FloatArray, count: IntArray, times: IntArray, want: IntArray, envelope: FloatArray,
    conv: float, vlim: float, drive_acc: float, budget: float, jlim: float, jerk_cap: float, tol: float,
    over: float,
) -> IntArray:
    """The second-order Viterbi pass of `_axis` over the candidates: the index of the chosen candidate at
    every knot, or an empty array when no path is admissible. States are pairs of consecutive knots'
    candidates; a segment's pair is admissible when it keeps the encoder's promises at every ms, and
    costs its in-segment jerk above the limit; a transition costs the step at the knot between."""
    n = times.size - 1
    width = cp.shape[1]
    inf = np.inf
    cost = np.full((width, width), inf)  # (c_{k-1}, c_k): best cost of the paths ending in that pair
    new_cost = np.full((width, width), inf)
    seg_cost = np.full((width, width), inf)
    acc_s = np.zeros((width, width))
    acc_e = np.zeros((width, width))
    prev_acc_end = np.zeros((width, width))
    back = np.zeros((n, width, width), dtype=np.int64)
    for k in range(n):
        t = times[k + 1] - times[k]
        tf = float(t)
        for i in range(count[k]):
            p0 = cp[k, i]
            v0 = cv[k, i] * conv
            for j in range(count[k + 1]):
                p1 = cp[k + 1, j]
                v1 = cv[k + 1, j] * conv
                dp = p1 - p0
                b = (-3.0 * dp + tf * (2.0 * v1 + v0)) / (tf * tf)
                a = (-2.0 * dp + tf * (v1 + v0)) / (tf * tf * tf)
                s0 = -6.0 * a * tf + 2.0 * b
                e0 = 2.0 * b
                jerk = 6.0 * a
                acc_s[i, j] = s0
                acc_e[i, j] = e0
                # the end accelerations and the jerk first: a pair that fails them skips the ticks
                peak = max(abs(s0), abs(e0))
                ok = peak <= drive_acc and peak - envelope[k] <= budget and abs(jerk) <= jerk_cap
                if ok:
                    for m in range(1, t):
                        tau = float(m) - tf
                        pos = ((a * tau + b) * tau + v1) * tau + p1
                        vel = (3.0 * a * tau + 2.0 * b) * tau + v1
                        demand = np.trunc(pos + np.copysign(0.5, pos))
                        if abs(demand - float(want[times[k] + m])) > tol or abs(vel) > vlim + 1e-12:
                            ok = False
                            break
                if ok:
                    excess = max(abs(jerk) / jlim - 1.0, 0.0)
                    seg_cost[i, j] = over * (excess * excess)
                else:
                    seg_cost[i, j] = inf
        any_finite = False
        if k == 0:
            for j in range(count[1]):
                cost[0, j] = seg_cost[0, j]
                any_finite = any_finite or cost[0, j] < inf
        else:
            # transition (c_{k-1}, c_k) -> (c_k, c_{k+1}): the step at knot k
            for j in range(count[k]):
                for m in range(count[k + 1]):
                    best = inf
                    arg = 0
                    for i in range(count[k - 1]):
                        step = abs(acc_s[j, m] - prev_acc_end[i, j]) / jlim
                        beyond = max(step - 1.0, 0.0)
                        total = cost[i, j] + (step * step + over * (beyond * beyond))
                        if i == 0 or total < best:  # np.argmin: the first of equal ones
                            best = total
                            arg = i
                    back[k, j, m] = arg
                    new_cost[j, m] = best + seg_cost[j, m]
                    any_finite = any_finite or new_cost[j, m] < inf
            for j in range(count[k]):
                for m in range(count[k + 1]):
                    cost[j, m] = new_cost[j, m]
        for i in range(count[k]):
            for j in range(count[k + 1]):
                prev_acc_end[i, j] = acc_e[i, j]
        if not any_finite:
            return np.zeros(0, dtype=np.int64)
    # the end knot has one candidate: the best pair ending there, then back through the choices
    best = inf
    ck, cn = 0, 0
    for i in range(count[n - 1]):
        for j in range(count[n]):
            if (i == 0 and j == 0) or cost[i, j] < best:
                best = cost[i, j]
                ck, cn = i, j
    if not best < inf:
        return np.zeros(0, dtype=np.int64)
    chosen = np.zeros(n + 1, dtype=np.int64)
    chosen[n], chosen[n - 1] = cn, ck
    for k in range(n - 1, 0, -1):
        chosen[k - 1] = back[k, chosen[k], chosen[k + 1]]
    return chosen


def _axis(
    want: IntArray,
    v_plan: FloatArray,
    times: IntArray,
    p_orig: IntArray,
    v_orig: IntArray,
    envelope: FloatArray,
    conv: float,
    vlim: float,
    drive_acc: float,
    budget: float,
    jlim: float,
    tol: float,
    own_jerk: float,
) -> tuple[IntArray, IntArray] | None:
    """One axis' values (positions, rpm) by the second-order Viterbi pass; None when no path is admissible."""
    cp, cv, count = _candidates(want, v_plan, times, p_orig, v_orig, conv, tol)
    jerk_cap = max(jlim * (1.0 + JERK_SLACK), own_jerk)
    chosen = _viterbi(cp, cv, count, np.ascontiguousarray(times, dtype=np.int64),
                      np.ascontiguousarray(want, dtype=np.int64), np.ascontiguousarray(envelope, dtype=np.float64),
                      conv, vlim, drive_acc, budget, jlim, jerk_cap, float(tol), OVER)
    if chosen.size == 0:
        return None
    knots = np.arange(times.size)
    return cp[knots, chosen].astype(np.int64), cv[knots, chosen].astype(np.int64)


def _limits(scales: AxisScales) -> tuple[FloatArray, FloatArray]:
    """Per axis the velocity the drive's values may reach (counts/ms) and the acceleration-excess budget."""
    quantum = scales.counts_per_ms_per_rpm
    vlim = np.minimum(
        scales.drive_velocity,
        np.maximum(scales.velocity_limit * (1.0 + VELOCITY_SLACK), scales.velocity_limit + quantum),
    )
    return vlim, ACC_EXCESS_LIMIT * scales.acceleration_axis * 0.999


def smooth_values(ref: Reference, knots: Knots, scales: AxisScales, tol: float, jerk_limit: FloatArray) -> Knots:
    """`knots` with every axis' values re-chosen for a continuous acceleration (module docstring);
    `jerk_limit` (n,) in counts/ms^3. The encoder's knots are returned where the result would not keep
    every promise of the encoding, or would not lower the largest jerk or step (`worst_ratio`)."""
    if knots.times_ms.size < 3:
        return knots
    want = planned_demand(ref, scales.toward_zero)
    env = segment_envelope(ref, knots.times_ms)
    quantum = scales.counts_per_ms_per_rpm
    vlim, budget = _limits(scales)
    pos = knots.positions.copy()
    vel = knots.velocities_rpm.copy()
    own = np.abs(knot_steps(knots, scales)[0]).max(axis=1)
    for i in range(ref.n_axes):
        got = _axis(
            want[i], ref.velocities[i], knots.times_ms, knots.positions[i], knots.velocities_rpm[i], env[i],
            float(quantum[i]), float(vlim[i]), float(scales.drive_acceleration[i]), float(budget[i]),
            float(jerk_limit[i]), tol, float(own[i]),
        )
        if got is not None:
            pos[i], vel[i] = got
    out = Knots(knots.times_ms, pos, vel)
    if not within_contract(ref, out, scales, tol):
        return knots
    if worst_ratio(out, scales, jerk_limit) >= worst_ratio(knots, scales, jerk_limit):
        return knots
    return out


def worst_ratio(knots: Knots, scales: AxisScales, jerk_limit: FloatArray) -> float:
    """The largest in-segment jerk or knot step (over the tick) of the reconstruction, over its limit."""
    jerk, steps = knot_steps(knots, scales)
    return float(max((np.abs(jerk) / jerk_limit[:, None]).max(initial=0.0),
                     (np.abs(steps) / jerk_limit[:, None]).max(initial=0.0)))


def knot_step_units(scales: AxisScales, jerk_limit: FloatArray, t_ms: IntArray) -> tuple[FloatArray, FloatArray]:
    """What the drive's units do to the acceleration step at a knot between two segments of T ms, over the
    bound J x 1 ms (`jerk_limit` (n,) in counts/ms^3), per axis and T (n, m): one count of a neighbouring
    knot's position moves it by 6/T^2 counts/ms^2 (the knot's own position cancels when both segments are
    T long), one rpm of the knot's own velocity by 8 q/T (q counts/ms per rpm; a neighbour's rpm, 2 q/T)."""
    t = np.asarray(t_ms, dtype=np.float64)[None, :]
    bound = np.asarray(jerk_limit, dtype=np.float64)[:, None]
    per_count = 6.0 / (t * t) / bound
    per_rpm = 8.0 * scales.counts_per_ms_per_rpm[:, None] / t / bound
    return per_count, per_rpm


# ----------------------------------------------------------------------------------------------------
# the shared knot times moved, a knot at a time, with every axis' values re-chosen around it


REFINE_SHIFTS = (-6, -4, -3, -2, -1, 1, 2, 3, 4, 6)  # ms a knot is tried earlier or later
REFINE_WINDOW = 3  # knots either side of the moved one whose values are re-chosen
REFINE_ROUNDS = 2
REFINE_KNOTS = 32  # the worst knots tried per round (bounds the planning time of long paths)


def _one(scales: AxisScales, i: int) -> AxisScales:
    """`scales` of axis `i` alone (what `knot_steps` reads)."""
    return dataclasses.replace(scales, counts_per_ms_per_rpm=scales.counts_per_ms_per_rpm[i : i + 1])


def refine_times(ref: Reference, knots: Knots, scales: AxisScales, tol: float, jerk_limit: FloatArray) -> Knots:
    """`knots` (smoothed values, `smooth_values`) with their shared times moved where that lowers the worst
    step or jerk: each knot whose step exceeds the bound on some axis, worst first, is tried up to 6 ms
    earlier or later (`REFINE_SHIFTS`), every axis' values re-chosen on the `REFINE_WINDOW` knots either
    side by the same Viterbi pass (the window's two outer knots on each side held, so the steps at its
    edges are costed too); a shift is kept when the window's worst ratio over every axis drops. One
    knot time serves every axis (the drives get the same record times), and the values that suit one
    axis at a time suit another only by chance: this searches the times for all axes at once. The
    result is checked as `smooth_values`' is, and `knots` returned where it does not keep every promise
    or is not better."""
    n = knots.times_ms.size - 1
    if n < 4:
        return knots
    times = knots.times_ms.astype(np.int64).copy()
    pos = knots.positions.copy()
    vel = knots.velocities_rpm.copy()
    want = planned_demand(ref, scales.toward_zero)
    vlim, budget = _limits(scales)
    quantum = scales.counts_per_ms_per_rpm
    caps = np.maximum(jerk_limit * (1.0 + JERK_SLACK), np.abs(knot_steps(knots, scales)[0]).max(axis=1))
    cap = segment_cap(scales, tol)  # a job's max_segment_ms (a short lead) holds for the moved times too
    longest = SEGMENT_TIME_MAX_MS if cap is None else max(cap, int(np.diff(knots.times_ms).max()))
    for _round in range(REFINE_ROUNDS):
        steps = np.abs(knot_steps(Knots(times, pos, vel), scales)[1]) / jerk_limit[:, None]
        worst = steps.max(axis=0)  # per interior knot 1..n-1
        order = [int(k) + 1 for k in np.argsort(-worst, kind="stable")[:REFINE_KNOTS] if worst[k] > 1.0]
        moved = False
        for k in order:
            lo, hi = max(0, k - REFINE_WINDOW - 1), min(n, k + REFINE_WINDOW + 1)
            if not (lo + 1 < k < hi - 1):
                continue
            sl = slice(lo, hi + 1)
            best = worst_ratio(Knots(times[sl], pos[:, sl], vel[:, sl]), scales, jerk_limit)
            axis_order = np.argsort(-steps[:, k - 1], kind="stable")
            choice: tuple[IntArray, IntArray, IntArray] | None = None
            for shift in REFINE_SHIFTS:
                t_new = int(times[k]) + shift
                if not times[k - 1] < t_new < times[k + 1] or max(t_new - times[k - 1], times[k + 1] - t_new) > longest:
                    continue
                wt = times[sl].copy()
                wt[k - lo] = t_new
                env = segment_envelope(ref, wt)
                wp, wv = pos[:, sl].copy(), vel[:, sl].copy()
                ok = True
                for i in axis_order:  # the worst axis first: a shift that does not help it is dropped at once
                    cp, cv, count = _candidates(want[i], ref.velocities[i], wt, pos[i, sl], vel[i, sl],
                                                float(quantum[i]), tol, held=2, moved=k - lo)
                    chosen = _viterbi(cp, cv, count, wt, np.ascontiguousarray(want[i], dtype=np.int64),
                                      np.ascontiguousarray(env[i], dtype=np.float64), float(quantum[i]),
                                      float(vlim[i]), float(scales.drive_acceleration[i]), float(budget[i]),
                                      float(jerk_limit[i]), float(caps[i]), float(tol), OVER)
                    if chosen.size == 0:
                        ok = False
                        break
                    rows = np.arange(wt.size)
                    wp[i], wv[i] = cp[rows, chosen].astype(np.int64), cv[rows, chosen].astype(np.int64)
                    alone = Knots(wt, wp[i : i + 1], wv[i : i + 1])
                    if worst_ratio(alone, _one(scales, i), jerk_limit[i : i + 1]) >= best:
                        ok = False
                        break
                if not ok:
                    continue
                ratio = worst_ratio(Knots(wt, wp, wv), scales, jerk_limit)
                if ratio < best * (1.0 - 1e-9):
                    best, choice = ratio, (wt, wp, wv)
            if choice is not None:
                times[sl], pos[:, sl], vel[:, sl] = choice
                moved = True
        if not moved:
            break
    out = Knots(times, pos, vel)
    if not within_contract(ref, out, scales, tol):
        return knots
    if worst_ratio(out, scales, jerk_limit) >= worst_ratio(knots, scales, jerk_limit):
        return knots
    return out
