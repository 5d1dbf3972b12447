"""The encoder's value search (planner/encoding/encoder.py, step 2 and the refinement of step 3) and its verification,
compiled in planner/encoding/quantise.py: the pruning before the check at every tick keeps exactly the candidates
that lie on a path of feasible pairs, so it never removes one the full search could have chosen; and the
compiled kernels reproduce the NumPy formulation they replaced (encoder_reference.py) bit for bit: the
pair costs (float32 near the plan, as NumPy computed them), the joint choice, the refinement, the drive's
reconstruction and the verification, on random plans with axes that round and axes that truncate. The
refinement's check at every tick starts from the costs at the sample ticks, which must bound the costs
from below: checked too."""

from __future__ import annotations

import dataclasses
import itertools

import encoder_reference as numpy_ref
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from planner.encoding import encoder, quantise
from planner.encoding.encoder import ACC_EXCESS_LIMIT, AxisScales, Knots
from planner.motion.reference import Reference


def _on_a_feasible_path(feasible: np.ndarray, fixed: list[int]) -> np.ndarray:
    """Brute force: every path of candidates through the knots, pinned knots at candidate 0."""
    n, nseg, c, _ = feasible.shape
    out = np.zeros((n, nseg + 1, c), dtype=bool)
    for a in range(n):
        for path in itertools.product(range(c), repeat=nseg + 1):
            if any(path[k] != 0 for k in fixed):
                continue
            if all(feasible[a, k, path[k], path[k + 1]] for k in range(nseg)):
                for k, ck in enumerate(path):
                    out[a, k, ck] = True
    return out


@given(
    st.integers(1, 2),
    st.integers(1, 4),
    st.integers(1, 3),
    st.floats(0.2, 0.9),
    st.integers(0, 2**32 - 1),
    st.booleans(),
)
def test_pruning_keeps_exactly_the_candidates_on_feasible_paths(
    n: int, nseg: int, c: int, share: float, seed: int, pin_ends: bool
) -> None:
    rng = np.random.default_rng(seed)
    feasible = rng.random((n, nseg, c, c)) < share
    fixed = [0, nseg] if pin_ends else []
    pinned = np.zeros(nseg + 1, dtype=bool)
    pinned[fixed] = True
    alive = np.stack([quantise.alive_candidates(feasible[a], pinned) for a in range(n)])
    assert np.array_equal(alive, numpy_ref._alive(feasible, fixed))
    truth = _on_a_feasible_path(feasible, fixed)
    for a in range(n):
        if truth[a].any():
            # a feasible path exists: pruned to exactly the candidates on one
            assert np.array_equal(alive[a], truth[a]), (feasible[a], alive[a], truth[a])
        else:
            # none: every knot keeps at least one candidate, so the search still returns its least bad path
            assert alive[a].any(axis=1).all()


# ----------------------------------------------------------------------------------------------------
# the compiled kernels against the NumPy reference


@given(st.integers(1, 5), st.integers(1, 8), st.integers(0, 2**32 - 1), st.booleans())
def test_best_path_is_numpys_argmin_path(nseg: int, c: int, seed: int, odd: bool) -> None:
    """The Viterbi pass (its minimum taken row by row, columns inner) against NumPy's argmin: ties to the
    first candidate, a nan is a minimum, inf; a pinned knot's columns all alike."""
    rng = np.random.default_rng(seed)
    if odd:
        costs = rng.choice([0.0, 0.5, 1.0, 2.0, 1.0e6, np.inf, np.nan], size=(nseg, c, c))
    else:
        costs = rng.integers(0, 4, (nseg, c, c)).astype(np.float64)
    pinned = rng.random(nseg + 1) < 0.3
    for k in range(nseg):
        if pinned[k + 1]:
            costs[k, :, 1:] = costs[k, :, :1]
    got = quantise._best_path(costs, pinned, np.empty((nseg + 1, c)), np.empty((nseg, c), np.int64), 0)
    assert np.array_equal(got, numpy_ref._viterbi(costs[None])[0])


@dataclasses.dataclass
class Problem:
    ref: Reference
    scales: AxisScales
    times: np.ndarray
    tol: float
    rng: np.random.Generator


def _problem(seed: int) -> Problem:
    """A random plan of 1-3 axes with piecewise-constant accelerations (a drive's scale: 0.02-0.5 counts/ms
    per rpm, accelerations up to the axis limit, so the acceleration budget decides between candidates;
    or coarse velocity steps), far from or near zero, positive and negative; knot times 1-120 ms apart;
    drive limits some pairs break; axes that truncate."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 4))
    m = int(rng.integers(8, 600))
    coarse = rng.random() < 0.2
    conv = rng.uniform(0.5, 3.0, n) if coarse else rng.uniform(0.02, 0.5, n)
    limit = rng.uniform(0.1, 2.0, n)
    acc = np.zeros((n, m))
    for i in range(n):
        steps = np.sort(rng.integers(0, m, int(rng.integers(1, 6))))
        levels = rng.uniform(-1.0, 1.0, steps.size + 1) * limit[i] * rng.choice([0.01, 0.3, 1.0])
        acc[i] = levels[np.searchsorted(steps, np.arange(m), side="right")]
    vel = np.zeros((n, m + 1))
    vel[:, 0] = rng.normal(0.0, 100.0, n) * rng.integers(0, 2, n)
    vel[:, 1:] = vel[:, :1] + np.cumsum(acc, axis=1)
    pos = np.zeros((n, m + 1))
    pos[:, 1:] = np.cumsum(vel[:, :-1] + 0.5 * acc, axis=1)
    pos += rng.choice([0.0, 0.3, -7.5, 1.0e6 + 0.25, -(2.0**30) + 0.5], n)[:, None]
    acc_left = np.concatenate([acc[:, :1], acc], axis=1)
    acc_right = np.concatenate([acc, acc[:, -1:]], axis=1)
    ref = Reference(pos, vel, acc_left, acc_right, np.arange(1, m))
    v_peak = np.abs(vel).max(axis=1) + conv
    scales = AxisScales(
        counts_per_ms_per_rpm=conv,
        velocity_limit=v_peak,
        acceleration_limit=limit,
        acceleration_axis=limit,
        drive_velocity=v_peak * rng.choice([0.95, 1.2, 10.0], n),
        drive_acceleration=limit * rng.choice([0.8, 1.5, 3.0], n),
        toward_zero=rng.random(n) < 0.4 if rng.random() < 0.7 else None,
    )
    gaps = rng.integers(1, rng.choice([20, 120]), m)
    inner = np.cumsum(gaps)
    times = np.concatenate([[0], inner[inner < m], [m]]).astype(np.int64)
    return Problem(ref, scales, times, float(rng.choice([1.0, 1.0, 2.0, 3.0])), rng)


def _ends(p: Problem) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    conv = p.scales.counts_per_ms_per_rpm
    n, m = p.ref.n_axes, p.ref.duration_ms
    first = np.round(p.ref.positions[:, 0]).astype(np.int64) + p.rng.integers(-1, 2, n)
    last = np.round(p.ref.positions[:, m]).astype(np.int64)
    v_first = np.round(p.ref.velocities[:, 0] / conv).astype(np.int64)
    v_last = np.round(p.ref.velocities[:, m] / conv).astype(np.int64) * p.rng.integers(0, 2, n)
    return first, v_first, last, v_last


def _perturbed(p: Problem, knots: Knots) -> Knots:
    pos = knots.positions + p.rng.integers(-2, 3, knots.positions.shape) * (p.rng.random(knots.positions.shape) < 0.3)
    vel = knots.velocities_rpm + p.rng.integers(-4, 5, knots.positions.shape) * (p.rng.random(pos.shape) < 0.3)
    pos[:, 0], vel[:, 0] = knots.positions[:, 0], knots.velocities_rpm[:, 0]
    return Knots(knots.times_ms, pos, vel)


@given(st.integers(0, 2**32 - 1), st.booleans(), st.booleans())
def test_pair_costs_are_the_numpy_ones(seed: int, wide: bool, tiny: bool) -> None:
    p = _problem(seed)
    if tiny:  # far below a count: where a pair passes at the sample ticks, its float error decides
        p.tol = 1.0e-4
    dv = (-3, -2, -1, 0, 1, 2, 3) if wide else (0, 1)
    cand_p, cand_v = numpy_ref._candidates(p.ref, p.times, p.scales, dv, {})
    if wide:  # the refinement reorders candidates per knot (the live ones first)
        order = np.argsort(p.rng.random(cand_p.shape), axis=2)
        cand_p = np.take_along_axis(cand_p, order, axis=2)
        cand_v = np.take_along_axis(cand_v, order, axis=2)
    want = numpy_ref._segment_costs(p.ref, p.times, p.scales, p.tol, cand_p, cand_v, exact=True)
    # what the refinement prunes by: the cost at the sample ticks (with its float error) below HARD
    passes = numpy_ref._segment_costs(p.ref, p.times, p.scales, p.tol, cand_p, cand_v, exact=False) < numpy_ref._HARD
    env = numpy_ref.segment_envelope(p.ref, p.times)
    tz = encoder._toward_zero(p.scales)
    got = np.empty_like(want)
    bound = np.empty_like(want)
    feasible = np.empty(want.shape, dtype=bool)
    free = np.zeros(p.times.size, dtype=bool)
    for a in range(p.ref.n_axes):
        args = (
            p.ref.positions[a], p.times, cand_p[a], cand_v[a], free, env[a], p.scales.counts_per_ms_per_rpm[a],
            ACC_EXCESS_LIMIT * p.scales.acceleration_axis[a], p.scales.drive_acceleration[a],
            p.scales.drive_velocity[a], tz[a], p.tol,
        )
        quantise.exact_costs(*args, got[a])
        dev = np.empty((*want.shape[1:3], quantise.padded(want.shape[3])), dtype=np.float32)
        quantise.sample_misses(*args, encoder._PROX, dev, feasible[a])
        quantise.sample_bounds(dev, *args[1:-2], p.tol, bound[a])
    assert np.array_equal(got, want)
    assert np.array_equal(feasible, passes)
    # what the lazy check at every tick starts from: never above the cost
    assert (bound <= got).all()


def _assert_refines_as_numpy(p: Problem, knots: Knots, bad: np.ndarray, fixed_knots: set[int]) -> None:
    if not bad.any():
        return
    env = encoder.segment_envelope(p.ref, knots.times_ms)
    got = encoder._refine(p.ref, knots, p.scales, p.tol, bad, fixed_knots, env)
    exp = numpy_ref._refine(p.ref, knots, p.scales, p.tol, bad, fixed_knots)
    assert np.array_equal(got.positions, exp.positions)
    assert np.array_equal(got.velocities_rpm, exp.velocities_rpm)


@settings(max_examples=5 * settings.default.max_examples)  # a window rule rarely decides: many plans
@given(st.integers(0, 2**32 - 1))
def test_choice_refinement_and_verification_are_the_numpy_ones(seed: int) -> None:
    p = _problem(seed)
    ends = _ends(p)
    fixed = {0: (ends[0], ends[1]), p.times.size - 1: (ends[2], ends[3])}
    env = encoder.segment_envelope(p.ref, p.times)
    pos, vel = encoder._choose_values(p.ref, p.times, p.scales, p.tol, ends, env)
    # the joint choice checks every tick (lazily): NumPy's choice with the costs at every tick
    want_pos, want_vel = numpy_ref._choose_values(p.ref, p.times, p.scales, p.tol, fixed, exact=True)
    assert np.array_equal(pos, want_pos) and np.array_equal(vel, want_vel)
    demand = encoder.planned_demand(p.ref, p.scales.toward_zero)
    ends_fixed = {0, p.times.size - 1}
    # as the encoder goes on: the segments the choice fails refined (then the window rules decide)
    chosen = Knots(p.times, pos, vel)
    chosen_misses = encoder._misses(chosen, p.scales, p.tol, demand, env)
    _assert_refines_as_numpy(p, chosen, chosen_misses[0] | chosen_misses[1], ends_fixed)

    # and on other values: the reconstruction, the verification, more windows and pinned knots
    knots = _perturbed(p, chosen)
    rec = encoder.reconstruct(knots, p.scales)
    rec_ref = numpy_ref.reconstruct(knots, p.scales)
    for f in dataclasses.fields(rec):
        assert np.array_equal(getattr(rec, f.name), getattr(rec_ref, f.name)), f.name
    for times in (p.times, p.times[: max(2, p.times.size - 1)]):  # the last segment's: up to the plan's end
        assert np.array_equal(encoder.segment_envelope(p.ref, times), numpy_ref.segment_envelope(p.ref, times))
    off_tol, off_budget = encoder._misses(knots, p.scales, p.tol, demand, env)
    mask = off_tol | off_budget
    assert np.array_equal(mask, numpy_ref._bad_mask(p.ref, knots, p.scales, p.tol, demand))
    axis, ticks = np.nonzero(np.abs(rec_ref.demand - demand) > p.tol)  # the ticks `_quantise` splits at
    tol_ref = np.zeros_like(mask)
    tol_ref[axis, np.clip(np.searchsorted(p.times, ticks, side="left") - 1, 0, p.times.size - 2)] = True
    assert np.array_equal(off_tol, tol_ref)
    # checked again only where values changed, from the misses of other values: the same
    again = encoder._misses(knots, p.scales, p.tol, demand, env, (chosen, *chosen_misses))
    assert np.array_equal(again[0], off_tol) and np.array_equal(again[1], off_budget)
    bad = mask | (p.rng.random(mask.shape) < p.rng.choice([0.05, 0.3]))
    _assert_refines_as_numpy(p, knots, bad, ends_fixed | set(p.rng.integers(0, p.times.size, 2).tolist()))
