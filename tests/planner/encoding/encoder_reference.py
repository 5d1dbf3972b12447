"""The PVT encoder's value search and verification as NumPy had them (planner/encoding/encoder.py at 60b5382, before
they were compiled into planner/encoding/quantise.py): the reference the compiled kernels must reproduce bit for
bit (tests/planner/encoding/test_value_search.py). Vectorised over axes, segments, candidate pairs and
ticks with (n, N, C, C) temporaries; kept only as that reference, the encoder never calls it."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from planner.encoding import hermite
from planner.encoding.encoder import (
    _DP_POSITIONS,
    _PROX,
    ACC_EXCESS_LIMIT,
    DP_VELOCITIES,
    AxisScales,
    Knots,
    Reconstruction,
)
from planner.encoding.record import VELOCITY_MAX, VELOCITY_MIN
from planner.motion.reference import FloatArray, IntArray, Reference

_HARD = 1.0e6


def _hermite_basis(
    offsets: FloatArray, lengths: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    s = offsets / lengths
    s2 = s * s
    h00 = 1.0 - 3.0 * s2 + 2.0 * s2 * s
    h01 = 1.0 - h00
    h10 = (s - 2.0 * s2 + s2 * s) * lengths
    h11 = (s2 * s - s2) * lengths
    return h00, h10, h01, h11


def segment_envelope(ref: Reference, times: IntArray) -> FloatArray:
    """Planned |acceleration| peak over each segment (both end ticks included), (n_axes, N)."""
    env = ref.acc_envelope()
    if times.size < 2:
        return np.zeros((ref.n_axes, 0))
    left: FloatArray = np.maximum.reduceat(env, times[:-1], axis=1)
    out: FloatArray = np.maximum(left, env[:, times[1:]])
    return out


def reconstruct(knots: Knots, scales: AxisScales) -> Reconstruction:
    """The drive's position demand at every ms of every axis, and the segments' end accelerations."""
    t = knots.times_ms
    dt = np.diff(t)
    n = knots.positions.shape[0]
    total = int(t[-1])
    demand = np.empty((n, total + 1), dtype=np.int64)
    pos = np.empty((n, total + 1))
    vel = np.empty((n, total + 1))
    acc_s = np.zeros((n, dt.size))
    acc_e = np.zeros((n, dt.size))
    tt = dt.astype(np.float64)
    for i in range(n):
        v = knots.velocities_rpm[i].astype(np.float64) * scales.counts_per_ms_per_rpm[i]
        p = knots.positions[i].astype(np.float64)
        pos[i], vel[i], _ = hermite.reconstruct(p, v, dt)
        tz = scales.toward_zero is not None and bool(scales.toward_zero[i])
        demand[i] = hermite.truncate_counts_array(pos[i]) if tz else hermite.round_counts_array(pos[i])
        if dt.size:
            dp = p[1:] - p[:-1]
            acc_s[i] = (6.0 * dp - 2.0 * tt * v[1:] - 4.0 * tt * v[:-1]) / (tt * tt)
            acc_e[i] = (-6.0 * dp + 4.0 * tt * v[1:] + 2.0 * tt * v[:-1]) / (tt * tt)
    return Reconstruction(demand, pos, vel, acc_s, acc_e)


def _bad_mask(
    ref: Reference, knots: Knots, scales: AxisScales, tol: float, want: IntArray
) -> NDArray[np.bool_]:
    """(n_axes, N): which axis misses the tolerance, 0x60C5 or the acceleration-excess budget where."""
    rec = reconstruct(knots, scales)
    times = knots.times_ms
    bad = np.zeros((ref.n_axes, times.size - 1), dtype=bool)
    axis, bad_ticks = np.nonzero(np.abs(rec.demand - want) > tol)
    bad[axis, np.clip(np.searchsorted(times, bad_ticks, side="left") - 1, 0, times.size - 2)] = True
    peak = np.maximum(np.abs(rec.acc_start), np.abs(rec.acc_end))
    excess = peak - segment_envelope(ref, times)  # encoder.acceleration_excess
    bad |= (excess > ACC_EXCESS_LIMIT * scales.acceleration_axis[:, None]) | (peak > scales.drive_acceleration[:, None])
    return bad


def _candidates(
    ref: Reference,
    times: IntArray,
    scales: AxisScales,
    dv: tuple[int, ...],
    fixed: dict[int, tuple[IntArray, IntArray]],
) -> tuple[FloatArray, FloatArray]:
    """Candidate (position counts, velocity rpm) per axis and knot: (n, K, C) each.

    Positions: the planned demand and one count either side (all within the tolerance at the knot;
    the side counts let a slow axis keep its motion smooth on a grid set by faster ones). Velocities:
    the offsets `dv` from the nearest rpm, or with `dv == (0, 1)` the two rpm values that bracket the
    plan's velocity.
    """
    conv = scales.counts_per_ms_per_rpm[:, None]
    rp = hermite.round_counts_array(ref.positions[:, times]).astype(np.float64)
    v_rpm = ref.velocities[:, times] / conv
    vr = np.floor(v_rpm) if dv == (0, 1) else np.round(v_rpm)
    cand_p = np.stack([rp + jp for _jv in dv for jp in _DP_POSITIONS], axis=2)
    cand_v = np.stack([vr + jv for jv in dv for _jp in _DP_POSITIONS], axis=2)
    for k, (pf, vf) in fixed.items():
        cand_p[:, k, :] = pf.astype(np.float64)[:, None]
        cand_v[:, k, :] = vf.astype(np.float64)[:, None]
    return cand_p, np.clip(cand_v, VELOCITY_MIN, VELOCITY_MAX)


def _segment_costs(
    ref: Reference,
    times: IntArray,
    scales: AxisScales,
    tolerance: float,
    cand_p: FloatArray,
    cand_v: FloatArray,
    exact: bool,
) -> FloatArray:
    """Cost of every (start candidate, end candidate) pair of every segment: (n, N, C, C).

    exact=False scores the float error at sample ticks (fast); exact=True checks the drive's rounded
    demand against the planned demand at every tick (used for the local refinement).
    """
    conv = scales.counts_per_ms_per_rpm[:, None, None]
    dt = np.diff(times).astype(np.float64)
    pa, pb = cand_p[:, :-1, :], cand_p[:, 1:, :]
    va, vb = cand_v[:, :-1, :] * conv, cand_v[:, 1:, :] * conv
    # the ticks looked at, flattened (segment `seg`, `off` ms into it; each segment's run starts at
    # `first`): every tick, or the sample ticks `_PROX` of each segment
    if exact:
        lengths = np.diff(times)
        seg = np.repeat(np.arange(dt.size), lengths)
        first = np.cumsum(lengths) - lengths
        off = (np.arange(int(lengths.sum())) - first[seg] + 1).astype(np.float64)
    else:
        q = _PROX.size
        seg = np.repeat(np.arange(dt.size), q)
        first = np.arange(dt.size) * q
        off = np.clip(np.round(_PROX[None, :] * dt[:, None]), 1.0, np.maximum(dt[:, None] - 1.0, 1.0)).ravel()
    h00, h10, h01, h11 = _hermite_basis(off, dt[seg])
    tick = times[seg] + off.astype(np.int64)
    p_at = ref.positions[:, tick]  # (n, T)
    base = np.floor(p_at)  # work relative to whole counts near the plan: small numbers, float32 will do
    f32 = np.float32
    ea = ((pa[:, seg, :] - base[:, :, None]) * h00[None, :, None] + va[:, seg, :] * h10[None, :, None]).astype(f32)
    eb = ((pb[:, seg, :] - base[:, :, None]) * h01[None, :, None] + vb[:, seg, :] * h11[None, :, None]).astype(f32)
    d = ea[:, :, :, None] + eb[:, :, None, :]  # Hermite - base, (n, T, C, C)
    want = (hermite.round_counts_array(p_at) - base).astype(f32)  # planned demand - base
    miss = np.abs(np.floor(d + f32(0.5)) - want[:, :, None, None])
    if scales.toward_zero is not None and scales.toward_zero.any():  # those drives truncate
        z = np.nonzero(scales.toward_zero)[0]
        bz = base[z][:, :, None, None]
        miss[z] = np.abs(np.trunc(d[z].astype(np.float64) + bz) - np.trunc(p_at[z])[:, :, None, None])
    # the drive's rounded demand against the planned demand (its float error too, at sample ticks: a
    # tie-breaker, smaller is more robust at the ticks in between); the verification that follows
    # rounds in float64 as the drive does
    dev = np.maximum.reduceat(miss, first, axis=1)
    if exact:
        dev_cost = _HARD * (dev > tolerance) + (dev / tolerance) ** 2
    else:
        frac = (p_at - base).astype(f32)
        err = np.maximum.reduceat(np.abs(d - frac[:, :, None, None]), first, axis=1)
        dev_cost = _HARD * (dev > tolerance) + 0.5 * (err / tolerance) ** 2
    t1 = dt[None, :, None, None]
    dp = pb[:, :, None, :] - pa[:, :, :, None]
    acc_s = (6.0 * dp - 2.0 * t1 * vb[:, :, None, :] - 4.0 * t1 * va[:, :, :, None]) / (t1 * t1)
    acc_e = (-6.0 * dp + 4.0 * t1 * vb[:, :, None, :] + 2.0 * t1 * va[:, :, :, None]) / (t1 * t1)
    peak = np.maximum(np.abs(acc_s), np.abs(acc_e))
    env = segment_envelope(ref, times)[:, :, None, None]
    excess = np.maximum(peak - env, 0.0) / (ACC_EXCESS_LIMIT * scales.acceleration_axis)[:, None, None, None]
    over = peak > scales.drive_acceleration[:, None, None, None]
    # velocity: the end velocities must respect 0x607F (the interior is checked on verification)
    vmax = np.maximum(np.abs(va)[:, :, :, None], np.abs(vb)[:, :, None, :])
    over_v = vmax > scales.drive_velocity[:, None, None, None]
    cost: FloatArray = dev_cost + _HARD * (over | over_v) + 1.0e3 * (excess > 0.9) + excess**2
    return cost


def _viterbi(cost: FloatArray, first: int = 0) -> IntArray:
    """Minimum-cost candidate path per axis; cost (n, N, C, C); knot 0 is pinned to `first`."""
    n, nseg, c, _ = cost.shape
    j = np.full((n, c), np.inf)
    j[:, first] = 0.0
    back = np.empty((nseg, n, c), dtype=np.int64)
    for k in range(nseg):
        tot = j[:, :, None] + cost[:, k]
        back[k] = tot.argmin(axis=1)
        j = tot.min(axis=1)
    choice = np.empty((n, nseg + 1), dtype=np.int64)
    choice[:, -1] = np.argmin(j, axis=1)
    rows = np.arange(n)
    for k in range(nseg - 1, -1, -1):
        choice[:, k] = back[k][rows, choice[:, k + 1]]
    return choice


def _alive(feasible: NDArray[np.bool_], fixed: list[int]) -> NDArray[np.bool_]:
    """(n, K, C): candidates that lie on at least one path of feasible pairs through every knot
    (`feasible` (n, K-1, C, C)), by forward and backward passes; at a `fixed` knot (all candidates the
    same values) only the first. A knot where none would be left keeps all its candidates (then no path
    passes, and the choice is the least bad one of all)."""
    n, nseg, c, _ = feasible.shape
    alive = np.ones((n, nseg + 1, c), dtype=bool)
    alive[:, fixed, 1:] = False
    for k in range(nseg):  # reachable from the start
        alive[:, k + 1] &= (feasible[:, k] & alive[:, k, :, None]).any(axis=1)
    for k in range(nseg - 1, -1, -1):  # and reaching the end
        alive[:, k] &= (feasible[:, k] & alive[:, k + 1, None, :]).any(axis=2)
    empty = ~alive.any(axis=2)
    alive[empty] = True
    return alive


def _choose_values(
    ref: Reference,
    times: IntArray,
    scales: AxisScales,
    tolerance: float,
    fixed: dict[int, tuple[IntArray, IntArray]],
    dv: tuple[int, ...] | None = None,
    exact: bool = False,
) -> tuple[IntArray, IntArray]:
    """Quantised positions (counts) and velocities (rpm) for every knot, chosen jointly."""
    cand_p, cand_v = _candidates(ref, times, scales, DP_VELOCITIES if dv is None else dv, fixed)
    if times.size == 1:
        return cand_p[:, :, 0].astype(np.int64), cand_v[:, :, 0].astype(np.int64)
    cost = _segment_costs(ref, times, scales, tolerance, cand_p, cand_v, exact)
    choice = _viterbi(cost)[:, :, None]
    pos = np.take_along_axis(cand_p, choice, axis=2)[:, :, 0].astype(np.int64)
    vel = np.take_along_axis(cand_v, choice, axis=2)[:, :, 0].astype(np.int64)
    return pos, vel


def _refine(
    ref: Reference,
    knots: Knots,
    scales: AxisScales,
    tolerance: float,
    bad: NDArray[np.bool_],
    fixed_knots: set[int],
) -> Knots:
    """Choose the values again around failing segments, with more candidates and an exact check.

    `bad` (n_axes, N) marks the failing segments of each axis; a window of two knots either side of
    them is chosen again on the axes that fail inside it (the others keep their values, which pass).
    """
    times = knots.times_ms
    pos = knots.positions.copy()
    vel = knots.velocities_rpm.copy()
    nk = times.size
    windows: list[tuple[int, int]] = []
    for s in np.nonzero(bad.any(axis=0))[0].tolist():
        lo, hi = max(0, s - 2), min(nk - 1, s + 3)
        if windows and lo <= windows[-1][1]:
            windows[-1] = (windows[-1][0], hi)
        else:
            windows.append((lo, hi))
    for lo, hi in windows:
        axes = np.nonzero(bad[:, lo:hi].any(axis=1))[0]
        sub = times[lo : hi + 1]
        fixed: dict[int, tuple[IntArray, IntArray]] = {
            0: (pos[axes, lo], vel[axes, lo]),
            hi - lo: (pos[axes, hi], vel[axes, hi]),
        }
        for k in range(lo + 1, hi):
            if k in fixed_knots:
                fixed[k - lo] = (pos[axes, k], vel[axes, k])
        part = ref.axes_subset(axes)
        sc = scales.subset(axes)
        cand_p, cand_v = _candidates(part, sub, sc, (-3, -2, -1, 0, 1, 2, 3), fixed)
        # the check at every tick only for the candidates that can lie on a path passing the cheap check
        # at the sample ticks (a pair that fails there fails at every tick too): typically a third
        feasible = _segment_costs(part, sub, sc, tolerance, cand_p, cand_v, exact=False) < _HARD
        alive = _alive(feasible, sorted(fixed))
        order = np.argsort(~alive, axis=2, kind="stable")[:, :, : max(1, int(alive.sum(axis=2).max()))]
        cand_p = np.take_along_axis(cand_p, order, axis=2)
        cand_v = np.take_along_axis(cand_v, order, axis=2)
        cost = _segment_costs(part, sub, sc, tolerance, cand_p, cand_v, exact=True)
        # the window's last knot is pinned too (all its candidates are the same values): reach one of them
        cost[:, -1, :, 1:] = np.inf
        choice = _viterbi(cost)[:, :, None]
        pos[axes, lo : hi + 1] = np.take_along_axis(cand_p, choice, axis=2)[:, :, 0].astype(np.int64)
        vel[axes, lo : hi + 1] = np.take_along_axis(cand_v, choice, axis=2)[:, :, 0].astype(np.int64)
    return Knots(times, pos, vel)
