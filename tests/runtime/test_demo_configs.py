"""Every file in configs/ through every command that takes it (issue 23 item 3): `pvt plan`, `pvt demo --fast`
and, for the jobs `pvt demo` refused, `pvt demo` in real time. The jobs are written for the demo cell
(configs/demo.toml); every cell runs the default demo job."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from planner.config import load_cell
from planner.job import load_job
from streamer import demo
from streamer.cli import main as pvt
from streamer.cli.demo import guarantees

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"
DEMO = CONFIGS / "demo.toml"
JOBS = sorted((CONFIGS / "jobs").iterdir()) + sorted((CONFIGS / "homing").iterdir())
CELLS = sorted(CONFIGS.glob("*.toml"))


def _check(out: Path, job: Path) -> dict:
    report = json.loads((out / "report.json").read_text())
    cell = load_cell(DEMO)
    loaded = load_job(job, cell)
    assert report["result"] == "done", report
    assert guarantees(report, loaded.tolerance_counts) == []
    # a job for some of the cell's axes moves those, no others
    assert [a["name"] for a in report["axes"]] == list(loaded.axes)
    for name in ("bus.log", "job.mcap"):  # motion.png: --no-plot (the plots: test_demo_guarantees.py)
        assert (out / name).stat().st_size > 0
    return report


@pytest.mark.virtual  # virtual time only: `make test` runs it on every core
@pytest.mark.parametrize("job", JOBS, ids=lambda p: p.name)
def test_every_job_plans_and_runs_in_the_fast_demo(job: Path, tmp_path: Path) -> None:
    assert pvt(["plan", str(job), "--config", str(DEMO)]) == 0
    code = pvt(["demo", "--fast", "--quiet", "--no-plot", "--config", str(DEMO), "--job", str(job),
                "--out", str(tmp_path)])
    if load_job(job, load_cell(DEMO)).kind == "home":
        assert code == 2  # a home job plans no motion: `pvt serve --sim` + `pvt submit` run it
        return
    assert code == 0
    _check(tmp_path, job)


@pytest.mark.virtual  # virtual time only: `make test` runs it on every core
@pytest.mark.parametrize("cell", CELLS, ids=lambda p: p.name)
def test_every_cell_plans_and_runs_the_default_job_in_the_fast_demo(cell: Path, tmp_path: Path) -> None:
    assert pvt(["plan", str(demo.DEFAULT_JOB), "--config", str(cell)]) == 0
    assert pvt(["demo", "--fast", "--quiet", "--no-plot", "--config", str(cell), "--out", str(tmp_path)]) == 0


@pytest.mark.virtual  # virtual time only: `make test` runs it on every core
def test_fast_demo_judges_a_velocity_job_on_the_whole_stream(tmp_path: Path) -> None:
    """The demo's velocity job runs its ramp, its cruise chunk after chunk and the chunk that brakes before the
    position limits; the report covers all of it: the deviation and the final position are the whole stream's,
    not its first chunk's (which once gave 182 counts and a final position error of 30,390 counts)."""
    cell, _job, first = demo.prepare(DEMO, CONFIGS / "jobs" / "velocity.toml", commissioned=True)
    assert first.open_ended
    report, trace = demo.run_fast(cell, first, tmp_path, plot=False)
    assert report["result"] == "done", report
    assert report["duration_s"] > 3 * first.duration_s  # the whole stream, many chunks
    for i, a in enumerate(report["axes"]):
        assert a["max_deviation_counts"] <= first.tolerance_counts, a
        assert a["final_position_error_counts"] == 0, a
        # the braking chunk stops before the software limits, not at the first chunk's last knot
        assert abs(trace.final_actual(a["node_id"]) - int(first.positions[i, -1])) > 10_000


@pytest.mark.realtime
@pytest.mark.parametrize("name", ["additive.toml", "velocity.toml"])
def test_realtime_demo_runs_the_jobs_it_refused(name: str, tmp_path: Path) -> None:
    job = CONFIGS / "jobs" / name
    assert pvt(["demo", "--quiet", "--no-plot", "--config", str(DEMO), "--job", str(job),
                "--out", str(tmp_path)]) == 0
    _check(tmp_path, job)


@pytest.mark.virtual  # virtual time only: `make test` runs it on every core
@pytest.mark.parametrize("cell", CELLS, ids=lambda p: p.name)
def test_a_jerk_limited_path_streams_on_every_cell(cell: Path, tmp_path: Path) -> None:
    """The demo path with `jerk_limited = true` (planned within its default 2 counts, its knot times moved
    for the jerk bound: planner/encoding/continuity.py) runs on EPOS, cyclic and mixed cells with every
    guarantee kept at that tolerance."""
    text = (CONFIGS / "jobs" / "demo-path.toml").read_text()
    job = tmp_path / "demo-path-jerk.toml"
    job.write_text(text.replace('kind = "path"\n', 'kind = "path"\njerk_limited = true\n', 1))
    loaded = load_job(job, load_cell(cell))
    assert loaded.tolerance_counts == 2
    out = tmp_path / "out"
    assert pvt(["demo", "--fast", "--quiet", "--no-plot", "--config", str(cell), "--job", str(job),
                "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["result"] == "done", report
    assert guarantees(report, loaded.tolerance_counts) == []
