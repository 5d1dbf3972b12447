"""`plan_job(max_segment_ms=...)`: a job whose change or stop must act within a short lead gets its PVT
segments bounded (issue 15: the feeders keep a few segments queued whatever the lead, so the lead only
shortens the reaction when the segments are short enough; StreamerSettings.segment_cap_ms)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from planner.config import load_cell
from planner.errors import PlanningError
from planner.job import job_from_dict, load_job
from planner.plan import plan_job
from streamer.core.settings import StreamerSettings

ROOT = Path(__file__).resolve().parents[2]
CELL = load_cell(ROOT / "configs" / "demo.toml")
MOVE = {"kind": "move", "axes": ["j1", "j2", "j3", "j4", "j5", "j6"], "target": [2.0, -1.5, 1.8, -1.0, 1.2, -0.8]}


@pytest.mark.parametrize("cap", [8, 20, 50])
def test_segments_never_exceed_the_bound_and_the_plan_stays_within_tolerance(cap: int) -> None:
    free = plan_job(job_from_dict(MOVE, CELL), CELL, start=[0.0] * 6)
    bounded = plan_job(job_from_dict(MOVE, CELL), CELL, start=[0.0] * 6, max_segment_ms=cap)
    # the bound in force: the job's, or the shortest segment the 5 % acceleration budget allows if longer
    in_force = int(bounded.info["max_segment_ms"])
    assert in_force >= cap and (in_force == cap or cap < 16)
    assert free.dt_ms.max() > in_force  # the bound is what shortens them
    assert bounded.dt_ms.max() <= in_force
    assert np.abs(bounded.deviation()).max() <= bounded.tolerance_counts
    assert bounded.duration_ms == free.duration_ms  # the same motion, finer records
    assert bounded.n_points > free.n_points


@pytest.mark.parametrize("jerk_limited", [False, True])
def test_a_path_job_is_bounded_too(jerk_limited: bool) -> None:
    """Both kinds of path; the jerk-limited one's knot-time moves (continuity.refine_times) once made a 30 ms
    segment of a 24 ms bound."""
    job = dataclasses.replace(load_job(ROOT / "configs" / "jobs" / "demo-path.toml", CELL), tolerance_counts=2)
    job = dataclasses.replace(job, data=dataclasses.replace(job.data, jerk_limited=jerk_limited))
    traj = plan_job(job, CELL, max_segment_ms=24)
    assert traj.info.get("jerk_limited", 0.0) == float(jerk_limited)
    assert traj.dt_ms.max() <= 24 and np.abs(traj.deviation()).max() <= traj.tolerance_counts


def test_the_bound_is_checked() -> None:
    with pytest.raises(PlanningError) as e:
        plan_job(job_from_dict(MOVE, CELL), CELL, start=[0.0] * 6, max_segment_ms=0)
    assert e.value.code == "LIMITS" and "max_segment_ms" in e.value.message


def test_segment_cap_follows_the_lead() -> None:
    s = StreamerSettings.from_cell(CELL)
    kept = s.repair_syncs + s.underflow_watermark
    assert s.segment_cap_ms(200) == 200 // kept and s.segment_cap_ms(30) == 30 // kept
    assert s.segment_cap_ms(10_000) == 255 and s.segment_cap_ms(1) == 1
