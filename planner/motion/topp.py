"""Time-optimal path parametrisation by reachability analysis (TOPP-RA), compiled.

Theory of operation. The problem is toppra's (Pham & Pham, "A New Approach to Time-Optimal Path
Parameterization based on Reachability Analysis", 2018) and so is the algorithm; only the loops are
ours, compiled (planner/jit.py). toppra runs the same two passes in Python, a few tens of microseconds
per gridpoint: 6-7 ms for a 20-waypoint path, more than the whole rest of the plan once that is compiled
too. Here the passes cost about 0.2 ms for 400 gridpoints and 90 constraint rows. toppra stays the
reference: tests/planner/motion/test_topp.py solves random paths with both and compares the profiles.

Along a geometric path q(s), with x = s_dot^2 at gridpoint s_i and a constant path acceleration u over
the interval [s_i, s_i+1] (so x_i+1 = x_i + 2 delta_i u_i), every joint velocity and acceleration
constraint is linear in (u, x) at any point of the interval (path.py explains the interior points):

    A_r u + B_r x <= G_r   for the rows r of gridpoint i,   0 <= x <= xmax_i (joint velocities).

1. Controllable sets, backward: K_N = {0} (the path ends at rest); K_i = [lo_i, hi_i], the x from which
   some admissible u reaches K_i+1. hi_i and lo_i are two linear programs in (u, x) (`_lp2d`).
2. Forward pass: x_0 = 0; at each gridpoint the largest admissible u whose next state stays in K_i+1, a
   one-dimensional problem. As toppra does, each next state is taken 0.01 % low (numerical errors must
   not leave the controllable set) and a state from which no u is admissible is lowered slightly and
   tried again (at most 10 times).

`_lp2d` is Seidel's incremental algorithm for two variables: start from the best corner of the box,
add the rows one by one, and when a row cuts off the current optimum, the new one lies on that row's
line: a one-dimensional problem over the rows before it. The rows active at the previous gridpoint are
added first (neighbouring gridpoints have nearly the same active rows), so the optimum rarely moves
after them and each program costs about one pass over its rows.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from planner.errors import INFEASIBLE, PlanningError
from planner.jit import kernel
from planner.motion.reference import FloatArray

THETAS = np.array([0.0, 0.25, 0.5, 0.75, 1.0])  # where inside each interval the constraints are imposed
U_MAX = 1.0e8  # bound on |u| that keeps every linear program bounded
X_MAX = 1.0e16  # bound on x where no joint velocity limits it
_TINY = 1.0e-8  # toppra's constants.TINY
_MAX_TRIES = 10  # toppra's constants.MAX_TRIES

# status of `_passes`
OK = 0
UNCONTROLLABLE = 1  # no controllable set at some gridpoint: the path cannot be followed within the limits
FORWARD_FAILED = 2  # the forward pass found no admissible u even from a lowered state


def constraint_rows(
    q1: FloatArray, q2: FloatArray, deltas: FloatArray, vlim: FloatArray, alim: FloatArray,
    row_scale: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The rows A u + B x <= G of every gridpoint, (N+1, 3 k d) each, from the path's first and second
    derivatives at the `THETAS` of each interval: q1, q2 (N+1, k, d); `deltas` (N+1,) the interval
    lengths (0 after the last gridpoint). Rows: joint acceleration <= alim and >= -alim, joint velocity
    squared <= vlim^2. `row_scale` (N+1, 2) >= 1 tightens a gridpoint's acceleration and velocity rows."""
    return _rows(np.ascontiguousarray(q1), np.ascontiguousarray(q2), deltas, vlim, alim,
                 _row_scales(row_scale, q1.shape[0]), THETAS)


def _row_scales(row_scale: FloatArray | None, gridpoints: int) -> FloatArray:
    """`row_scale` as the kernels take it: (N+1, 2), contiguous, ones where none is given."""
    if row_scale is None:
        return np.ones((gridpoints, 2))
    return np.ascontiguousarray(row_scale, dtype=np.float64)


@kernel
def _rows(
    q1: FloatArray, q2: FloatArray, deltas: FloatArray, vlim: FloatArray, alim: FloatArray, scale: FloatArray,
    thetas: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """`constraint_rows`: for theta k and axis j, column k d + j of the acceleration rows (<= alim, then
    their negation, >= -alim) and of the squared-velocity rows."""
    n1, k, d = q1.shape
    m = k * d
    a = np.empty((n1, 3 * m))
    b = np.empty((n1, 3 * m))
    g = np.empty((n1, 3 * m))
    for i in range(n1):
        for t in range(k):
            th = thetas[t] * deltas[i]
            for j in range(d):
                col = t * d + j
                p1, p2 = q1[i, t, j], q2[i, t, j]
                a_acc = (p1 + 2.0 * th * p2) * scale[i, 0]
                b_acc = p2 * scale[i, 0]
                a[i, col], a[i, m + col], a[i, 2 * m + col] = a_acc, -a_acc, 2.0 * th * p1 * p1 * scale[i, 1]
                b[i, col], b[i, m + col], b[i, 2 * m + col] = b_acc, -b_acc, p1 * p1 * scale[i, 1]
                g[i, col], g[i, m + col], g[i, 2 * m + col] = alim[j], alim[j], vlim[j] * vlim[j]
    return a, b, g


@kernel
def _velocity_bound(q1: FloatArray, vlim: FloatArray) -> FloatArray:
    """xmax at every gridpoint: the largest x = s_dot^2 with every |q1 s_dot| <= vlim (q1 (N+1, k, d) at
    the intervals' starts: theta 0); at most `X_MAX`."""
    out = np.empty(q1.shape[0])
    for i in range(q1.shape[0]):
        bound = np.inf
        for j in range(q1.shape[2]):
            if q1[i, 0, j] != 0.0:
                bound = min(bound, (vlim[j] / abs(q1[i, 0, j])) ** 2)
        out[i] = min(bound, X_MAX)
    return out


def velocity_bound(q1: FloatArray, vlim: FloatArray) -> FloatArray:
    """The largest x = s_dot^2 at every gridpoint that keeps every joint within `vlim` (`_velocity_bound`)."""
    out: FloatArray = _velocity_bound(np.ascontiguousarray(q1, dtype=np.float64), vlim)
    return out


@dataclass(frozen=True, eq=False)
class PathSamples:
    """A path's derivatives where the constraints are imposed: q1, q2 (N+1, k, d) at the `THETAS` of
    every interval; the gridpoints and the interval lengths `deltas` (N+1,: 0 after the last)."""

    gridpoints: FloatArray
    deltas: FloatArray
    q1: FloatArray
    q2: FloatArray


def sample_path(path: Callable[[FloatArray, int], FloatArray], gridpoints: FloatArray) -> PathSamples:
    """`path(s, order)` (the geometry, (len(s), d)) sampled for `solve`: once per gridpoint set, however
    many times the constraints are tightened."""
    g = np.asarray(gridpoints, dtype=np.float64)
    deltas = np.append(np.diff(g), 0.0)
    s = np.minimum(g[:, None] + THETAS[None, :] * deltas[:, None], g[-1]).ravel()
    q1 = np.asarray(path(s, 1))
    q2 = np.asarray(path(s, 2))
    shape = (g.size, THETAS.size, q1.shape[1])
    return PathSamples(g, deltas, q1.reshape(shape), q2.reshape(shape))


def solve(samples: PathSamples, vlim: FloatArray, alim: FloatArray, row_scale: FloatArray | None = None) -> FloatArray:
    """The time-optimal path velocities s_dot at the gridpoints, rest to rest, under the joint velocity
    `vlim` and acceleration `alim` limits (per axis; `row_scale` tightens them per gridpoint, see
    `constraint_rows`). Raises PlanningError(INFEASIBLE) when no admissible profile exists."""
    sd, status, where = _solve(samples.q1, samples.q2, samples.deltas, vlim, alim,
                               _row_scales(row_scale, samples.q1.shape[0]), THETAS)
    _check(status, where, samples.gridpoints.size)
    return sd


@kernel
def _solve(
    q1: FloatArray, q2: FloatArray, deltas: FloatArray, vlim: FloatArray, alim: FloatArray, scale: FloatArray,
    thetas: FloatArray,
) -> tuple[FloatArray, int, int]:
    """`solve` in one call: the rows, the velocity bound, the passes, s_dot."""
    a, b, g = _rows(q1, q2, deltas, vlim, alim, scale, thetas)
    x, status, where = _passes(a, b, g, _velocity_bound(q1, vlim), deltas[:-1].copy())
    return np.sqrt(np.maximum(x, 0.0)), status, where


def parametrize(
    a: FloatArray, b: FloatArray, g: FloatArray, xmax: FloatArray, gridpoints: FloatArray
) -> FloatArray:
    """s_dot at the gridpoints for the rows a u + b x <= g and 0 <= x <= xmax of every gridpoint (module
    docstring). Raises PlanningError(INFEASIBLE) when no admissible profile exists."""
    deltas = np.ascontiguousarray(np.diff(gridpoints), dtype=np.float64)
    x, status, where = _passes(
        np.ascontiguousarray(a, dtype=np.float64), np.ascontiguousarray(b, dtype=np.float64),
        np.ascontiguousarray(g, dtype=np.float64), np.ascontiguousarray(xmax, dtype=np.float64), deltas,
    )
    _check(status, where, gridpoints.size)
    out: FloatArray = np.sqrt(np.maximum(x, 0.0))
    return out


def _check(status: int, where: int, gridpoints: int) -> None:
    if status != OK:
        what = "no controllable set" if status == UNCONTROLLABLE else "the forward pass found no admissible step"
        raise PlanningError(
            INFEASIBLE,
            f"no feasible time parametrisation: {what} at gridpoint {where} of {gridpoints}",
            detail={"solver": "topp-ra", "return_code": "Uncontrollable" if status == UNCONTROLLABLE
                    else "ForwardFailed", "gridpoint": int(where)},
        )


@kernel
def _lp2d(
    cu: float, cx: float, a: FloatArray, b: FloatArray, g: FloatArray, m: int,
    ulo: float, uhi: float, xlo: float, xhi: float, first: int, second: int, out: FloatArray,
) -> bool:
    """Maximise cu u + cx x subject to a[r] u + b[r] x <= g[r] (r < m), u in [ulo, uhi], x in [xlo, xhi].
    Rows `first` and `second` (-1: none) are added first. out = (u, x, row active last, the row that
    bounded it, or -1). False when infeasible."""
    if ulo > uhi or xlo > xhi:
        return False
    u = uhi if cu > 0.0 else ulo
    x = xhi if cx > 0.0 else xlo
    act = -1
    other = -1
    for k in range(-2, m):
        r = first if k == -2 else (second if k == -1 else k)
        if r < 0 or (k >= 0 and r in (first, second)):
            continue
        ar, br, gr = a[r], b[r], g[r]
        if ar * u + br * x <= gr + 1e-12 * (abs(gr) + 1.0):
            continue
        nn = ar * ar + br * br
        if nn == 0.0:
            return False
        # the new optimum lies on the line ar u + br x = gr: p + t (du, dx)
        du, dx = -br, ar
        pu, px = ar * gr / nn, br * gr / nn
        tlo, thi = -np.inf, np.inf
        lo_row, hi_row = -1, -1
        if du > 0.0:
            thi, tlo = min(thi, (uhi - pu) / du), max(tlo, (ulo - pu) / du)
        elif du < 0.0:
            thi, tlo = min(thi, (ulo - pu) / du), max(tlo, (uhi - pu) / du)
        elif pu > uhi + 1e-12 or pu < ulo - 1e-12:
            return False
        if dx > 0.0:
            thi, tlo = min(thi, (xhi - px) / dx), max(tlo, (xlo - px) / dx)
        elif dx < 0.0:
            thi, tlo = min(thi, (xlo - px) / dx), max(tlo, (xhi - px) / dx)
        elif px > xhi + 1e-12 or px < xlo - 1e-12:
            return False
        for k2 in range(-2, k):
            j = first if k2 == -2 else (second if k2 == -1 else k2)
            if j < 0 or j == r or (k2 >= 0 and j in (first, second)):
                continue
            slope = a[j] * du + b[j] * dx
            room = g[j] - (a[j] * pu + b[j] * px)
            if slope > 0.0:
                t = room / slope
                if t < thi:
                    thi, hi_row = t, j
            elif slope < 0.0:
                t = room / slope
                if t > tlo:
                    tlo, lo_row = t, j
            elif room < -1e-12 * (abs(g[j]) + 1.0):
                return False
        if tlo > thi + 1e-12 * (abs(thi) + 1.0):
            return False
        gain = cu * du + cx * dx
        if gain > 0.0:
            t, other = thi, hi_row
        elif gain < 0.0:
            t, other = tlo, lo_row
        else:
            t = tlo if tlo > -np.inf else (thi if thi < np.inf else 0.0)
            other = lo_row
        u, x = pu + t * du, px + t * dx
        act = r
    out[0], out[1], out[2], out[3] = u, x, act, other
    return True


@kernel
def _passes(
    a: FloatArray, b: FloatArray, g: FloatArray, xmax: FloatArray, deltas: FloatArray
) -> tuple[FloatArray, int, int]:
    """x = s_dot^2 at every gridpoint (rest to rest), the status and the gridpoint where it failed."""
    n = deltas.size
    m = a.shape[1]
    lo = np.zeros(n + 1)
    hi = np.zeros(n + 1)
    out = np.zeros(4)
    ar = np.empty(m + 2)
    br = np.empty(m + 2)
    gr = np.empty(m + 2)
    up0, up1, dn0, dn1 = -1, -1, -1, -1  # the rows active at the previous gridpoint, for each program
    for i in range(n - 1, -1, -1):
        d2 = 2.0 * deltas[i]
        ar[:m] = a[i]
        br[:m] = b[i]
        gr[:m] = g[i]
        ar[m], br[m], gr[m] = d2, 1.0, hi[i + 1]  # x + 2 delta u <= hi_i+1
        ar[m + 1], br[m + 1], gr[m + 1] = -d2, -1.0, -lo[i + 1]  # x + 2 delta u >= lo_i+1
        if not _lp2d(-1e-9, 1.0, ar, br, gr, m + 2, -U_MAX, U_MAX, 0.0, xmax[i], up0, up1, out):
            return np.full(n + 1, np.nan), UNCONTROLLABLE, i
        hi[i], up0, up1 = out[1], int(out[2]), int(out[3])
        if not _lp2d(1e-9, -1.0, ar, br, gr, m + 2, -U_MAX, U_MAX, 0.0, xmax[i], dn0, dn1, out):
            return np.full(n + 1, np.nan), UNCONTROLLABLE, i
        lo[i], dn0, dn1 = max(out[1], 0.0), int(out[2]), int(out[3])
    xs = np.zeros(n + 1)
    for i in range(n):
        x = xs[i]
        d2 = 2.0 * deltas[i]
        ok = False
        u = 0.0
        for _try in range(_MAX_TRIES + 1):
            ulo = (lo[i + 1] - x) / d2
            uhi = (hi[i + 1] - x) / d2
            for r in range(m):
                rhs = g[i, r] - b[i, r] * x
                if a[i, r] > 0.0:
                    uhi = min(uhi, rhs / a[i, r])
                elif a[i, r] < 0.0:
                    ulo = max(ulo, rhs / a[i, r])
            if ulo <= uhi:
                ok, u = True, uhi
                break
            x = max(x - _TINY, 0.999 * x)
        if not ok:
            return np.full(n + 1, np.nan), FORWARD_FAILED, i
        xs[i] = x
        step = x + d2 * u
        step = max(step - _TINY, 0.9999 * step)
        xs[i + 1] = min(hi[i + 1], max(lo[i + 1], step))
    return xs, OK, -1


# ----------------------------------------------------------------------------------------------------
# toppra, the reference (tests and benchmarks: the planner itself never calls it)


def toppra_path(path: Callable[[FloatArray, int], FloatArray], dof: int, length: float) -> Any:
    """`path(s, order)` on [0, length] as a toppra geometric path (toppra is imported here, lazily)."""
    from toppra.interpolator import AbstractGeometricPath

    class _Path(AbstractGeometricPath):  # type: ignore[misc]
        def __call__(self, path_positions: Any, order: int = 0) -> FloatArray:
            return path(np.atleast_1d(np.asarray(path_positions, dtype=np.float64)), order)

        @property
        def dof(self) -> int:
            return dof

        @property
        def path_interval(self) -> FloatArray:
            return np.array([0.0, length])

    return _Path()


def toppra_solve(
    path: Callable[[FloatArray, int], FloatArray], dof: int, gridpoints: FloatArray, vlim: FloatArray,
    alim: FloatArray, row_scale: FloatArray | None = None,
) -> FloatArray | None:
    """toppra's seidel solver on the same rows as `solve` (the interior points included): s_dot at the
    gridpoints, or None where toppra fails."""
    import logging

    from toppra.algorithm import TOPPRA
    from toppra.constraint import DiscretizationType, JointVelocityConstraint
    from toppra.constraint.linear_constraint import LinearConstraint

    samples = sample_path(path, gridpoints)
    a, b, g = constraint_rows(samples.q1, samples.q2, samples.deltas, vlim, alim, row_scale)

    class _Rows(LinearConstraint):  # type: ignore[misc]
        def __init__(self) -> None:
            super().__init__()
            self.dof = dof
            self.identical = True
            self.discretization_type = DiscretizationType.Collocation

        def compute_constraint_params(self, *args: Any, **kwargs: Any) -> Any:
            return a, b, np.zeros_like(a), np.eye(a.shape[1]), g[0], None, None

    logger = logging.getLogger("toppra")
    level = logger.level
    logger.setLevel(logging.CRITICAL)  # toppra logs (and returns None) where it fails
    try:
        inst = TOPPRA([JointVelocityConstraint(np.vstack([-vlim, vlim]).T), _Rows()],
                      toppra_path(path, dof, float(gridpoints[-1])), gridpoints=gridpoints,
                      solver_wrapper="seidel", parametrizer="ParametrizeConstAccel")
        _sdd, sd, _v = inst.compute_parameterization(0.0, 0.0)
    finally:
        logger.setLevel(level)
    return None if sd is None else np.asarray(sd, dtype=np.float64)
