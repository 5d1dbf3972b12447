"""Hermite chain: a time-optimal path profile turned into a motion the drive can follow exactly.

The encoder needs segments of at least `min_seg` ms, but a blended path's time-optimal profile has
acceleration features of a few ms. So for blended paths the plan itself is a chain of cubic Hermite
segments on whole-ms knots through the profile's exact positions and velocities. `fit_chain` places knots
greedily between the profile's switches: the longest segment within `budget` of the path and within the
joint limits (limit checks first, samples only where they pass: `_first_passing`; compiled). Where no
`min_seg` segment passes, its limit ratios (`ChainFit.acc_ratio`, `vel_ratio`) make path.plan_run slow
the profile there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from planner.jit import kernel
from planner.motion.reference import FloatArray, IntArray

ACC_SLACK = 1.0e-3
VEL_SLACK = 1.0e-4
_LADDER = np.array([0.6, 0.8, 1.0, 1.25, 1.6, 2.0, 3.0])
_SHORT = np.array([0.75, 0.5, 0.35])  # of min_seg: shorter segments, when no longer one passes
SHORT_MS = 4
_SAMPLES = np.array([0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 0.875])  # where the greedy search checks
_CANDIDATES = _LADDER.size + 4 + _SHORT.size

# rows of a fit's limits (n,) each: budget (user units), velocity and acceleration limits (per ms, per
# ms^2), the box
_BUDGET, _VLIM, _ALIM, _LOWER, _UPPER = range(5)

# what the kernels take of a fit: positions, velocities, the unit tangent of the path (scaled by the
# budget), each (M+1, n) (a tick's axes contiguous); whether each ms is in a blend (M+1,); the limits
_Path = tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_], FloatArray]


@dataclass(frozen=True)
class ChainFit:
    """Knots of the chain and the chain itself at every ms (user units, per ms, per ms^2)."""

    knots: IntArray  # (K,) ms, knots[0] == 0, knots[-1] == M
    positions: FloatArray  # (n, M+1)
    velocities: FloatArray  # (n, M+1)
    acc_left: FloatArray  # (n, M+1) on (m-1, m)
    acc_right: FloatArray  # (n, M+1) on (m, m+1)
    acc_ratio: FloatArray  # (M+1,) largest |acceleration| / limit over the axes (both sides)
    vel_ratio: FloatArray  # (M+1,) largest |velocity| / limit over the axes


def fit_chain(
    q: FloatArray,
    v: FloatArray,
    direction: FloatArray,
    curved: NDArray[np.bool_],
    mandatory: IntArray,
    budget: FloatArray,
    vlim: FloatArray,
    alim: FloatArray,
    min_seg: int,
    max_seg: int,
    allow_short: bool = True,
    box: tuple[FloatArray, FloatArray] | None = None,
) -> ChainFit:
    """The chain through the profile `q`, `v` (n, M+1; user units, per ms) (module docstring).

    `direction` (n, M+1): the path's tangent q'(s) at every ms, `curved` (M+1,): whether that ms is in
    a blend (module docstring, geometry). `mandatory`: knots the chain must have (0, M and the profile's
    switches); `budget` (n,) user units;
    `vlim` per ms and `alim` per ms^2 (n,); `min_seg`/`max_seg`: the encoder's segment bounds (ms).
    `allow_short`: where no segment of `min_seg` passes, try shorter ones (down to `SHORT_MS`) before
    taking one that overshoots. `box`: the position limits (n,) x 2, which the chain must not leave
    (the path itself stays inside them: near a waypoint on a limit there is no room for a deviation).
    """
    m = q.shape[1] - 1
    mand = np.unique(np.concatenate([[0, m], mandatory])).astype(np.int64)
    budget = np.maximum(budget, 1e-12)
    if box is None:
        box = (np.full(q.shape[0], -np.inf), np.full(q.shape[0], np.inf))
    path: _Path = (
        np.ascontiguousarray(q.T, dtype=np.float64),
        np.ascontiguousarray(v.T, dtype=np.float64),
        _tangent(np.ascontiguousarray(direction.T, dtype=np.float64), budget),
        np.ascontiguousarray(curved, dtype=np.bool_),
        np.ascontiguousarray(np.stack([budget, vlim, alim, box[0], box[1]]), dtype=np.float64),
    )
    knots, _fallbacks = _greedy(path, mand, min_seg, max_seg, allow_short, True)
    if allow_short:
        knots = _lengthen(path, knots, mand, min_seg, max_seg)
    return ChainFit(*_chain(path, knots))


# ----------------------------------------------------------------------------------------------------
# kernels (planner/jit.py). The Python-facing kernels take a fit's arrays as one `_Path`; the inner ones
# take them one by one and work on whole segments, not ticks (a call with arrays for arguments costs about
# what a tick does).


@kernel
def _nanmax(a: float, b: float) -> float:
    """The larger of `a` and `b`, nan if either is nan (np.maximum)."""
    return a if a >= b or a != a else b


@kernel
def _tangent(direction: FloatArray, budget: FloatArray) -> FloatArray:
    """The path's unit tangent, scaled by the budget (M+1, n), from its `direction` (M+1, n)."""
    total, n = direction.shape
    out = np.empty((total, n))
    for t in range(total):
        for i in range(n):
            out[t, i] = direction[t, i] / budget[i]
        s = 0.0
        for i in range(n):
            s += out[t, i] * out[t, i]
        norm = _nanmax(np.sqrt(s), 1e-300)
        for i in range(n):
            out[t, i] = out[t, i] / norm
    return out


@kernel
def _end_acc(qa: float, qb: float, va: float, vb: float, t1: float) -> tuple[float, float]:
    """The acceleration at both ends of a segment of `t1` ms (it is linear in between)."""
    dp = qb - qa
    tt = t1 * t1
    return (6.0 * dp - 2.0 * t1 * vb - 4.0 * t1 * va) / tt, (-6.0 * dp + 4.0 * t1 * vb + 2.0 * t1 * va) / tt


@kernel
def _ticks(
    q: FloatArray, v: FloatArray, tangent: FloatArray, curved: NDArray[np.bool_], lim: FloatArray,
    a: int, b: int, sampled: bool, pos: FloatArray, vel: FloatArray, col: int, d: FloatArray,
) -> float:
    """The segment a..b at its `_SAMPLES` (`sampled`) or at every tick a+1..b: its Hermite position and
    velocity (into columns col, col+1, ... of `pos`, `vel`) and its largest deviation from the path
    there (`d` (n,): scratch).

    The deviation is per axis, as a share of the budget: on a straight piece the distance from its line
    (being ahead or behind along it is no deviation), in a blend the distance from where the profile is
    at that same ms (conservative); 2 (or more) where the chain leaves the box."""
    n = q.shape[1]
    tt = float(b - a)
    geo = -np.inf
    for j in range(_SAMPLES.size if sampled else b - a):
        off = min(max(np.round(_SAMPLES[j] * tt), 1.0), tt) if sampled else float(j + 1)
        x = off / tt
        x2 = x * x
        h00 = 1.0 - 3.0 * x2 + 2.0 * x2 * x
        h10 = (x - 2.0 * x2 + x2 * x) * tt
        h11 = (x2 * x - x2) * tt
        d00 = (6.0 * x2 - 6.0 * x) / tt
        d10 = 1.0 - 4.0 * x + 3.0 * x2
        d11 = 3.0 * x2 - 2.0 * x
        tick = a + int(off)
        outside = False
        for i in range(n):
            pa, pb, va, vb = q[a, i], q[b, i], v[a, i], v[b, i]
            p = pa * h00 + pb * (1.0 - h00) + va * h10 + vb * h11
            pos[i, col + j] = p
            vel[i, col + j] = (pa - pb) * d00 + va * d10 + vb * d11
            outside = outside or p < lim[_LOWER, i] or p > lim[_UPPER, i]
            d[i] = (p - q[tick, i]) / lim[_BUDGET, i]
        err = -np.inf
        if curved[tick]:
            for i in range(n):
                err = _nanmax(err, abs(d[i]))
        else:
            along = 0.0
            for i in range(n):
                along += d[i] * tangent[tick, i]
            for i in range(n):
                err = _nanmax(err, abs(d[i] - tangent[tick, i] * along))
        geo = _nanmax(geo, _nanmax(err, 2.0) if outside else err)
    return geo


@kernel
def _limits_ok(q: FloatArray, v: FloatArray, lim: FloatArray, a: int, length: int) -> bool:
    """End accelerations (the acceleration is linear: its peak is at an end) and the velocity peak (the
    vertex of the velocity parabola, where it lies inside) of the segment within the limits."""
    b = a + length
    t1 = float(length)
    # per axis: the largest ratio over the axes passes exactly where every axis' ratio does
    for i in range(q.shape[1]):
        qa, qb, va, vb = q[a, i], q[b, i], v[a, i], v[b, i]
        acc_s, acc_e = _end_acc(qa, qb, va, vb, t1)
        if not (abs(acc_s) / lim[_ALIM, i] - ACC_SLACK <= 1.0 and abs(acc_e) / lim[_ALIM, i] - ACC_SLACK <= 1.0):
            return False
        dp = (qa - qb) / t1  # velocity in x = t / T: A x^2 + B x + C
        a2 = 6.0 * dp + 3.0 * va + 3.0 * vb
        b1 = -6.0 * dp - 4.0 * va - 2.0 * vb
        x = -b1 / (2.0 * a2) if a2 != 0.0 else -1.0
        peak = abs(a2 * x * x + b1 * x + va) if 0.0 < x < 1.0 else 0.0
        if not (peak / lim[_VLIM, i] - VEL_SLACK <= 1.0):
            return False
    return True


@kernel
def _samples_ok(
    q: FloatArray, v: FloatArray, tangent: FloatArray, curved: NDArray[np.bool_], lim: FloatArray,
    a: int, length: int, pos: FloatArray, vel: FloatArray, d: FloatArray,
) -> bool:
    """At the `_SAMPLES` ticks of the segment: the velocity within the limits, the position within the
    budget of the path and inside the box (`pos`, `vel` (n, samples), `d` (n,): scratch)."""
    if not (_ticks(q, v, tangent, curved, lim, a, a + length, True, pos, vel, 0, d) <= 1.0):
        return False
    for j in range(_SAMPLES.size):
        for i in range(q.shape[1]):
            if not (abs(vel[i, j]) / lim[_VLIM, i] - VEL_SLACK <= 1.0):
                return False
    return True


@kernel
def _segment_ok(
    q: FloatArray, v: FloatArray, tangent: FloatArray, curved: NDArray[np.bool_], lim: FloatArray,
    a: int, length: int, pos: FloatArray, vel: FloatArray, d: FloatArray,
) -> bool:
    """Both checks, the cheap one first."""
    return _limits_ok(q, v, lim, a, length) and _samples_ok(q, v, tangent, curved, lim, a, length, pos, vel, d)


@kernel
def _first_passing(
    path: _Path, a: int, lens: IntArray, prefer: IntArray, lazy: bool, pos: FloatArray, vel: FloatArray,
    d: FloatArray,
) -> tuple[int, int]:
    """The length of the most preferred candidate segment from `a` that passes, 0 if none does;
    `lens`, `prefer`: the candidates, a preference determining its length (`prefer` is used up).

    `lazy`: the candidates in their order of preference, each checked until one passes (the samples only
    where the cheap limit checks pass). Else every candidate is checked (the tests' reference). Also
    returns how often the samples turned down a candidate that passed the limits (the case that makes
    the lazy search go on to the next one)."""
    q, v, tangent, curved, lim = path
    if not lazy:
        top = 0
        for j in range(lens.size):
            if _segment_ok(q, v, tangent, curved, lim, a, lens[j], pos, vel, d):
                top = max(top, prefer[j])
        return top % 1024, 0
    fallbacks = 0
    while True:
        top = 0
        for j in range(lens.size):
            top = max(top, prefer[j])
        if top == 0:
            return 0, fallbacks
        length = top % 1024
        if _limits_ok(q, v, lim, a, length):
            if _samples_ok(q, v, tangent, curved, lim, a, length, pos, vel, d):
                return length, fallbacks
            fallbacks += 1
        for j in range(lens.size):
            if lens[j] == length:
                prefer[j] = 0


@kernel
def _greedy(
    path: _Path, mand: IntArray, min_seg: int, max_seg: int, allow_short: bool, lazy: bool
) -> tuple[IntArray, int]:
    """The knots of the greedy search (module docstring), section after section; and how often the
    samples turned down the preferred candidate (`_first_passing`)."""
    total, n = path[0].shape
    pos, vel, d = np.empty((n, _SAMPLES.size)), np.empty((n, _SAMPLES.size)), np.empty(n)
    knots = np.empty(total, dtype=np.int64)
    count = 0
    fallbacks = 0
    lens_f = np.empty(_CANDIDATES)
    lens = np.empty(_CANDIDATES, dtype=np.int64)
    prefer = np.empty(_CANDIDATES, dtype=np.int64)
    for sec in range(mand.size - 1):
        cur, end = mand[sec], mand[sec + 1]
        knots[count] = cur
        count += 1
        prev = min(end - cur, max_seg)
        while cur < end:
            room = end - cur
            hi = min(room, max_seg)
            lo = min(room, min_seg)
            short = min(room, SHORT_MS if allow_short else min_seg)
            half = np.ceil(room / 2.0)
            for j in range(_LADDER.size):
                lens_f[j] = np.round(prev * _LADDER[j])
            c = _LADDER.size
            lens_f[c], lens_f[c + 1], lens_f[c + 2], lens_f[c + 3] = hi, half, np.ceil(room / 3.0), lo
            for j in range(_SHORT.size):
                lens_f[c + 4 + j] = np.round(lo * _SHORT[j])
            # preference: at least min_seg (the encoder's quantisation needs it); finish the section;
            # else the longest that leaves at least min_seg; else a half; shorter ones only when nothing
            # else passes (a preference determines its length: lengths are below 1024)
            for j in range(_CANDIDATES):
                length = int(min(max(lens_f[j], short), hi))
                rem = room - length
                lens[j] = length
                prefer[j] = (length + 8192 * (length >= lo) + 4096 * (rem == 0) + 2048 * (rem >= min_seg)
                             + 1024 * (length == half))
            best, fb = _first_passing(path, cur, lens, prefer, lazy, pos, vel, d)
            fallbacks += fb
            if best <= 0:
                best = short  # nothing passes: the shortest allowed (its violation is reported to the caller)
            cur += best
            prev = max(best, lo)
            if cur < end:
                knots[count] = cur
                count += 1
    knots[count] = mand[-1]
    return knots[: count + 1].copy(), fallbacks


@kernel
def _lengthen(path: _Path, knots: IntArray, mand: IntArray, min_seg: int, max_seg: int) -> IntArray:
    """Remove the short segments the greedy fit left, where a neighbouring knot can move (or go) so that
    every segment concerned is at least `min_seg` long and passes: the greedy only looks forward, and a
    knot a few ms earlier often avoids the short segment after it.

    The short segments are taken one after the other (a change moves the neighbours of the next one).
    For each, the first that passes of: removing its first knot, moving it earlier (the latest position
    first, 8 at most), removing its last knot, moving it later (the earliest first, 8 at most); the
    knots in `mand` stay."""
    q, v, tangent, curved, lim = path
    n = q.shape[1]
    pos, vel, d = np.empty((n, _SAMPLES.size)), np.empty((n, _SAMPLES.size)), np.empty(n)
    t = knots.copy()
    size = t.size
    fixed = np.zeros(size, dtype=np.bool_)
    j = 0
    for i in range(size):  # both sorted
        while j < mand.size and mand[j] < t[i]:
            j += 1
        fixed[i] = j < mand.size and mand[j] == t[i]
    k = 0
    while k + 1 < size:
        if t[k + 1] - t[k] >= min_seg:
            k += 1
            continue
        a, b = t[k], t[k + 1]
        drop, move = -1, -1  # the knot to remove or to move to `value`
        value = 0
        if k >= 1 and not fixed[k]:
            p = t[k - 1]
            if b - p <= max_seg and _segment_ok(q, v, tangent, curved, lim, p, b - p, pos, vel, d):
                drop = k
            else:
                for x in range(b - min_seg, max(p + min_seg - 1, b - min_seg - 8), -1):
                    if (_segment_ok(q, v, tangent, curved, lim, p, x - p, pos, vel, d)
                            and _segment_ok(q, v, tangent, curved, lim, x, b - x, pos, vel, d)):
                        move, value = k, x
                        break
        if drop < 0 and move < 0 and k + 2 < size and not fixed[k + 1]:
            nx = t[k + 2]
            if nx - a <= max_seg and _segment_ok(q, v, tangent, curved, lim, a, nx - a, pos, vel, d):
                drop = k + 1
            else:
                for x in range(a + min_seg, min(nx - min_seg + 1, a + min_seg + 8)):
                    if (_segment_ok(q, v, tangent, curved, lim, a, x - a, pos, vel, d)
                            and _segment_ok(q, v, tangent, curved, lim, x, nx - x, pos, vel, d)):
                        move, value = k + 1, x
                        break
        if drop >= 0:
            t[drop : size - 1] = t[drop + 1 : size]
            fixed[drop : size - 1] = fixed[drop + 1 : size]
            size -= 1
        elif move >= 0:
            t[move] = value
        k += 1
    return t[:size].copy()


@kernel
def _chain(
    path: _Path, knots: IntArray
) -> tuple[IntArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """The search looked at a few ticks per segment: check every tick, halve what fails the geometry
    (4 rounds at most); then the chain at every ms (the fields of `ChainFit`)."""
    q, v, tangent, curved, lim = path
    total, n = q.shape
    positions = np.empty((n, total))
    velocities = np.empty((n, total))
    d = np.empty(n)
    for rnd in range(5):
        geo = np.empty(knots.size - 1)
        for s in range(geo.size):
            geo[s] = _ticks(q, v, tangent, curved, lim, knots[s], knots[s + 1], False, positions, velocities,
                            knots[s] + 1, d)
        bad = 0
        for s in range(geo.size):
            if geo[s] > 1.0 and knots[s + 1] - knots[s] >= 2:
                bad += 1
        if bad == 0 or rnd == 4:  # 4 rounds of halving at most: the 5th pass only samples their knots
            break
        halved = np.empty(knots.size + bad, dtype=np.int64)
        c = 0
        for s in range(geo.size):
            halved[c] = knots[s]
            c += 1
            if geo[s] > 1.0 and knots[s + 1] - knots[s] >= 2:
                halved[c] = (knots[s] + knots[s + 1]) // 2
                c += 1
        halved[c] = knots[-1]
        knots = halved
    positions[:, 0], velocities[:, 0] = q[0], v[0]
    for s in range(knots.size):
        positions[:, knots[s]], velocities[:, knots[s]] = q[knots[s]], v[knots[s]]
    # acceleration is linear inside a segment: interpolate its two ends
    acc_left = np.empty((n, total))
    acc_right = np.empty((n, total))
    x = np.empty(total)
    for s in range(knots.size - 1):
        a, b = knots[s], knots[s + 1]
        length = float(b - a)
        for off in range(1, b - a + 1):
            x[off] = off / length
        for i in range(n):
            acc_s, acc_e = _end_acc(q[a, i], q[b, i], v[a, i], v[b, i], length)
            left, right = acc_left[i], acc_right[i]
            right[a] = acc_s  # the end of the segment before is on the left
            for off in range(1, b - a + 1):
                left[a + off] = right[a + off] = acc_s * (1.0 - x[off]) + acc_e * x[off]
    acc_left[:, 0] = acc_right[:, 0]
    acc_ratio = np.full(total, -np.inf)
    vel_ratio = np.full(total, -np.inf)
    for i in range(n):
        for m in range(total):
            acc_ratio[m] = _nanmax(acc_ratio[m], _nanmax(abs(acc_left[i, m]), abs(acc_right[i, m])) / lim[_ALIM, i])
            vel_ratio[m] = _nanmax(vel_ratio[m], abs(velocities[i, m]) / lim[_VLIM, i])
    return knots, positions, velocities, acc_left, acc_right, acc_ratio, vel_ratio
