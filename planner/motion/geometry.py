"""Geometric paths for path jobs: straight segments between the waypoints with blended corners.

A path job goes along the segments and rounds corners within a per-axis tolerance (G64 in CNC, MoveIt's
TOTG blends). In z = q / v_max a blend is a quintic Bezier with its control points on the two legs: C2
(joint accelerations step only where the path acceleration does) and inside the corner's triangle (so
within the position limits when the waypoints are). Its size is homothetic in the leg length, measured in
q / tol so every axis keeps its tolerance, at most half of each segment; of the shapes `RHOS` the fastest
wins. Exact stops cut the path into rest-to-rest runs (`PiecewisePath`): zero tolerance on a moving axis, a
reversal, or a blend too fast for the drive's segments.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from math import comb

import numpy as np
from numpy.typing import NDArray

from planner.jit import kernel
from planner.motion.reference import FloatArray, IntArray

# candidate blend shapes d / l (module docstring, 2); 1/2 puts the two middle control points on c
RHOS = np.array([0.06, 0.09, 0.12, 0.16, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5])
_T = np.linspace(0.0, 1.0, 129)  # samples of a blend (odd: includes its middle)
MIN_BLEND_SHARE = 1e-6  # a blend smaller than this share of its shorter segment is an exact stop
COLLINEAR_COS = 1.0 - 1e-12  # corners straighter than this are no corners (the path goes straight on)
REVERSAL_COS = -1.0 + 1e-9  # corners sharper than this are reversals (the path turns back on itself)
S_MIN, S_MAX = 1e-2, 2.0  # toppra's seidel solver (our solver's reference) is reliable in this range (path.py)
GRID_PER_BLEND = 12  # toppra gridpoint intervals per blend ...
GRID_LINES = 100  # ... and at least this many over the straight pieces of a run, in proportion to length
GRID_PER_LINE_MIN = 8
GRID_RAMP = 10  # intervals over each end of a long straight piece (PiecewisePath.gridpoints)
GRID_MAX = 1500
_CHUNK = 512  # corners evaluated together (bounds the temporary arrays)


def _bernstein_to_power() -> FloatArray:
    """M with B(t) = sum_m (M @ P)[m] t^m for the quintic Bezier with control points P."""
    m = np.zeros((6, 6))
    for k in range(6):
        for i in range(6 - k):
            m[k + i, k] = comb(5, k) * comb(5 - k, i) * (-1.0) ** i
    return m


_M = _bernstein_to_power()


def _shape_coefficients(rho: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Power-basis coefficients (len(rho), 6) of f and g with B(t) - c = l (f(t) u1 + g(t) u2)."""
    r = np.asarray(rho, dtype=np.float64)[:, None]
    zero = np.zeros_like(r)
    one = np.ones_like(r)
    alpha = np.hstack([-one, -(1.0 - r), -(1.0 - 2.0 * r), zero, zero, zero])
    beta = np.hstack([zero, zero, zero, 1.0 - 2.0 * r, 1.0 - r, one])
    f: FloatArray = alpha @ _M.T
    g: FloatArray = beta @ _M.T
    return f, g


def _powers(t: FloatArray, order: int) -> FloatArray:
    """(len(t), 6): d^order/dt^order of t^m for m = 0..5."""
    out = np.zeros((t.size, 6))
    for k in range(order, 6):
        c = float(np.prod(np.arange(k - order + 1, k + 1))) if order else 1.0
        out[:, k] = c * t ** (k - order)
    return out


_D1 = np.array([5.0, 4.0, 3.0, 2.0, 1.0])  # d/ds of the quintic's terms, highest order first
_D2 = np.array([20.0, 12.0, 6.0, 2.0])  # d2/ds2
_D3 = np.array([60.0, 24.0, 6.0])  # d3/ds3
_F, _G = _shape_coefficients(RHOS)
# each shape on its own (a run's pieces: the product of one row is not always the bits of a row of the product)
_ONE_SHAPE = [_shape_coefficients(RHOS[k : k + 1]) for k in range(RHOS.size)]
_P0, _P1, _P2 = _powers(_T, 0), _powers(_T, 1), _powers(_T, 2)
# samples of f, g and their t-derivatives: (n_rho, n_t)
_FS, _GS = _F @ _P0.T, _G @ _P0.T
_F1, _G1 = _F @ _P1.T, _G @ _P1.T
_F2, _G2 = _F @ _P2.T, _G @ _P2.T
_F3, _G3 = _F @ _powers(_T, 3).T, _G @ _powers(_T, 3).T


@dataclass(frozen=True)
class Corner:
    """The blend at one interior waypoint (z coordinates); `half_length` 0 means an exact stop."""

    index: int  # waypoint index
    half_length: float  # l: the blend starts l before the corner and ends l after it (z units)
    rho: float  # d / l
    deviation: float  # largest deviation of the blend in tolerance-scaled units (<= 1)


class PiecewisePath:
    """One rest-to-rest run: straight pieces and quintic blends, a C2 piecewise polynomial q(s)."""

    def __init__(
        self,
        breakpoints: FloatArray,
        coefficients: FloatArray,
        blends: IntArray,
        n_axes: int,
        ramps: FloatArray | None = None,
    ):
        self.breakpoints = breakpoints  # (P+1,) s at the piece boundaries
        self.blends = blends  # (P,) 1 where the piece is a blend
        # (P,) on a straight piece, the path length over which it reaches its top speed from rest (inf:
        # unknown, or a blend): where the time-optimal profile accelerates, toppra needs its gridpoints
        self.ramps = ramps if ramps is not None else np.full(blends.size, np.inf)
        self._dof = n_axes
        # the coefficients of q, q', q'' and q''' (user units; of (s - s_j)^(5-k), highest order first, as scipy's
        # PPoly and its derivatives have them), evaluated by `_evaluate`
        c = np.ascontiguousarray(coefficients, dtype=np.float64)  # (6, P, n_axes)
        self._coefficients = (c, c[:-1] * _D1[:, None, None], c[:-2] * _D2[:, None, None],
                              np.ascontiguousarray(c[:-3] * _D3[:, None, None]))

    @property
    def length(self) -> float:
        return float(self.breakpoints[-1])

    @property
    def dof(self) -> int:
        return self._dof

    @property
    def waypoints(self) -> FloatArray:
        return self(self.breakpoints)

    def __call__(self, s: FloatArray, order: int = 0) -> FloatArray:
        """q(s) (order 0), q'(s), q''(s) or q'''(s) at the path positions `s` (clipped to the path): (len(s), n)."""
        x = np.clip(np.asarray(s, dtype=np.float64), 0.0, self.length)
        return _evaluate(self._coefficients[order], self.breakpoints, np.ascontiguousarray(x.ravel()))

    def trace(self, s: FloatArray, sd: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
        """Along a traversal (path position `s` and velocity `sd` at every ms): q, the joint velocities
        q' sd and the direction q', each (len(s), n) (a tick's axes contiguous), and whether each ms is in
        a blend. One pass for what `__call__` and `merge_safe` give, to the bit."""
        x = np.clip(np.asarray(s, dtype=np.float64), 0.0, self.length)
        return _trace(self._coefficients[0], self._coefficients[1], self.breakpoints, self.blends, x,
                      np.asarray(sd, dtype=np.float64))

    def merge_safe(self, s: FloatArray) -> NDArray[np.bool_]:
        """True on the straight pieces (path.Profile merges short switch pieces only there)."""
        piece = np.clip(np.searchsorted(self.breakpoints, s, side="right") - 1, 0, self.blends.size - 1)
        out: NDArray[np.bool_] = self.blends[piece] == 0
        return out

    def gridpoints(self) -> FloatArray:
        """toppra's gridpoints: `GRID_PER_BLEND` intervals in every blend (its curvature needs them), the
        straight pieces in proportion to their length, with `GRID_RAMP` more near each end of a long
        one, where the profile accelerates or brakes (a long slow line otherwise has a handful of
        intervals there, and the duration suffers: 2 % measured on 3 s lines at a third of the speed);
        every piece boundary a gridpoint."""
        b = self.breakpoints
        lengths = np.diff(b)
        lines = self.blends == 0
        total_line = float(lengths[lines].sum())
        n_lines = int(lines.sum())
        budget = max(GRID_LINES, GRID_PER_LINE_MIN * n_lines)
        counts = np.where(
            lines,
            np.maximum(GRID_PER_LINE_MIN, np.round(budget * lengths / max(total_line, 1e-300))),
            GRID_PER_BLEND,
        ).astype(np.int64)
        long = lines & (lengths > 3.0 * self.ramps)
        counts = counts + np.where(long, 2 * GRID_RAMP, 0)
        if counts.sum() > GRID_MAX:  # very many pieces: fewer per piece, at least one interval each
            counts = np.maximum(1, np.floor(counts * GRID_MAX / counts.sum())).astype(np.int64)
            long = long & (counts > 2 * GRID_RAMP)
        parts = []
        for k in range(lengths.size):
            if long[k]:
                r = 1.5 * float(self.ramps[k])
                middle = int(counts[k]) - 2 * GRID_RAMP
                ends = np.arange(GRID_RAMP) / GRID_RAMP * r
                mid = r + (lengths[k] - 2.0 * r) * np.arange(max(middle, 1)) / max(middle, 1)
                parts.append(b[k] + np.concatenate([ends, mid, lengths[k] - r + ends]))
            else:
                parts.append(b[k] + lengths[k] * np.arange(counts[k]) / counts[k])
        out: FloatArray = np.unique(np.concatenate([*parts, b[-1:]]))
        return out


@kernel
def _evaluate(c: FloatArray, x: FloatArray, s: FloatArray) -> FloatArray:
    """A piecewise polynomial (coefficients c (K, P, n) of (s - x_j)^(K-1-k), breakpoints x) at `s`, each
    point in the piece [x_j, x_j+1) that holds it (the end in the last one): scipy's PPoly, term by term
    (the powers summed from the lowest), so the values are scipy's to the bit."""
    k, pieces, n = c.shape
    out = np.empty((s.size, n))
    for i in range(s.size):
        j = min(max(np.searchsorted(x, s[i], side="right") - 1, 0), pieces - 1)
        d = s[i] - x[j]
        for a in range(n):
            res = 0.0
            z = 1.0
            for kp in range(k):
                res = res + c[k - kp - 1, j, a] * z
                if kp < k - 1:
                    z *= d
            out[i, a] = res
    return out


@kernel
def _trace(
    c0: FloatArray, c1: FloatArray, x: FloatArray, blends: IntArray, s: FloatArray, sd: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
    """`PiecewisePath.trace`: q and q' as `_evaluate` computes them, with the piece of each (sorted) s
    followed instead of searched."""
    k, pieces, n = c0.shape
    total = s.size
    q, v, q1 = np.empty((total, n)), np.empty((total, n)), np.empty((total, n))
    curved = np.empty(total, dtype=np.bool_)
    power = np.empty(k)
    j = 0
    for i in range(total):
        if i == 0 or s[i] < s[i - 1]:
            j = min(max(np.searchsorted(x, s[i], side="right") - 1, 0), pieces - 1)
        while j + 1 < pieces and x[j + 1] <= s[i]:
            j += 1
        curved[i] = blends[j] != 0
        # the powers of s - x_j as `_evaluate` forms them (z *= d), shared by q and q'
        power[0] = 1.0
        for kp in range(1, k):
            power[kp] = power[kp - 1] * (s[i] - x[j])
        for a in range(n):
            res = 0.0
            for kp in range(k):
                res = res + c0[k - kp - 1, j, a] * power[kp]
            q[i, a] = res
            res = 0.0
            for kp in range(k - 1):
                res = res + c1[k - kp - 2, j, a] * power[kp]
            q1[i, a] = res
            v[i, a] = res * sd[i]
    return q, v, q1, curved


def corner_blends(
    waypoints: FloatArray,
    vlim: FloatArray,
    tolerance: FloatArray,
    alim: FloatArray | None = None,
    min_blend_ms: float = 0.0,
    jerk: FloatArray | None = None,
) -> tuple[list[Corner], FloatArray, FloatArray]:
    """The blend of every interior waypoint (see the module docstring), and the segments' unit
    directions (K-1, n) and lengths (K-1,) in z coordinates. `tolerance` (n,) in user units; an axis
    with tolerance <= 0 must not deviate at all. With `alim`, a blend that cannot last `min_blend_ms`
    (`blend_duration_ms`: even at the largest speed its curvature allows) is an exact stop instead.
    With `jerk` (and `alim`), the shape of each blend is the one crossed fastest at a constant speed
    (`_constant_speed_shapes`) rather than the one of the largest radius."""
    z = waypoints / vlim[None, :]
    seg = np.diff(z, axis=0)
    lengths = np.linalg.norm(seg, axis=1)
    u = seg / np.maximum(lengths, 1e-300)[:, None]
    k = waypoints.shape[0]
    corners: list[Corner] = []
    if k < 3:
        return corners, u, lengths
    u1, u2 = u[:-1], u[1:]
    cos = np.clip(np.einsum("ij,ij->i", u1, u2), -1.0, 1.0)
    exact_axis = tolerance <= 0.0
    moving = np.abs(seg) > 0.0
    stop = (moving[:-1] | moving[1:])[:, exact_axis].any(axis=1) & (cos < COLLINEAR_COS)
    scale = vlim / np.where(exact_axis, 1.0, tolerance)  # z -> y per axis
    y1, y2 = u1 * scale[None, :], u2 * scale[None, :]
    a11 = np.einsum("ij,ij->i", y1, y1)
    a12 = np.einsum("ij,ij->i", y1, y2)
    a22 = np.einsum("ij,ij->i", y2, y2)
    half = 0.5 * np.minimum(lengths[:-1], lengths[1:])
    hl = np.zeros(k - 2)
    rho = np.full(k - 2, RHOS[-1])
    dev = np.zeros(k - 2)
    for lo in range(0, k - 2, _CHUNK):
        sl = slice(lo, min(lo + _CHUNK, k - 2))
        if jerk is not None and alim is not None:
            h, r, d = _constant_speed_shapes(cos[sl], a11[sl], a12[sl], a22[sl], half[sl], u1[sl], u2[sl],
                                             vlim, alim, jerk)
        else:
            h, r, d = _size(cos[sl], a11[sl], a12[sl], a22[sl], half[sl])
        hl[sl], rho[sl], dev[sl] = h, r, d
    tiny = hl < MIN_BLEND_SHARE * 2.0 * half
    if alim is not None and min_blend_ms > 0.0 and k > 2:
        tiny = tiny | (blend_duration_ms(u1, u2, hl, rho, vlim, alim) < min_blend_ms)
    # a reversal stops anyway: a blend would only turn back before the waypoint, in a fold the chain
    # cannot follow within a few ms
    tiny = tiny | (cos <= REVERSAL_COS)
    for i in range(k - 2):
        if cos[i] >= COLLINEAR_COS:
            corners.append(Corner(i + 1, 0.0, 0.0, 0.0))  # straight on: no blend, no stop
        elif stop[i] or tiny[i]:
            corners.append(Corner(i + 1, -1.0, 0.0, 0.0))  # exact stop
        else:
            corners.append(Corner(i + 1, float(hl[i]), float(rho[i]), float(dev[i])))
    return corners, u, lengths


def blend_duration_ms(
    u1: FloatArray, u2: FloatArray, half_length: FloatArray, rho: FloatArray, vlim: FloatArray, alim: FloatArray
) -> FloatArray:
    """A lower bound of the time each blend takes (ms): along it, no faster than its curvature lets
    every joint's centripetal acceleration stay within its limit (and never above full speed).

    A blend much shorter in time than the encoder's shortest segment swings the joints' accelerations
    faster than any sequence of drive segments can follow within one count; planner.plan makes those
    corners exact stops (`MIN_BLEND_SEGMENTS`).
    """
    shape = np.where(rho > 0, np.abs(RHOS[None, :] - rho[:, None]).argmin(axis=1), RHOS.size - 1)
    return _blend_duration(u1, u2, half_length, shape, vlim / alim, _F1, _G1, _F2, _G2, _T)


@kernel
def _blend_duration(
    u1: FloatArray, u2: FloatArray, half_length: FloatArray, shape: IntArray, v_over_a: FloatArray,
    f1: FloatArray, g1: FloatArray, f2: FloatArray, g2: FloatArray, t: FloatArray,
) -> FloatArray:
    """`blend_duration_ms`: along each blend (shape `shape`, half-length l, legs u1, u2), at the samples t of
    its Bezier parameter, the speed |B'| and the curvature vector kappa = (B'' - (B''.T) T) / |B'|^2
    (B' = l (f' u1 + g' u2), T = B' / |B'|); the joints allow a speed (z per s) of at most
    1 / sqrt(max_j |kappa_j| vlim_j / alim_j), and never above 1; the time is the integral of |B'| / speed
    over the parameter (trapezoids)."""
    corners, n = u1.shape
    out = np.zeros(corners)
    b1 = np.empty(n)
    b2 = np.empty(n)
    for c in range(corners):
        r = shape[c]
        ell = half_length[c]
        previous = 0.0
        total = 0.0
        for k in range(t.size):
            speed2 = 0.0
            for j in range(n):
                b1[j] = ell * (f1[r, k] * u1[c, j] + g1[r, k] * u2[c, j])
                b2[j] = ell * (f2[r, k] * u1[c, j] + g2[r, k] * u2[c, j])
                speed2 += b1[j] * b1[j]
            speed = np.sqrt(speed2)
            along = 0.0
            for j in range(n):
                along += b2[j] * b1[j] / max(speed, 1e-300)
            need = 0.0
            for j in range(n):
                curv = (b2[j] - along * b1[j] / max(speed, 1e-300)) / max(speed, 1e-150) ** 2
                need = max(need, abs(curv) * v_over_a[j])
            value = speed / min(1.0, 1.0 / np.sqrt(max(need, 1e-300)))
            if k > 0:
                total += (t[k] - t[k - 1]) * (value + previous) / 2.0
            previous = value
        out[c] = 1000.0 * total
    return out


def _size(
    cos: FloatArray, a11: FloatArray, a12: FloatArray, a22: FloatArray, half: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Half-length l, shape rho and scaled deviation of the blends of a chunk of corners."""
    best, hl, dev = _size_kernel(cos, a11, a12, a22, half, _FS, _GS, _F1, _G1, _F2, _G2, REVERSAL_COS)
    return hl, RHOS[best], dev


def _constant_speed_shapes(
    cos: FloatArray, a11: FloatArray, a12: FloatArray, a22: FloatArray, half: FloatArray, u1: FloatArray,
    u2: FloatArray, vlim: FloatArray, alim: FloatArray, jerk: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """`_size` for blends crossed at one constant path speed (planner/motion/jerkpath.py): of the shapes,
    each at the largest half-length its deviation allows, the one whose speed bound is highest. At a
    constant speed v the joints move at q' v, accelerate at q'' v^2 and jerk at q''' v^3; with
    B = c + l (f u1 + g u2) in z and the parameter length 5 rho l, q^(k)_j = vlim_j l (f^(k) u1_j +
    g^(k) u2_j) / (5 rho l)^k. The largest radius (`_size`) is the acceleration's criterion; a blend
    sized for it is often short and tight where the jerk bound, which grows as l^(2/3), is the one
    that holds the speed down (on the demo path: 0.12-0.85 of full speed against 0.53-1.0)."""
    corners = cos.size
    speeds = np.full((RHOS.size, corners), -np.inf)
    lengths = np.zeros((RHOS.size, corners))
    devs = np.zeros((RHOS.size, corners))
    for r in range(RHOS.size):
        one = slice(r, r + 1)
        _best, hl, dev = _size_kernel(cos, a11, a12, a22, half, _FS[one], _GS[one], _F1[one], _G1[one], _F2[one],
                                      _G2[one], REVERSAL_COS)
        lengths[r], devs[r] = hl, dev
        lb = 5.0 * RHOS[r] * np.maximum(hl, 1e-300)
        bound = np.full(corners, np.inf)
        for order, (f, g, limit, root) in enumerate(((_F1, _G1, vlim, 1.0), (_F2, _G2, alim, 0.5),
                                                     (_F3, _G3, jerk, 1.0 / 3.0)), start=1):
            # (corners, samples, axes): the joints' k-th derivative along the path at each sample
            qk = (f[r][None, :, None] * u1[:, None, :] + g[r][None, :, None] * u2[:, None, :]) * (
                vlim[None, None, :] * (hl / lb**order)[:, None, None])
            with np.errstate(divide="ignore"):
                worst = np.max(np.abs(qk) / limit[None, None, :], axis=(1, 2))
                bound = np.minimum(bound, np.where(worst > 0.0, worst ** -root, np.inf))
        speeds[r] = np.where(hl > 0.0, bound, -np.inf)
    best = np.argmax(speeds, axis=0)
    best = np.where(cos <= REVERSAL_COS, RHOS.size - 1, best)
    pick = np.arange(corners)
    return lengths[best, pick], RHOS[best], devs[best, pick]


@kernel
def _size_kernel(
    cos: FloatArray, a11: FloatArray, a12: FloatArray, a22: FloatArray, half: FloatArray, fs: FloatArray,
    gs: FloatArray, f1: FloatArray, g1: FloatArray, f2: FloatArray, g2: FloatArray, reversal_cos: float,
) -> tuple[IntArray, FloatArray, FloatArray]:
    """For each corner, over the shapes (rows of the samples fs, gs: (R, T)): the blend's deviation at l = 1
    (the larger of its closest approach to the corner and its largest distance from the legs, in the
    y = q / tol norm: |p|^2 = f^2 |Y1|^2 + 2 f g Y1.Y2 + g^2 |Y2|^2), its length (deviation 1, at most
    `half`) and its smallest radius of curvature in z (kappa = |f'g'' - g'f''| sin / |B'|^3); the shape
    of the largest radius wins (the middle one for a reversal, which turns back whatever the shape)."""
    corners = cos.size
    shapes, samples = fs.shape
    best = np.zeros(corners, dtype=np.int64)
    hl = np.zeros(corners)
    dev = np.zeros(corners)
    length = np.empty(shapes)
    dev1 = np.empty(shapes)
    # the curvature's terms that do not depend on the corner
    f1_2, f1g1_2, g1_2 = np.empty((shapes, samples)), np.empty((shapes, samples)), np.empty((shapes, samples))
    cross1 = np.empty((shapes, samples))
    for r in range(shapes):
        for t in range(samples):
            f1_2[r, t] = f1[r, t] ** 2
            f1g1_2[r, t] = 2.0 * f1[r, t] * g1[r, t]
            g1_2[r, t] = g1[r, t] ** 2
            cross1[r, t] = abs(f1[r, t] * g2[r, t] - g1[r, t] * f2[r, t])
    for c in range(corners):
        b11, b12, b22 = a11[c], a12[c], a22[c]
        sin = np.sqrt(max(1.0 - cos[c] * cos[c], 0.0))
        top = -np.inf
        for r in range(shapes):
            dist_c = np.inf
            dist_legs = -np.inf
            kmax = -np.inf
            for t in range(samples):
                f, g = fs[r, t], gs[r, t]
                pp = f * f * b11 + 2.0 * f * g * b12 + g * g * b22
                dist_c = min(dist_c, np.sqrt(max(pp, 0.0)))
                # distance to leg 1 {-lam Y1} and leg 2 {lam Y2}, lam in [0, 1]
                p_y1 = f * b11 + g * b12
                lam1 = min(max(-p_y1 / max(b11, 1e-300), 0.0), 1.0)
                d1 = pp + 2.0 * lam1 * p_y1 + lam1 * lam1 * b11
                p_y2 = f * b12 + g * b22
                lam2 = min(max(p_y2 / max(b22, 1e-300), 0.0), 1.0)
                d2 = pp - 2.0 * lam2 * p_y2 + lam2 * lam2 * b22
                dist_legs = max(dist_legs, np.sqrt(max(min(d1, d2), 0.0)))
                speed2 = f1_2[r, t] + f1g1_2[r, t] * cos[c] + g1_2[r, t]
                cross = cross1[r, t] * sin
                kmax = max(kmax, cross / max(speed2, 1e-300) ** 1.5 if speed2 > 1e-24 else np.inf)
            dev1[r] = max(dist_c, dist_legs)
            length[r] = min(1.0 / max(dev1[r], 1e-300), half[c])
            radius = length[r] / kmax if np.isfinite(kmax) and kmax > 0 else 0.0
            if radius > top:
                top, best[c] = radius, r
        if cos[c] <= reversal_cos:
            best[c] = shapes - 1
        hl[c] = length[best[c]]
        dev[c] = dev1[best[c]] * hl[c]
    return best, hl, dev


def blended_runs(
    waypoints: FloatArray,
    vlim: FloatArray,
    tolerance: FloatArray,
    alim: FloatArray | None = None,
    min_blend_ms: float = 0.0,
    jerk: FloatArray | None = None,
) -> tuple[list[PiecewisePath], list[Corner]]:
    """The runs (between exact stops) of the blended polyline through `waypoints` (user units); with
    `jerk`, blends shaped for a constant-speed crossing (`corner_blends`)."""
    n = waypoints.shape[1]
    corners, u, lengths = corner_blends(waypoints, vlim, tolerance, alim, min_blend_ms, jerk)
    z = waypoints / vlim[None, :]
    k = waypoints.shape[0]
    cut = [0] + [c.index for c in corners if c.half_length < 0] + [k - 1]
    hl = np.zeros(k)
    rho = np.zeros(k)
    for c in corners:
        if c.half_length > 0:
            hl[c.index], rho[c.index] = c.half_length, c.rho
    ramps = _ramps(u, vlim, alim)
    runs = [_run(z, u, lengths, hl, rho, a, b, vlim, n, ramps) for a, b in itertools.pairwise(cut)]
    return runs, corners


def _run(
    z: FloatArray,
    u: FloatArray,
    lengths: FloatArray,
    hl: FloatArray,
    rho: FloatArray,
    first: int,
    last: int,
    vlim: FloatArray,
    n: int,
    ramps: FloatArray,
) -> PiecewisePath:
    """Pieces of the run from waypoint `first` to `last` as power-basis coefficients in s (z units);
    `ramps`: each segment's `_ramps`."""
    coefs: list[FloatArray] = []  # each (6, n): coefficient of (s - s0)^m, m = 0..5
    plen: list[float] = []
    blend: list[int] = []
    ramp: list[float] = []
    for seg in range(first, last):
        start_off = hl[seg] if seg > first else 0.0
        end_off = hl[seg + 1] if seg + 1 < last else 0.0
        line = lengths[seg] - start_off - end_off
        if line > 1e-12 * lengths[seg]:
            c = np.zeros((6, n))
            c[0] = z[seg] + start_off * u[seg]
            c[1] = u[seg]
            coefs.append(c)
            plen.append(float(line))
            blend.append(0)
            ramp.append(float(ramps[seg]))
        if seg + 1 < last and hl[seg + 1] > 0.0:
            corner = seg + 1
            ell = hl[corner]
            f, g = _ONE_SHAPE[int(np.argmin(np.abs(RHOS - rho[corner])))]  # rho is one of the shapes
            lb = 5.0 * rho[corner] * ell  # parameter length: q'(s) at the ends equals the lines'
            c = np.zeros((6, n))
            c[0] = z[corner]
            c += ell * (f[0][:, None] * u[seg][None, :] + g[0][:, None] * u[seg + 1][None, :])
            c = c / (lb ** np.arange(6))[:, None]
            coefs.append(c)
            plen.append(float(lb))
            blend.append(1)
            ramp.append(np.inf)
    if not coefs:  # a run of one vanishing segment: a zero-length line (callers merge such waypoints)
        c = np.zeros((6, n))
        c[0] = z[first]
        c[1] = u[first] if first < u.shape[0] else 0.0
        coefs.append(c)
        plen.append(max(float(lengths[first]) if first < lengths.size else 0.0, 1e-12))
        blend.append(0)
        ramp.append(np.inf)
    total = float(np.sum(plen))
    # rescale s so toppra sees a path length in [S_MIN, S_MAX]: coefficient m scales by 1/k^m
    k = S_MAX / total if total > S_MAX else (S_MIN / total if total < S_MIN else 1.0)
    x = np.concatenate([[0.0], np.cumsum(plen)]) * k
    x[-1] = max(x[-1], x[-2] + 1e-15)
    cc = np.stack(coefs, axis=1)  # (6, P, n) lowest order first
    cc = cc / (k ** np.arange(6))[:, None, None]
    cc = cc * vlim[None, None, :]  # z -> user units
    return PiecewisePath(x, cc[::-1].copy(), np.array(blend, dtype=np.int64), n, np.array(ramp) * k)


def _ramps(directions: FloatArray, vlim: FloatArray, alim: FloatArray | None) -> FloatArray:
    """For each segment, the path length (z units) a straight piece along its unit `directions` row (z)
    needs to reach its top speed from rest: top speed 1 / max |u_j| (the first joint at its velocity
    limit), path acceleration the tightest alim_j / (vlim_j |u_j|); inf where nothing moves."""
    out = np.full(directions.shape[0], np.inf)
    if alim is None:
        return out
    share = np.abs(directions)
    moving = share > 0.0
    rows = moving.any(axis=1)
    with np.errstate(divide="ignore"):
        top = 1.0 / share.max(axis=1)
        acc = np.where(moving, alim[None, :] / (vlim[None, :] * share), np.inf).min(axis=1)
    out[rows] = (top * top / (2.0 * acc))[rows]
    return out


def polyline_deviation(points: FloatArray, waypoints: FloatArray, scale: FloatArray) -> FloatArray:
    """How far each of `points` (M, n) is from the polyline through `waypoints` (K, n), per axis in
    units of `scale` (n,): the smallest, over the points p of the polyline, of max_j |x_j - p_j| / scale_j.
    A measurement for tests and benchmarks (the planner keeps its paths within 1 by construction).

    The scaled Euclidean distance bounds it from above and is cheap; points where that bound exceeds 1
    get the exact value (the minimum over each segment of a convex piecewise-linear function of the
    segment parameter, reached at one of its breakpoints).
    """
    x = points / scale[None, :]
    w = waypoints / scale[None, :]
    a, d = w[:-1], np.diff(w, axis=0)  # segments a + lam d
    dd = np.einsum("kj,kj->k", d, d)
    best = np.full(x.shape[0], np.inf)
    for k in range(a.shape[0]):
        r = x - a[k][None, :]
        lam = np.clip(r @ d[k] / dd[k], 0.0, 1.0) if dd[k] > 0 else np.zeros(x.shape[0])
        best = np.minimum(best, np.linalg.norm(r - lam[:, None] * d[k][None, :], axis=1))
    hard = np.nonzero(best > 1.0)[0]
    if hard.size:
        best[hard] = _box_distance(x[hard], a, d)
    return best


def point_to_path(points: FloatArray, path: FloatArray, scale: FloatArray) -> FloatArray:
    """For each of a few `points` (P, n), how close the polyline through the many samples `path` (M, n)
    comes (same metric as `polyline_deviation`): does a sampled motion pass a waypoint?"""
    y = path / scale[None, :]
    a, d = y[:-1], np.diff(y, axis=0)
    dd = np.maximum(np.einsum("kj,kj->k", d, d), 1e-300)
    out = np.empty(points.shape[0])
    for i, p in enumerate(points / scale[None, :]):
        r = p[None, :] - a
        lam = np.clip(np.einsum("kj,kj->k", r, d) / dd, 0.0, 1.0)
        euclid = np.linalg.norm(r - lam[:, None] * d, axis=1)
        k = int(np.argmin(euclid))
        out[i] = euclid[k]
        if out[i] > 1.0:  # exact, on the segments that can still be within 1
            near = np.nonzero(euclid <= np.sqrt(p.size) * max(out[i], 1.0))[0]
            out[i] = float(_box_distance(p[None, :], a[near], d[near]).min()) if near.size else out[i]
    return out


def _box_distance(x: FloatArray, a: FloatArray, d: FloatArray) -> FloatArray:
    """Exact min over segments and lam in [0, 1] of max_j |x_j - a_j - lam d_j| (see polyline_deviation)."""
    n = x.shape[1]
    out = np.full(x.shape[0], np.inf)
    for k in range(a.shape[0]):
        r = x - a[k][None, :]  # (P, n); f(lam) = max_j |r_j - lam d_j|
        dk = d[k]
        cands = [np.zeros(x.shape[0]), np.ones(x.shape[0])]
        with np.errstate(divide="ignore", invalid="ignore"):
            for j in range(n):
                if dk[j] != 0.0:
                    cands.append(r[:, j] / dk[j])
                for i in range(j + 1, n):
                    for sgn in (1.0, -1.0):
                        den = dk[j] - sgn * dk[i]
                        if den != 0.0:
                            cands.append((r[:, j] - sgn * r[:, i]) / den)
        lam = np.clip(np.nan_to_num(np.stack(cands, axis=1)), 0.0, 1.0)  # (P, C)
        val = np.abs(r[:, None, :] - lam[:, :, None] * dk[None, None, :]).max(axis=2).min(axis=1)
        out = np.minimum(out, val)
    return out
