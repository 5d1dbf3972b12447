"""Hermite chain: a time-optimal path profile turned into a motion the drive can follow exactly.

Theory of operation. A drive interpolates PVT knots with cubic Hermite segments, and the encoder can
only make segments of at least `min_seg` ms without the one-count and one-rpm quantisation of the knots
shaking the drive's acceleration by more than its 5 % budget (encoder.segment_bounds). toppra's
time-optimal profile along a blended path has acceleration features much shorter than that: a blend
traversed in 40-60 ms swings the non-limiting joints' accelerations through most of their range within
10 ms, and a short line between two blends accelerates and decelerates in a few tens of ms. To follow
such a plan within one count the encoder would need segments of a few ms, and fails its budget.

So for blended paths the *plan* is a chain of cubic Hermite segments (whole-ms knots, at least
`min_seg` apart wherever the profile allows), through the exact positions and velocities of toppra's
profile at its knots: the motion the drive itself produces, which the encoder then only has to
quantise. `fit_chain` places the knots greedily (the longest segment that passes, per section between
the profile's bang-bang switches, which are knots of their own since a cubic cannot follow a step):

- geometry: every ms of the segment within `budget` (per axis, user units) of the path: on a straight
  piece, of its line; in a blend, of where the exact profile is at that same ms (a conservative bound
  of the distance from the blend). The blends leave that share of the path tolerance free
  (plan.lines_geometry), so the chain stays within the path tolerance of the polyline;
- limits: the segment's velocity at every ms and its acceleration (linear, so its peak is at an end)
  within the joint limits (`ACC_SLACK`, `VEL_SLACK`: numerical noise).

Where no segment of at least `min_seg` ms passes, the shortest one is taken and its limit ratios are
reported at every ms (`ChainFit.acc_ratio`, `vel_ratio`): path.plan_run then slows the profile down
there (tightening toppra's constraints) and fits again.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from planner.reference import FloatArray, IntArray

ACC_SLACK = 1.0e-3
VEL_SLACK = 1.0e-4
_LADDER = np.array([0.6, 0.8, 1.0, 1.25, 1.6, 2.0, 3.0])
_SHORT = np.array([0.75, 0.5, 0.35])  # of min_seg: shorter segments, when no longer one passes
SHORT_MS = 4
_SAMPLES = np.array([0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 0.875])  # where the greedy search checks



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


def _segments(
    q: FloatArray, v: FloatArray, starts: IntArray, lengths: IntArray, sampled: bool = False
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, IntArray, IntArray]:
    """Every tick 1..L of the given segments (or, `sampled`, the ticks at `_SAMPLES` of each): Hermite
    position and velocity (n, ticks), the two end accelerations (n, segs), the tick numbers and the
    segment of every tick."""
    if sampled:
        k = _SAMPLES.size
        seg = np.repeat(np.arange(starts.size), k)
        ln = lengths[seg].astype(np.float64)
        off = np.clip(np.round(np.tile(_SAMPLES, starts.size) * ln), 1.0, ln)
    else:
        total = int(lengths.sum())
        seg = np.repeat(np.arange(starts.size), lengths)
        first = np.cumsum(lengths) - lengths
        off = (np.arange(total) - first[seg] + 1).astype(np.float64)
    tt = lengths[seg].astype(np.float64)
    x = off / tt
    x2 = x * x
    h00 = 1.0 - 3.0 * x2 + 2.0 * x2 * x
    h10 = (x - 2.0 * x2 + x2 * x) * tt
    h11 = (x2 * x - x2) * tt
    d00 = (6.0 * x2 - 6.0 * x) / tt
    d10 = 1.0 - 4.0 * x + 3.0 * x2
    d11 = 3.0 * x2 - 2.0 * x
    a, b = starts[seg], starts[seg] + lengths[seg]
    pa, pb, va, vb = q[:, a], q[:, b], v[:, a], v[:, b]
    pos = pa * h00 + pb * (1.0 - h00) + va * h10 + vb * h11
    vel = (pa - pb) * d00 + va * d10 + vb * d11
    t1 = lengths.astype(np.float64)
    e = starts + lengths
    dp = q[:, e] - q[:, starts]
    acc_s = (6.0 * dp - 2.0 * t1 * v[:, e] - 4.0 * t1 * v[:, starts]) / (t1 * t1)
    acc_e = (-6.0 * dp + 4.0 * t1 * v[:, e] + 2.0 * t1 * v[:, starts]) / (t1 * t1)
    ticks = (a + off.astype(np.int64)).astype(np.int64)
    return pos, vel, acc_s, acc_e, ticks, seg


def _scores(
    q: FloatArray,
    v: FloatArray,
    tangent: FloatArray,
    curved: NDArray[np.bool_],
    starts: IntArray,
    lengths: IntArray,
    budget: FloatArray,
    vlim: FloatArray,
    alim: FloatArray,
    box: tuple[FloatArray, FloatArray],
    sampled: bool = False,
) -> tuple[FloatArray, FloatArray]:
    """Per candidate segment: the geometric error over the budget (2 where it leaves the position
    limits) and the larger limit ratio; at every tick, or (`sampled`, for the greedy search) at a few
    ticks of each segment plus the exact velocity peak (the velocity of a cubic is a parabola)."""
    pos, vel, acc_s, acc_e, ticks, _seg = _segments(q, v, starts, lengths, sampled)
    first = np.arange(starts.size) * _SAMPLES.size if sampled else np.cumsum(lengths) - lengths
    err = _deviation(pos, q, tangent, curved, ticks, budget)
    outside = ((pos < box[0][:, None]) | (pos > box[1][:, None])).any(axis=0)
    err = np.where(outside, np.maximum(err, 2.0), err)
    vr = (np.abs(vel) / vlim[:, None]).max(axis=0)
    geo = np.maximum.reduceat(err, first)
    vel_r = np.maximum.reduceat(vr, first)
    if sampled:
        vel_r = np.maximum(vel_r, (_velocity_peak(q, v, starts, lengths) / vlim[:, None]).max(axis=0))
    acc_r = (np.maximum(np.abs(acc_s), np.abs(acc_e)) / alim[:, None]).max(axis=0)
    lim = np.maximum((acc_r - ACC_SLACK), (vel_r - VEL_SLACK))
    return geo, lim


def _velocity_peak(q: FloatArray, v: FloatArray, starts: IntArray, lengths: IntArray) -> FloatArray:
    """|velocity| at the vertex of each segment's velocity parabola, where it lies inside (n, segs)."""
    t1 = lengths.astype(np.float64)
    e = starts + lengths
    dp = (q[:, starts] - q[:, e]) / t1  # velocity in x = t / T: A x^2 + B x + C
    va, vb = v[:, starts], v[:, e]
    a2 = 6.0 * dp + 3.0 * va + 3.0 * vb
    b1 = -6.0 * dp - 4.0 * va - 2.0 * vb
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.where(a2 != 0.0, -b1 / (2.0 * a2), -1.0)
    inside = (x > 0.0) & (x < 1.0)
    peak = np.abs(a2 * x * x + b1 * x + va)
    out: FloatArray = np.where(inside, peak, 0.0)
    return out


def _deviation(
    pos: FloatArray,
    q: FloatArray,
    tangent: FloatArray,
    curved: NDArray[np.bool_],
    ticks: IntArray,
    budget: FloatArray,
) -> FloatArray:
    """Largest per-axis deviation (share of the budget) of the chain at `ticks` from the path: on a
    straight piece the distance from its line (being ahead or behind along it is no deviation), in a
    blend the distance from where the profile is at that same ms (conservative)."""
    d = (pos - q[:, ticks]) / budget[:, None]
    t = tangent[:, ticks]
    along = np.einsum("it,it->t", d, t)
    perp = d - t * along[None, :]
    out: FloatArray = np.where(curved[ticks], np.abs(d).max(axis=0), np.abs(perp).max(axis=0))
    return out


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
    ty = direction / budget[:, None]
    tangent = ty / np.maximum(np.linalg.norm(ty, axis=0), 1e-300)[None, :]
    sec_start, sec_end = mand[:-1].copy(), mand[1:].copy()
    cur = sec_start.copy()
    prev = np.minimum(sec_end - sec_start, max_seg).astype(np.int64)
    found: list[IntArray] = [mand]
    while True:
        act = np.nonzero(cur < sec_end)[0]
        if act.size == 0:
            break
        c = cur[act]
        room = sec_end[act] - c
        hi = np.minimum(room, max_seg)
        lo = np.minimum(room, min_seg)
        short = np.minimum(room, SHORT_MS if allow_short else min_seg)
        lens = np.concatenate(
            [
                np.round(prev[act][:, None] * _LADDER[None, :]),
                hi[:, None],
                np.ceil(room / 2.0)[:, None],
                np.ceil(room / 3.0)[:, None],
                lo[:, None],
                np.round(lo[:, None] * _SHORT[None, :]),
            ],
            axis=1,
        )
        lens = np.clip(lens, short[:, None], hi[:, None]).astype(np.int64)
        k = lens.shape[1]
        geo, lim = _scores(q, v, tangent, curved, np.repeat(c, k), lens.ravel(), budget, vlim, alim, box, True)
        ok = ((geo <= 1.0) & (lim <= 1.0)).reshape(-1, k)
        rem = room[:, None] - lens
        # preference: at least min_seg (the encoder's quantisation needs it); finish the section; else
        # the longest that leaves at least min_seg; else a half; shorter ones only when nothing else passes
        half = lens == np.ceil(room / 2.0)[:, None]
        long = lens >= lo[:, None]
        score = np.where(
            ok, lens + 8192 * long + 4096 * (rem == 0) + 2048 * (rem >= min_seg) + 1024 * half, 0
        )
        best = score.max(axis=1) % 1024
        # nothing passes: the shortest allowed segment (its violation is reported to the caller)
        best = np.where(best > 0, best, short)
        cur[act] += best
        prev[act] = np.maximum(best, lo)
        found.append(cur[act].copy())
    knots = np.unique(np.concatenate(found)).astype(np.int64)
    if allow_short:
        knots = _lengthen(q, v, tangent, curved, knots, mand, budget, vlim, alim, min_seg, max_seg, box)
    # the search looked at a few ticks per segment: check every tick, halve what fails the geometry
    for _round in range(4):
        geo, _lim = _scores(q, v, tangent, curved, knots[:-1], np.diff(knots), budget, vlim, alim, box)
        bad = np.nonzero((geo > 1.0) & (np.diff(knots) >= 2))[0]
        if bad.size == 0:
            break
        knots = np.unique(np.concatenate([knots, (knots[bad] + knots[bad + 1]) // 2]))
    return _chain(q, v, knots, vlim, alim)


def _lengthen(
    q: FloatArray,
    v: FloatArray,
    tangent: FloatArray,
    curved: NDArray[np.bool_],
    knots: IntArray,
    mand: IntArray,
    budget: FloatArray,
    vlim: FloatArray,
    alim: FloatArray,
    min_seg: int,
    max_seg: int,
    box: tuple[FloatArray, FloatArray],
) -> IntArray:
    """Remove the short segments the greedy fit left, where a neighbouring knot can move (or go) so that
    every segment concerned is at least `min_seg` long and passes: the greedy only looks forward, and a
    knot a few ms earlier often avoids the short segment after it."""
    t = knots.copy()
    fixed = np.isin(t, mand)
    k = 0
    while k + 1 < t.size:
        a, b = int(t[k]), int(t[k + 1])
        k += 1
        if b - a >= min_seg:
            continue
        k -= 1
        options: list[tuple[int, int, list[tuple[int, int]]]] = []  # (knot index, new value or -1, segments)
        if k >= 1 and not fixed[k]:
            p = int(t[k - 1])
            if b - p <= max_seg:
                options.append((k, -1, [(p, b)]))
            for x in range(b - min_seg, p + min_seg - 1, -1)[:8]:
                options.append((k, x, [(p, x), (x, b)]))
        if k + 2 < t.size and not fixed[k + 1]:
            n = int(t[k + 2])
            if n - a <= max_seg:
                options.append((k + 1, -1, [(a, n)]))
            for x in range(a + min_seg, n - min_seg + 1)[:8]:
                options.append((k + 1, x, [(a, x), (x, n)]))
        k += 1
        if not options:
            continue
        segs = [seg for opt in options for seg in opt[2]]
        st = np.array([x[0] for x in segs], dtype=np.int64)
        ln = np.array([x[1] - x[0] for x in segs], dtype=np.int64)
        geo, lim = _scores(q, v, tangent, curved, st, ln, budget, vlim, alim, box, True)
        good = (geo <= 1.0) & (lim <= 1.0)
        pos = 0
        for idx, value, sg in options:
            if good[pos : pos + len(sg)].all():
                if value < 0:
                    t = np.delete(t, idx)
                    fixed = np.delete(fixed, idx)
                else:
                    t[idx] = value
                break
            pos += len(sg)
    return t


def _chain(q: FloatArray, v: FloatArray, knots: IntArray, vlim: FloatArray, alim: FloatArray) -> ChainFit:
    n, total = q.shape[0], q.shape[1]
    starts, lengths = knots[:-1], np.diff(knots)
    pos, vel, acc_s, acc_e, ticks, seg = _segments(q, v, starts, lengths)
    positions = np.empty((n, total))
    velocities = np.empty((n, total))
    positions[:, 0], velocities[:, 0] = q[:, 0], v[:, 0]
    positions[:, ticks], velocities[:, ticks] = pos, vel
    positions[:, knots], velocities[:, knots] = q[:, knots], v[:, knots]
    # acceleration is linear inside a segment: interpolate its two ends
    x = ((ticks - starts[seg]) / lengths[seg].astype(np.float64))[None, :]
    acc_left = np.empty((n, total))
    acc_left[:, 0] = acc_s[:, 0]
    acc_left[:, ticks] = acc_s[:, seg] * (1.0 - x) + acc_e[:, seg] * x
    acc_right = acc_left.copy()
    acc_right[:, knots[:-1]] = acc_s
    acc_right[:, -1] = acc_left[:, -1]
    acc_ratio = (np.maximum(np.abs(acc_left), np.abs(acc_right)) / alim[:, None]).max(axis=0)
    vel_ratio = (np.abs(velocities) / vlim[:, None]).max(axis=0)
    return ChainFit(knots, positions, velocities, acc_left, acc_right, acc_ratio, vel_ratio)
