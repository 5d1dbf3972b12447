"""The repair loop of path.plan_run: how many toppra solves and chain fits a plan costs.

A chain is fitted on every profile the loop tries; a profile is determined by toppra's solution and its
whole-ms duration, so a slow-down that rounds to a duration already tried gives the same chain and must
not be fitted again.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from planner_checks import assert_invariants

import planner.encoding.chain as chain_mod
import planner.motion.path as path_mod
from planner import plan_job
from planner.config import CellConfig
from planner.job import job_from_dict

# random path 12 of benchmarks.bench_planner's corpus (seed 13): without the blends' margin of the first
# solve (path.BLEND_MARGIN, which spares it the repair), its first chain overshoots by 0.1 %, and the
# smallest slow-down of the ladder rounds to the same duration (3833 ms); the acceleration-only plan (the
# chain and its repairs are that plan's)
SAME_DURATION = {
    "kind": "path",
    "jerk_limited": False,
    "job_id": "repair-same-duration",
    "axes": ["j3", "j6", "j4", "j1", "j5"],
    "waypoints": [
        [-0.3204250628764327, -0.45676644743166994, -1.6902494527032708, 1.072857205802677, 0.3361518353753854],
        [0.19594495672365309, -0.8173382074871429, 2.1597714718634573, 0.9764909225937606, 0.9292407228259139],
        [0.20564885807804867, 0.5122800006152821, 0.829624080056186, -0.9173597982187305, -0.6853457544958315],
        [0.9352012632385338, -0.8021037424621902, -2.049013302199026, -0.1619049425524115, 1.0117287666907884],
    ],
}


def test_no_chain_is_fitted_twice_on_the_same_profile(cell: CellConfig, monkeypatch: pytest.MonkeyPatch) -> None:
    fitted: list[tuple[Any, Any]] = []
    fit = chain_mod.fit_chain

    def recording(q: Any, v: Any, *args: Any, **kwargs: Any) -> Any:
        fitted.append((q.copy(), v.copy()))
        return fit(q, v, *args, **kwargs)

    monkeypatch.setattr(chain_mod, "fit_chain", recording)
    monkeypatch.setattr(path_mod, "BLEND_MARGIN", 0.0)
    job = job_from_dict(SAME_DURATION, cell)
    traj = plan_job(job, cell)
    assert traj.info["topp_solves"] >= 2  # the case needs a repair (else it tests nothing)
    assert len(fitted) >= 2
    for i, (qa, va) in enumerate(fitted):
        for qb, vb in fitted[i + 1 :]:
            assert not (qa.shape == qb.shape and np.array_equal(qa, qb) and np.array_equal(va, vb))
    assert_invariants(traj, cell)


def _first_solve(cell: CellConfig, monkeypatch: pytest.MonkeyPatch, data: dict[str, Any]) -> tuple[Any, ...]:
    """Plan `data`, returning the plan, the first run's geometry and gridpoints, and its first solve's
    samples, limits and row scales."""
    sampled: list[tuple[Any, Any]] = []
    solves: list[tuple[Any, ...]] = []
    sample, solve = path_mod.topp.sample_path, path_mod.solve_profile

    def sample_path(geom: Any, grid: Any) -> Any:
        sampled.append((geom, grid))
        return sample(geom, grid)

    def solve_profile(samples: Any, vlim: Any, alim: Any, row_scale: Any = None) -> Any:
        solves.append((samples, vlim, alim, None if row_scale is None else row_scale.copy()))
        return solve(samples, vlim, alim, row_scale)

    monkeypatch.setattr(path_mod.topp, "sample_path", sample_path)
    monkeypatch.setattr(path_mod, "solve_profile", solve_profile)
    traj = plan_job(job_from_dict(data, cell), cell)
    monkeypatch.undo()
    return traj, *sampled[0], *solves[0]


def test_a_chains_first_solve_keeps_the_margin_in_the_blends_only(
    cell: CellConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    traj, geom, grid, samples, _vlim, _alim, rows = _first_solve(cell, monkeypatch, SAME_DURATION)
    assert traj.info["blended_corners"] == 2 and samples.gridpoints is grid
    b = geom.breakpoints
    in_blend = np.zeros(grid.size, dtype=bool)
    for k in np.nonzero(geom.blends)[0]:
        in_blend |= (grid >= b[k]) & (grid <= b[k + 1])
    assert 0 < in_blend.sum() < grid.size
    assert rows.shape == (grid.size, 2)
    assert np.all(rows[in_blend] == 1.0 + path_mod.BLEND_MARGIN) and np.all(rows[~in_blend] == 1.0)


def test_the_reported_optimum_is_a_lower_bound_of_the_unmargined_solve(
    cell: CellConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    traj, geom, grid, samples, vlim, alim, rows = _first_solve(cell, monkeypatch, SAME_DURATION)
    margined = path_mod.Profile(grid, path_mod.topp.solve(samples, vlim, alim, rows), geom, alim).optimal_ms
    optimum = path_mod.Profile(grid, path_mod.topp.solve(samples, vlim, alim), geom, alim).optimal_ms
    assert optimum < margined <= optimum * (1.0 + path_mod.BLEND_MARGIN)
    assert 1000 * traj.info["optimal_s"] == pytest.approx(margined / (1.0 + path_mod.BLEND_MARGIN))
    assert 1000 * traj.info["optimal_s"] <= optimum


def test_the_blend_margin_spares_a_repair(cell: CellConfig, monkeypatch: pytest.MonkeyPatch) -> None:
    """Pinned: this path's first chain overshoots in a blend without the margin and needs another solve."""
    assert plan_job(job_from_dict(SAME_DURATION, cell), cell).info["topp_solves"] == 1
    monkeypatch.setattr(path_mod, "BLEND_MARGIN", 0.0)
    assert plan_job(job_from_dict(SAME_DURATION, cell), cell).info["topp_solves"] >= 2


@pytest.mark.parametrize("waypoints", [[[0.0, 0.0], [0.6, 0.3]], [[0.0, 0.0], [0.6, 0.3], [0.1, 0.5]]],
                         ids=["straight run", "blended run"])
def test_the_reported_optimum_does_not_depend_on_the_slow_down(waypoints: list[list[float]]) -> None:
    """`optimal_s` is the optimum on the path, whatever `time_scale` the encoder asks for: a straight run's
    closed form computes it from the slowed-down limits, and once reported it times time_scale squared."""
    from planner.motion.geometry import blended_runs

    vlim, alim = np.array([2.0, 1.5]), np.array([8.0, 6.0])
    runs, _corners = blended_runs(np.array(waypoints), vlim, np.full(2, 0.01), alim, 10.0)
    chain = path_mod.ChainSpec(np.full(2, 1e-3), 10, 200, np.full(2, -5.0), np.full(2, 5.0))
    cpu = np.full(2, 65189.86)
    plain = path_mod.plan_path(runs, cpu, vlim, alim, chain=chain)
    slower = path_mod.plan_path(runs, cpu, vlim, alim, time_scale=2.0, chain=chain)
    assert slower[0].duration_ms >= 1.9 * plain[0].duration_ms  # it is played slower
    assert slower[1]["optimal_s"] == pytest.approx(plain[1]["optimal_s"], rel=1e-9)
