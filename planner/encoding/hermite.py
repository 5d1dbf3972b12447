"""The drive's cubic interpolation between two PVT reference points (seed 000, section 4.2.3).

The single definition of what a drive does with its records: the encoder verifies with it, the simulated
drive's demand (0x6062) comes from it. In tau = t - t0 from the segment END (tau in [-T, 0]):

    d = P[n]                c = V[n]
    b = T^-2 * (-3 * (P[n] - P[n-1]) + T * (2 * V[n] + V[n-1]))
    a = T^-3 * (-2 * (P[n] - P[n-1]) + T * (V[n] + V[n-1]))
    P(tau) = a tau^3 + b tau^2 + c tau + d,   V(tau) = 3a tau^2 + 2b tau + c,   A(tau) = 6a tau + 2b

The seed's extracted text lost these minus signs; its own definition (the cubic through both end positions
and velocities) wins (tests/planner/encoding/test_hermite.py). Units: counts, ms, rpm (counts_per_rev / 60000 counts
per ms); the demand is rounded half away from zero each tick. quantise.py evaluates it bit for bit alike.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

MS_PER_MINUTE = 60_000.0


def rpm_to_counts_per_ms(rpm: float, counts_per_rev: float) -> float:
    """Velocity in drive units (rpm of the motor shaft) to counts per millisecond."""
    return rpm * counts_per_rev / MS_PER_MINUTE


def counts_per_ms_to_rpm(counts_per_ms: float, counts_per_rev: float) -> float:
    return counts_per_ms * MS_PER_MINUTE / counts_per_rev


def coefficients(
    p_prev: float, v_prev: float, p_end: float, v_end: float, time_ms: float
) -> tuple[float, float, float, float]:
    """(a, b, c, d) of the seed's polynomial for one segment; velocities in counts/ms, tau in ms."""
    t = float(time_ms)
    dp = p_end - p_prev
    d = float(p_end)
    c = float(v_end)
    b = (-3.0 * dp + t * (2.0 * v_end + v_prev)) / (t * t)
    a = (-2.0 * dp + t * (v_end + v_prev)) / (t * t * t)
    return a, b, c, d


def evaluate(coeffs: tuple[float, float, float, float], tau: float) -> tuple[float, float, float]:
    """Position (counts), velocity (counts/ms) and acceleration (counts/ms^2) at tau in [-T, 0]."""
    a, b, c, d = coeffs
    return (
        ((a * tau + b) * tau + c) * tau + d,
        (3.0 * a * tau + 2.0 * b) * tau + c,
        6.0 * a * tau + 2.0 * b,
    )


def round_counts(x: float) -> int:
    """The drive's position demand: half away from zero, to whole counts."""
    return math.floor(x + 0.5) if x >= 0 else -math.floor(-x + 0.5)


def round_counts_array(x: NDArray[np.float64]) -> NDArray[np.int64]:
    """`round_counts` of every element (half away from zero): trunc(x + 0.5) above zero, and the
    mirror image below (x - 0.5 is exactly -(|x| + 0.5) there), in two passes instead of four."""
    return np.trunc(x + np.copysign(0.5, x)).astype(np.int64)


def truncate_counts(x: float) -> int:
    """The other reading of the demand's rounding the manuals permit: toward zero."""
    return math.trunc(x)


def truncate_counts_array(x: NDArray[np.float64]) -> NDArray[np.int64]:
    return np.trunc(x).astype(np.int64)


def demand_from_coefficients(coeffs: tuple[float, float, float, float], time_ms: int,
                             toward_zero: bool = False) -> list[int]:
    """Position demand at each tick tau = k - T, k = 1..T, of a segment with these coefficients.

    The drive's inner loop, so it is written out: the same float evaluation order as `evaluate`
    (((a*tau + b)*tau + c)*tau + d) and the same rounding as `round_counts` (or `truncate_counts` with
    `toward_zero`), without a call per tick.
    """
    a, b, c, d = coeffs
    out = []
    if toward_zero:
        trunc = math.trunc
        for tau in range(1 - time_ms, 1):
            out.append(trunc(((a * tau + b) * tau + c) * tau + d))
        return out
    floor = math.floor
    for tau in range(1 - time_ms, 1):
        x = ((a * tau + b) * tau + c) * tau + d
        out.append(floor(x + 0.5) if x >= 0 else -floor(-x + 0.5))
    return out


def segment_demand(p_prev: int, v_prev: float, p_end: int, v_end: float, time_ms: int) -> list[int]:
    """Position demand at each 1 ms tick k = 1..T of one segment (velocities in counts/ms)."""
    return demand_from_coefficients(coefficients(p_prev, v_prev, p_end, v_end, time_ms), time_ms)


def reconstruct(
    positions: NDArray[np.int64] | NDArray[np.float64],
    velocities_counts_per_ms: NDArray[np.float64],
    dt_ms: NDArray[np.int64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Vectorised drive reconstruction of one axis over the whole trajectory.

    `positions` and `velocities_counts_per_ms` have one entry per knot (N+1), `dt_ms` one per segment
    (N). Returns unrounded position, velocity (counts/ms) and acceleration (counts/ms^2) sampled at
    every ms from t = 0 to t = sum(dt_ms), i.e. sum(dt_ms) + 1 samples. Where a segment ends at a
    knot, the sample is that knot (the next segment's tau = -T equals it by construction).
    """
    p = np.asarray(positions, dtype=np.float64)
    v = np.asarray(velocities_counts_per_ms, dtype=np.float64)
    dt = np.asarray(dt_ms, dtype=np.int64)
    n_seg = dt.shape[0]
    if p.shape != (n_seg + 1,) or v.shape != (n_seg + 1,):
        raise ValueError(f"need {n_seg + 1} knots for {n_seg} segments, got {p.shape} and {v.shape}")
    total = int(dt.sum())
    if n_seg == 0:
        return p[:1].copy(), v[:1].copy(), np.zeros(1)
    t = dt.astype(np.float64)
    dp = p[1:] - p[:-1]
    a = (-2.0 * dp + t * (v[1:] + v[:-1])) / t**3
    b = (-3.0 * dp + t * (2.0 * v[1:] + v[:-1])) / t**2
    seg = np.repeat(np.arange(n_seg), dt)  # segment of every tick 1..total
    ends = np.cumsum(dt)
    tau = (np.arange(1, total + 1) - ends[seg]).astype(np.float64)  # in [-T+1, 0]
    aa, bb, cc, dd = a[seg], b[seg], v[1:][seg], p[1:][seg]
    pos = np.empty(total + 1)
    vel = np.empty(total + 1)
    acc = np.empty(total + 1)
    pos[0], vel[0] = p[0], v[0]
    acc[0] = 6.0 * a[0] * (-t[0]) + 2.0 * b[0]
    pos[1:] = ((aa * tau + bb) * tau + cc) * tau + dd
    vel[1:] = (3.0 * aa * tau + 2.0 * bb) * tau + cc
    acc[1:] = 6.0 * aa * tau + 2.0 * bb
    return pos, vel, acc
