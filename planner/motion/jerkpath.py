"""Jerk-limited traversal of a path (`jerk_limited` path jobs): what plan_job plans instead of the
acceleration-only optimum of planner/motion/path.py when every axis' jerk limit must hold too.

Theory of operation. Fed the runs of a path (rest to rest, between exact stops) and the joints' velocity,
acceleration and jerk limits; emits the plan at every ms (a `Reference` in counts whose acceleration is
continuous: no `breaks`; its `hints` are where a cubic piece of it ends). Per run:

1. Along straight pieces and blends (`plan_corner_run`, planner/motion/geometry.py's runs): every blend crossed
   at one constant path speed, the largest at which every joint's velocity q' s', acceleration q'' s'^2
   and jerk q''' s'^3 stay within their limits (the jerk within `PLAN_JERK_SHARE`; geometry.py shapes
   each blend for that crossing: `corner_blends` with `jerk`); every straight piece
   a time-optimal jerk-limited 1-DoF motion (ruckig, along the line) between the speeds at its two
   ends at zero path acceleration: where a piece meets a blend, q'' is 0, so the acceleration is
   continuous. A forward and a backward pass lower the speeds no straight piece can connect (a
   jerk-limited change of speed is symmetric in time: `_change`, `_reach`). A corner whose blend is
   slower than stopping on its waypoint becomes a stop (`_choose_stops`, a Viterbi pass over the
   corners). plan_job also compares the whole path with jerk-limited moves from waypoint to waypoint whose
   stops are cut short within the tolerance (planner/motion/stop_moves.py) and keeps the faster.
2. Any other geometry (a spline: `plan_jerk_run`): TOPP-RA's acceleration-only optimum re-timed onto
   whole ms (path.Profile), then its path acceleration averaged over a sliding window of W ms
   (`fir_retime`: the FIR filter of Biagiotti & Melchiorri, "FIR filters for online trajectory
   planning", 2012): a step of s_ddot becomes a ramp of W ms, the path jerk is (s_ddot(t) -
   s_ddot(t - W)) / W, the motion ends exactly at rest at the path's end, W ms later. W is the
   shortest (of a ladder) that keeps every joint's share |q'| |s'''| within `JERK_SHARE` of its limit.
   The averaged motion would arrive at the optimum's dips (where a bound holds it back) faster than the
   optimum does: the solve is repeated with the optimum's speed at each dip imposed for a window before
   and after it (`dip_caps`). Whatever still fails at some ms tightens the solver's constraint rows of
   those path intervals and solves again (`REPAIR_ROUNDS`), then the run is played slower.
With `jerk_timing = "fastest"` each run is also planned at the third-order time-optimal speed along its
geometry (`plan_fastest_run`, planner/motion/jerk_scp.py), which is kept where it is shorter.
3. Every run is checked at every ms on the joint motion itself (`ratios`): velocity and acceleration
   within their limits, the change of acceleration over every ms within `PLAN_JERK_SHARE` of the jerk
   limit (the rest is left to the drive's quantisation: planner/encoding/continuity.py), and slowed down where
   it is not.

Why this method and what it costs, measured: docs/formats.md, "jerk_limited".
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planner.errors import INFEASIBLE, TOO_LARGE, PlanningError
from planner.motion import topp
from planner.motion.path import GeometricPath, Profile, solve_profile
from planner.motion.reference import FloatArray, IntArray, Reference

JERK_SHARE = 0.7  # of each joint's jerk limit, for the path-jerk term q' s''' (the window's choice)
PLAN_JERK_SHARE = 0.9  # the plan's jerk over every ms within this share of the limit (the rest: encoder)
REPAIR_ROUNDS = 4
ACC_SLACK = 1.0e-3
VEL_SLACK = 1.0e-4
MAX_WINDOW_MS = 2000
_WINDOW_STEP = 1.04  # the ladder of windows tried: each 4 % longer than the one before


@dataclass(frozen=True)
class JerkRun:
    """One run re-timed with bounded jerk: joint samples at every ms (user units, per ms)."""

    q: FloatArray  # (n, M+1)
    v: FloatArray
    acc: FloatArray  # continuous: one value per ms
    optimal_ms: float  # the acceleration-only optimum of this run (TOPP-RA, first solve)
    window_ms: int
    solves: int
    time_scale: float  # the slow-down the repairs needed (1: none)
    hints: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # ms where a cubic piece ends


def dip_caps(grid: FloatArray, sd: FloatArray, window_ms: float) -> FloatArray:
    """Caps on s_dot at the gridpoints: around every interior local minimum of the optimum `sd` (where a
    velocity or acceleration bound holds the path back: a blend, a slow stretch), its value over the
    gridpoints within `window_ms` of it either side (in the optimum's time); inf elsewhere. The averaged
    motion reaches a dip up to a window late and leaves it up to a window late: with the optimum held at
    the dip's speed that long before and after, the average cannot exceed it there."""
    vsum = sd[:-1] + sd[1:]
    t = np.concatenate([[0.0], np.cumsum(2.0 * np.diff(grid) / np.maximum(vsum, 1e-300))]) * 1000.0
    inner = np.arange(1, sd.size - 1)
    dips = inner[(sd[inner] <= sd[inner - 1]) & (sd[inner] <= sd[inner + 1]) & (sd[inner] > 0.0)]
    caps = np.full(sd.size, np.inf)
    lo = np.searchsorted(t, t[dips] - window_ms, side="left")
    hi = np.searchsorted(t, t[dips] + window_ms, side="right")
    for d, a, b in zip(dips, lo, hi, strict=True):
        np.minimum(caps[a:b], sd[d], out=caps[a:b])
    return caps


def solve_capped(
    samples: topp.PathSamples, vlim: FloatArray, alim: FloatArray, row_scale: FloatArray | None, caps: FloatArray
) -> FloatArray:
    """TOPP-RA's optimum (planner/motion/topp.py) with s_dot at most `caps` at the gridpoints as well."""
    a, b, g = topp.constraint_rows(samples.q1, samples.q2, samples.deltas, vlim, alim, row_scale)
    xmax = np.minimum(topp.velocity_bound(samples.q1, vlim), caps * caps)
    return topp.parametrize(a, b, g, xmax, samples.gridpoints)


def fir_retime(acc_ms: FloatArray, s_end: float, window: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """s, s_dot, s_ddot at every ms 0..M+W of the path acceleration `acc_ms` (M,) (per ms^2, constant over
    each ms, from rest) averaged over `window` ms: exact (the averaged acceleration is linear over each
    ms), rescaled to end exactly at `s_end`."""
    m = acc_ms.size
    total = m + window
    padded = np.concatenate([np.zeros(window), acc_ms, np.zeros(window)])
    csum = np.concatenate([[0.0], np.cumsum(padded)])
    # A_f(t) = (1/W) sum_{k=t-W}^{t-1} a[k], t = 0..M+W (index k of `padded` is k - W of acc_ms)
    t = np.arange(total + 1)
    acc = (csum[t + window] - csum[t]) / window
    sd = np.concatenate([[0.0], np.cumsum(0.5 * (acc[:-1] + acc[1:]))])
    s = np.concatenate([[0.0], np.cumsum(sd[:-1] + acc[:-1] / 3.0 + acc[1:] / 6.0)])
    sig = s_end / s[-1] if s[-1] > 0 else 1.0
    sd[-1] = 0.0
    return s * sig, np.maximum(sd * sig, 0.0), acc * sig


def choose_window(
    acc_ms: FloatArray, q1_abs: FloatArray, jlim_ms: FloatArray, share: float = JERK_SHARE
) -> int:
    """The shortest window (ms, of a ladder 4 % apart) whose path jerk keeps every joint's q' s''' term
    within `share` of its limit: `acc_ms` (M,) the path acceleration per ms, `q1_abs` (M, n) the
    joints' |q'| at those ms, `jlim_ms` (n,) per ms^3. The averaged motion is on ms t about where the
    optimum was within the window before: |q'| is taken as its largest over that window."""
    lim = share * jlim_ms[None, :]
    # a lower bound: a step of the path acceleration spread over the window
    w = max(1, int(float((q1_abs.min(axis=0) * np.ptp(acc_ms) / (share * jlim_ms)).max()) / 4.0))
    while w < MAX_WINDOW_MS:
        padded = np.concatenate([np.zeros(w), acc_ms, np.zeros(w)])
        steps = np.abs(padded[w:] - padded[:-w])  # t = 0..M+W-1: a[t] - a[t - W]
        q1_pad = np.concatenate([q1_abs, np.repeat(q1_abs[-1:], w, axis=0)])
        q1w = _sliding_max(q1_pad, w)[: steps.size]
        if float((steps[:, None] * q1w / lim).max()) <= w:
            return w
        w = max(w + 1, int(np.ceil(w * _WINDOW_STEP)))
    return MAX_WINDOW_MS


def _sliding_max(x: FloatArray, window: int) -> FloatArray:
    """The largest value of x (M, n) over the rows [m - window, m] for every m (clipped at row 0)."""
    out = x.copy()
    span = 1  # out[m] is the largest over [m - span + 1, m]
    rows = out.shape[0]
    while span < window + 1:
        step = min(span, window + 1 - span, rows)
        shifted = np.concatenate([np.repeat(out[:1], step, axis=0), out[: rows - step]])
        out = np.maximum(out, shifted)
        span += step
        if step == rows:
            break
    return out


def joint_motion(
    geom: GeometricPath, s: FloatArray, sd: FloatArray, sdd: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """q, q_dot, q_ddot (n, M+1) per ms of the traversal s(t)."""
    q = geom(s, 0).T
    q1 = geom(s, 1).T
    q2 = geom(s, 2).T
    return q, q1 * sd, q2 * sd * sd + q1 * sdd


def ratios(
    v: FloatArray, acc: FloatArray, vlim_ms: FloatArray, alim_ms: FloatArray, jlim_ms: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per ms the largest velocity, acceleration and jerk ratio over the axes (jerk: the change of
    acceleration over the tick before and after, each ms the larger)."""
    vel_ratio = (np.abs(v) / vlim_ms[:, None]).max(axis=0)
    acc_ratio = (np.abs(acc) / alim_ms[:, None]).max(axis=0)
    jerk = (np.abs(np.diff(acc, axis=1)) / jlim_ms[:, None]).max(axis=0)
    pad = np.concatenate([[0.0], jerk, [0.0]])
    return vel_ratio, acc_ratio, np.maximum(pad[:-1], pad[1:])


def plan_jerk_run(
    geom: GeometricPath,
    vlim: FloatArray,
    alim: FloatArray,
    jlim: FloatArray,
    *,
    time_scale: float = 1.0,
    max_duration_ms: float = 900.0e3,
) -> JerkRun:
    """A rest-to-rest, jerk-limited traversal of one geometric path (module docstring)."""
    grid = geom.gridpoints()
    samples = topp.sample_path(geom, grid)
    vlim_ms, alim_ms, jlim_ms = vlim / 1.0e3, alim / 1.0e6, jlim / 1.0e9
    jplan = jlim_ms * PLAN_JERK_SHARE
    row_scale: FloatArray | None = None
    solves = 0
    optimal_ms = 0.0
    widen = 1.0
    sd_topp = np.zeros(0)
    best: tuple[float, FloatArray, float] | None = None  # (excess, solution, widen)

    def evaluate(sol: FloatArray, scale: float, wid: float, min_window: int = 0) -> tuple[FloatArray, ...]:
        prof = Profile(grid, sol, geom, alim, scale)
        s0, _sd0, _al, acc_r = prof.sample()
        acc_ms = acc_r[:-1]
        window = max(int(np.ceil(choose_window(acc_ms, np.abs(geom(s0[:-1], 1)), jlim_ms) * wid)), min_window)
        s, sd, sdd = fir_retime(acc_ms, geom.length, window)
        q, v, acc = joint_motion(geom, s, sd, sdd)
        vr, ar, jr = ratios(v, acc, vlim_ms, alim_ms, jplan)
        # the share of the jerk that comes from the path jerk (the window) rather than the curvature
        q1s = geom(s, 1).T
        path_jerk = np.abs(np.diff(sdd))
        pj = np.concatenate([[0.0], path_jerk])
        pj = np.maximum(pj, np.concatenate([path_jerk, [0.0]]))
        window_part = (np.abs(q1s) * pj[None, :] / jplan[:, None]).max(axis=0)
        return q, v, acc, s, vr, ar, jr, window_part, np.array([float(window), float(prof.duration_ms)])

    out: tuple[FloatArray, ...] | None = None
    for attempt in range(REPAIR_ROUNDS + 1):
        try:
            sd_opt = solve_profile(samples, vlim, alim, row_scale)
            solves += 1
            opt = Profile(grid, sd_opt, geom, alim, time_scale)
            s_opt, _sdo, _alo, acc_opt = opt.sample()
            w_opt = choose_window(acc_opt[:-1], np.abs(geom(s_opt[:-1], 1)), jlim_ms) * widen
            sd_new = solve_capped(samples, vlim, alim, row_scale, dip_caps(grid, sd_opt, w_opt / time_scale))
            solves += 1
        except PlanningError:
            if out is None:
                raise
            break
        sd_topp = sd_new
        if attempt == 0:
            first = Profile(grid, sd_opt, geom, alim, 1.0)
            optimal_ms = first.optimal_ms
            if first.duration_ms * time_scale > max_duration_ms:
                raise PlanningError(
                    TOO_LARGE,
                    f"the path takes at least {first.duration_ms * time_scale / 1000:.1f} s, more than the "
                    f"limit of {max_duration_ms / 1000:g} s",
                    path="waypoints",
                )
        out = evaluate(sd_topp, time_scale, widen)
        _q, _v, _a, s, vr, ar, jr, wpart, _meta = out
        excess = max(float(vr.max()), float(np.sqrt(ar.max())), float(np.cbrt(jr.max())))
        if vr.max() <= 1.0 + VEL_SLACK and ar.max() <= 1.0 + ACC_SLACK and jr.max() <= 1.0:
            break
        if best is None or excess < best[0]:
            best = (excess, sd_topp, widen)
        if attempt == REPAIR_ROUNDS:
            break
        # the window's own share too large where the jerk fails: widen it
        bad = jr > 1.0
        if bad.any() and float(wpart[bad].max()) > 0.8 * float(jr[bad].max()):
            widen *= float(min(jr.max(), 1.5))
        # tighten the rows of the path intervals where a bound fails (jerk ~ s_dot^3: as acc its 2/3 power)
        worst = np.maximum(np.maximum(ar, vr**2), np.maximum(jr, 1.0) ** (2.0 / 3.0))
        idx = np.clip(np.searchsorted(grid, s, side="right") - 1, 0, grid.size - 2)
        ratio = np.ones(grid.size)
        np.maximum.at(ratio, idx, worst)
        np.maximum.at(ratio, idx + 1, worst)
        # a neighbourhood: the averaging reaches back a window's worth of path
        for _ in range(3):
            ratio[1:] = np.maximum(ratio[1:], ratio[:-1])
            ratio[:-1] = np.maximum(ratio[:-1], ratio[1:])
        ratio = np.where(ratio > 1.0, ratio * (1.0 + 3 * ACC_SLACK), 1.0)
        step = np.stack([ratio, ratio], axis=1)
        row_scale = step if row_scale is None else row_scale * step
    assert out is not None
    scale = time_scale
    q, v, acc, s, vr, ar, jr, _wp, meta = out
    if not (vr.max() <= 1.0 + VEL_SLACK and ar.max() <= 1.0 + ACC_SLACK and jr.max() <= 1.0):
        if best is not None and best[0] < max(float(vr.max()), float(np.sqrt(ar.max())), float(np.cbrt(jr.max()))):
            sd_topp, widen = best[1], best[2]
        for _ in range(12):
            over = max(float(vr.max()) / (1.0 + VEL_SLACK), float(np.sqrt(ar.max() / (1.0 + ACC_SLACK))),
                       float(np.cbrt(jr.max())), 1.0)
            # the same motion played slower: its window stretched with it (a window chosen anew on the
            # slower profile's smaller accelerations would be shorter, and the jerk would not fall)
            factor = over * (1.0 + 1e-3)
            scale *= factor
            stretched = int(np.ceil(meta[0] * factor))
            q, v, acc, s, vr, ar, jr, _wp, meta = evaluate(sd_topp, scale, widen, stretched)
            if vr.max() <= 1.0 + VEL_SLACK and ar.max() <= 1.0 + ACC_SLACK and jr.max() <= 1.0:
                break
        else:
            raise PlanningError(
                INFEASIBLE,
                f"no jerk-limited traversal found within the limits (velocity {vr.max():.3f}, acceleration "
                f"{ar.max():.3f}, jerk {jr.max():.3f} of the limits after slowing down {scale:.2f}x)",
                detail={"stage": "jerk"},
            )
    return JerkRun(q, v, acc, optimal_ms, int(meta[0]), solves, scale / time_scale)


SWITCH_SHARE = 0.15  # of the jerk limit: a change of some joint's jerk within one ms that makes a hint ...
SWITCH_GAP_MS = 8  # ... at least this far from a larger one


def jerk_switches(acc: FloatArray, jlim_ms: FloatArray) -> IntArray:
    """The ms where some joint's jerk changes fastest (by at least `SWITCH_SHARE` of its limit within one
    ms), at least `SWITCH_GAP_MS` apart, the largest first: the ends of what is nearly a cubic on either
    side, where the encoder's sections end (`Reference.hints`). Measured on 8 paths planned "fastest"
    (demo-path, bench-20, 6 random): the largest knot step over all axes 1.47 and 1.23 x the bound on the
    first two with them, 1.61 and 1.35 without; 1.33 and 1.35 in median; a share of 0.08 or 0.3: no better."""
    jerk = np.diff(acc, axis=1) / jlim_ms[:, None]  # over ms m..m+1
    change = np.abs(np.diff(jerk, axis=1)).max(axis=0)  # at ms m+1
    taken = np.zeros(acc.shape[1], dtype=bool)
    out = []
    for k in np.argsort(-change, kind="stable"):
        if change[k] < SWITCH_SHARE:
            break
        m = int(k) + 1
        if 0 < m < acc.shape[1] - 1 and not taken[max(0, m - SWITCH_GAP_MS + 1) : m + SWITCH_GAP_MS].any():
            taken[m] = True
            out.append(m)
    return np.array(sorted(out), dtype=np.int64)


def plan_fastest_run(
    geom: GeometricPath, vlim: FloatArray, alim: FloatArray, jlim: FloatArray, *, time_scale: float = 1.0
) -> JerkRun | None:
    """A rest-to-rest, jerk-limited traversal of one geometric path at the third-order time-optimal speed
    (`jerk_timing = "fastest"`: planner/motion/jerk_scp.py), played `time_scale` times slower and checked at
    every ms like every run here (`ratios`, the jerk within `PLAN_JERK_SHARE`), slower where that fails.
    None when the solver finds nothing or the check still fails after `jerk_scp.REPLAYS` slower replays."""
    from planner.motion import jerk_scp

    jplan = jlim * PLAN_JERK_SHARE
    solved = jerk_scp.solve_speed(geom, vlim, alim, jplan)
    if solved is None:
        return None
    speed, solves = solved
    vlim_ms, alim_ms, jplan_ms = vlim / 1.0e3, alim / 1.0e6, jplan / 1.0e9
    slow = time_scale
    for _ in range(jerk_scp.REPLAYS + 1):
        s, sd, sdd = speed.play(slow)
        q, v, acc = joint_motion(geom, s, sd, sdd)
        vr, ar, jr = ratios(v, acc, vlim_ms, alim_ms, jplan_ms)
        over = max(float(vr.max()) / (1.0 + VEL_SLACK), float(np.sqrt(ar.max() / (1.0 + ACC_SLACK))),
                   float(np.cbrt(jr.max())))
        if over <= 1.0:
            return JerkRun(q, v, acc, 0.0, 0, solves, slow / time_scale, jerk_switches(acc, jplan_ms))
        slow *= over * (1.0 + 1.0e-3)
    return None


def plan_jerk_path(
    runs: Sequence[GeometricPath],
    counts_per_unit: FloatArray,
    vlim: FloatArray,
    alim: FloatArray,
    jlim: FloatArray,
    *,
    time_scale: float = 1.0,
    max_duration_s: float = 900.0,
    fastest: bool = False,
) -> tuple[Reference, dict[str, float]]:
    """Reference (counts) for the runs played one after the other, each rest to rest, jerk-limited. With
    `fastest` (`jerk_timing = "fastest"`), each run at the third-order time-optimal speed
    (`plan_fastest_run`) where that is found and shorter.

    Info: `optimal_s` (the acceleration-only optimum on the same grids, summed over the runs),
    `jerk_window_ms` (the longest averaging window), `jerk_slowdown` (the largest slow-down a run's repairs
    needed), `topp_solves` (a fastest run's: its LPs), `runs`; with `fastest`, `jerk_fastest_runs` (the runs
    at that speed)."""
    plans: list[JerkRun] = []
    spent = 0.0
    fastest_runs = 0
    for geom in runs:
        corner = plan_corner_run(geom, vlim, alim, jlim, time_scale=time_scale)
        if corner is not None:
            grid = geom.gridpoints()
            optimum = Profile(grid, solve_profile(topp.sample_path(geom, grid), vlim, alim), geom, alim).optimal_ms
            rp = JerkRun(corner.q, corner.v, corner.acc, optimum, 0, 1, corner.time_scale, corner.hints)
        else:
            rp = plan_jerk_run(
                geom, vlim, alim, jlim, time_scale=time_scale, max_duration_ms=max_duration_s * 1000.0 - spent
            )
        fast = plan_fastest_run(geom, vlim, alim, jlim, time_scale=time_scale) if fastest else None
        if fast is not None and fast.q.shape[1] < rp.q.shape[1]:
            rp = replace(fast, optimal_ms=rp.optimal_ms)
            fastest_runs += 1
        spent += rp.q.shape[1] - 1
        plans.append(rp)
    if spent > max_duration_s * 1000.0:
        raise PlanningError(
            TOO_LARGE,
            f"the path takes {spent / 1000:.1f} s, more than the limit of {max_duration_s:g} s",
            path="waypoints",
        )
    q = np.concatenate([plans[0].q] + [p.q[:, 1:] for p in plans[1:]], axis=1)
    v = np.concatenate([plans[0].v] + [p.v[:, 1:] for p in plans[1:]], axis=1)
    acc = np.concatenate([plans[0].acc] + [p.acc[:, 1:] for p in plans[1:]], axis=1)
    cpu = counts_per_unit[:, None]
    starts = np.concatenate([[0], np.cumsum([p.q.shape[1] - 1 for p in plans])]).astype(np.int64)
    hints = np.concatenate([p.hints + starts[k] for k, p in enumerate(plans)] + [starts[1:-1]])
    empty: IntArray = np.zeros(0, dtype=np.int64)
    ref = Reference(q * cpu, v * cpu, acc * cpu, acc * cpu, empty, hints.astype(np.int64))
    info = {
        "optimal_s": sum(p.optimal_ms for p in plans) / 1000.0,
        "jerk_window_ms": float(max(p.window_ms for p in plans)),
        "jerk_slowdown": float(max(p.time_scale for p in plans)),
        "topp_solves": float(sum(p.solves for p in plans)),
        "runs": float(len(plans)),
    }
    if fastest:
        info["jerk_fastest_runs"] = float(fastest_runs)
    return ref, info


# ----------------------------------------------------------------------------------------------------
# blended corners at constant speed, jerk-limited moves between them (`plan_corner_run`)

CORNER_MARGIN = 0.98  # of each corner's speed bound (its curvature's q''' sampled, not exact)
_CORNER_SAMPLES = 401


def _change(dv: float, a: float, j: float) -> float:
    """Time (s) of the fastest jerk-limited change of speed by `dv` from and to zero acceleration."""
    dv = abs(dv)
    return 2.0 * float(np.sqrt(dv / j)) if dv <= a * a / j else dv / a + a / j


def _reach(v: float, length: float, vmax: float, a: float, j: float) -> float:
    """The largest speed (at most `vmax`) a jerk-limited change from `v` reaches within `length`: the
    change's velocity is symmetric in time, so it covers (v + v') / 2 times its duration."""
    if 0.5 * (v + vmax) * _change(vmax - v, a, j) <= length:
        return vmax
    lo, hi = 0.0, vmax
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if 0.5 * (v + mid) * _change(mid - v, a, j) <= length:
            lo = mid
        else:
            hi = mid
    return lo


def _line_move(length: float, v_in: float, v_out: float, vmax: float, a: float, j: float) -> Any:
    """ruckig's time-optimal 1-DoF motion along a line piece, from speed `v_in` to `v_out` at zero acceleration."""
    from planner.motion.jerk import line_input, solve_ruckig

    return solve_ruckig(line_input(length, vmax, a, j, v_in=v_in, v_out=v_out), 1)


def _phases(traj: Any) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Start times and start states (p, v, a) and jerks of a 1-DoF ruckig profile's phases, then a hold."""
    prof = traj.profiles[0][0]
    durs = [prof.t[k] for k in range(7)]
    starts = np.concatenate([[0.0], np.cumsum(durs)])
    p = np.array([prof.p[k] for k in range(8)])
    v = np.array([prof.v[k] for k in range(8)])
    a = np.array([prof.a[k] for k in range(8)])
    jj = np.array([prof.j[k] for k in range(7)] + [0.0])
    return starts, p, v, a, jj


@dataclass(frozen=True, eq=False)
class _Line:
    """A straight piece: q = start + direction * x for x in [0, length] (direction: dq/ds of the path)."""

    start: FloatArray
    direction: FloatArray
    length: float


@dataclass(frozen=True, eq=False)
class _Blend:
    """A blend of the geometry, s in [s0, s1], crossed at the constant path speed `cap` at most."""

    geom: Any
    s0: float
    s1: float
    cap: float


def _line_limits(u: FloatArray, vlim: FloatArray, alim: FloatArray, jplan: FloatArray) -> tuple[float, float, float]:
    moving = np.abs(u) > 1.0e-12 * float(np.abs(u).max())  # an axis that barely moves limits nothing
    au = np.abs(u[moving])
    return (float(np.min(vlim[moving] / au)), float(np.min(alim[moving] / au)), float(np.min(jplan[moving] / au)))


def _blend_cap(geom: Any, s0: float, s1: float, vlim: FloatArray, alim: FloatArray, jplan: FloatArray) -> float:
    """The constant path speed at which every joint keeps its velocity, acceleration (q'' s'^2) and jerk
    (q''' s'^3, q''' from q'' sampled densely) limits along the blend, less `CORNER_MARGIN`."""
    s = np.linspace(s0, s1, _CORNER_SAMPLES)
    q1, q2 = np.abs(geom(s, 1)), geom(s, 2)
    q3 = np.abs(np.gradient(q2, s, axis=0))
    q2 = np.abs(q2)
    with np.errstate(divide="ignore"):
        bounds = (
            float(np.min(vlim[None, :] / q1)),
            float(np.sqrt(np.min(alim[None, :] / q2))),
            float(np.cbrt(np.min(jplan[None, :] / q3))),
        )
    return CORNER_MARGIN * min(bounds)


def _geometry_pieces(geom: Any, vlim: FloatArray, alim: FloatArray, jplan: FloatArray) -> list[_Line | _Blend] | None:
    """The pieces of a run of straight pieces and blends (planner/motion/geometry.py), None for other geometries."""
    blends = getattr(geom, "blends", None)
    bp = getattr(geom, "breakpoints", None)
    if blends is None or bp is None:
        return None
    out: list[_Line | _Blend] = []
    for p in range(int(blends.size)):
        s0, s1 = float(bp[p]), float(bp[p + 1])
        if blends[p]:
            out.append(_Blend(geom, s0, s1, _blend_cap(geom, s0, s1, vlim, alim, jplan)))
        else:
            u = geom(np.array([0.5 * (s0 + s1)]), 1)[0]
            if not np.any(u != 0.0):
                return None
            out.append(_Line(geom(np.array([s0]), 0)[0], u, s1 - s0))
    return out


def _corner_point(before: _Line, after: _Line) -> tuple[float, float]:
    """Where two straight pieces meet (their corner, the waypoint): the length of `before` to it and where
    `after` starts from it (negative: before its start), by least squares of their two lines."""
    m = np.stack([before.direction, -after.direction], axis=1)
    x, *_ = np.linalg.lstsq(m, after.start - before.start, rcond=None)
    return float(x[0]), float(x[1])


def _with_stops(pieces: list[_Line | _Blend], stops: Sequence[bool]) -> tuple[list[_Line | _Blend], list[int]]:
    """The pieces with the blends flagged in `stops` (one flag per blend, in order) replaced by the corner
    itself: the straight piece before goes on to the waypoint, the one after starts there. Returns the
    pieces and the boundaries (indices into the pieces' boundaries) where the motion stops."""
    out: list[_Line | _Blend] = []
    at_rest: list[int] = []
    b = 0
    k = 0
    while k < len(pieces):
        piece = pieces[k]
        if isinstance(piece, _Blend):
            stop = stops[b]
            b += 1
            prev, nxt = out[-1], pieces[k + 1]
            if stop and isinstance(prev, _Line) and isinstance(nxt, _Line):
                to_corner, from_corner = _corner_point(prev, nxt)
                out[-1] = _Line(prev.start, prev.direction, to_corner)
                corner = prev.start + prev.direction * to_corner
                out.append(_Line(corner, nxt.direction, nxt.length - from_corner))
                at_rest.append(len(out) - 1)
                k += 2
                continue
        out.append(piece)
        k += 1
    return out, at_rest


def _speeds(
    pieces: list[_Line | _Blend], at_rest: Sequence[int], vlim: FloatArray, alim: FloatArray, jplan: FloatArray
) -> FloatArray:
    """The path speed at every boundary of the pieces: 0 at the ends and at the stops, a blend's speed at
    its boundaries, lowered by a forward and a backward pass until every straight piece can connect its
    two speeds (`_reach`: a jerk-limited change of speed is symmetric in time)."""
    n = len(pieces)
    speed = np.full(n + 1, np.inf)
    speed[0] = speed[-1] = 0.0
    speed[list(at_rest)] = 0.0
    lines: dict[int, tuple[float, float, float]] = {}
    for p, piece in enumerate(pieces):
        if isinstance(piece, _Blend):
            speed[p] = min(speed[p], piece.cap)
            speed[p + 1] = min(speed[p + 1], piece.cap)
        else:
            lines[p] = _line_limits(piece.direction, vlim, alim, jplan)
            speed[p] = min(speed[p], lines[p][0])
            speed[p + 1] = min(speed[p + 1], lines[p][0])
    kinds = np.array([isinstance(x, _Blend) for x in pieces])
    # a group of blends in a row: one speed
    p = 0
    while p < n:
        if kinds[p]:
            q = p
            while q + 1 < n and kinds[q + 1]:
                q += 1
            speed[p : q + 2] = speed[p : q + 2].min()
            p = q + 1
        else:
            p += 1
    order = sorted(lines)
    for p in order:
        vmax, a, j = lines[p]
        speed[p + 1] = min(speed[p + 1], _reach(float(speed[p]), pieces[p].length, vmax, a, j))  # type: ignore[union-attr]
        _spread(speed, kinds, p + 1)
    for p in order[::-1]:
        vmax, a, j = lines[p]
        speed[p] = min(speed[p], _reach(float(speed[p + 1]), pieces[p].length, vmax, a, j))  # type: ignore[union-attr]
        _spread(speed, kinds, p, backward=True)
    return speed


def _corner_motion(
    pieces: list[_Line | _Blend],
    at_rest: Sequence[int],
    vlim: FloatArray,
    alim: FloatArray,
    jlim: FloatArray,
    time_scale: float,
) -> JerkRun | None:
    """The motion through `pieces` (module docstring of `plan_corner_run`), sampled at every ms and checked."""
    jplan = jlim * PLAN_JERK_SHARE
    speed = _speeds(pieces, at_rest, vlim, alim, jplan)
    timed: list[tuple[float, Any]] = []  # (duration s, ruckig phases or the blend's speed)
    for p, piece in enumerate(pieces):
        if isinstance(piece, _Blend):
            cross = float(speed[p])
            if cross <= 0.0:
                return None
            timed.append(((piece.s1 - piece.s0) / cross, cross))
        else:
            if piece.length <= 0.0:
                if speed[p] > 0.0 or speed[p + 1] > 0.0:
                    return None
                timed.append((0.0, None))
                continue
            vmax, a, j = _line_limits(piece.direction, vlim, alim, jplan)
            traj = _line_move(piece.length, float(speed[p]), float(speed[p + 1]), vmax, a, j)
            timed.append((float(traj.duration), _phases(traj)))
    total = sum(d for d, _x in timed)
    if total <= 0.0:
        return None
    starts = np.concatenate([[0.0], np.cumsum([d for d, _x in timed])])
    vlim_ms, alim_ms, jlim_ms = vlim / 1.0e3, alim / 1.0e6, jlim / 1.0e9
    n_axes = vlim.size
    scale = time_scale
    for _ in range(12):
        m = max(int(np.ceil(total * 1000.0 * scale - 1e-6)), 1)
        lam = m / (total * 1000.0)  # >= scale: the run played lam times slower, on whole ms
        t = np.arange(m + 1) / (lam * 1000.0)  # the unscaled time of every ms (s)
        t[-1] = total
        q = np.empty((n_axes, m + 1))
        v = np.empty((n_axes, m + 1))
        acc = np.empty((n_axes, m + 1))
        idx = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(pieces) - 1)
        while True:  # a zero-length piece takes no ms: its ms belong to the next one
            empty = np.array([timed[k][0] <= 0.0 for k in idx]) & (idx < len(pieces) - 1)
            if not empty.any():
                break
            idx[empty] += 1
        f1, f2 = 1.0 / (lam * 1000.0), 1.0 / (lam * 1000.0) ** 2
        for k, (dur, data) in enumerate(timed):
            sel = idx == k
            if not sel.any():
                continue
            dt = np.minimum(t[sel] - starts[k], dur)
            piece = pieces[k]
            if isinstance(piece, _Blend):
                x = np.minimum(piece.s0 + data * dt, piece.s1)
                qb, q1b, q2b = (piece.geom(x, o).T for o in range(3))
                q[:, sel], v[:, sel], acc[:, sel] = qb, q1b * data * f1, q2b * (data * f1) ** 2
            else:
                ps, p0, v0, a0, j0 = data
                ph = np.clip(np.searchsorted(ps, dt, side="right") - 1, 0, 7)
                x = dt - ps[ph]
                xs = np.clip(p0[ph] + x * (v0[ph] + x * (a0[ph] / 2.0 + x * j0[ph] / 6.0)), 0.0, piece.length)
                xd = v0[ph] + x * (a0[ph] + x * j0[ph] / 2.0)
                xdd = a0[ph] + x * j0[ph]
                u = piece.direction[:, None]
                q[:, sel], v[:, sel], acc[:, sel] = piece.start[:, None] + u * xs, u * xd * f1, u * xdd * f2
        last = pieces[-1]
        q[:, -1] = last.start + last.direction * last.length if isinstance(last, _Line) else last.geom(
            np.array([last.s1]), 0)[0]
        v[:, -1] = 0.0
        acc[:, -1] = 0.0
        vr, ar, jr = ratios(v, acc, vlim_ms, alim_ms, jlim_ms * PLAN_JERK_SHARE)
        over = max(float(vr.max()) / (1.0 + VEL_SLACK), float(np.sqrt(ar.max() / (1.0 + ACC_SLACK))),
                   float(np.cbrt(jr.max())))
        if over <= 1.0:
            # where the jerk changes: the pieces' ends and the ruckig phases' (on the nearest ms)
            switch = [starts[k] + (data[0][1:-1] if isinstance(data, tuple) else np.zeros(0))
                      for k, (_d, data) in enumerate(timed)]
            at = np.round(np.concatenate([starts[1:-1], *switch]) * lam * 1000.0).astype(np.int64)
            hints = np.unique(at[(at > 0) & (at < m)])
            return JerkRun(q, v, acc, 0.0, 0, 0, lam / time_scale, hints)
        scale = lam * over * (1.0 + 1e-3)
    return None


def _choose_stops(
    pieces: list[_Line | _Blend], vlim: FloatArray, alim: FloatArray, jplan: FloatArray
) -> list[bool]:
    """Which blended corners are faster as stops: a Viterbi pass over the corners, each blended (crossed at
    its speed) or a stop at the waypoint, costed by the time of the straight pieces between them (ruckig,
    their end speeds each limited by what the piece can reach from the other) and of the blends."""
    blends = [k for k, x in enumerate(pieces) if isinstance(x, _Blend)]
    if not blends or any(not isinstance(pieces[k - 1], _Line) or not isinstance(pieces[k + 1], _Line)
                         for k in blends):
        return [False] * len(blends)
    corners = [_corner_point(pieces[k - 1], pieces[k + 1]) for k in blends]  # type: ignore[arg-type]

    def line_time(k: int, stop_before: bool | None, stop_after: bool | None) -> float:
        """Time of straight piece k with the corner before it (None: the run's start) and after it."""
        line = pieces[k]
        assert isinstance(line, _Line)
        length = line.length
        v_in = v_out = 0.0
        if stop_before is not None:
            c = blends.index(k - 1)
            if stop_before:
                length -= corners[c][1]
            else:
                v_in = pieces[k - 1].cap  # type: ignore[union-attr]
        if stop_after is not None:
            c = blends.index(k + 1)
            if stop_after:
                length += corners[c][0] - line.length
            else:
                v_out = pieces[k + 1].cap  # type: ignore[union-attr]
        vmax, a, j = _line_limits(line.direction, vlim, alim, jplan)
        v_in, v_out = min(v_in, vmax), min(v_out, vmax)
        if length <= 0.0:
            return np.inf if (v_in > 0 or v_out > 0) else 0.0
        v_out = min(v_out, _reach(v_in, length, vmax, a, j))
        v_in = min(v_in, _reach(v_out, length, vmax, a, j))
        try:
            return float(_line_move(length, v_in, v_out, vmax, a, j).duration)
        except PlanningError:
            return np.inf

    def blend_time(c: int) -> float:
        b = pieces[blends[c]]
        assert isinstance(b, _Blend)
        return (b.s1 - b.s0) / b.cap

    nc = len(blends)
    # cost[c][choice]: the best time up to corner c with that choice (0 blend, 1 stop), back pointers
    cost = np.array([line_time(blends[0] - 1, None, False) + blend_time(0), line_time(blends[0] - 1, None, True)])
    back: list[IntArray] = []
    for c in range(1, nc):
        k = blends[c] - 1
        new = np.empty(2)
        arg = np.zeros(2, dtype=np.int64)
        for choice in (0, 1):
            options = [cost[prev] + line_time(k, bool(prev), bool(choice)) for prev in (0, 1)]
            arg[choice] = int(np.argmin(options))
            new[choice] = options[arg[choice]] + (blend_time(c) if choice == 0 else 0.0)
        back.append(arg)
        cost = new
    last = blends[-1] + 1
    final = [cost[ch] + line_time(last, bool(ch), None) for ch in (0, 1)]
    choice = int(np.argmin(final))
    out = [choice]
    for arg in reversed(back):
        choice = int(arg[choice])
        out.append(choice)
    out.reverse()
    return [bool(x) for x in out]


def plan_corner_run(
    geom: Any, vlim: FloatArray, alim: FloatArray, jlim: FloatArray, *, time_scale: float = 1.0
) -> JerkRun | None:
    """A rest-to-rest, jerk-limited traversal of one run of straight pieces and blends (planner/motion/geometry.py).

    Every blend is crossed at a constant path speed (there the joints' acceleration is q'' s'^2 and their
    jerk q''' s'^3: the speed is the largest that keeps both, and the joint velocity, within the limits),
    or, where that is faster, the corner is a stop on its waypoint instead (`_choose_stops`); every
    straight piece is a time-optimal jerk-limited 1-DoF motion (ruckig) between the speeds at its two
    ends at zero path acceleration, so the acceleration is continuous where a piece meets a blend (a
    blend's q'' is 0 at its ends). Speeds no piece can connect are lowered by a forward and a backward
    pass (`_speeds`). The run is played slower to end on a whole ms and wherever the check at every ms
    (velocity, acceleration, jerk within `PLAN_JERK_SHARE`) needs it. Of the plan with the chosen stops and
    the one blending every corner, the shorter. None when `geom` is not made of straight pieces and blends."""
    jplan = jlim * PLAN_JERK_SHARE
    pieces = _geometry_pieces(geom, vlim, alim, jplan)
    if pieces is None:
        return None
    candidates = [_corner_motion(pieces, [], vlim, alim, jlim, time_scale)]
    stops = _choose_stops(pieces, vlim, alim, jplan)
    if any(stops):
        mixed, at_rest = _with_stops(pieces, stops)
        candidates.append(_corner_motion(mixed, at_rest, vlim, alim, jlim, time_scale))
    found = [c for c in candidates if c is not None]
    if not found:
        return None
    return min(found, key=lambda c: c.q.shape[1])


def _spread(speed: FloatArray, kinds: NDArray[np.bool_], boundary: int, backward: bool = False) -> None:
    """A blend group keeps one speed: a lowered boundary speed lowers the group it starts (or ends)."""
    n = kinds.size
    if not backward:
        p = boundary
        while p < n and kinds[p]:
            speed[p + 1] = min(speed[p + 1], speed[p])
            p += 1
    else:
        p = boundary - 1
        while p >= 0 and kinds[p]:
            speed[p] = min(speed[p], speed[p + 1])
            p -= 1
