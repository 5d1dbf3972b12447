"""planner/motion/topp.py, the compiled TOPP-RA, against toppra itself (the reference): the same rows on the same
gridpoints give the same profile, on blended paths and splines of 1-6 axes, with and without tightened
rows; and a problem without an admissible profile is refused, naming the gridpoint."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from planner.errors import INFEASIBLE, PlanningError
from planner.motion import topp
from planner.motion.geometry import blended_runs
from planner.motion.path import SplineGeometry


def _duration(sd: np.ndarray, grid: np.ndarray) -> float:
    return float(np.sum(2.0 * np.diff(grid) / (sd[:-1] + sd[1:])))


@st.composite
def problems(draw: st.DrawFn) -> tuple[object, np.ndarray, np.ndarray, np.ndarray | None]:
    n = draw(st.integers(1, 6))
    k = draw(st.integers(2, 8))
    wp = np.array(draw(st.lists(st.lists(st.floats(-1.0, 1.0), min_size=n, max_size=n), min_size=k, max_size=k)))
    for i in range(1, k):  # distinct consecutive waypoints
        if np.abs(wp[i] - wp[i - 1]).max() < 1e-3:
            wp[i, 0] = wp[i - 1, 0] + 0.1
    vlim = np.array(draw(st.lists(st.floats(0.5, 3.0), min_size=n, max_size=n)))
    alim = np.array(draw(st.lists(st.floats(1.0, 20.0), min_size=n, max_size=n)))
    if draw(st.booleans()):
        geom: object = SplineGeometry(wp, vlim)
    else:
        runs, _ = blended_runs(wp, vlim, np.full(n, draw(st.floats(1e-3, 0.2))), alim)
        geom = runs[0]
    grid = geom.gridpoints()  # type: ignore[attr-defined]
    scale = None
    if draw(st.booleans()):
        rng = np.random.default_rng(draw(st.integers(0, 2**31)))
        scale = 1.0 + rng.uniform(0.0, 0.3, (grid.size, 2)) * (rng.random((grid.size, 1)) < 0.2)
    return geom, vlim, alim, scale


@given(problems())
def test_the_compiled_passes_find_toppras_profile_on_the_same_rows(
        problem: tuple[object, np.ndarray, np.ndarray, np.ndarray | None]) -> None:
    geom, vlim, alim, scale = problem
    grid = geom.gridpoints()  # type: ignore[attr-defined]
    reference = topp.toppra_solve(geom, geom.dof, grid, vlim, alim, scale)  # type: ignore[arg-type, attr-defined]
    ours = topp.solve(topp.sample_path(geom, grid), vlim, alim, scale)  # type: ignore[arg-type]
    assert reference is not None
    assert _duration(ours, grid) == pytest.approx(_duration(reference, grid), rel=1e-4)
    assert np.abs(ours - reference).max() <= 1e-3 * reference.max()


def test_a_problem_without_an_admissible_profile_is_refused_at_its_gridpoint() -> None:
    grid = np.linspace(0.0, 1.0, 11)
    a = np.zeros((11, 1))
    b = np.zeros((11, 1))
    g = np.zeros((11, 1))
    b[6, 0], g[6, 0] = -1.0, -1.0  # x >= 1 at gridpoint 6: with |u| <= 1 no motion brakes to rest in the 0.4 left
    a[:, 0] = 0.0
    rows_a = np.hstack([a, np.ones((11, 1)), -np.ones((11, 1))])  # and |u| <= 1
    rows_b = np.hstack([b, np.zeros((11, 2))])
    rows_g = np.hstack([g, np.ones((11, 2))])
    with pytest.raises(PlanningError) as e:
        topp.parametrize(rows_a, rows_b, rows_g, np.full(11, 10.0), grid)
    assert e.value.code == INFEASIBLE
    assert e.value.detail["return_code"] == "Uncontrollable" and e.value.detail["gridpoint"] == 6


def test_a_straight_line_reaches_the_trapezoid_of_its_limits() -> None:
    """One axis along s in [0, 2] with |s_dot| <= 1 and |s_ddot| <= 1: accelerate 1 s, cruise, brake 1 s."""
    grid = np.linspace(0.0, 2.0, 401)

    def line(s: np.ndarray, order: int) -> np.ndarray:
        return (np.ones_like(s) if order == 1 else np.zeros_like(s))[:, None]

    sd = topp.solve(topp.sample_path(line, grid), np.ones(1), np.ones(1))
    assert sd[0] == 0.0 and sd[-1] == 0.0
    assert sd.max() == pytest.approx(1.0, rel=1e-3)
    assert _duration(sd, grid) == pytest.approx(3.0, rel=1e-3)
