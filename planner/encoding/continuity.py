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
and one count either side, the two rpm values around the plan and one more either side, and the
encoder's own choice (so the encoder's encoding is always one of the paths). A pair is admissible when
its segment keeps the encoder's promises at every ms (the drive's rounded demand within the tolerance of
the planned demand, velocity within the limits, acceleration within 0x60C5 and the excess budget) and
its in-segment jerk within JERK_SLACK of the limit or, on an axis where the encoder's own values already
exceed that, within the encoder's largest there (a bound per axis, not per segment, so never worse than
the encoder's peak: a segment a little above the limit can buy a much smaller step at a knot, 12 -> 2.3
times the bound on one random path); its
cost penalises an in-segment jerk above the limit; a knot's cost is its acceleration step over the
tick against the jerk limit (squared, and heavily beyond the limit). The result is checked with the
encoder's own verification (`encoder.within_contract`); an encoding that does not pass is not used.
"""

from __future__ import annotations

import numpy as np

from planner.encoding import hermite
from planner.encoding.encoder import ACC_EXCESS_LIMIT, VELOCITY_SLACK, within_contract
from planner.encoding.reconstruction import AxisScales, Knots, planned_demand, segment_envelope
from planner.motion.reference import FloatArray, IntArray, Reference

JERK_SLACK = 0.05  # in-segment jerk allowed above the limit (the issue's +5 %)
OVER = 1.0e4  # weight of a step or jerk beyond the limit (against 1 for a step at the limit)
_POSITIONS = (-1, 0, 1)  # counts around the planned demand
_VELOCITIES = (-1, 0, 1)  # rpm around the plan's rounded velocity (+-2 measured no better)


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


def _segment(
    p0: FloatArray, v0: FloatArray, p1: FloatArray, v1: FloatArray, t: int
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """For every pair (start candidate, end candidate): the position and velocity at the inner ticks
    (Ca, Cb, T-1), the accelerations at both ends and the jerk (Ca, Cb)."""
    tf = float(t)
    dp = p1[None, :] - p0[:, None]
    b = (-3.0 * dp + tf * (2.0 * v1[None, :] + v0[:, None])) / (tf * tf)
    a = (-2.0 * dp + tf * (v1[None, :] + v0[:, None])) / (tf * tf * tf)
    c = np.broadcast_to(v1[None, :], dp.shape)
    d = np.broadcast_to(p1[None, :], dp.shape)
    tau = np.arange(1, t, dtype=np.float64) - tf
    aa, bb, cc, dd = a[..., None], b[..., None], c[..., None], d[..., None]
    pos = ((aa * tau + bb) * tau + cc) * tau + dd
    vel = (3.0 * aa * tau + 2.0 * bb) * tau + cc
    return pos, vel, -6.0 * a * tf + 2.0 * b, 2.0 * b, 6.0 * a


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
    n = times.size - 1
    cands_p: list[FloatArray] = []
    cands_v: list[FloatArray] = []
    for k in range(n + 1):
        if k in (0, n):
            cp, cv = np.array([float(p_orig[k])]), np.array([float(v_orig[k])])
        else:
            w = float(want[times[k]])
            r = float(np.round(v_plan[times[k]] / conv))
            pairs = {(w + dp, r + dv) for dp in _POSITIONS for dv in _VELOCITIES}
            pairs.add((float(p_orig[k]), float(v_orig[k])))
            arr = np.array(sorted(pairs))
            cp, cv = arr[:, 0], arr[:, 1]
        cands_p.append(cp)
        cands_v.append(cv)
    jerk_cap = max(jlim * (1.0 + JERK_SLACK), own_jerk)
    step_lim = jlim * 1.0  # the step over the 1 ms tick the jerk limit allows (counts/ms^2)
    cost: FloatArray | None = None  # (C_{k-1}, C_k) best cost of the paths ending in that pair
    back: list[IntArray] = []
    prev_acc_end: FloatArray | None = None
    for k in range(n):
        t = int(times[k + 1] - times[k])
        pos, vel, acc_s, acc_e, jerk = _segment(
            cands_p[k], cands_v[k] * conv, cands_p[k + 1], cands_v[k + 1] * conv, t
        )
        ok = np.ones(acc_s.shape, dtype=bool)
        if t > 1:
            demand = hermite.round_counts_array(pos)
            ok &= (np.abs(demand - want[times[k] + 1 : times[k + 1]][None, None, :]) <= tol).all(axis=2)
            ok &= (np.abs(vel) <= vlim + 1e-12).all(axis=2)
        peak = np.maximum(np.abs(acc_s), np.abs(acc_e))
        ok &= peak <= drive_acc
        ok &= peak - envelope[k] <= budget
        # the in-segment jerk within the limit + JERK_SLACK, or the encoder's own largest on this axis
        ok &= np.abs(jerk) <= jerk_cap
        seg_cost = np.where(ok, OVER * np.maximum(np.abs(jerk) / jlim - 1.0, 0.0) ** 2, np.inf)
        if cost is None or prev_acc_end is None:
            cost = seg_cost  # (1, C_1)
        else:
            # transition (c_{k-1}, c_k) -> (c_k, c_{k+1}): the step at knot k
            step = np.abs(acc_s[None, :, :] - prev_acc_end[:, :, None]) / step_lim
            knot_cost = step * step + OVER * np.maximum(step - 1.0, 0.0) ** 2
            total = cost[:, :, None] + knot_cost  # (C_{k-1}, C_k, C_{k+1})
            arg = np.argmin(total, axis=0)  # (C_k, C_{k+1})
            best = np.take_along_axis(total, arg[None, :, :], axis=0)[0]
            back.append(arg)
            cost = best + seg_cost
        prev_acc_end = acc_e
        if not np.isfinite(cost).any():
            return None
    assert cost is not None
    # the end knot has one candidate: the best pair ending there, then back through the choices
    ck, cn = np.unravel_index(int(np.argmin(cost)), cost.shape)
    if not np.isfinite(cost[ck, cn]):
        return None
    chosen = [int(cn), int(ck)]
    for arg in reversed(back):
        chosen.append(int(arg[chosen[-1], chosen[-2]]))
    chosen.reverse()
    p = np.array([cands_p[k][c] for k, c in enumerate(chosen)]).astype(np.int64)
    v = np.array([cands_v[k][c] for k, c in enumerate(chosen)]).astype(np.int64)
    return p, v


def smooth_values(ref: Reference, knots: Knots, scales: AxisScales, tol: float, jerk_limit: FloatArray) -> Knots:
    """`knots` with every axis' values re-chosen for a continuous acceleration (module docstring);
    `jerk_limit` (n,) in counts/ms^3. The encoder's knots are returned where the result would not keep
    every promise of the encoding, or would not lower the largest jerk or step (`worst_ratio`)."""
    if knots.times_ms.size < 3:
        return knots
    want = planned_demand(ref, scales.toward_zero)
    env = segment_envelope(ref, knots.times_ms)
    quantum = scales.counts_per_ms_per_rpm
    vlim = np.minimum(
        scales.drive_velocity,
        np.maximum(scales.velocity_limit * (1.0 + VELOCITY_SLACK), scales.velocity_limit + quantum),
    )
    pos = knots.positions.copy()
    vel = knots.velocities_rpm.copy()
    own = np.abs(knot_steps(knots, scales)[0]).max(axis=1)
    for i in range(ref.n_axes):
        got = _axis(
            want[i], ref.velocities[i], knots.times_ms, knots.positions[i], knots.velocities_rpm[i], env[i],
            float(quantum[i]), float(vlim[i]), float(scales.drive_acceleration[i]),
            ACC_EXCESS_LIMIT * float(scales.acceleration_axis[i]) * 0.999, float(jerk_limit[i]), tol,
            float(own[i]),
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
