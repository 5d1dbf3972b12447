"""The baseline an encoding is measured against: the coarsest uniform grid that meets the same tolerance.

Theory of operation. Sample the plan every `dt` ms (knots at the planned demand and the nearest rpm, the
first at the start state, the last at rest on the end); the grid meets the tolerance when the drive's
reconstruction stays within `tolerance_counts` at every ms (the encoder's contract without its
acceleration budget). Passing is not monotone in `dt`, so every `dt` is tried from the longest down.
The adaptive encoder must not use more points (tests/planner, benchmarks/bench_planner.py). With
`margins` a grid must also keep the encoder's velocity, acceleration and excess-budget promises: a short
last segment can meet the tolerance by luck while shaking the acceleration far beyond the budget.
"""

from __future__ import annotations

import numpy as np

from planner.encoding.encoder import within_contract
from planner.encoding.reconstruction import AxisScales, Knots, planned_demand, reconstruct
from planner.encoding.record import SEGMENT_TIME_MAX_MS
from planner.motion.reference import IntArray, Reference


def uniform_knots(ref: Reference, scales: AxisScales, dt: int, first: Knots) -> Knots:
    """The plain encoding of `ref` on a uniform grid of `dt` ms (knot 0 taken from `first`)."""
    m = ref.duration_ms
    times = np.unique(np.concatenate([np.arange(0, m, dt), [m]])).astype(np.int64)
    pos = planned_demand(ref, scales.toward_zero)[:, times].copy()
    vel = np.round(ref.velocities[:, times] / scales.counts_per_ms_per_rpm[:, None]).astype(np.int64)
    pos[:, 0], vel[:, 0] = first.positions[:, 0], first.velocities_rpm[:, 0]
    vel[:, -1] = 0
    return Knots(times, pos, vel)


def meets(
    ref: Reference, scales: AxisScales, tolerance: int, dt: int, first: Knots, want: IntArray, margins: bool = False
) -> bool:
    knots = uniform_knots(ref, scales, dt, first)
    dev = np.abs(reconstruct(knots, scales).demand - want)
    if (dev > tolerance).any():
        return False
    return within_contract(ref, knots, scales, float(tolerance)) if margins else True


def coarsest_uniform(
    ref: Reference, scales: AxisScales, tolerance: int, first: Knots, margins: bool = False
) -> tuple[int, int]:
    """(dt_ms, points) of the coarsest uniform grid meeting `tolerance` (and with `margins`, every other
    promise of the encoder) on `ref`; points include knot 0.

    `first`: knot 0 as the trajectory has it (one knot: its positions and velocities).
    """
    m = ref.duration_ms
    want = planned_demand(ref, scales.toward_zero)
    for dt in range(min(SEGMENT_TIME_MAX_MS, max(m, 1)), 0, -1):
        if meets(ref, scales, tolerance, dt, first, want, margins):
            return dt, -(-m // dt) + 1
    return 1, m + 1
