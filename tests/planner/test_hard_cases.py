"""Pinned hard cases (tests/planner/data/hard_cases.toml): zero motion, 1e-8 motion, duplicate
waypoints, waypoints 1e-4 apart, one axis with 1000x larger limits, 180-degree reversals, jobs longer
than 60 s, paths that came out slower than toppra's optimum. Each one plans on the demo cell (with its
axis overrides, or `axis_count` axes as `CellConfig.with_axes` makes them) and satisfies every invariant."""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from planner_checks import assert_invariants

from planner import plan_job
from planner.config import CellConfig
from planner.errors import PlanningError
from planner.job import job_from_dict

CASES: list[dict[str, Any]] = tomllib.loads(
    (Path(__file__).parent / "data" / "hard_cases.toml").read_text(encoding="utf-8")
)["case"]


def _cell(base: CellConfig, overrides: dict[str, dict[str, float]]) -> CellConfig:
    axes = tuple(dataclasses.replace(a, **overrides.get(a.name, {})) for a in base.axes)
    return dataclasses.replace(base, axes=axes)


def _job(case: dict[str, Any], jerk_limited: bool) -> dict[str, Any]:
    """The case's job; a path as the acceleration-only plan the cases were found on, or jerk-limited."""
    job = dict(case["job"])
    if job.get("kind") == "path":
        job.setdefault("jerk_limited", jerk_limited)
    return job


@pytest.mark.parametrize("case", CASES, ids=[c["name"] for c in CASES])
def test_hard_case(cell: CellConfig, case: dict[str, Any]) -> None:
    c = _cell(cell.with_axes(case.get("axis_count", len(cell.axes))), case.get("cell_axes", {}))
    case = {**case, "job": _job(case, False)}
    expect = case["expect"]
    if expect not in ("ok", "noop"):
        with pytest.raises(PlanningError) as e:
            plan_job(job_from_dict(case["job"], c), c)
        assert e.value.code == expect, e.value
        return
    job = job_from_dict(case["job"], c)
    traj = plan_job(job, c)
    assert_invariants(traj, c)
    if expect == "noop":
        assert np.all(traj.positions == traj.positions[:, :1]) and np.all(traj.velocities == 0)
        assert np.all(traj.demand() == traj.positions[:, :1])
    if "min_duration_s" in case:
        assert traj.duration_s >= case["min_duration_s"]
    if "max_duration_s" in case:
        assert traj.duration_s <= case["max_duration_s"]
    if "min_points" in case:
        assert traj.n_points >= case["min_points"]
    if "max_points" in case:
        assert traj.n_points <= case["max_points"], (traj.n_points, traj.knot_times_ms)
    if "max_segment_ms" in case:
        assert int(traj.dt_ms.max()) <= case["max_segment_ms"]
    if "max_over_optimum" in case:
        # as test_properties.test_path_jobs: toppra's optimum on the planner's grid, played
        # `time_scale` slower where the quantisation needed it, plus 1 ms per run of whole-ms re-timing
        bound = case["max_over_optimum"] * traj.info["time_scale"] * traj.info["optimal_s"]
        assert traj.duration_s <= bound + 0.001 * traj.info.get("runs", 1.0), (traj.duration_s, traj.info)


PATH_CASES = [c for c in CASES if c["job"].get("kind") == "path" and c["expect"] == "ok"]


@pytest.mark.parametrize("case", PATH_CASES, ids=[c["name"] for c in PATH_CASES])
def test_hard_path_case_jerk_limited(cell: CellConfig, case: dict[str, Any]) -> None:
    """The same paths planned with every axis' jerk limit (the default): every promise kept, never faster
    than the acceleration-only optimum."""
    c = _cell(cell.with_axes(case.get("axis_count", len(cell.axes))), case.get("cell_axes", {}))
    traj = plan_job(job_from_dict(_job(case, True), c), c)
    assert_invariants(traj, c)
    assert traj.info["jerk_limited"] == 1.0
    if "optimal_s" in traj.info and not traj.info.get("jerk_transitions"):
        # (the acceleration-only optimum along the blends; moves whose corner stops are cut short take
        # other corners within the same tolerance, and may be a little faster: planner/motion/stop_moves.py)
        assert traj.duration_s >= 0.999 * traj.info["optimal_s"]
