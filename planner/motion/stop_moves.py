"""Jerk-limited moves from waypoint to waypoint of a lines path, each stop at a corner replaced, where the path
tolerance leaves room, by a ruckig transition that does not stop (`stop_moves`).

Theory of operation. The plan a jerk-limited lines path falls back on (and the one plan_job takes where the
blended traversal of planner/motion/jerkpath.py is slower) is the polyline itself: one rest-to-rest ruckig
move per segment (planner/motion/jerk.py `move_reference`), every axis' velocity, acceleration and jerk
limit kept. At an interior waypoint the axes need not come to rest: from the state of the arriving move
some ms before its end (position, velocity, acceleration) to the state of the leaving move some ms after
its start, ruckig gives the time-optimal jerk-limited motion between the two states (all axes
time-synchronised, on whole ms, the jerk within `TRANSITION_JERK_SHARE` of each limit), the acceleration
continuous at both joints. It replaces the two pieces when it is shorter, stays within the software
position limits and the path tolerance of the polyline at every ms (each axis' deviation from the nearer
of the two segments, through the tolerance-scaled projection) and passes the waypoint within it. The
joints are tried on a ladder of distances from the corner, the largest share of the tolerance first; the
transition that saves the most is kept. A corner's transition reaches at most half-way into the leaving
move, so the next corner has the other half. The limits hold by construction (ruckig), the tolerance by the check, and a
corner where no transition fits stays a stop: the plan is never slower than stopping at every corner.

Where it stands against the blended traversal (constant speed through a blend shaped for it): on a sharp
corner with a small tolerance the blend's jerk bound q''' v^3 <= J holds the speed near zero for the
whole blend, and stopping is faster; a transition cuts the stop's last and the next move's first
milliseconds without the blend's slow crossing. Measured in docs/formats.md ("jerk_limited").
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from planner.errors import TOO_LARGE, PlanningError
from planner.motion.jerk import CYCLE_S, move_reference, ruckig_input, sample_at, solve_ruckig
from planner.motion.reference import FloatArray, IntArray, Reference

# the distances from the corner where a transition may join the moves, as shares of the largest the path
# tolerance allows on the arriving (leaving) segment
JOIN_SHARES = (1.0, 0.75, 0.55, 0.4, 0.28, 0.2, 0.14, 0.1, 0.07, 0.05)
DEVIATION_SLACK = 1.0e-9  # of the tolerance (the check is on the same samples the plan is made of)
# a transition's jerk, as a share of each axis' limit: its time-synchronised phases (7 per axis, each axis'
# own) put knots 10-40 ms apart, where a count or an rpm of the drive's units is a large jerk; measured on the
# benchmark's random paths (bench_planner, 20 per corpus), the drive's worst in-segment jerk / limit with
# 1.0, 0.9, 0.75, 0.6, 0.5 of it: 2.02, 1.58, 1.29, 1.13, 1.05 (the moves and blends: 1.03), for durations
# 1.046-1.087 x the acceleration-only optimum in median
TRANSITION_JERK_SHARE = 0.5

# ruckig 0.19.4 ends the process (a segmentation fault, no exception) on some inputs: seen on an axis that
# reverses from (p, v, a) to (p, -v, a), which constant acceleration joins exactly (a transition between two
# mirrored moves, joined at mirrored samples), with a on the limit and 0.2 % inside it; with a 1e-9 inside
# the limit, or the target 1e-4 away, it did not. Such joints are left out of the ladder (`_crashes_ruckig`)
ACC_EDGE = 1.0e-6
MIRROR = 1.0e-6  # of the velocity: how near a reversal is to the exact mirror that crashed

# a stretch of the plan: positions, velocities, accelerations left and right of each ms, breaks, hints
_Piece = tuple[FloatArray, FloatArray, FloatArray, FloatArray, IntArray, IntArray]


@dataclass(frozen=True)
class _Transition:
    start: int  # sample of the arriving move (from the part's current start) where the transition begins
    end: int  # sample of the leaving move where it ends
    pos: FloatArray  # (n, T + 1), counts
    vel: FloatArray  # counts / ms
    acc: FloatArray  # counts / ms^2
    hints: IntArray  # ms (from the transition's start) where a phase of some axis ends


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
    # the moves are played this much slower; a transition's jerk keeps a share for the drive's units
    limits = (vlim / scale, alim / scale**2, jlim * TRANSITION_JERK_SHARE / scale**3)
    tol_counts = None if tolerance is None else np.maximum(np.asarray(tolerance, dtype=np.float64) * cpu, 1e-9)
    bounds = None if box is None else (box[0] * cpu, box[1] * cpu)
    pieces: list[_Piece] = []
    transitions = 0
    first = 0  # the sample the current move starts from (after the last transition)
    for k, part in enumerate(parts):
        last = part.positions.shape[1] - 1
        found = None
        if tol_counts is not None and k + 1 < len(parts):
            found = _transition(part, first, parts[k + 1], waypoints[k:k + 3] * cpu[None, :], tol_counts, cpu,
                                limits, bounds)
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
    arriving: Reference, first: int, leaving: Reference, corner: FloatArray, tol: FloatArray, cpu: FloatArray,
    limits: tuple[FloatArray, FloatArray, FloatArray], bounds: tuple[FloatArray, FloatArray] | None,
) -> _Transition | None:
    """The transition that saves the most between the arriving move (from its sample `first`) and the leaving
    move, within `tol` (counts per axis) of the segments corner[0]->corner[1] and corner[1]->corner[2] (counts)
    and within `bounds` (counts), or None (the corner stays a stop)."""
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
        t = _solve(arriving, i1, leaving, i2, cpu, limits)
        if t is None:
            continue
        saving = cut - (t.pos.shape[1] - 1)
        inside = bounds is None or bool(np.all((t.pos >= bounds[0][:, None]) & (t.pos <= bounds[1][:, None])))
        if saving > best_saving and inside and _within(t.pos, corner, tol):
            best, best_saving = t, saving
    return best


def _solve(a: Reference, i1: int, b: Reference, i2: int, cpu: FloatArray,
           limits: tuple[FloatArray, FloatArray, FloatArray]) -> _Transition | None:
    """ruckig's time-optimal motion from sample i1 of move a to sample i2 of move b (whole ms), in counts;
    None when ruckig finds none."""
    n = cpu.size
    inp = ruckig_input(n, *limits)
    c = cpu
    p0, v0, a0 = a.positions[:, i1] / c, a.velocities[:, i1] * 1000.0 / c, a.acc_right[:, i1] * 1.0e6 / c
    p1, v1, a1 = b.positions[:, i2] / c, b.velocities[:, i2] * 1000.0 / c, b.acc_left[:, i2] * 1.0e6 / c
    if _crashes_ruckig(p0, v0, a0, p1, v1, a1, limits[1]):
        return None
    inp.current_position, inp.current_velocity, inp.current_acceleration = list(p0), list(v0), list(a0)
    inp.target_position, inp.target_velocity, inp.target_acceleration = list(p1), list(v1), list(a1)
    try:
        traj = solve_ruckig(inp, n)
    except PlanningError:
        return None
    steps = max(round(traj.duration / CYCLE_S), 1)
    pos, vel, acc = sample_at(traj, n, np.arange(steps + 1, dtype=np.float64) * CYCLE_S)
    cc = c[:, None]
    pos, vel, acc = pos * cc, vel * cc / 1000.0, acc * cc / 1.0e6
    # the joints exactly on the moves' samples
    pos[:, 0], vel[:, 0], acc[:, 0] = a.positions[:, i1], a.velocities[:, i1], a.acc_right[:, i1]
    pos[:, -1], vel[:, -1], acc[:, -1] = b.positions[:, i2], b.velocities[:, i2], b.acc_left[:, i2]
    phase_ends = [np.cumsum([traj.profiles[0][i].t[k] for k in range(7)]) for i in range(n)]
    hints = np.unique(np.round(np.concatenate(phase_ends) / CYCLE_S).astype(np.int64))
    hints = hints[(hints > 0) & (hints < steps)]
    return _Transition(i1, i2, pos, vel, acc, hints)


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


def _crashes_ruckig(p0: FloatArray, v0: FloatArray, a0: FloatArray, p1: FloatArray, v1: FloatArray,
                    a1: FloatArray, amax: FloatArray) -> bool:
    """Is this transition of the kind that made ruckig end the process (see `ACC_EDGE`)? A joint on the
    acceleration limit, or an axis whose target mirrors its start (same position and acceleration, the
    velocity reversed)."""
    edge = amax * (1.0 - ACC_EDGE)
    if np.any(np.abs(a0) >= edge) or np.any(np.abs(a1) >= edge):
        return True
    scale = np.maximum(np.abs(v0), 1e-12)
    mirror = ((np.abs(v0 + v1) <= MIRROR * scale) & (np.abs(a1 - a0) <= MIRROR * np.maximum(np.abs(a0), 1e-12))
              & (np.abs(p1 - p0) * 1000.0 <= MIRROR * scale) & (np.abs(v0) > 0.0))
    return bool(mirror.any())
