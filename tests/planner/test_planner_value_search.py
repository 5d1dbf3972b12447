"""The encoder's value search (planner/encoder.py, step 2 and the refinement of step 3): the pruning
before the check at every tick keeps exactly the candidates that lie on a path of feasible pairs, so
it never removes one the full search could have chosen."""

from __future__ import annotations

import itertools

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from planner.encoder import _alive


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
    alive = _alive(feasible, fixed)
    truth = _on_a_feasible_path(feasible, fixed)
    for a in range(n):
        if truth[a].any():
            # a feasible path exists: pruned to exactly the candidates on one
            assert np.array_equal(alive[a], truth[a]), (feasible[a], alive[a], truth[a])
        else:
            # none: every knot keeps at least one candidate, so the search still returns its least bad path
            assert alive[a].any(axis=1).all()
