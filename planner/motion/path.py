"""Time-optimal traversal of a geometric path (TOPP-RA), re-timed onto whole milliseconds.

Per rest-to-rest run: the geometry (planner/motion/geometry.py's blends, or a C2 spline,
`SplineGeometry`) in time-normalised arc length squeezed into [0.01, 2] (toppra's seidel solver, the
reference, fails spuriously on long parametrisations); the time-optimal profile (planner/motion/topp.py)
with the limits also at interior points of each interval (`topp.THETAS`: the profile overshoots between
gridpoints otherwise); re-timing every breakpoint onto a whole ms (`Profile`: a Hermite segment cannot
follow an acceleration step inside it); for blends, the Hermite chain (planner/encoding/chain.py), for a
single straight segment the closed-form trapezoid (`straight_run`). Verification at every ms: overshoots
tighten their rows and solve again (`REPAIR_ROUNDS`), a residual is played slower (`RESCALE_SHARE`,
`SLOWER_LADDER`: a refitted chain's pass is not monotone in the slow-down). docs/formats.md ("path") has
the measured durations.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray

from planner.errors import INFEASIBLE, TOO_LARGE, PlanningError
from planner.jit import kernel
from planner.motion import topp
from planner.motion.reference import FloatArray, IntArray, Reference
from planner.motion.topp import PathSamples

if TYPE_CHECKING:
    from planner.encoding.chain import ChainFit

# one evaluation of a profile (plan_run): q, v, acc_left, acc_right, the chain (if any), acc and vel ratios
_Evaluation = tuple[FloatArray, FloatArray, FloatArray, FloatArray, "ChainFit | None", FloatArray, FloatArray]

REPAIR_ROUNDS = 3
MAX_DURATION_S = 900.0
RESCALE_SHARE = 0.005  # a residual overshoot needing less slow-down than this is fixed by slowing down
STEP_SHARE = 0.15  # a path-acceleration step above this share of a joint's limit is a switch
CHATTER_MS = 8  # big steps closer than this are chattering, not switches (`_switch_mask`)
SWITCH_SHARE = 0.35  # a step above this share that stands alone is a real switch (a chain's knot)
ACC_SLACK = 1.0e-3  # planned acceleration may exceed the limit by this share (numerical noise)
VEL_SLACK = 1.0e-4
# extra slow-downs tried for a chain's small residual overshoot (plan_run): a chain is fitted anew on
# each, so whether it passes is not monotone in the slow-down (measured on a 17 s 6-axis path: 0.08 %
# slower overshoots by 10.6 %, 0.1 % passes, 0.13 % overshoots by 6 %, 0.4 % passes)
SLOWER_LADDER = (1e-4, 1e-3, 2.5e-3, 5e-3)
# a chain's first solve keeps this share below the limits in the blends' rows (acceleration and velocity):
# there q'' changes within a grid interval and the chain's short segments overshoot the solved profile by a
# few tenths of a percent, each overshoot a repair round (solve + chain fit). Measured on 400 random blended
# paths (benchmarks/bench_planner.py's corpus): solves 561 -> 510, planning CPU -9 %, durations unchanged
# (median ratio 1.0000, mean -0.005 %); 0.1 % saved fewer solves (537), 0.3 % (517) and on every row,
# lines included (519, durations +0.06 % mean) no more
BLEND_MARGIN = 2.0e-3


def grid_size(n_waypoints: int) -> int:
    """Gridpoints for the solver: ~20 per waypoint interval (duration within 0.5 % of a fine grid)."""
    return int(min(1500, max(100, 20 * (n_waypoints - 1) + 40)))


class GeometricPath(Protocol):
    """What the solver and the re-timing evaluate: q(s) and its derivatives on [0, length]."""

    @property
    def length(self) -> float: ...

    @property
    def dof(self) -> int: ...

    def __call__(self, s: FloatArray, order: int = 0) -> FloatArray: ...

    @property
    def breakpoints(self) -> FloatArray: ...  # s where q(s)'s pieces meet (0 and length included)

    def gridpoints(self) -> FloatArray: ...

    def merge_safe(self, s: FloatArray) -> NDArray[np.bool_]: ...

    def trace(self, s: FloatArray, sd: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]: ...


class SplineGeometry:
    """The C2 spline through the waypoints (user units), parametrised by scaled chord length
    (`geometry = "spline"`)."""

    def __init__(self, waypoints: FloatArray, velocity_limits: FloatArray, shape: str = "spline"):
        from scipy.interpolate import CubicSpline, PchipInterpolator

        d = np.linalg.norm(np.diff(waypoints, axis=0) / velocity_limits[None, :], axis=1)
        ss = np.concatenate([[0.0], np.cumsum(d)])
        # keep s well scaled: toppra's seidel solver (the reference of ours) reports spurious "uncontrollable"
        # failures on long parametrisations (measured here: erratic from a path length of 5, never from
        # 1e-2 to 3), whatever the motion, so long paths are squeezed to a length of 2
        if ss[-1] < 1e-2:
            ss = ss * (1e-2 / ss[-1])
        elif ss[-1] > 2.0:
            ss = ss * (2.0 / ss[-1])
        self.ss: FloatArray = ss
        self.waypoints = waypoints
        if shape == "pchip":
            # The fallback for one axis (plan.py): a C2 spline through uneven back-and-forth steps
            # (0.60 -> 0.62 -> 0.60 -> -0.20) swings far past them (to -3 on the demo's j1 column).
            # The shape-preserving cubic (PCHIP, C1) moves monotonically between waypoints and comes to
            # rest at every reversal, where a single axis has to stop anyway. Its acceleration steps
            # at the waypoints make the re-timing slower than the time-optimal profile (up to ~2x measured).
            self.spline = PchipInterpolator(self.ss, waypoints, axis=0)
        else:
            self.spline = CubicSpline(self.ss, waypoints, bc_type="not-a-knot", axis=0)
        self.d1 = self.spline.derivative(1)
        self.d2 = self.spline.derivative(2)
        self.d3 = self.spline.derivative(3)

    @property
    def length(self) -> float:
        return float(self.ss[-1])

    @property
    def breakpoints(self) -> FloatArray:
        """The waypoints' s: the ends of the cubic pieces, where the third derivative jumps."""
        return self.ss

    @property
    def dof(self) -> int:
        return int(self.waypoints.shape[1])

    def __call__(self, s: FloatArray, order: int = 0) -> FloatArray:
        f = (self.spline, self.d1, self.d2, self.d3)[order]
        out: FloatArray = np.asarray(f(s), dtype=np.float64)
        return out

    def gridpoints(self) -> FloatArray:
        out: FloatArray = np.linspace(0.0, self.length, grid_size(self.waypoints.shape[0]))
        return out

    def merge_safe(self, s: FloatArray) -> NDArray[np.bool_]:
        """Where short switch pieces may be merged (`_merge_switch_pieces`): everywhere on a spline, as
        measured on the spline paths it was made for."""
        return np.ones(np.shape(s), dtype=bool)

    def trace(self, s: FloatArray, sd: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
        """q, q' sd, q' (len(s), n) and where the path curves for the chain (not where `merge_safe`) along a
        traversal."""
        q1 = self(s, 1)
        return self(s, 0), q1 * np.asarray(sd)[:, None], q1, ~self.merge_safe(s)


def solve_profile(
    samples: PathSamples, vlim: FloatArray, alim: FloatArray, row_scale: FloatArray | None = None
) -> FloatArray:
    """The optimal path velocities s_dot at the gridpoints (motion/topp.py; raises PlanningError(INFEASIBLE))."""
    return topp.solve(samples, vlim, alim, row_scale)


class Profile:
    """A path-velocity profile on the drive's clock: constant path acceleration per piece, every
    breakpoint on a whole millisecond.

    Built from the solver's gridpoint velocities: the total time is rounded up to whole ms (the motion is
    played that little bit slower), the path velocity is taken at the gridpoint times rounded to whole
    ms and interpolated linearly in time between them. Each piece's path acceleration is then the
    secant of the solver's profile over it, an average of the solver's own neighbouring accelerations, so it
    never exceeds them. Pieces shorter than `min_piece_ms` between two switches are merged (see
    `_merge_switch_pieces`). `switches` lists the breakpoints where some joint's acceleration steps by
    more than `STEP_SHARE` of its limit: the encoder puts a knot on each.
    """

    def __init__(
        self,
        gridpoints: FloatArray,
        sd: FloatArray,
        geom: GeometricPath,
        alim: FloatArray,
        time_scale: float = 1.0,
        min_piece_ms: int = 1,
    ):
        ds = np.diff(gridpoints)
        vsum = sd[:-1] + sd[1:]
        if np.any(vsum <= 0):
            raise PlanningError(
                INFEASIBLE,
                "the time-optimal profile stops inside the path",
                detail={"solver": "topp-ra", "return_code": "ZeroVelocity"},
            )
        t_ms = np.concatenate([[0.0], np.cumsum(2.0 * ds / vsum)]) * 1000.0
        self.optimal_ms = float(t_ms[-1])
        self.duration_ms = max(int(np.ceil(self.optimal_ms * time_scale - 1e-6)), 1)
        lam = self.duration_ms / self.optimal_ms
        tp = t_ms * lam
        vp = sd / 1000.0 / lam  # path units per ms
        tau = np.unique(np.concatenate([[0], np.round(tp).astype(np.int64), [self.duration_ms]]))
        vt = np.interp(tau, tp, vp)
        vt[0] = 0.0
        vt[-1] = 0.0
        tau, vt = _merge_switch_pieces(tau, vt, geom, alim, min_piece_ms)
        h = np.diff(tau).astype(np.float64)
        s_at = np.concatenate([[0.0], np.cumsum(0.5 * (vt[:-1] + vt[1:]) * h)])
        sig = geom.length / s_at[-1]  # land exactly on the path's end
        self.tau: IntArray = tau.astype(np.int64)
        self.v: FloatArray = vt * sig
        self.s: FloatArray = s_at * sig
        self.w: FloatArray = np.diff(self.v) / h  # path acceleration of each piece, per ms^2
        self._geom, self._alim = geom, alim

    # the switch lists, each computed when a plan asks for it (a chain needs one of the last two)
    @functools.cached_property
    def _steps(self) -> FloatArray:
        return _joint_steps(self.tau, self.v, self._geom, self._alim)

    @functools.cached_property
    def switches(self) -> IntArray:
        out: IntArray = self.tau[1:-1][self._steps > STEP_SHARE]
        return out

    @functools.cached_property
    def real_switches(self) -> IntArray:
        out: IntArray = self.tau[1:-1][_switch_mask(self.tau, self.v, self._steps, self._geom)]
        return out

    @functools.cached_property
    def long_switches(self) -> IntArray:
        """With every big step on a straight piece (for a chain without short segments: `_switch_mask`)."""
        out: IntArray = self.tau[1:-1][_switch_mask(self.tau, self.v, self._steps, self._geom, True)]
        return out

    def sample(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """s, s_dot, s_ddot (left), s_ddot (right) at every ms 0..M."""
        return _sample_profile(self.tau, self.s, self.v, self.w)


@kernel
def _sample_profile(
    tau: IntArray, s: FloatArray, v: FloatArray, w: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """`Profile.sample`: every ms m in the piece j with tau_j <= m < tau_j+1 (the end in the last one)."""
    total = tau[-1] + 1
    pieces = w.size
    s_ms, sd, acc_left, acc_right = np.empty(total), np.empty(total), np.empty(total), np.empty(total)
    j = 0
    for m in range(total):
        while j + 1 < pieces and tau[j + 1] <= m:
            j += 1
        x = float(m - tau[j])
        s_ms[m] = min(max(s[j] + (v[j] + 0.5 * w[j] * x) * x, 0.0), s[-1])
        sd[m] = max(v[j] + w[j] * x, 0.0)
        acc_right[m] = w[j]
        acc_left[m] = w[j - 1] if m == tau[j] and j > 0 else w[j]
    return s_ms, sd, acc_left, acc_right


def _joint_steps(tau: IntArray, vt: FloatArray, geom: GeometricPath, alim: FloatArray) -> FloatArray:
    """Largest joint-acceleration step (share of the limit) at every interior breakpoint."""
    h = np.diff(tau).astype(np.float64)
    w = np.diff(vt) / h
    s_lin = np.concatenate([[0.0], np.cumsum(0.5 * (vt[:-1] + vt[1:]) * h)])
    q1 = np.abs(geom(np.clip(s_lin[1:-1] * (geom.length / s_lin[-1]), 0.0, geom.length), 1))
    out: FloatArray = (np.abs(np.diff(w))[:, None] * q1 * 1.0e6 / alim[None, :]).max(axis=1)
    return out


def _switch_mask(
    tau: IntArray, vt: FloatArray, steps: FloatArray, geom: GeometricPath, straight_steps: bool = False
) -> NDArray[np.bool_]:
    """The real switches among the interior breakpoints (`steps`: their `_joint_steps`): a joint-acceleration
    step above `SWITCH_SHARE` that stands out from its neighbours (the path-acceleration step more than twice
    theirs). Steps of similar size in a row are the solver's gridpoint staircase along a smoothly changing
    bound (a steep one in a tight blend), not a bang-bang change.

    `straight_steps` (the smooth plan's chain, whose segments are at least the encoder's `min_seg`):
    where the path is straight (q'' = 0) there is no such staircase, so every big step is a switch,
    also when the re-timing onto whole ms split one switch into two steps with a piece of intermediate
    acceleration between them (measured: 0.58 + 0.42 of the limit 24 ms apart; a long chain segment
    across either overshoots by up to 18 %, depending on where its knots happen to fall). Not for the
    first plan: there the knots it adds can be a few ms apart, too close for the encoder's quantisation.
    """
    h = np.diff(tau).astype(np.float64)
    signed = np.diff(np.diff(vt) / h)
    dw = np.abs(signed)
    pad = np.concatenate([[0.0], dw, [0.0]])
    alone = dw > 2.0 * np.maximum(pad[:-2], pad[2:])
    if straight_steps:
        s_lin = np.concatenate([[0.0], np.cumsum(0.5 * (vt[:-1] + vt[1:]) * h)])
        s_at = np.clip(s_lin[1:-1] * (geom.length / s_lin[-1]), 0.0, geom.length)
        alone = alone | ~np.any(geom(s_at, 2) != 0.0, axis=1)
    big = steps > SWITCH_SHARE
    # two big steps of opposite signs within `CHATTER_MS`: the solver chattering along a constraint (a dip
    # of a few ms), which the chain smooths over, not a switch
    at = tau[1:-1][big]
    sign = np.sign(signed[big])
    near = np.zeros(at.size, dtype=bool)
    if at.size > 1:
        close = (np.diff(at) < CHATTER_MS) & (sign[1:] != sign[:-1])
        near[:-1] |= close
        near[1:] |= close
    chatter = np.zeros(big.size, dtype=bool)
    chatter[np.nonzero(big)[0]] = near
    out: NDArray[np.bool_] = big & alone & ~chatter
    return out


def _merge_switch_pieces(
    tau: IntArray, vt: FloatArray, geom: GeometricPath, alim: FloatArray, gap: int
) -> tuple[IntArray, FloatArray]:
    """Turn short transitions between two switches (acceleration steps) into a single switch.

    A bang-bang switch rarely falls on a whole ms, and the solver chatters where the active constraint
    changes: the re-timed profile then has one or a few pieces shorter than `gap` ms between two steps,
    and the encoder would need knots a few ms apart (quantisation noise) or a segment across a step
    (deviation). The breakpoints of such a transition (at most 2 `gap` long) become one (at either
    end), whose velocity is chosen so that both new pieces keep accelerations within the range of those
    they replace and the path velocity there does not exceed the planned one: the merged profile never
    asks for more acceleration or speed. Only where the path is straight (`merge_safe`): in a curve the
    joint acceleration also depends on the speed (q'' s_dot^2), which the merge changes.
    """
    if gap <= 1 or tau.size <= 4 or float(tau[-1]) <= 2 * gap:
        return tau, vt
    t = tau.astype(np.float64)
    big = np.concatenate([[True], _joint_steps(tau, vt, geom, alim) > STEP_SHARE, [True]])
    h = np.diff(t)
    s_lin = np.concatenate([[0.0], np.cumsum(0.5 * (vt[:-1] + vt[1:]) * h)])
    safe = geom.merge_safe(np.clip(s_lin * (geom.length / s_lin[-1]), 0.0, geom.length))
    keep, v = _merge_transitions(t, vt, big, safe, gap)
    out_t: IntArray = tau[keep]
    out_v: FloatArray = v[keep]
    return out_t, out_v


@kernel
def _merge_transitions(
    t: FloatArray, vt: FloatArray, big: NDArray[np.bool_], safe: NDArray[np.bool_], gap: int
) -> tuple[NDArray[np.bool_], FloatArray]:
    """`_merge_switch_pieces` on the breakpoints `t` (ms) with path velocities `vt`, where the joint
    acceleration steps (`big`) and where a merge is safe: which breakpoints stay, and the velocities."""
    n = t.size
    v = vt.copy()
    keep = np.ones(n, dtype=np.bool_)
    w = np.empty(n - 1)
    for i in range(n - 1):
        w[i] = (v[i + 1] - v[i]) / (t[i + 1] - t[i])
    # transitions: clusters of big steps, each less than `gap` after the previous one, at most 2 gap long
    # (those of more than one step), then the transitions next to the start and the end
    starts = np.empty(n + 2, dtype=np.int64)
    ends = np.empty(n + 2, dtype=np.int64)
    count = 0
    first_big, last_big = -1, -1
    for i in range(1, n - 1):
        if not big[i]:
            continue
        if first_big < 0:
            first_big = i
        last_big = i
        if count and t[i] - t[ends[count - 1]] < gap and t[i] - t[starts[count - 1]] < 2 * gap:
            ends[count - 1] = i
        else:
            starts[count], ends[count] = i, i
            count += 1
    multi = 0
    for c in range(count):
        if ends[c] > starts[c]:
            starts[multi], ends[multi] = starts[c], ends[c]
            multi += 1
    count = multi
    if first_big >= 0 and t[first_big] < gap:
        starts[count], ends[count] = 0, first_big
        count += 1
    if last_big >= 0 and t[n - 1] - t[last_big] < gap:
        starts[count], ends[count] = last_big, n - 1
        count += 1
    for c in range(count):
        a, b = starts[c], ends[c]
        if not safe[a : b + 1].all():
            continue
        if a == 0 or b == n - 1:
            # at the start or the end (rest): the transition's inner breakpoint goes, if the one piece
            # that replaces it accelerates within the range of those it replaces
            if a == 0 and b + 1 < n and safe[b + 1]:
                e0, e1, d0, d1 = 0, b + 1, 1, b + 1
            elif b == n - 1 and a >= 1 and keep[a - 1] and safe[a - 1]:
                e0, e1, d0, d1 = a - 1, b, a, b
            else:
                continue
            slope = (v[e1] - v[e0]) / (t[e1] - t[e0])
            if w[e0:e1].min() - 1e-15 <= slope <= w[e0:e1].max() + 1e-15:
                keep[d0:d1] = False
            continue
        if not (keep[a - 1] and safe[a - 1] and safe[b + 1]):
            continue
        wl, wr = w[a - 1], w[b]
        wm_lo, wm_hi = w[a:b].min(), w[a:b].max()
        best_loss, best_c, best_v = np.inf, -1, 0.0
        for cc in (a, b):
            dl, dr = t[cc] - t[a - 1], t[b + 1] - t[cc]
            lo = max(v[a - 1] + min(wl, wm_lo) * dl, v[b + 1] - max(wm_hi, wr) * dr, 0.0)
            hi = min(v[a - 1] + max(wl, wm_hi) * dl, v[b + 1] - min(wm_lo, wr) * dr, v[cc])
            if lo <= hi + 1e-15:
                vc = max(min(hi, v[cc]), lo)
                loss = v[cc] - vc
                if best_c < 0 or loss < best_loss:
                    best_loss, best_c, best_v = loss, cc, vc
        if best_c < 0:
            continue
        v[best_c] = best_v
        keep[a : b + 1] = False
        keep[best_c] = True
    return keep, v


def joint_samples(geom: GeometricPath, prof: Profile) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """q, q_dot, q_ddot (left, right) at every ms in user units and per ms (n_axes, M+1)."""
    s, sd, al, ar = prof.sample()
    q = geom(s, 0).T
    q1 = geom(s, 1).T
    q2 = geom(s, 2).T
    sd2 = sd * sd
    v = q1 * sd
    acc_l = q2 * sd2 + q1 * al
    acc_r = q2 * sd2 + q1 * ar
    return q, v, acc_l, acc_r


@dataclass
class RunPlan:
    """One run re-timed on the drive's clock: joint samples at every ms (user units, per ms)."""

    q: FloatArray
    v: FloatArray
    acc_left: FloatArray
    acc_right: FloatArray
    switches: IntArray  # ms where the acceleration steps (knots for the encoder)
    hints: IntArray  # ms where one cubic piece of the plan ends (the chain's knots), or none
    optimal_ms: float
    gridpoints: int
    solves: int


@dataclass(frozen=True)
class ChainSpec:
    """How a run becomes a Hermite chain (planner/encoding/chain.py): geometric budget per axis (user units)
    and the encoder's segment bounds (ms)."""

    budget: FloatArray
    min_seg: int
    max_seg: int
    lower: FloatArray  # position limits (user units), which the chain must not leave
    upper: FloatArray
    short: bool = True  # segments shorter than min_seg where nothing else passes (else: slow down)


def _ratios(
    q: FloatArray,
    v: FloatArray,
    acc_l: FloatArray,
    acc_r: FloatArray,
    vlim_ms: FloatArray,
    alim_ms: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    acc_ratio = (np.maximum(np.abs(acc_l), np.abs(acc_r)) / alim_ms[:, None]).max(axis=0)
    vel_ratio = (np.abs(v) / vlim_ms[:, None]).max(axis=0)
    return acc_ratio, vel_ratio


def blend_margin_rows(geom: GeometricPath, grid: FloatArray) -> FloatArray | None:
    """The first solve's row scales of a chain's run (`topp.solve`): 1 + `BLEND_MARGIN` on both
    gridpoints of every grid interval inside a blend, 1 elsewhere; None without blends."""
    curved = ~geom.merge_safe(0.5 * (grid[:-1] + grid[1:]))
    if not curved.any():
        return None
    rows = np.zeros(grid.size, dtype=np.bool_)
    rows[:-1] |= curved
    rows[1:] |= curved
    out: FloatArray = np.where(rows, 1.0 + BLEND_MARGIN, 1.0)[:, None].repeat(2, axis=1)
    return out


def plan_run(
    geom: GeometricPath,
    vlim: FloatArray,
    alim: FloatArray,
    *,
    time_scale: float = 1.0,
    min_piece_ms: int = 1,
    max_duration_ms: float = 900.0e3,
    chain: ChainSpec | None = None,
) -> RunPlan:
    """A rest-to-rest traversal of one geometric path (TOPP-RA, re-timed, verified; module docstring).

    With `chain`, the plan is the Hermite chain fitted to the re-timed profile (planner/encoding/chain.py) and
    the verification and repairs apply to the chain.
    """
    from planner.encoding.chain import fit_chain

    grid = geom.gridpoints()
    samples = topp.sample_path(geom, grid)  # once: the repairs only tighten the rows
    vlim_ms = vlim / 1000.0
    alim_ms = alim / 1.0e6
    row_scale = blend_margin_rows(geom, grid) if chain is not None else None
    solves = 0
    optimal_ms = 0.0
    prof: Profile | None = None
    sd = np.zeros(0)
    fit: ChainFit | None = None
    best: tuple[Any, ...] | None = None

    # a profile is determined by the solver's solution and its whole-ms duration (time_scale only rounds
    # to it): a slow-down that rounds to a duration already evaluated on the same solution gives the
    # same plan, so its evaluation (a chain fit) is reused, not repeated
    seen: dict[int, tuple[FloatArray, _Evaluation]] = {}

    def evaluate(p: Profile, allow_short: bool = chain is None or chain.short) -> _Evaluation:
        """The plan on profile `p` (made from `sd`) at every ms, and its acceleration and velocity ratios."""
        hit = seen.get(p.duration_ms)
        if hit is not None and hit[0] is sd:
            return hit[1]
        out = _evaluate(p, allow_short)
        seen[p.duration_ms] = (sd, out)
        return out

    def _evaluate(p: Profile, allow_short: bool) -> _Evaluation:
        if chain is None:
            q, v, acc_l, acc_r = joint_samples(geom, p)
            return q, v, acc_l, acc_r, None, *_ratios(q, v, acc_l, acc_r, vlim_ms, alim_ms)
        s_ms, sd = p.sample()[:2]
        # q, q' sd and the direction q' at every ms, a tick's axes contiguous (as the chain's kernels want
        # them: the transposed views are not copied)
        q, v, direction, curved = geom.trace(s_ms, sd)
        f = fit_chain(
            q.T,
            v.T,
            direction.T,
            curved,
            p.real_switches if allow_short else p.long_switches,
            chain.budget,
            vlim_ms,
            alim_ms,
            chain.min_seg,
            chain.max_seg,
            allow_short,
            (chain.lower, chain.upper),
        )
        return f.positions, f.velocities, f.acc_left, f.acc_right, f, f.acc_ratio, f.vel_ratio

    for attempt in range(REPAIR_ROUNDS + 1):
        try:
            sd_new = solve_profile(samples, vlim, alim, row_scale)
        except PlanningError:
            if prof is None:
                raise
            attempt = REPAIR_ROUNDS  # a tightened problem failed: keep the last profile and slow it down
        else:
            sd = sd_new
            solves += 1
            prof = Profile(grid, sd, geom, alim, time_scale, min_piece_ms)
            if attempt == 0:
                # with the blends' margin the solve is up to 1 + BLEND_MARGIN slower than the optimum (the
                # optimum played that much slower meets the tightened rows): report the lower bound
                optimal_ms = prof.optimal_ms / (1.0 + BLEND_MARGIN) if row_scale is not None else prof.optimal_ms
                if prof.duration_ms > max_duration_ms:
                    raise PlanningError(
                        TOO_LARGE,
                        f"the path takes at least {prof.duration_ms / 1000:.1f} s, more than the "
                        f"limit of {MAX_DURATION_S:g} s",
                        path="waypoints",
                    )
        q, v, acc_l, acc_r, fit, acc_ratio, vel_ratio = evaluate(prof)
        if acc_ratio.max() <= 1.0 + ACC_SLACK and vel_ratio.max() <= 1.0 + VEL_SLACK:
            break
        excess = max(float(np.sqrt(acc_ratio.max())), float(vel_ratio.max()))
        if best is None or excess < best[0]:
            best = (excess, sd, prof, q, v, acc_l, acc_r, fit, acc_ratio, vel_ratio)
        elif attempt == REPAIR_ROUNDS:
            # the repairs made it worse: slow down the best profile seen instead
            _e, sd, prof, q, v, acc_l, acc_r, fit, acc_ratio, vel_ratio = best
        small = max(float(np.sqrt(acc_ratio.max())), float(vel_ratio.max())) <= 1.0 + RESCALE_SHARE
        over = max(float(np.sqrt(acc_ratio.max() / (1.0 + ACC_SLACK))), float(vel_ratio.max()))
        if chain is not None and (small or attempt == REPAIR_ROUNDS):
            # a chain fitted anew on a slightly slower profile may overshoot elsewhere (its knots move),
            # and not monotonically in the slow-down: try a few, the fastest that passes wins; else
            # repair locally what is left (or, after the last round, slow down further below)
            passed = False
            # before the last round only the smallest: a local repair usually costs less time
            for extra in SLOWER_LADDER if attempt == REPAIR_ROUNDS else SLOWER_LADDER[:1]:
                slower = Profile(grid, sd, geom, alim, time_scale * max(over, 1.0) * (1.0 + extra), min_piece_ms)
                q2, v2, al2, ar2, fit2, acc2, vel2 = evaluate(slower)
                passed = bool(acc2.max() <= 1.0 + ACC_SLACK and vel2.max() <= 1.0 + VEL_SLACK)
                if passed:
                    prof, q, v, acc_l, acc_r, fit = slower, q2, v2, al2, ar2, fit2
                    break
            if passed:
                break
        if attempt == REPAIR_ROUNDS or (small and chain is None):
            # what is left is small: play the whole motion slower (acceleration ~ 1/f^2); a chain is
            # fitted again on the slower profile, so check again
            scale = time_scale
            for _ in range(8):
                over = max(float(np.sqrt(acc_ratio.max() / (1.0 + ACC_SLACK))), float(vel_ratio.max()))
                scale *= max(over, 1.0) * (1.0 + 1e-4)
                prof = Profile(grid, sd, geom, alim, scale, min_piece_ms)
                q, v, acc_l, acc_r, fit, acc_ratio, vel_ratio = evaluate(prof)
                if acc_ratio.max() <= 1.0 + ACC_SLACK and vel_ratio.max() <= 1.0 + VEL_SLACK:
                    break
            break
        # tighten the constraint rows of the intervals (in s) that overshoot, and their neighbours
        if fit is None:
            worst = np.maximum(acc_ratio, vel_ratio**2)
            worst = np.stack([worst, worst], axis=1)
            power = 1.5
        else:
            # a chain segment overshoots at its ends because of what the profile does inside it (a swing
            # too fast for one cubic): slow the whole segment down, in the rows that overshoot
            worst = np.stack([acc_ratio, vel_ratio**2], axis=1)
            seg_worst = np.maximum.reduceat(worst, fit.knots[:-1], axis=0)
            worst = np.repeat(seg_worst, np.diff(fit.knots), axis=0)
            worst = np.vstack([worst, worst[-1:]])
            power = 1.0
        s_ms = prof.sample()[0]
        # each ms's worst ratio onto both gridpoints of its interval (s grows with time: the intervals of
        # consecutive ms are sorted, so each interval's ms form one run)
        idx = np.clip(np.searchsorted(grid, s_ms, side="right") - 1, 0, grid.size - 2)
        runs = np.concatenate([[0], np.nonzero(np.diff(idx))[0] + 1])
        per_interval = np.maximum.reduceat(worst, runs, axis=0)
        ratio = np.ones((grid.size, 2))
        ratio[idx[runs]] = np.maximum(1.0, per_interval)
        ratio[idx[runs] + 1] = np.maximum(ratio[idx[runs] + 1], per_interval)
        ratio[1:] = np.maximum(ratio[1:], ratio[:-1])
        ratio[:-1] = np.maximum(ratio[:-1], ratio[1:])
        ratio = np.where(ratio > 1.0, ratio**power * (1.0 + 3 * ACC_SLACK), 1.0)
        row_scale = ratio if row_scale is None else row_scale * ratio
    assert prof is not None
    if fit is not None:
        knots = fit.knots[1:-1]
        return RunPlan(q, v, acc_l, acc_r, knots, knots, optimal_ms, int(grid.size), solves)
    empty = np.zeros(0, dtype=np.int64)
    return RunPlan(q, v, acc_l, acc_r, prof.switches, empty, optimal_ms, int(grid.size), solves)


def straight_run(geom: GeometricPath, vlim: FloatArray, alim: FloatArray, time_scale: float = 1.0) -> RunPlan | None:
    """The time-optimal rest-to-rest motion along a run that is one straight piece, in closed form.

    Along a line every joint moves in proportion, so the path's own limits are the tightest of the
    joints' limits over their share of it, and the optimum is a trapezoid (or a triangle): accelerate,
    cruise, decelerate. Its phases are put on whole ms (each rounded up, the cruise velocity and the
    acceleration then lowered to cover the line exactly), so its two switches are steps on whole ms and
    each phase is one polynomial: no solve and no chain needed (within 2 ms of the continuous
    optimum). None when `geom` is not a single straight piece.
    """
    blends = getattr(geom, "blends", None)
    if blends is None or blends.size != 1 or blends[0] != 0:
        return None
    q0 = geom(np.array([0.0]), 0)[0]
    slope = geom(np.array([0.0]), 1)[0]  # dq/ds, constant
    length = geom.length
    share = np.abs(slope)
    moving = share > 0.0
    if not moving.any() or length <= 0.0:
        return None
    v = float(np.min(vlim[moving] / share[moving])) / 1000.0 / time_scale  # s per ms
    a = float(np.min(alim[moving] / share[moving])) / 1.0e6 / time_scale**2  # s per ms^2
    if length >= v * v / a:
        t_acc = v / a
        optimal = 2.0 * t_acc + (length - v * v / a) / v
        n1 = max(1, int(np.ceil(t_acc - 1e-9)))
        n2 = max(0, int(np.ceil(length / v - n1 - 1e-9)))
    else:
        t_acc = float(np.sqrt(length / a))
        optimal = 2.0 * t_acc
        n1, n2 = max(1, int(np.ceil(t_acc - 1e-9))), 0
    peak = length / (n1 + n2)  # the area of the trapezoid: peak * (n1 + n2)
    acc = peak / n1
    total = 2 * n1 + n2
    t = np.arange(total + 1, dtype=np.float64)
    t2 = np.clip(t - n1 - n2, 0.0, n1)
    sd = np.minimum(t, n1) * acc - t2 * acc
    s_pos = np.where(
        t <= n1,
        0.5 * acc * t * t,
        np.where(t <= n1 + n2, 0.5 * peak * n1 + peak * (t - n1), length - 0.5 * acc * (total - t) ** 2),
    )
    s_pos[-1], sd[-1] = length, 0.0
    w_right = np.where(t < n1, acc, np.where(t < n1 + n2, 0.0, -acc))
    w_left = np.where(t <= n1, acc, np.where(t <= n1 + n2, 0.0, -acc))
    w_right[-1], w_left[0] = w_left[-1], w_right[0]
    q = q0[:, None] + slope[:, None] * s_pos[None, :]
    vq = slope[:, None] * sd[None, :]
    switches = np.array(sorted({n1, n1 + n2} - {0, total}), dtype=np.int64)
    return RunPlan(
        q,
        vq,
        slope[:, None] * w_left[None, :],
        slope[:, None] * w_right[None, :],
        switches,
        switches,
        optimal / time_scale,  # `optimal` is of the slowed-down motion (v and a above); the optimum is not
        0,
        0,
    )


def plan_path(
    runs: Sequence[GeometricPath],
    counts_per_unit: FloatArray,
    vlim: FloatArray,
    alim: FloatArray,
    *,
    time_scale: float = 1.0,
    min_piece_ms: int = 1,
    max_duration_s: float = MAX_DURATION_S,
    chain: ChainSpec | None = None,
) -> tuple[Reference, dict[str, float]]:
    """Reference (counts) for the runs played one after the other, each from rest to rest.

    `vlim`/`alim` in user units/s and /s^2; `time_scale` >= 1 plays the motion slower (the encoder asks
    for it when quantisation needs longer segments). Returns the reference and info: the solver's own
    duration for these grids (`optimal_s`, summed over the runs), the gridpoints and solves used (`topp_solves`)
    and the number of runs (`runs`: exact stops + 1).
    """
    plans: list[RunPlan] = []
    spent = 0.0
    for geom in runs:
        line = straight_run(geom, vlim, alim, time_scale) if chain is not None else None
        if line is not None:
            spent += line.q.shape[1] - 1
            plans.append(line)
            continue
        rp = plan_run(
            geom,
            vlim,
            alim,
            time_scale=time_scale,
            min_piece_ms=min_piece_ms,
            max_duration_ms=max_duration_s * 1000.0 - spent,
            chain=chain,
        )
        spent += rp.q.shape[1] - 1
        plans.append(rp)
    # one after the other: every run starts where (and when) the previous one came to rest
    q = np.concatenate([plans[0].q] + [p.q[:, 1:] for p in plans[1:]], axis=1)
    v = np.concatenate([plans[0].v] + [p.v[:, 1:] for p in plans[1:]], axis=1)
    acc_l = np.concatenate([plans[0].acc_left] + [p.acc_left[:, 1:] for p in plans[1:]], axis=1)
    acc_r = np.concatenate([p.acc_right[:, :-1] for p in plans] + [plans[-1].acc_right[:, -1:]], axis=1)
    starts = np.concatenate([[0], np.cumsum([p.q.shape[1] - 1 for p in plans])]).astype(np.int64)
    breaks = np.concatenate([p.switches + starts[k] for k, p in enumerate(plans)] + [starts[1:-1]])
    hints = np.concatenate([p.hints + starts[k] for k, p in enumerate(plans)] + [starts[1:-1]])
    if chain is None:
        hints = np.zeros(0, dtype=np.int64)
    cpu = counts_per_unit[:, None]
    ref = Reference(
        q * cpu, v * cpu, acc_l * cpu, acc_r * cpu, breaks.astype(np.int64), hints.astype(np.int64)
    )
    return ref, {
        "optimal_s": sum(p.optimal_ms for p in plans) / 1000.0,
        "gridpoints": float(sum(p.gridpoints for p in plans)),
        "topp_solves": float(sum(p.solves for p in plans)),
        "runs": float(len(plans)),
    }
