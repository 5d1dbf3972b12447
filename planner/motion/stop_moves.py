"""Jerk-limited moves from waypoint to waypoint of a lines path, each stop at a corner replaced, where the path
tolerance leaves room, by a transition that does not stop (`stop_moves`).

Theory of operation. The plan a jerk-limited lines path falls back on (and the one plan_job takes where the
blended traversal of planner/motion/jerkpath.py is slower) is the polyline itself: one rest-to-rest ruckig
move per segment (planner/motion/jerk.py `move_reference`), every axis' velocity, acceleration and jerk
limit kept. At an interior waypoint the axes need not come to rest: from the state of the arriving move
some ms before its end (position, velocity, acceleration) to the state of the leaving move some ms after
its start, a transition of three constant-jerk phases whose ends every axis shares (`_common_phases`: equal
thirds on whole ms; each axis' three jerks are the one solution of its three end conditions, position,
velocity and acceleration) joins them, the acceleration continuous at both joints; the shortest duration
whose jerks, accelerations and velocities keep every axis' limits is taken. It replaces the two pieces
when it is shorter, stays within the software position limits and the path tolerance of the polyline at
every ms (each axis' deviation from the nearer of the two segments, through the tolerance-scaled
projection) and passes the waypoint within it. The joints are tried on a ladder of distances from the
corner, the largest share of the tolerance first; the transition that saves the most is kept. A corner's
transition reaches at most half-way into the leaving move, so the next corner has the other half. The
limits hold by construction, the tolerance by the check, and a corner where no transition fits stays a
stop: the plan is never slower than stopping at every corner.

Why shared phases rather than the time-optimal motion between the two states (ruckig, each axis its own
seven phases), measured on the benchmark's random paths (bench_planner, 20 per corpus): the drive's
cubic reproduces a constant-jerk phase exactly only between knots at its ends, and knots are shared by
every axis, so each axis' own phases put knots 10-40 ms apart, where one count or one rpm of the drive's
units is a large step of acceleration. ruckig's transitions needed half the jerk limit to keep the
drive's in-segment jerk within 1.05 of it, and left the median path's largest knot step at 1.24 x the
bound (J x 1 ms); three shared phases at the full limit make the paths shorter (1.066 against 1.087 x
the acceleration-only optimum in median), leave that knot step at 0.97 and the drive's jerk within 1.047
of the limit on every corpus, and call no solver that can end the process (ruckig 0.19.4 did on
transitions between mirrored states).

Where it stands against the blended traversal (constant speed through a blend shaped for it): on a sharp
corner with a small tolerance the blend's jerk bound q''' v^3 <= J holds the speed near zero for the
whole blend, and stopping is faster; a transition cuts the stop's last and the next move's first
milliseconds without the blend's slow crossing. Measured in docs/formats.md ("jerk_limited").
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from planner.errors import TOO_LARGE, PlanningError
from planner.motion.jerk import move_reference
from planner.motion.reference import FloatArray, IntArray, Reference

# the distances from the corner where a transition may join the moves, as shares of the largest the path
# tolerance allows on the arriving (leaving) segment
JOIN_SHARES = (1.0, 0.75, 0.55, 0.4, 0.28, 0.2, 0.14, 0.1, 0.07, 0.05)
DEVIATION_SLACK = 1.0e-9  # of the tolerance (the check is on the same samples the plan is made of)
PHASES = 3  # a transition's constant-jerk phases, shared by every axis: three end conditions, one solution
# the shortest phase tried, in turn: a phase is a segment of the drive's cubic, where each count or rpm of its
# units is an acceleration step of 6 / T^2 or 4 / T at a knot; 35 ms first, any length where that finds none
# (measured on the benchmark's random paths, median knot step / bound with 35 and 1 ms: 0.99 / 1.03 on paths,
# 0.97 / 0.99 on sharp ones; on paths of a few counts 35 ms alone left most corners stopping)
MIN_PHASE_MS = (35, 1)
WITHIN_TRIES = 4  # durations tried at one pair of joints, shortest first, for one that keeps the tolerance

# a stretch of the plan: positions, velocities, accelerations left and right of each ms, breaks, hints
_Piece = tuple[FloatArray, FloatArray, FloatArray, FloatArray, IntArray, IntArray]


@dataclass(frozen=True)
class _Transition:
    start: int  # sample of the arriving move (from the part's current start) where the transition begins
    end: int  # sample of the leaving move where it ends
    pos: FloatArray  # (n, T + 1), counts
    vel: FloatArray  # counts / ms
    acc: FloatArray  # counts / ms^2
    hints: IntArray  # ms (from the transition's start) where its phases end (every axis' alike)


def stop_moves(
    waypoints: FloatArray,
    counts_per_unit: FloatArray,
    vlim: FloatArray,
    alim: FloatArray,
    jlim: FloatArray,
    *,
    tolerance: FloatArray | None = None,
    box: tuple[FloatArray, FloatArray] | None = None,
    time_scale: float = 1.0,
    max_duration_s: float = 900.0,
    info: dict[str, float] | None = None,
) -> Reference:
    """The jerk-limited moves along the straight lines from waypoint to waypoint (user units, the ends
    snapped), one after the other; with `tolerance` (user units per axis) each stop at an interior waypoint
    replaced by a transition within it where one is faster (see the module docstring), and within `box`
    (the software position limits, user units: a corner on a limit may not be cut beyond it). `info`
    receives `jerk_transitions` (the corners that do not stop)."""
    cpu = counts_per_unit
    parts: list[Reference] = []
    spent = 0.0
    for a, b in itertools.pairwise(waypoints):
        ref = move_reference(a, b, vlim, alim, jlim, cpu, time_scale=time_scale,
                             max_duration_s=max_duration_s - spent / 1000.0)
        spent += ref.duration_ms
        parts.append(ref)
    scale = max(time_scale, 1.0)
    # the moves are played this much slower; the transitions keep the same limits, in counts per ms
    limits = (vlim * cpu / (1.0e3 * scale), alim * cpu / (1.0e6 * scale**2), jlim * cpu / (1.0e9 * scale**3))
    tol_counts = None if tolerance is None else np.maximum(np.asarray(tolerance, dtype=np.float64) * cpu, 1e-9)
    bounds = None if box is None else (box[0] * cpu, box[1] * cpu)
    pieces: list[_Piece] = []
    transitions = 0
    first = 0  # the sample the current move starts from (after the last transition)
    for k, part in enumerate(parts):
        last = part.positions.shape[1] - 1
        found = None
        if tol_counts is not None and k + 1 < len(parts):
            found = _transition(part, first, parts[k + 1], waypoints[k:k + 3] * cpu[None, :], tol_counts, limits,
                                bounds)
        stop = last if found is None else found.start
        pieces.append(_window(part, first, stop))
        if found is None:
            first = 0
            continue
        transitions += 1
        pieces.append((found.pos, found.vel, found.acc, found.acc, np.zeros(0, dtype=np.int64), found.hints))
        first = found.end
    ref = _joined(pieces)
    if ref.duration_ms > max_duration_s * 1000.0:
        raise PlanningError(
            TOO_LARGE,
            f"the path takes {ref.duration_ms / 1000:.1f} s, more than the limit of {max_duration_s:g} s",
            path="waypoints",
        )
    if info is not None:
        info["jerk_transitions"] = float(transitions)
    return ref


def _window(part: Reference, lo: int, hi: int) -> _Piece:
    """Samples lo..hi of a move (both included), its acceleration steps and phase ends re-based to lo."""
    sl = slice(lo, hi + 1)
    breaks = part.breaks[(part.breaks > lo) & (part.breaks < hi)] - lo
    hints = part.hints[(part.hints > lo) & (part.hints < hi)] - lo
    return part.positions[:, sl], part.velocities[:, sl], part.acc_left[:, sl], part.acc_right[:, sl], breaks, hints


def _joined(pieces: list[_Piece]) -> Reference:
    """The pieces one after the other (each starts at the sample the one before ends on), their joints as
    hints. The acceleration is continuous at every joint (a move starts and ends at rest with none, a
    transition at the moves' own)."""
    starts = np.concatenate([[0], np.cumsum([p[0].shape[1] - 1 for p in pieces])]).astype(np.int64)
    pos = np.concatenate([pieces[0][0]] + [p[0][:, 1:] for p in pieces[1:]], axis=1)
    vel = np.concatenate([pieces[0][1]] + [p[1][:, 1:] for p in pieces[1:]], axis=1)
    acc_l = np.concatenate([pieces[0][2]] + [p[2][:, 1:] for p in pieces[1:]], axis=1)
    acc_r = np.concatenate([p[3][:, :-1] for p in pieces] + [pieces[-1][3][:, -1:]], axis=1)
    breaks = np.concatenate([p[4] + starts[k] for k, p in enumerate(pieces)]).astype(np.int64)
    hints = np.concatenate([p[5] + starts[k] for k, p in enumerate(pieces)] + [starts[1:-1]])
    return Reference(pos, vel, acc_l, acc_r, breaks, hints.astype(np.int64))


def _transition(
    arriving: Reference, first: int, leaving: Reference, corner: FloatArray, tol: FloatArray,
    limits: tuple[FloatArray, FloatArray, FloatArray], bounds: tuple[FloatArray, FloatArray] | None,
) -> _Transition | None:
    """The transition that saves the most between the arriving move (from its sample `first`) and the leaving
    move, within `tol` (counts per axis) of the segments corner[0]->corner[1] and corner[1]->corner[2] (counts)
    and within `bounds` (counts), with the longest phases of `MIN_PHASE_MS` that find one; None: the corner
    stays a stop."""
    for shortest in MIN_PHASE_MS:
        found = _best_transition(arriving, first, leaving, corner, tol, limits, bounds, shortest)
        if found is not None:
            return found
    return None


def _best_transition(
    arriving: Reference, first: int, leaving: Reference, corner: FloatArray, tol: FloatArray,
    limits: tuple[FloatArray, FloatArray, FloatArray], bounds: tuple[FloatArray, FloatArray] | None, shortest: int,
) -> _Transition | None:
    """`_transition` with phases at least `shortest` ms long."""
    pa, pb = arriving.positions, leaving.positions
    end_a = pa.shape[1] - 1
    half_b = (pb.shape[1] - 1) // 2
    # the share of the tolerance left between each sample and the corner: how far it still is from the
    # waypoint (arriving), how far it has gone (leaving)
    remain = np.max(np.abs(pa[:, first:] - pa[:, -1:]) / tol[:, None], axis=0)
    gone = np.max(np.abs(pb[:, :half_b + 1] - pb[:, :1]) / tol[:, None], axis=0)
    best: _Transition | None = None
    best_saving = 0
    tried: set[tuple[int, int]] = set()
    for share in JOIN_SHARES:
        i1 = first + int(np.argmax(remain <= share))  # the earliest sample this close to the corner
        i2 = int(np.nonzero(gone <= share)[0][-1])  # the latest sample of the leaving move this close
        if (i1, i2) in tried or (i1 >= end_a and i2 <= 0):
            continue
        tried.add((i1, i2))
        cut = (end_a - i1) + i2  # ms of the two moves the transition replaces
        if cut <= best_saving + 1:
            continue
        for t in itertools.islice(_common_phases(arriving, i1, leaving, i2, limits, shortest, cut - best_saving - 1),
                                  WITHIN_TRIES):
            inside = bounds is None or bool(np.all((t.pos >= bounds[0][:, None]) & (t.pos <= bounds[1][:, None])))
            if inside and _within(t.pos, corner, tol):
                best, best_saving = t, cut - (t.pos.shape[1] - 1)
                break
    return best


def _within(pos: FloatArray, corner: FloatArray, tol: FloatArray) -> bool:
    """Every sample within `tol` (per axis) of the segment corner[0]->corner[1] or corner[1]->corner[2] (the
    deviation from the point of each segment nearest in tolerance-scaled coordinates: an upper bound on the
    distance to the segment), and some sample within `tol` of the waypoint corner[1] (the path passes it:
    on a corner that nearly reverses, a motion can keep near both segments and turn back early)."""
    x = pos / tol[:, None]
    w = corner / tol[None, :]
    if float(np.min(np.max(np.abs(x - w[1][:, None]), axis=0))) > 1.0 + DEVIATION_SLACK:
        return False
    ok = np.zeros(pos.shape[1], dtype=bool)
    for p, q in ((w[0], w[1]), (w[1], w[2])):
        d = q - p
        dd = float(d @ d)
        lam = np.zeros(pos.shape[1]) if dd == 0.0 else np.clip((d @ (x - p[:, None])) / dd, 0.0, 1.0)
        near = p[:, None] + d[:, None] * lam[None, :]
        ok |= np.max(np.abs(x - near), axis=0) <= 1.0 + DEVIATION_SLACK
    return bool(ok.all())


def _phase_powers(t: FloatArray, starts: FloatArray, ends: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """What a unit jerk on [starts, ends] (ms) adds to the position, velocity and acceleration at the times t:
    t (..., 1) broadcast against the phases (..., k)."""
    u = np.maximum(t - starts, 0.0)
    w = np.maximum(t - ends, 0.0)
    return (u**3 - w**3) / 6.0, (u**2 - w**2) / 2.0, u - w


def _common_phases(a: Reference, i1: int, b: Reference, i2: int,
                   limits: tuple[FloatArray, FloatArray, FloatArray], shortest: int, longest: int,
                   ) -> Iterator[_Transition]:
    """The motions from sample i1 of move a to sample i2 of move b made of `PHASES` constant-jerk phases whose
    ends every axis shares (equal shares of the duration, on whole ms, each at least `shortest` ms), shortest
    first, up to `longest` ms, that keep every axis' velocity, acceleration and jerk limits (counts per ms).
    Each axis' jerks are the one solution of its end conditions (position, velocity and acceleration)."""
    p0, v0, a0 = a.positions[:, i1], a.velocities[:, i1], a.acc_right[:, i1]
    p1, v1, a1 = b.positions[:, i2], b.velocities[:, i2], b.acc_left[:, i2]
    vmax, amax, jmax = limits
    durations = np.arange(PHASES * max(shortest, 1), longest + 1, dtype=np.int64)
    if durations.size == 0:
        return
    d = durations.astype(np.float64)[:, None]
    ends = np.round(d * np.arange(PHASES + 1, dtype=np.float64)[None, :] / PHASES)  # (D, PHASES + 1), whole ms
    m = np.stack(_phase_powers(d, ends[:, :-1], ends[:, 1:]), axis=1)  # (D, 3, PHASES): the end conditions
    rhs = np.stack([p1[None, :] - p0[None, :] - v0[None, :] * d - a0[None, :] * d * d / 2.0,
                    (v1 - v0)[None, :] - a0[None, :] * d,
                    np.broadcast_to(a1 - a0, (d.size, a0.size))], axis=1)  # (D, 3, n)
    jerk = np.linalg.solve(m, rhs)  # (D, PHASES, n); the phases are at least 1 ms, so m is regular
    for k in np.nonzero(np.all(np.abs(jerk) <= jmax[None, None, :] * (1.0 + 1e-12), axis=(1, 2)))[0]:
        steps = int(durations[k])
        t = np.arange(steps + 1, dtype=np.float64)[:, None]
        sp, sv, sa = _phase_powers(t, ends[k, :-1][None, :], ends[k, 1:][None, :])  # (T + 1, PHASES)
        j = jerk[k]
        vel = (v0[None, :] + a0[None, :] * t + sv @ j).T
        acc = (a0[None, :] + sa @ j).T
        if np.any(np.abs(vel) > vmax[:, None] * (1.0 + 1e-9)) or np.any(np.abs(acc) > amax[:, None] * (1.0 + 1e-9)):
            continue
        pos = (p0[None, :] + v0[None, :] * t + a0[None, :] * t * t / 2.0 + sp @ j).T
        # the joints exactly on the moves' samples
        pos[:, 0], vel[:, 0], acc[:, 0] = p0, v0, a0
        pos[:, -1], vel[:, -1], acc[:, -1] = p1, v1, a1
        yield _Transition(i1, i2, pos, vel, acc, ends[k, 1:-1].astype(np.int64))
