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

The search is cheap where it can be: every candidate segment gets the per-segment limit checks (end
accelerations, the vertex of the velocity parabola), and only the most preferred one that passes them
is sampled (`_first_passing`; the geometry rarely fails); `_lengthen` checks all its candidates in one
batch; the final every-ms check and the chain share their samples.

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


_Ticks = tuple[FloatArray, FloatArray, FloatArray, FloatArray, IntArray, IntArray]


def _segments(q: FloatArray, v: FloatArray, starts: IntArray, lengths: IntArray, sampled: bool = False) -> _Ticks:
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


class _Candidates:
    """Checks candidate segments of one fit at `_SAMPLES` of each (the greedy search and `_lengthen`).

    A segment passes when its end accelerations and the vertex of its velocity parabola are within the
    limits (`limits_ok`: per segment, cheap) and, at the sample ticks, its velocity is within the limits
    and its position within the budget of the path and inside the box (`samples_ok`: per sample). The
    searches ask for the cheap check of all their candidates and for the samples of only the best
    candidate that passed it, in their order of preference: the geometry rarely fails, so most
    candidates are never sampled.
    """

    def __init__(
        self,
        q: FloatArray,
        v: FloatArray,
        tangent: FloatArray,
        curved: NDArray[np.bool_],
        budget: FloatArray,
        vlim: FloatArray,
        alim: FloatArray,
        box: tuple[FloatArray, FloatArray],
    ):
        self.q, self.v, self.tangent, self.curved = q, v, tangent, curved
        self.budget = budget[:, None]
        self.vlim = vlim[:, None]
        self.alim = alim[:, None]
        self.lower = box[0][:, None]
        self.upper = box[1][:, None]
        self.cache: dict[tuple[int, int], bool] = {}

    def limits_ok(self, starts: IntArray, lengths: IntArray) -> NDArray[np.bool_]:
        """End accelerations (the acceleration is linear: its peak is at an end) and the velocity peak."""
        q, v = self.q, self.v
        t1 = lengths.astype(np.float64)
        e = starts + lengths
        qa, qb, va, vb = q[:, starts], q[:, e], v[:, starts], v[:, e]
        dp = qb - qa
        tt = t1 * t1
        acc_s = (6.0 * dp - 2.0 * t1 * vb - 4.0 * t1 * va) / tt
        acc_e = (-6.0 * dp + 4.0 * t1 * vb + 2.0 * t1 * va) / tt
        acc_r = (np.maximum(np.abs(acc_s), np.abs(acc_e)) / self.alim).max(axis=0)
        peak = (_peak(qa, qb, va, vb, t1) / self.vlim).max(axis=0)
        out: NDArray[np.bool_] = (acc_r - ACC_SLACK <= 1.0) & (peak - VEL_SLACK <= 1.0)
        return out

    def samples_ok(self, starts: IntArray, lengths: IntArray) -> NDArray[np.bool_]:
        """Velocity, geometry and the box at the sample ticks of each segment."""
        pos, vel, _acc_s, _acc_e, ticks, _seg = _segments(self.q, self.v, starts, lengths, True)
        k = _SAMPLES.size
        vel_r = (np.abs(vel) / self.vlim).max(axis=0).reshape(-1, k).max(axis=1)
        err = _deviation(pos, self.q, self.tangent, self.curved, ticks, self.budget[:, 0])
        outside = ((pos < self.lower) | (pos > self.upper)).any(axis=0)
        geo = np.where(outside, np.maximum(err, 2.0), err).reshape(-1, k).max(axis=1)
        out: NDArray[np.bool_] = (geo <= 1.0) & (vel_r - VEL_SLACK <= 1.0)
        return out

    def ok(self, starts: IntArray, lengths: IntArray) -> NDArray[np.bool_]:
        """Both checks (samples only where the limits pass), remembered for this fit."""
        out = self.limits_ok(starts, lengths)
        idx = np.nonzero(out)[0]
        if idx.size:
            out[idx] = self.samples_ok(starts[idx], lengths[idx])
        return out


def _peak(qa: FloatArray, qb: FloatArray, va: FloatArray, vb: FloatArray, t1: FloatArray) -> FloatArray:
    """|velocity| at the vertex of each segment's velocity parabola, where it lies inside (n, segs)."""
    dp = (qa - qb) / t1  # velocity in x = t / T: A x^2 + B x + C
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
    cands = _Candidates(q, v, tangent, curved, budget, vlim, alim, box)
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
        rem = room[:, None] - lens
        # preference: at least min_seg (the encoder's quantisation needs it); finish the section; else
        # the longest that leaves at least min_seg; else a half; shorter ones only when nothing else passes
        # (a preference determines its length: lengths are below 1024)
        half = lens == np.ceil(room / 2.0)[:, None]
        long = lens >= lo[:, None]
        prefer = lens + 8192 * long + 4096 * (rem == 0) + 2048 * (rem >= min_seg) + 1024 * half
        best = _first_passing(cands, c, lens, prefer)
        # nothing passes: the shortest allowed segment (its violation is reported to the caller)
        best = np.where(best > 0, best, short)
        cur[act] += best
        prev[act] = np.maximum(best, lo)
        found.append(cur[act].copy())
    knots = np.unique(np.concatenate(found)).astype(np.int64)
    if allow_short:
        knots = _lengthen(cands, knots, mand, min_seg, max_seg)
    # the search looked at a few ticks per segment: check every tick, halve what fails the geometry
    every: _Ticks | None = None
    for _round in range(4):
        lengths = np.diff(knots)
        every = _segments(q, v, knots[:-1], lengths)
        pos, ticks = every[0], every[4]
        err = _deviation(pos, q, tangent, curved, ticks, budget)
        outside = ((pos < box[0][:, None]) | (pos > box[1][:, None])).any(axis=0)
        geo = np.maximum.reduceat(np.where(outside, np.maximum(err, 2.0), err), np.cumsum(lengths) - lengths)
        bad = np.nonzero((geo > 1.0) & (np.diff(knots) >= 2))[0]
        if bad.size == 0:
            break
        knots = np.unique(np.concatenate([knots, (knots[bad] + knots[bad + 1]) // 2]))
        every = None
    return _chain(q, v, knots, vlim, alim, every)


def _first_passing(cands: _Candidates, starts: IntArray, lens: IntArray, prefer: IntArray) -> IntArray:
    """Per section (row): the length of its most preferred candidate segment from `starts` that passes,
    0 where none does; `lens`, `prefer` (sections, candidates), a preference determining its length.

    Every candidate gets the cheap limit checks, and the samples of only the best that passed them:
    where that fails, the next best, until each section has one or has none left. The same choice as
    checking every candidate fully (tests/planner/test_planner_chain.py)."""
    k = lens.shape[1]
    prefer = np.where(cands.limits_ok(np.repeat(starts, k), lens.ravel()).reshape(-1, k), prefer, 0)
    best = np.zeros(starts.size, dtype=np.int64)
    rows = np.arange(starts.size)
    while rows.size:
        top = prefer[rows].max(axis=1)
        rows, length = rows[top > 0], top[top > 0] % 1024
        if rows.size == 0:
            break
        good = cands.samples_ok(starts[rows], length)
        best[rows[good]] = length[good]
        rows, length = rows[~good], length[~good]
        prefer[rows] = np.where(lens[rows] == length[:, None], 0, prefer[rows])
    return best


def _lengthen(cands: _Candidates, knots: IntArray, mand: IntArray, min_seg: int, max_seg: int) -> IntArray:
    """Remove the short segments the greedy fit left, where a neighbouring knot can move (or go) so that
    every segment concerned is at least `min_seg` long and passes: the greedy only looks forward, and a
    knot a few ms earlier often avoids the short segment after it.

    The short segments are taken one after the other (a change moves the neighbours of the next one);
    the candidate segments of all of them are checked at once first, and only those a change made new
    are checked on the way."""
    t = knots.copy()
    fixed = np.isin(t, mand)

    def options(k: int) -> list[tuple[int, int, list[tuple[int, int]]]]:
        """(knot index, new value or -1 to remove it, the segments that makes) for short segment k."""
        a, b = int(t[k]), int(t[k + 1])
        out: list[tuple[int, int, list[tuple[int, int]]]] = []
        if k >= 1 and not fixed[k]:
            p = int(t[k - 1])
            if b - p <= max_seg:
                out.append((k, -1, [(p, b)]))
            for x in range(b - min_seg, p + min_seg - 1, -1)[:8]:
                out.append((k, x, [(p, x), (x, b)]))
        if k + 2 < t.size and not fixed[k + 1]:
            n = int(t[k + 2])
            if n - a <= max_seg:
                out.append((k + 1, -1, [(a, n)]))
            for x in range(a + min_seg, n - min_seg + 1)[:8]:
                out.append((k + 1, x, [(a, x), (x, n)]))
        return out

    def check(segs: list[tuple[int, int]]) -> None:
        new = sorted({s for s in segs if s not in cands.cache})
        if new:
            st = np.array([s[0] for s in new], dtype=np.int64)
            ok = cands.ok(st, np.array([s[1] for s in new], dtype=np.int64) - st)
            cands.cache.update(zip(new, ok.tolist(), strict=True))

    short = np.nonzero(np.diff(t) < min_seg)[0]
    check([s for k in short.tolist() for opt in options(k) for s in opt[2]])
    k = 0
    while k + 1 < t.size:
        if int(t[k + 1]) - int(t[k]) >= min_seg:
            k += 1
            continue
        opts = options(k)
        k += 1
        check([s for opt in opts for s in opt[2]])
        for idx, value, sg in opts:
            if all(cands.cache[s] for s in sg):
                if value < 0:
                    t = np.delete(t, idx)
                    fixed = np.delete(fixed, idx)
                else:
                    t[idx] = value
                break
    return t


def _chain(
    q: FloatArray,
    v: FloatArray,
    knots: IntArray,
    vlim: FloatArray,
    alim: FloatArray,
    every: _Ticks | None = None,
) -> ChainFit:
    n, total = q.shape[0], q.shape[1]
    starts, lengths = knots[:-1], np.diff(knots)
    pos, vel, acc_s, acc_e, ticks, seg = every if every is not None else _segments(q, v, starts, lengths)
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
