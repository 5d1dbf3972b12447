"""Tables fit 80 columns (issue 14, section 3): wrap or drop columns, never cut a value; units in the
headers; numbers never as 1e+03; plots label the axis unit (the cell's `unit`)."""

from __future__ import annotations

import contextlib
import dataclasses
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from rich.cells import cell_len
from rich.console import Console

from planner.config import CellConfig, load_cell
from planner.plan import plan_job
from streamer.api.errors import JobFailedError
from streamer.api.model import JobState
from streamer.cli.tables import Col, fit_table, number
from tests.api.conftest import Served
from tests.api.fakes import FakeBackend, TrackingFake, timed_job
from tests.cli.conftest import assert_fits, flat, pvt, words_in

Serve = Callable[..., Served]

LONG_ID = "pick-and-place-station-a-" + "x" * 30  # 55 characters
MESSAGE = ("node 3 raised FOLLOWING_ERROR: the actual position of axis 'j3' was 20001 counts away from the "
           "demand, more than 0x6065 allows (following_error_counts 20000)")


def gantry(tmp_path: Path) -> Path:
    """A 2-axis gantry in mm, the way a new user writes it from docs/formats.md."""
    text = "\n".join([
        '[cell]', 'name = "gantry"', 'sync_period_ms = 10', '',
        *[line for axis, node, top in (("x", 1, 1200.0), ("y", 2, 800.0)) for line in (
            '[[axis]]', f'name = "{axis}"', f'node_id = {node}', 'unit = "mm"', 'counts_per_unit = 2000.0',
            'counts_per_rev = 8192', 'velocity = 500.0', 'acceleration = 2000.0', 'jerk = 20000.0',
            'position_min = 0.0', f'position_max = {top}', 'max_profile_velocity_rpm = 8000',
            'max_acceleration = 3000.0', '')],
    ])
    path = tmp_path / "gantry.toml"
    path.write_text(text, encoding="utf-8")
    return path


def test_fit_table_never_cuts_a_value() -> None:
    columns = [Col("#", justify="right"), Col("job_id"), Col("kind", drop=2), Col("state"),
               Col("planned [s]", justify="right"), Col("submitted", drop=1), Col("error", text=True)]
    rows = [["12", LONG_ID, "path", "failed", "2.345", "12:00:01", f"FOLLOWING_ERROR: {MESSAGE}"]]
    for width in (40, 60, 80, 120, 200):
        console = Console(width=width, record=True, color_system=None)
        console.print(fit_table(columns, rows, width, title="jobs"))
        text = console.export_text()
        assert_fits(text, width)
        assert words_in(text, MESSAGE)
        if width >= 80:
            assert LONG_ID in text and "planned" in text and "[s]" in text  # whole, and the header's unit
    # the optional columns that do not fit are named under the table
    console = Console(width=120, record=True, color_system=None)
    console.print(fit_table(columns, rows, 120))
    assert "not shown at 120 columns: submitted" in flat(console.export_text())


@pytest.mark.parametrize(("value", "text"), [(1000.0, "1000"), (1234.5678, "1235"), (0.41234, "0.4123"),
                                             (2.0, "2.000"), (0.00012345, "0.0001234"), (-3.0, "-3.000"),
                                             (123456789.0, "123456789"), (1e-12, "0"), (7, "7"), (None, "-")])
def test_numbers_are_printed_without_exponents(value: Any, text: str) -> None:
    assert number(value) == text


def test_pvt_jobs_fits_80_columns_locally_and_remotely(serve: Serve) -> None:
    served = serve(fail_code="FOLLOWING_ERROR")
    with served.client() as client:
        job = client.submit(timed_job(0.1), job_id=LONG_ID)
        with pytest.raises(JobFailedError):
            job.wait(timeout=10)
        served.backend.reset()
        client.submit(timed_job(0.1), job_id="short").wait(timeout=10)
    for argv in (("jobs", "--store", str(served.store.path)), ("jobs", "--connect", served.endpoint),
                 ("jobs", "--store", str(served.store.path), "--events", LONG_ID),
                 ("jobs", "--connect", served.endpoint, "--events", LONG_ID)):
        out = pvt(*argv)
        assert out.returncode == 0, out.stderr
        assert_fits(out.stdout)
        if "--events" in argv:
            assert words_in(out.stdout, '"message":"node 3 raised FOLLOWING_ERROR"')
        else:
            assert LONG_ID in out.stdout and "short" in out.stdout
            assert words_in(out.stdout, "FOLLOWING_ERROR: node 3 raised FOLLOWING_ERROR")
            assert "planned" in out.stdout and "[s]" in out.stdout


INFEASIBLE = ("the queued move of axes ['j1', 'j2', 'j3'] no longer starts where the axes stand: axis 'j2' "
              "stands at 0.4312 rad, the job's first row is at -0.2500 rad (off by 6812 counts, tolerance 2); "
              "re-plan it with start = \"current\" or submit configs/jobs/pick-and-place-station-a.toml again")


class FailingFake(FakeBackend):
    """Every job whose name starts with "bad" fails INFEASIBLE with a long message (the cell stays ready)."""

    def execute(self, planned: Any, emit: Any, cancel: Any) -> Any:
        if str(planned.job.get("name", "")).startswith("bad"):
            return self._report("failed", planned, 0.0, error={"code": "INFEASIBLE", "node": None,
                                                               "message": INFEASIBLE})
        return super().execute(planned, emit, cancel)


def test_pvt_jobs_keeps_one_line_per_job_at_80_columns_with_long_errors(serve: Serve, demo_cell: CellConfig) -> None:
    """Issue 23 item 6: a journal with a few long errors (and the service's own 32-character job ids) lists one
    line per job at 80 columns: id, kind, state and planned duration whole, the error cut to the line, the
    caption says where the whole text is, and `pvt jobs show ID` prints it."""
    served = serve(backend=FailingFake(demo_cell))
    ids: list[str] = []
    with served.client() as client:
        for name in ("ok-1", "bad-1", "ok-2", "bad-2", "bad-3"):
            job = client.submit(timed_job(0.1, name=name))
            with contextlib.suppress(JobFailedError):
                job.wait(timeout=10)
            ids.append(job.job_id)
    assert all(len(i) == 32 for i in ids)
    out = pvt("jobs", "--store", str(served.store.path))
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert all(cell_len(line) <= 80 for line in lines), lines
    for job_id, name in zip(ids, ("ok-1", "bad-1", "ok-2", "bad-2", "bad-3"), strict=True):
        rows = [line for line in lines if job_id in line]
        assert len(rows) == 1, out.stdout  # one line, the whole id on it
        state = "failed" if name.startswith("bad") else "done"
        assert "timed" in rows[0] and state in rows[0] and "0.100" in rows[0], rows[0]
        if state == "failed":
            assert "INFEASIBLE" in rows[0] and "…" in rows[0]  # the code, the rest cut to the line
    assert len(lines) <= len(ids) + 10, out.stdout  # title, header, borders, caption: not 9-line cards
    assert "pvt jobs show ID" in flat(out.stdout)
    shown = pvt("jobs", "show", ids[1], "--store", str(served.store.path))
    assert words_in(shown.stdout, f"error INFEASIBLE: {INFEASIBLE}"), shown.stdout


def test_pvt_status_shows_positions_in_the_axis_unit(serve: Serve, tmp_path: Path) -> None:
    cell = load_cell(gantry(tmp_path))
    backend = TrackingFake(cell)
    served = serve(backend=backend)
    with served.client() as client:  # the service's cell: gantry
        job = {**timed_job(0.1, axes=["x", "y"]), "positions": [[0.0, 0.0], [1000.0, 612.5]]}
        assert client.submit(job).wait(timeout=10).state == JobState.DONE
    out = pvt("status", "--connect", served.endpoint, "--cell", "gantry")
    assert out.returncode == 0, out.stderr
    assert_fits(out.stdout)
    assert "[mm]" in out.stdout and "[mm/s]" in out.stdout
    assert "1000.00" in out.stdout and "612.500" in out.stdout and "e+0" not in out.stdout


def test_pvt_demo_summary_fits_80_columns_with_units(tmp_path: Path) -> None:
    out = pvt("demo", "--fast", "--no-plot", "--out", str(tmp_path / "out"))
    assert out.returncode == 0, out.stdout + out.stderr
    assert_fits(out.stdout)
    said = flat(out.stdout)
    for word in ("deviation", "following", "final", "error", "underflow", "warnings", "FIFO", "min/max"):
        assert word in out.stdout, word  # the headers, whole (wrapped over header lines)
    assert out.stdout.count("[counts]") == 3
    assert "start SYNC" in said and "(all axes)" in said
    assert "[unit]" not in out.stdout
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    for axis in report["axes"]:
        assert f" {axis['name']} " in out.stdout


def test_the_motion_plot_labels_the_axis_unit(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                               demo_cell: CellConfig) -> None:
    import matplotlib.figure

    from streamer import demo

    labels: list[str] = []
    save = matplotlib.figure.Figure.savefig

    def capture(fig: Any, *args: Any, **kw: Any) -> Any:
        labels.extend(ax.get_ylabel() for ax in fig.axes)
        return save(fig, *args, **kw)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", capture)
    cell = dataclasses.replace(demo_cell, axes=tuple(dataclasses.replace(a, unit="deg") if a.name == "j2" else a
                                                     for a in demo_cell.axes))
    job = demo.load_job(demo.DEFAULT_JOB, cell)
    traj = demo.plan_job(job, cell)
    demo.run_fast(cell, traj, tmp_path)
    assert "j1\nposition [rad]" in labels and "j2\nposition [deg]" in labels
    assert not [label for label in labels if "[unit]" in label]


def test_pvt_plan_fits_80_columns_with_units_and_no_exponents(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    job = tmp_path / "move.toml"
    job.write_text('kind = "move"\naxes = ["x", "y"]\ntarget = [1000.0, 600.0]\n', encoding="utf-8")
    cell = gantry(tmp_path)
    out = pvt("plan", str(job), "--config", str(cell))
    assert out.returncode == 0, out.stderr
    assert_fits(out.stdout)
    assert "[mm/s]" in out.stdout and "[mm/s²]" in out.stdout and "[counts]" in out.stdout
    assert "e+0" not in out.stdout and "500.0/500.0" in out.stdout and "/2000 " in out.stdout
    # the plot's labels are the axis unit
    import matplotlib.figure

    from planner.job import load_job
    from streamer.cli import plan as cli_plan

    labels: list[str] = []
    save = matplotlib.figure.Figure.savefig

    def capture(fig: Any, *args: Any, **kw: Any) -> Any:
        labels.extend(ax.get_ylabel() for ax in fig.axes)
        return save(fig, *args, **kw)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", capture)
    loaded = load_cell(cell)
    traj = plan_job(load_job(job, loaded), loaded)
    cli_plan.plot(traj, tmp_path / "plot.png", units=["mm", "mm"])
    assert {"position [mm]", "velocity [mm/s]", "acceleration [mm/s²]", "deviation [counts]"} <= set(labels)
    assert not [label for label in labels if "[unit" in label]


def test_the_readme_shows_the_jobs_layout_pvt_jobs_prints() -> None:
    """The README's `pvt jobs` example at 80 columns is what the job table prints for those rows."""
    from streamer.cli.jobs import JOB_COLUMNS

    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text(encoding="utf-8")
    block = readme.split("`pvt jobs` keeps one line per job", 1)[1].split("```text\n", 1)[1].split("```", 1)[0]
    rows = [["3", "5c5f5e0fb3bb4b96957da18ae5f728f6", "move", "failed", "api", "2.412", "41", "12:00:09",
             "INFEASIBLE: the queued move of axes ['j1', 'j2'] no longer starts where the axes stand"],
            ["2", "pick-1", "path", "done", "api", "3.870", "96", "12:00:04", ""],
            ["1", "0aca1aae31934139aca4cae18b05af8e", "move", "done", "cli", "1.205", "22", "12:00:01", ""]]
    console = Console(width=80, record=True, color_system=None)
    console.print(fit_table(JOB_COLUMNS, rows, 80, title="jobs in ~/.local/state/pvt/demo.jobs.sqlite (3 total)"))
    printed = [line.rstrip() for line in console.export_text().splitlines()]
    assert printed == block.rstrip("\n").splitlines()
