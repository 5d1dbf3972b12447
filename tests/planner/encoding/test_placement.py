"""The encoder's knot placement (planner/encoding/encoder.py, step 1), compiled: the same knots as the NumPy placement
it replaced (placement_reference.py) on random plans with acceleration steps and hints, for random
budgets, segment bounds and variants; the rebalancing of short segments and the coarsening on knot times
full of short segments (where neighbouring changes collide); the uniform grids' quick check."""

from __future__ import annotations

import numpy as np
import placement_reference as numpy_ref
from hypothesis import given
from hypothesis import strategies as st

from planner.encoding import encoder
from planner.encoding.encoder import AxisScales
from planner.motion.reference import Reference


def _plan(rng: np.random.Generator) -> tuple[Reference, AxisScales]:
    """1-3 axes with piecewise-constant accelerations (steps at random ms, some of them big), hints at
    random ms (a chain's knots, a move's phases), positions far from zero or near it."""
    n = int(rng.integers(1, 4))
    m = int(rng.integers(20, 900))
    limit = rng.uniform(0.001, 0.05, n)
    acc = np.zeros((n, m))
    steps = np.sort(rng.choice(np.arange(1, m), size=min(m - 1, int(rng.integers(1, 12))), replace=False))
    for i in range(n):
        levels = rng.uniform(-1.0, 1.0, steps.size + 1) * limit[i] * rng.choice([0.05, 0.5, 1.0])
        acc[i] = levels[np.searchsorted(steps, np.arange(m), side="right")]
    vel = np.zeros((n, m + 1))
    vel[:, 1:] = np.cumsum(acc, axis=1)
    pos = np.zeros((n, m + 1))
    pos[:, 1:] = np.cumsum(vel[:, :-1] + 0.5 * acc, axis=1)
    pos += rng.choice([0.0, 0.3, -7.5, 1.0e6 + 0.25], n)[:, None]
    acc_left = np.concatenate([acc[:, :1], acc], axis=1)
    acc_right = np.concatenate([acc, acc[:, -1:]], axis=1)
    hints = np.unique(rng.integers(1, m, int(rng.integers(0, 30)))) if rng.random() < 0.7 else np.zeros(0, np.int64)
    ref = Reference(pos, vel, acc_left, acc_right, steps, hints)
    scales = AxisScales(
        counts_per_ms_per_rpm=rng.uniform(0.02, 0.5, n), velocity_limit=np.abs(vel).max(axis=1) + 1.0,
        acceleration_limit=limit, acceleration_axis=limit, drive_velocity=np.full(n, 1e9),
        drive_acceleration=np.full(n, 1e9),
    )
    return ref, scales


@given(st.integers(0, 2**32 - 1))
def test_the_placement_is_the_numpy_one(seed: int) -> None:
    rng = np.random.default_rng(seed)
    ref, scales = _plan(rng)
    budget = float(rng.choice([0.2, 0.5, 0.7, 2.0]))
    min_seg = int(rng.integers(2, 30))
    max_seg = int(rng.integers(min_seg, 256))
    acc_share = float(rng.choice([0.02, 0.04, 0.5]))
    hint_gap = int(rng.choice([0, 1, 7]))
    keep_kinks = bool(rng.random() < 0.7)
    ours = encoder.place_knots(ref, scales, budget, min_seg, max_seg, acc_share, hint_gap, keep_kinks)
    theirs = numpy_ref.place_knots(ref, scales, budget, min_seg, max_seg, acc_share, hint_gap, keep_kinks)
    assert np.array_equal(ours, theirs)


@given(st.integers(0, 2**32 - 1))
def test_rebalancing_and_coarsening_many_short_segments_are_the_numpy_ones(seed: int) -> None:
    rng = np.random.default_rng(seed)
    ref, scales = _plan(rng)
    m = ref.duration_ms
    times = np.unique(np.concatenate([[0, m], rng.integers(1, m, int(rng.integers(2, m // 2)))])).astype(np.int64)
    mand = np.unique(np.concatenate([[0, m], rng.choice(times, int(rng.integers(0, 4)))])).astype(np.int64)
    budget = float(rng.choice([0.2, 0.7, 3.0, 50.0]))
    min_seg = int(rng.integers(2, 20))
    max_seg = int(rng.integers(min_seg, 120))
    args = (mand, budget, min_seg, max_seg, scales.acceleration_axis, float(rng.choice([0.02, 0.5, 5.0])))
    assert np.array_equal(encoder._rebalance(ref, times, *args), numpy_ref._rebalance(ref, times, *args))
    assert np.array_equal(encoder._coarsen(ref, times, *args), numpy_ref._coarsen(ref, times, *args))


@given(st.integers(0, 2**32 - 1))
def test_the_uniform_grids_quick_check_is_the_numpy_one(seed: int) -> None:
    rng = np.random.default_rng(seed)
    ref, scales = _plan(rng)
    m = ref.duration_ms
    tz = rng.random(ref.n_axes) < 0.5
    scales = AxisScales(scales.counts_per_ms_per_rpm, scales.velocity_limit, scales.acceleration_limit,
                        scales.acceleration_axis, scales.drive_velocity, scales.drive_acceleration, tz)
    want = encoder.planned_demand(ref, tz)
    conv = scales.counts_per_ms_per_rpm
    p_first = want[:, 0] + rng.integers(-1, 2, ref.n_axes)
    v_first = np.round(ref.velocities[:, 0] / conv).astype(np.int64)
    v_last = np.round(ref.velocities[:, m] / conv).astype(np.int64)
    tol = float(rng.choice([1.0, 2.0]))
    lengths = np.arange(min(m, 255), 0, -1)
    grids = [np.unique(np.concatenate([np.arange(0, m, dt), [m]])).astype(np.int64) for dt in lengths.tolist()]
    theirs = numpy_ref._quick_misses(ref, grids, want, tol, scales, (p_first, v_first, v_last), (0.25, 0.5, 0.75))
    ours = encoder._uniform_misses(want, ref.velocities, conv, tz, tol, p_first, v_first, v_last, lengths,
                                   np.array([0.5, 0.25, 0.75]))
    assert np.array_equal(ours, theirs)
