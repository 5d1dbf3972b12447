"""Third-order time-optimal traversal of a path by sequential linear programming (`jerk_limited` paths).

Theory of operation. Fed one rest-to-rest run of a path q(s) (straight pieces and blends, or a spline) and
the joints' velocity, acceleration and jerk limits; finds the path speed as b(s) = s_dot^2 as fast as every
limit allows (`solve_speed`), and plays it at every ms (`Speed.play`; planner/motion/jerkpath.py
`plan_fastest_run` checks it and makes it a run). It is the planner of `jerk_timing = "fastest"`.

b(s) = phi(s) B(s): B a cubic B-spline (`SPANS_PER_PIECE` spans per piece of the geometry), phi(s) =
(s (L - s) / L)^(4/3). A jerk-limited start from rest has s = c t^3, so b ~ s^(4/3): with phi, every b
starts and ends at rest with zero acceleration, and B stays smooth there (a polynomial b does not follow
s^(4/3): it starts slowly). b, b' and b'' are linear in B's coefficients, and so are the joints' velocity
q' sqrt(b) and acceleration q' b'/2 + q'' b (TOPP's convexity); their jerk is a linear expression times
sqrt(b):

    d3q/dt3 = sqrt(b) L(b),   L(b) = q' b''/2 + 3 q'' b'/2 + q''' b.

|sqrt(b) L(b)| <= J is |L(b)| <= J / sqrt(b), whose right side is convex in b: its tangent at any b_k lies
below it, so |L(b)| <= tangent_k(b) is linear and keeps the true bound (the convex-concave split of
Debrouwere et al., "Time-optimal path following for robots with convex-concave constraints using
sequential convex programming", IEEE T-RO 2013). The duration, the integral of ds / sqrt(b), is convex; its
gradient at b_k, within a trust region on the coefficients, is the objective. Each iteration is one LP
(scipy's HiGHS; the rows no point of the trust region reaches are left out) from a point that keeps every
limit to another that keeps them, kept only when it is faster; the iterations stop when one gains less
than `GAIN` or the trust region has shrunk below `MIN_TRUST`. The start is B = 1 scaled down until every
constraint holds (they are homogeneous in B: the scale has a closed form, `feasible_scale`). A run of many
pieces (`COARSE_FROM` coefficients) is solved first on a coarse spline, whose solution, scaled into the
fine problem's constraints, starts the fine one with a smaller trust region.

The constraints hold at collocation points: `PER_SPAN` per knot span, `END_POINTS` toward each end, and
either side of every end of a piece of the geometry (where q''' jumps). Between them b is smooth; the check
at every ms (the one every jerk-limited plan passes: jerkpath.ratios, velocity, acceleration, and the jerk
within `PLAN_JERK_SHARE`) decides, and the run is played slower where it fails. The jerk is solved within
`JERK_MARGIN` of that share, the rest for what the collocation points do not see.

From b(s) to every ms: t(s) by quadrature on a fine grid (b linear over each interval, s ~ t^3 over the
first and the last), s at every ms by inverting it, s_dot = sqrt(b(s)), s_ddot = b'(s) / 2, then the joints.

Why this method and what it costs, measured: docs/formats.md, "jerk_timing".
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.interpolate import BSpline
from scipy.optimize import linprog

from planner.motion.path import GeometricPath
from planner.motion.reference import FloatArray

SPANS_PER_PIECE = 8  # knot spans per piece of the geometry ...
MIN_SPANS, MAX_SPANS = 40, 240  # ... within these
COARSE_SPANS_PER_PIECE, COARSE_MIN_SPANS = 2, 10  # the first solve's (its solution starts the fine one) ...
COARSE_FROM = 100  # ... where the fine spline has this many coefficients
END_NEAR = 1.0e-5  # collocation points toward each end, from this share of the path ...
END_POINTS = 30  # ... to the first span, spaced geometrically
PER_SPAN = 4  # collocation points per knot span
JERK_MARGIN = 0.97  # of the plan's jerk share, solved for (the rest: between the collocation points)
ACC_MARGIN = 0.99
MAX_ITERATIONS = 60
GAIN = 2.0e-4  # stop when an iteration shortens the run by less than this share ...
MIN_TRUST = 4.0e-3  # ... or the trust region (a share of each coefficient) is this small
TRUST = 0.5
REFINE_TRUST = 0.1  # the fine solve's first trust region (its start is close)
FINE = 20000  # intervals of the quadrature of t(s), and geometric ones toward each end
FINE_ENDS = 300
REPLAYS = 8  # slower replays tried when the check at every ms fails (jerkpath.plan_fastest_run)


class _Problem:
    """The LP's data on one path: the spline's basis at the collocation points and the joints' path
    derivatives there."""

    def __init__(self, geom: GeometricPath, vlim: FloatArray, alim: FloatArray, jsolve: FloatArray,
                 per_piece: int = SPANS_PER_PIECE, min_spans: int = MIN_SPANS):
        length = geom.length
        pieces = max(1, int(np.asarray(geom.breakpoints).size) - 1)
        spans = int(np.clip(per_piece * pieces, min_spans, MAX_SPANS))
        brk = np.linspace(0.0, length, spans + 1)
        self.length = length
        self.knots = np.concatenate([[0.0] * 3, brk, [length] * 3])  # cubic: B'' continuous
        self.nc = self.knots.size - 4
        col = (brk[:-1, None] + np.diff(brk)[:, None] * np.arange(PER_SPAN)[None, :] / PER_SPAN).ravel()
        inner = np.asarray(geom.breakpoints, dtype=np.float64)[1:-1]
        eps = 1.0e-9 * length
        near = length * np.geomspace(END_NEAR, 1.0 / spans, END_POINTS)  # where a start from rest spends its time
        col = np.concatenate([col, near, length - near, inner - eps, inner + eps])
        col = np.unique(col[(col > 0.0) & (col < length)])  # b = 0 at both ends, and phi'' is infinite there
        basis = BSpline(self.knots, np.eye(self.nc), 3)
        n0, n1, n2 = basis(col), basis(col, 1), basis(col, 2)
        f0, f1, f2 = self.weight(col)
        b0 = f0[:, None] * n0
        b1 = f1[:, None] * n0 + f0[:, None] * n1
        b2 = f2[:, None] * n0 + 2.0 * f1[:, None] * n1 + f0[:, None] * n2
        q1, q2, q3 = geom(col, 1), geom(col, 2), geom(col, 3)
        self.b0 = sparse.csr_matrix(b0)
        self.weights = np.diff(col, prepend=col[0]) / 2.0 + np.diff(col, append=col[-1]) / 2.0
        self.jsolve = jsolve
        rows, rhs = [], []
        with np.errstate(divide="ignore", over="ignore"):
            bmax = np.min((vlim[None, :] / np.abs(q1)) ** 2, axis=1)
        fin = np.isfinite(bmax)
        rows.append(b0[fin])
        rhs.append(bmax[fin])
        for j in range(q1.shape[1]):
            acc = q1[:, j : j + 1] * 0.5 * b1 + q2[:, j : j + 1] * b0
            rows += [acc, -acc]
            rhs += [np.full(col.size, alim[j] * ACC_MARGIN)] * 2
        self.static = sparse.csr_matrix(np.vstack(rows))
        self.static_rhs = np.concatenate(rhs)
        # L_j(b) per joint: q' b''/2 + 3 q'' b'/2 + q''' b
        self.jerk = [
            sparse.csr_matrix(q1[:, j : j + 1] * 0.5 * b2 + q2[:, j : j + 1] * 1.5 * b1 + q3[:, j : j + 1] * b0)
            for j in range(q1.shape[1])
        ]
        fine = np.linspace(0.0, length, FINE + 1)
        near = length * np.geomspace(1.0e-10, 1.0e-3, FINE_ENDS)
        self.fine = np.unique(np.concatenate([fine, near, length - near]))

    def weight(self, s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """phi(s) = u^(4/3), u = s (L - s) / L, and its first two derivatives (the second infinite at the ends)."""
        length = self.length
        u = np.maximum(s * (length - s) / length, 0.0)
        du = (length - 2.0 * s) / length
        cbrt = np.cbrt(u)
        with np.errstate(divide="ignore"):
            f2 = 4.0 / 9.0 * du * du / (cbrt * cbrt) - 8.0 / 3.0 * cbrt / length
        return u * cbrt, 4.0 / 3.0 * cbrt * du, f2

    def b(self, c: FloatArray, s: FloatArray, order: int = 0) -> FloatArray:
        """b(s) = phi(s) B(s) (order 0) or its first derivative at `s`, for B's coefficients `c`."""
        spline = BSpline(self.knots, c, 3)
        f0, f1, _f2 = self.weight(s)
        out: FloatArray = f0 * spline(s) if order == 0 else f1 * spline(s) + f0 * spline(s, 1)
        return out

    def duration_s(self, c: FloatArray) -> float:
        """The run's duration at b (`timing`)."""
        return float(self.timing(c)[0][-1])

    def timing(self, c: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The time at every fine gridpoint (quadrature: b linear over each interval but the first and the
        last, where b ~ s^(4/3) and the time is 3 h / sqrt(b(h)), not 2), and b there."""
        b = np.maximum(self.b(c, self.fine), 0.0)
        root = np.sqrt(b)
        h = np.diff(self.fine)
        dt = 2.0 * h / np.maximum(root[:-1] + root[1:], 1e-300)
        dt[0] = 3.0 * h[0] / max(root[1], 1e-300)
        dt[-1] = 3.0 * h[-1] / max(root[-2], 1e-300)
        t = np.concatenate([[0.0], np.cumsum(dt)])
        return t, b

    def feasible_scale(self, c: FloatArray) -> float:
        """The largest factor on c that keeps every constraint (velocity and acceleration scale with it,
        the jerk with its 3/2 power); inf on a path too short for the limits to bind (solve_speed: none)."""
        with np.errstate(over="ignore", divide="ignore"):
            lhs = self.static @ c
            pos = lhs > 0.0
            lam = float(np.min(self.static_rhs[pos] / lhs[pos])) if pos.any() else np.inf
            root = np.sqrt(np.maximum(self.b0 @ c, 0.0))
            for j, lj in enumerate(self.jerk):
                peak = float(np.max(np.abs(lj @ c) * root))
                if peak > 0.0:
                    lam = min(lam, (self.jsolve[j] / peak) ** (2.0 / 3.0))
        return lam

    def step(self, c: FloatArray, trust: float) -> FloatArray | None:
        """One LP: the constraints linearised at c, the duration's gradient at c, within the trust region."""
        b = self.b0 @ c
        bk = np.maximum(b, 1.0e-12 * float(b.max()))  # exact but where b vanishes
        grad = self.b0.T @ (-0.5 * self.weights / bk**1.5)
        rows, rhs = [self.static], [self.static_rhs]
        slope = sparse.diags(0.5 / bk**1.5) @ self.b0
        for j, lj in enumerate(self.jerk):
            tangent = self.jsolve[j] * slope
            rows += [lj + tangent, -lj + tangent]
            rhs += [self.jsolve[j] * 1.5 / np.sqrt(bk)] * 2
        room = trust * np.maximum(c, 1.0e-3 * float(c.max()))
        lo, hi = np.maximum(c - room, 0.0), c + room
        a_ub = sparse.vstack(rows).tocsr()
        b_ub = np.concatenate(rhs)
        # rows that no point of the trust region reaches cannot be active: left out (a third of the time)
        keep = a_ub @ c + abs(a_ub) @ room > b_ub - 1.0e-12 * np.abs(b_ub)
        res = linprog(grad, A_ub=a_ub[keep], b_ub=b_ub[keep], bounds=np.stack([lo, hi], axis=1), method="highs")
        if res.status != 0:
            return None
        out: FloatArray = np.asarray(res.x, dtype=np.float64)
        return out


class Speed:
    """A solved path speed: b(s) = s_dot^2 as the spline's coefficients on its problem."""

    def __init__(self, prob: _Problem, coefficients: FloatArray):
        self.prob = prob
        self.c = coefficients
        self.t, self.b_fine = prob.timing(coefficients)  # at the fine gridpoints, for every replay

    def play(self, slow: float = 1.0) -> tuple[FloatArray, FloatArray, FloatArray]:
        """s, s_dot, s_ddot at every ms (per ms, per ms^2) of the path played `slow` times slower, stretched to
        end on a whole ms: t(s) on the fine grid (`_Problem.timing`), inverted at every ms."""
        prob, c, t, b = self.prob, self.c, self.t, self.b_fine
        dur_s = float(t[-1])
        m = max(1, int(np.ceil(dur_s * 1.0e3 * slow - 1e-9)))
        k = m / (dur_s * 1.0e3)  # ms of the played run per ms of b's
        tt = np.arange(m + 1) / k / 1.0e3
        fine = prob.fine
        root = np.sqrt(b)
        i = np.clip(np.searchsorted(t, tt, side="right") - 1, 0, fine.size - 2)
        tau = tt - t[i]
        acc = (b[i + 1] - b[i]) / (2.0 * (fine[i + 1] - fine[i]))
        s = fine[i] + root[i] * tau + 0.5 * acc * tau * tau
        first, last = tt < t[1], tt > t[-2]  # from and to rest: s ~ t^3
        s[first] = fine[1] * (tt[first] / t[1]) ** 3
        s[last] = prob.length - (prob.length - fine[-2]) * ((t[-1] - tt[last]) / (t[-1] - t[-2])) ** 3
        s = np.clip(s, 0.0, prob.length)
        s[-1] = prob.length
        sd = np.sqrt(np.maximum(prob.b(c, s), 0.0)) / (1.0e3 * k)
        sdd = 0.5 * prob.b(c, s, 1) / (1.0e6 * k * k)
        sd[0] = sd[-1] = sdd[0] = sdd[-1] = 0.0
        return s, sd, sdd


def solve_speed(geom: GeometricPath, vlim: FloatArray, alim: FloatArray, jlim: FloatArray) -> tuple[Speed, int] | None:
    """The fastest b(s) for one run (module docstring) within the velocity, acceleration and jerk limits
    `vlim`, `alim`, `jlim` (the share of the jerk the plan may use), and the LPs solved; None when no
    start is found. Solved first on a coarse spline (`COARSE_SPANS_PER_PIECE`), whose solution, scaled into
    the fine problem's constraints, starts the fine one: half the time of the fine solve from B = 1 on the
    example paths (0.5 against 1.1 s, 0.75 against 2.0), the same durations within 0.1 ms."""
    jsolve = jlim * JERK_MARGIN
    fine = _Problem(geom, vlim, alim, jsolve)
    if fine.nc < COARSE_FROM:  # a few pieces: the fine solve alone is quicker
        start = _start(fine, np.ones(fine.nc))
        if start is None:
            return None
        c, lps = _iterate(fine, start, TRUST)
        return Speed(fine, c), lps
    coarse = _Problem(geom, vlim, alim, jsolve, COARSE_SPANS_PER_PIECE, COARSE_MIN_SPANS)
    start = _start(coarse, np.ones(coarse.nc))
    if start is None:
        return None
    c, lps = _iterate(coarse, start, TRUST)
    grev = np.array([fine.knots[i + 1 : i + 4].mean() for i in range(fine.nc)])
    start = _start(fine, np.maximum(BSpline(coarse.knots, c, 3)(grev), 0.0), up=False)
    if start is None:
        return None
    c, more = _iterate(fine, start, REFINE_TRUST)
    return Speed(fine, c), lps + more


def _start(prob: _Problem, c: FloatArray, *, up: bool = True) -> FloatArray | None:
    """`c` scaled until the tightest constraint holds with equality (`up`; else only scaled down where one
    fails); None when no scale does."""
    lam = prob.feasible_scale(c)
    if not np.isfinite(lam) or lam <= 0.0:
        return None
    out: FloatArray = c * (lam if up else min(lam, 1.0)) * (1.0 - 1.0e-9)
    return out


def _iterate(prob: _Problem, c: FloatArray, trust: float) -> tuple[FloatArray, int]:
    """The LPs from `c` (module docstring) until a step gains less than `GAIN`, the trust region is below
    `MIN_TRUST` or `MAX_ITERATIONS` were solved: the fastest point found and the LPs solved."""
    best = prob.duration_s(c)
    solves = 0
    while solves < MAX_ITERATIONS and trust >= MIN_TRUST:
        nxt = prob.step(c, trust)
        solves += 1
        if nxt is None:
            trust *= 0.5
            continue
        dur = prob.duration_s(nxt)
        if dur < best * (1.0 - 1.0e-9):
            gain = (best - dur) / best
            c, best = nxt, dur
            if gain < GAIN:
                break
        else:
            trust *= 0.5
    return c, solves
