"""Home jobs at the command line (issue 14), as a user runs `pvt` (a subprocess at 80 columns): `pvt plan` of a
home job says what the drives will do (per axis the method, speeds, acceleration, home position), `--out` /
`--plot` and `pvt demo --job` are refused with a message and status 2, never a traceback; `pvt status` shows
per axis whether it is referenced (the runtime's `referenced`); `pvt serve --sim` runs the example home job."""

from __future__ import annotations

import json
import signal
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from planner.config import CellConfig
from streamer.api.client import MotionClient
from streamer.api.errors import MotionError
from streamer.api.model import JobState
from tests.api.conftest import Served, free_port
from tests.api.fakes import FakeBackend
from tests.cli.conftest import assert_fits, flat, pvt, start_pvt
from tests.conftest import CONFIGS

Serve = Callable[..., Served]
HOME_DEMO = str(CONFIGS / "homing" / "home-demo.toml")


def _headers(stdout: str) -> list[str]:
    """The first table's column headers, each joined over its wrapped lines."""
    lines: list[list[str]] = []
    for line in stdout.splitlines():
        if line.startswith("┃"):
            lines.append(line.split("┃")[1:-1])
        elif lines:
            break
    return [" ".join(w for w in (r[k].strip() for r in lines) if w) for k in range(len(lines[0]))]


def _no_traceback(out: Any) -> None:
    assert "Traceback" not in out.stdout + out.stderr, out.stderr


def test_plan_of_a_home_job_says_what_the_drives_will_do() -> None:
    out = pvt("plan", HOME_DEMO)
    assert out.returncode == 0, out.stderr
    _no_traceback(out)
    assert_fits(out.stdout)
    text = flat(out.stdout)
    assert "home job on cell demo: 6 axis(es), homing mode (6), at most 60 s (timeout_s)" in text
    assert "nothing is planned" in text
    assert _headers(out.stdout) == ["axis", "node", "method", "search [rad/s]", "zero [rad/s]",
                                    "acceleration [rad/s²]", "home position [rad]"]
    rows = [line.split("│")[1:-1] for line in out.stdout.splitlines() if line.startswith("│")]
    cells = [[c.strip() for c in r] for r in rows]
    assert cells[0] == ["j1", "1", "19", "0.2", "0.02", "2", "0"], cells
    assert [r[2] for r in cells] == ["19", "35", "35", "35", "35", "35"]
    assert "method 19 (j1): home switch active above its edge: the edge, left moving negative" in text
    assert "method 35 (j2, j3, j4, j5, j6): current position: no motion" in text

    data = json.loads(pvt("plan", HOME_DEMO, "--json").stdout)
    assert data["kind"] == "home" and data["planned"] is False and data["timeout_s"] == 60.0
    assert [(a["name"], a["method"], a["search_speed"], a["zero_speed"], a["acceleration"], a["home_position"])
            for a in data["axes"][:2]] == [("j1", 19, 0.2, 0.02, 2.0, 0.0), ("j2", 35, 0.2, 0.02, 2.0, 0.0)]


def test_plan_of_a_home_job_on_axes_of_different_units_and_defaults(tmp_path: Path) -> None:
    # the defaults come from the axes' limits (a tenth, a hundredth of the velocity; the acceleration)
    job = tmp_path / "home.json"
    job.write_text(json.dumps({"kind": "home", "axes": ["x", "j1"], "method": [35, 18], "offset": [5.0, 0.1]}))
    cell = tmp_path / "cell.toml"
    demo = (CONFIGS / "demo.toml").read_text(encoding="utf-8")
    # the demo cell with a linear axis x (mm) in front
    cell.write_text(demo.replace('[[axis]]\nname = "j1"', '[[axis]]\nname = "x"\nnode_id = 9\nunit = "mm"\n'
                                 'counts_per_unit = 1000.0\ncounts_per_rev = 4096\nvelocity = 500.0\n'
                                 'acceleration = 2000.0\njerk = 20000.0\nposition_min = 0.0\nposition_max = 800.0\n'
                                 'max_profile_velocity_rpm = 8000\nmax_acceleration = 3000.0\n\n'
                                 '[[axis]]\nname = "j1"', 1), encoding="utf-8")
    out = pvt("plan", str(job), "--config", str(cell))
    assert out.returncode == 0, out.stderr
    assert_fits(out.stdout)
    text = flat(out.stdout)
    rows = [[c.strip() for c in line.split("│")[1:-1]] for line in out.stdout.splitlines() if line.startswith("│")]
    assert [rows[0][0], *rows[0][2:]] == ["x", "35", "50 mm/s", "5 mm/s", "2000 mm/s²", "5 mm"], rows
    assert [rows[1][0], *rows[1][2:]] == ["j1", "18", "0.2 rad/s", "0.02 rad/s", "8 rad/s²", "0.1 rad"], rows
    assert "method 18 (j1): positive limit switch" in text


def test_plan_out_and_plot_and_demo_refuse_a_home_job(tmp_path: Path) -> None:
    for option in ("--out", "--plot"):
        target = tmp_path / f"x{option[2:]}"
        out = pvt("plan", HOME_DEMO, option, str(target))
        assert out.returncode == 2, out
        _no_traceback(out)
        assert "is a home job: it plans no PVT points" in flat(out.stderr) and not target.exists()
    demo_out = tmp_path / "demo-out"
    for fast in (["--fast"], []):
        out = pvt("demo", "--job", HOME_DEMO, "--out", str(demo_out), "--quiet", *fast)
        assert out.returncode == 2, out
        _no_traceback(out)
        assert_fits(out.stdout)
        text = flat(out.stdout)
        assert "is a home job: `pvt demo` streams a planned motion, and a home job plans none" in text
        assert "pvt serve --sim" in text and "pvt plan JOB" in text
        assert not demo_out.exists()


def test_status_headline_of_a_running_home_job() -> None:
    from streamer.cli.status import headline

    running = {"job_id": "h", "kind": "home", "state": "running", "progress": 0.5, "planned_duration_s": 0.0}
    assert headline({"cell": "demo", "ready": True, "running": running})[-1] == (
        "running: job h (home), running, 50.0% of its axes homed")  # not "of 0 s": it has no planned duration
    move = {**running, "kind": "move", "planned_duration_s": 2.0}
    assert headline({"cell": "demo", "ready": True, "running": move})[-1] == (
        "running: job h (move), running, 50.0% of 2.000 s")


class HomedFake(FakeBackend):
    """The fake backend with the motion runtime's `referenced` per axis (j1 and j2 homed)."""

    def telemetry(self) -> list[dict[str, Any]]:
        return [{**a, "referenced": a["name"] in ("j1", "j2")} for a in super().telemetry()]


def test_status_shows_which_axes_are_referenced(serve: Serve, demo_cell: CellConfig) -> None:
    served = serve(backend=HomedFake(demo_cell))
    out = pvt("status", "--connect", served.endpoint, "--cell", "demo")
    assert out.returncode == 0, out.stderr
    assert_fits(out.stdout)
    rows = {r[0]: r for r in ([c.strip() for c in line.split("│")[1:-1]] for line in out.stdout.splitlines()
                              if line.startswith("│")) if r and r[0].startswith("j")}
    assert _headers(out.stdout) == ["axis", "node", "state", "position [rad]", "velocity [rad/s]", "FIFO", "homed"]
    assert [rows[f"j{k}"][-1] for k in range(1, 7)] == ["yes", "yes", "no", "no", "no", "no"]
    raw = json.loads(pvt("status", "--connect", served.endpoint, "--cell", "demo", "--json").stdout)
    assert [d["referenced"] for d in raw["drives"]] == [True, True, False, False, False, False]


@pytest.mark.slow
def test_pvt_serve_sim_runs_the_example_home_job(tmp_path: Path) -> None:
    """`pvt serve --sim` on the demo cell with `require_homing = true`: a move is refused NOT_HOMED, `pvt submit
    --wait` of configs/homing/home-demo.toml ends done (exit 0), `pvt status` shows every axis homed, and the move
    is then accepted and done."""
    config = tmp_path / "demo.toml"
    text = (CONFIGS / "demo.toml").read_text(encoding="utf-8")
    config.write_text(text.replace('name = "demo"\n', 'name = "demo"\nrequire_homing = true\n', 1), encoding="utf-8")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = start_pvt("serve", "--config", str(config), "--sim", "--listen", endpoint, "--store", str(tmp_path / "s"),
                     "--no-record", "--log-level", "WARNING")
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()  # "pvt serve: cell 'demo' ready on ..."
        assert "ready" in line, (line, proc.stderr.read() if proc.poll() is not None and proc.stderr else "")
        with MotionClient(connect=endpoint, cell="demo") as client:
            with pytest.raises(MotionError) as refused:
                client.submit({"kind": "move", "axes": ["j1"], "target": [0.1]})
            assert refused.value.code == "NOT_HOMED"
            out = pvt("submit", HOME_DEMO, "--connect", endpoint, "--cell", "demo", "--wait", "--timeout", "60")
            assert out.returncode == 0, out.stdout + out.stderr
            _no_traceback(out)
            assert_fits(out.stderr)  # the progress and the outcome go to stderr
            assert out.stderr.rstrip().endswith(": done"), out.stderr
            assert "queued: a home job (nothing planned: the drives search their home positions)" in flat(out.stderr)
            status = json.loads(pvt("status", "--connect", endpoint, "--cell", "demo", "--json").stdout)
            assert [d["referenced"] for d in status["drives"]] == [True] * 6
            assert status["ready"] is True
            assert client.submit({"kind": "move", "axes": ["j1"], "target": [0.1]}).wait(timeout=30).state == \
                JobState.DONE
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)
