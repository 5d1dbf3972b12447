"""planner/encoding/cyclic.py: one set point per SYNC, the cyclic drives' interpolation, its bound, refusals."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from planner.config import CellConfig, load_cell
from planner.encoding import cyclic
from planner.errors import AXIS_ID, CONFIG, ENCODING_RANGE, INFEASIBLE, PlanningError
from planner.job import load_job
from planner.plan import plan_job

ROOT = Path(__file__).resolve().parents[3]
DEMO_JOB = ROOT / "configs" / "jobs" / "demo-path.toml"


def _quadratic(a: float, m: int = 400) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(m + 1, dtype=np.float64)
    return 0.5 * a * t * t, a * t


def _cubic(j: float, m: int = 400) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(m + 1, dtype=np.float64)
    return j * t**3 / 6.0, j * t * t / 2.0


def test_sample_is_the_plan_at_every_period_rounded_and_ends_at_rest() -> None:
    pos, vel = _quadratic(0.013, 95)
    sp = cyclic.sample(pos, vel, 10, pv=True)
    assert sp.n == 10 and sp.end_ms == 100  # the last set point is the end, at the first multiple >= 95 ms
    assert list(sp.positions[:10]) == [round(0.5 * 0.013 * (10 * j) ** 2) for j in range(10)]
    assert sp.positions[-1] == round(pos[-1]) and sp.velocities[-1] == 0
    assert sp.velocities[3] == round(0.013 * 30 * 1000)  # counts/s
    assert not cyclic.sample(pos, vel, 10, pv=False).velocities.any()


def test_the_interpolations_are_the_documented_formulas() -> None:
    # a constant acceleration: the chord sags a P^2 / 8 in the middle; the parabola (P3) and the Hermite
    # with the exact velocities (PV) are exact
    a, p = 0.04, 10
    pos, vel = _quadratic(a, 200)
    big = 1000.0  # scale up so that the set points' rounding does not hide the shape
    pos, vel = pos * big, vel * big
    for interp, want in (("linear", a * big * p * p / 8.0), ("pv", 0.0), ("p3", 0.0)):
        sp = cyclic.sample(pos, vel, p, pv=interp == "pv")
        curve = cyclic.drive_curve(sp, interp)
        err = np.abs(curve[20:180] - pos[20:180]).max()  # away from the ends (P3 primes with x_-1 = x_0)
        assert err == pytest.approx(want, abs=0.6), interp
    # a cubic (constant jerk): PV is still exact (Hermite through exact slopes), P3 is not
    pos, vel = _cubic(2e-4 * big, 200)
    pv = cyclic.drive_curve(cyclic.sample(pos, vel, p, pv=True), "pv")
    p3 = cyclic.drive_curve(cyclic.sample(pos, vel, p, pv=False), "p3")
    assert np.abs(pv[:190] - pos[:190]).max() < 0.6  # (the last period ends at rest, the cubic does not)
    assert np.abs(p3[20:180] - pos[20:180]).max() > 5.0


def test_the_drive_reaches_every_set_point_at_its_sync() -> None:
    pos, vel = _cubic(3e-3, 300)
    for interp in cyclic.INTERPOLATIONS:
        sp = cyclic.sample(pos, vel, 7, pv=interp == "pv")
        curve = cyclic.drive_curve(sp, interp)
        assert np.allclose(curve[::7], sp.positions)


def test_deviation_counts_both_roundings() -> None:
    sp = cyclic.Setpoints(10, np.array([10, 20], dtype=np.int64), np.zeros(2, dtype=np.int64))
    chord = np.linspace(10.0, 20.0, 11)
    # the plan 0.55 above the chord: rounded to nearest they differ by a count, truncated they do not
    whole, raw = cyclic.deviation(chord + 0.55, sp, "linear")
    assert (whole, raw) == (1, pytest.approx(0.55))
    # the plan 0.3 below: rounded to nearest they agree, truncated they differ by a count
    whole, raw = cyclic.deviation(chord - 0.3, sp, "linear")
    assert (whole, raw) == (1, pytest.approx(0.3))
    assert cyclic.deviation(chord + 0.2, sp, "linear")[0] == 0


def _cell(path: str) -> CellConfig:
    return load_cell(ROOT / "configs" / path)


def test_xtrapuls_and_mixed_cells_plan_the_demo_within_tolerance_and_report_per_axis() -> None:
    for name in ("xtrapuls.toml", "mixed.toml"):
        cell = _cell(name)
        traj = plan_job(load_job(DEMO_JOB, cell), cell)
        for st, ax in zip(traj.stats, cell.axes, strict=True):
            if ax.profile == "epos-ipm":
                assert st.interpolation == "pvt" and st.setpoint_period_ms == 0
            else:
                assert st.interpolation == "pv" and st.setpoint_period_ms == cell.sync_period_ms
                assert set(st.interpolation_alternatives) == {"linear", "p3"}
            assert st.max_deviation_counts <= traj.tolerance_counts


def test_a_sub_mode_that_strays_is_refused_naming_what_would_meet_it() -> None:
    cell = _cell("mixed.toml")
    axes = tuple(replace(a, ip_submode="linear") if a.name == "j6" else a for a in cell.axes)
    cell = replace(cell, axes=axes)
    job = load_job(DEMO_JOB, cell)
    tol = job.tolerance_counts  # (2: the demo path is jerk-limited by default)
    with pytest.raises(PlanningError) as e:
        plan_job(job, cell)
    err = e.value
    assert err.code == INFEASIBLE and "'j6'" in err.message and "linear" in err.message
    d = err.detail
    assert d["axis"] == "j6" and d["deviation_counts"] > tol and d["tolerance_counts"] == tol
    assert d["alternatives"]["pv"] <= tol and "sub-mode 'pv'" in err.message
    assert d["period_that_meets_ms"] is not None and f"{d['period_that_meets_ms']} ms" in err.message
    # and the period it names does meet it
    cell2 = replace(cell, sync_period_ms=d["period_that_meets_ms"])
    traj = plan_job(load_job(DEMO_JOB, cell2), cell2)
    assert traj.stats[5].max_deviation_counts <= tol


def test_a_16_bit_step_is_refused_naming_the_axis() -> None:
    cell = _cell("xtrapuls.toml")
    j4 = next(a for a in cell.axes if a.name == "j4")  # in mux_group 2: 16-bit set points
    pos, vel = _quadratic(0.5, 600)  # reaches 300 counts/ms: 3000 counts per 10 ms period, then more
    cyclic.assess(replace(j4, ip_submode="p3"), pos[:300], vel[:300], 10, 1000)  # 1500 counts/period: fits
    with pytest.raises(PlanningError) as e:
        cyclic.assess(replace(j4, ip_submode="p3"), pos * 20, vel * 20, 10, 10**6)
    err = e.value
    assert err.code == ENCODING_RANGE and "'j4'" in err.message and "32767" in err.message
    assert err.detail["step_counts"] > 32767 and "mux_group 2" in err.message


def test_a_multiplexed_pv_velocity_must_fit_16_bits() -> None:
    cell = _cell("xtrapuls.toml")
    j1 = next(a for a in cell.axes if a.name == "j1")  # in mux_group 1, PV: a 16-bit velocity
    pos, vel = _quadratic(0.02, 1000)  # up to 20 counts/ms = 20000 counts/s: fits
    cyclic.assess(j1, pos, vel, 10, 1000)
    pos, vel = _quadratic(0.05, 1000)  # up to 50000 counts/s: does not
    with pytest.raises(PlanningError) as e:
        cyclic.assess(j1, pos, vel, 10, 1000)
    assert e.value.code == ENCODING_RANGE and "'j1'" in e.value.message and "16-bit velocity" in e.value.message
    # the same axis with an RPDO of its own carries 32 bits
    cyclic.assess(replace(j1, mux_group=0), pos, vel, 10, 1000)


def test_a_job_with_part_of_a_multiplexed_group_is_refused() -> None:
    cell = _cell("xtrapuls.toml")
    from planner.job import job_from_dict

    job = job_from_dict({"kind": "move", "axes": ["j1", "j3"], "target": [0.1, 0.1]}, cell)
    with pytest.raises(PlanningError) as e:
        plan_job(job, cell)
    assert e.value.code == AXIS_ID and "'j1'" in e.value.message and "j2" in e.value.message


@pytest.mark.parametrize(
    ("change", "needle"),
    [
        ({"mux_group": 1, "ip_submode": "pv"}, "needs 96 bits"),  # three PV axes in one frame
        ({"node_id": 64}, "node ids 1..63"),
    ],
)
def test_cell_checks_of_the_families(change: dict[str, object], needle: str) -> None:
    cell = _cell("xtrapuls.toml")
    axes = tuple(replace(a, **change) if a.name == "j3" else a for a in cell.axes)  # type: ignore[arg-type]
    with pytest.raises(PlanningError) as e:
        replace(cell, axes=axes)
    assert e.value.code == CONFIG and needle in e.value.message
    with pytest.raises(PlanningError) as e:
        replace(cell, sync_period_ms=200)
    assert "at most 150 ms" in e.value.message


def test_interpolation_of_each_family() -> None:
    cell = _cell("mixed.toml")
    assert [cyclic.interpolation_of(a) for a in cell.axes] == [None, None, None, "pv", "pv", "pv"]
    assert cyclic.interpolation_of(replace(cell.axes[0], profile="cia402-csp")) == "linear"
