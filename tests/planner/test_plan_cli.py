"""`pvt plan` on every example job in configs/jobs/ (examples are tests), and its outputs."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
from planner_checks import CONFIGS

from streamer.cli import main

JOBS = sorted((CONFIGS / "jobs").iterdir())
DEMO = str(CONFIGS / "demo.toml")


@pytest.mark.parametrize("job", JOBS, ids=[j.name for j in JOBS])
def test_every_example_job(job: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["plan", str(job), "--config", DEMO, "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["points"] >= 2 and summary["duration_s"] > 0
    assert summary["points_per_second"] == pytest.approx(summary["points"] / summary["duration_s"])
    for axis in summary["axes"]:
        assert axis["max_deviation_counts"] <= summary["tolerance_counts"]
        assert axis["acceleration_excess_share"] <= 0.05


def test_table_csv_and_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out, png = tmp_path / "pvt.csv", tmp_path / "pvt.png"
    job = CONFIGS / "jobs" / "demo-path.toml"
    assert main(["plan", str(job), "--config", DEMO, "--out", str(out), "--plot", str(png)]) == 0
    text = capsys.readouterr().out
    assert "points per axis" in text and "j6" in text and "max dev" in text
    rows = list(csv.DictReader(out.open()))
    assert list(rows[0]) == ["axis", "node_id", "index", "time_s", "dt_ms", "position_counts", "velocity_rpm"]
    firsts = [r for r in rows if r["index"] == "0"]
    assert [r["axis"] for r in firsts] == ["j1", "j2", "j3", "j4", "j5", "j6"]
    assert all(r["dt_ms"] == "0" and r["time_s"] == "0.000" for r in firsts)
    j1 = [r for r in rows if r["axis"] == "j1"]
    assert all(1 <= int(r["dt_ms"]) <= 255 for r in j1[1:])
    assert j1[-1]["velocity_rpm"] == "0"
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"


def test_default_config(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["plan", str(CONFIGS / "jobs" / "move.toml"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["cell"] == "demo"


def test_rejected_job(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"kind": "path", "axes": ["j1", "j3"], "waypoints": [[0, 0], [0, "x"]]}))
    assert main(["plan", str(bad), "--config", DEMO]) == 2
    assert "TYPE at waypoints[1][1]" in capsys.readouterr().err
    assert main(["plan", str(bad), "--config", DEMO, "--json"]) == 2
    err = json.loads(capsys.readouterr().out)["error"]
    assert err["code"] == "TYPE" and err["path"] == "waypoints[1][1]" and "'j3'" in err["message"]


def test_demo_fits_every_per_axis_field_to_the_axes(tmp_path: Path) -> None:
    """`pvt demo --axes N --job JOB`: the job's start, limits and path tolerance are fitted to N axes too."""
    move = CONFIGS / "jobs" / "move.toml"  # has `start` for 6 axes
    assert main(["demo", "--fast", "--quiet", "--axes", "3", "--job", str(move), "--out", str(tmp_path)]) == 0
    from planner.config import load_cell
    from planner.job import MoveData, PathData, job_from_dict
    from streamer.demo import fit_job_to_cell

    cell = load_cell(DEMO)
    body = {"kind": "path", "axes": ["j1", "j2"], "waypoints": [[0.0, 0.0], [0.5, 0.2], [0.1, 0.3]],
            "path_tolerance": [0.01, 0.02], "limits": {"velocity": [1.0, 1.5]}}
    fitted = fit_job_to_cell(job_from_dict(body, cell), cell.with_axes(3), repeat=True)
    assert fitted.axes == ("j1", "j2", "j3") and fitted.velocity_limit == (1.0, 1.5, 1.0)
    assert isinstance(fitted.data, PathData) and fitted.data.path_tolerance == (0.01, 0.02, 0.01)
    moved = fit_job_to_cell(job_from_dict({"kind": "move", "axes": ["j1"], "start": [0.2], "target": [0.4]}, cell),
                            cell.with_axes(2), repeat=True)
    assert isinstance(moved.data, MoveData) and moved.data.start is not None and moved.data.start.size == 2


def test_plan_says_how_the_motion_follows_its_geometry(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["plan", str(CONFIGS / "jobs" / "move.toml"), "--config", DEMO, "--json"]) == 0
    move = json.loads(capsys.readouterr().out)
    assert move["geometry"].startswith("along the straight line") and move["info"]["straight_line"] == 1.0
    assert main(["plan", str(CONFIGS / "jobs" / "rectangle.toml"), "--config", DEMO]) == 0
    assert "geometry: along the straight segments" in capsys.readouterr().out
    from planner.config import load_cell
    from planner.job import load_job
    from streamer.cli.plan import geometry_note

    job = load_job(CONFIGS / "jobs" / "move.toml", load_cell(DEMO))
    note = geometry_note(job, {"straight_line": 0.0, "line_deviation_counts": 812.0})
    assert note.startswith("NOT along the straight line") and "812 counts" in note


def test_rectangle_along_its_segments_and_the_spline_refused_at_its_peak(tmp_path: Path) -> None:
    """The example rectangle: within its path tolerance of the polyline at every ms; the same waypoints on
    a spline leave j2's limits, and the refusal names the peak excursion, not the first sample out."""
    from planner_checks import assert_invariants, assert_path_within

    from planner.config import load_cell
    from planner.errors import PlanningError
    from planner.job import job_from_dict, job_to_dict, load_job
    from planner.plan import plan_job

    cell = load_cell(DEMO)
    job = load_job(CONFIGS / "jobs" / "rectangle.toml", cell)
    traj = plan_job(job, cell)
    assert_invariants(traj, cell)
    assert_path_within(traj, job, cell)
    body = job_to_dict(job)
    body.pop("path_tolerance")
    body["geometry"] = "spline"
    with pytest.raises(PlanningError) as e:
        plan_job(job_from_dict(body, cell), cell)
    assert e.value.code == "POSITION_LIMIT"
    peak = e.value.detail["peak"]
    assert peak == e.value.detail["max"] and peak > 2.2  # the farthest it goes, well past the first sample out
    assert f"{peak:.6g}" in e.value.message and "'j2'" in e.value.message


def test_velocity_job_summary(capsys: pytest.CaptureFixture[str]) -> None:
    """`pvt plan` on a velocity move plans its first, open-ended chunk and says so."""
    assert main(["plan", str(CONFIGS / "jobs" / "velocity.toml"), "--config", DEMO, "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["open_ended"] is True and summary["info"]["velocity_ramp_ms"] > 0
    assert summary["geometry"].startswith("endless travel") and "open-ended" in summary["geometry"]


def test_plan_shows_the_jerk_against_its_limit_and_the_duration_against_the_optimum(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`pvt plan` of a jerk-limited path (issue 26): the duration against the acceleration-only optimum, the
    drive's jerk per axis against its limit (inside segments and at the knots), and in --json every axis'
    jerk figures."""
    job = tmp_path / "jerk.toml"
    job.write_text('kind = "path"\naxes = ["j1", "j2"]\nwaypoints = [[0.0, 0.0], [0.6, 0.2], [0.9, -0.3]]\n'
                   "jerk_limited = true\n")
    assert main(["plan", str(job), "--config", DEMO]) == 0
    out = capsys.readouterr().out
    assert "jerk-limited:" in out and "x the acceleration-only optimum" in out
    assert "drive jerk / limit (in segments / at knots over 1 ms): j1 " in out
    assert main(["plan", str(job), "--config", DEMO, "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["info"]["jerk_limited"] == 1.0 and summary["duration_s"] >= summary["info"]["optimal_s"]
    for axis in summary["axes"]:
        assert axis["jerk_limit"] > 0 and 0 < axis["planned_peak_jerk"] <= axis["jerk_limit"] * (1 + 1e-6)
        assert axis["peak_jerk"] > 0 and axis["knot_acceleration_step"] >= 0


def test_plan_says_when_a_path_is_timed_fastest(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`jerk_timing = "fastest"`: `pvt plan` says how many runs took the third-order optimum, and is shorter
    than the same job's smooth timing."""
    text = 'kind = "path"\naxes = ["j1", "j2"]\nwaypoints = [[0.0, 0.0], [0.6, 0.2], [0.9, -0.3], [0.2, 0.1]]\n'
    durations = {}
    for timing in ("smooth", "fastest"):
        job = tmp_path / f"{timing}.toml"
        job.write_text(text + f'jerk_timing = "{timing}"\n')
        assert main(["plan", str(job), "--config", DEMO]) == 0
        out = capsys.readouterr().out
        assert ("(fastest: 1 of 1 run(s) at the third-order optimum)" in out) == (timing == "fastest"), out
        assert main(["plan", str(job), "--config", DEMO, "--json"]) == 0
        durations[timing] = json.loads(capsys.readouterr().out)["duration_s"]
    assert durations["fastest"] < durations["smooth"]
