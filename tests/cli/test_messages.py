"""What the product says when a new user gets something wrong (issue 14, section 3): config mistakes named
with the axes and the intended key, limits beyond int32 counts refused at load, a relative move's error in
the user's own terms, `pvt demo` on another cell without --job, --fast with --external-drives; the
service's log line per job; its state files in a data directory, not beside the config."""

from __future__ import annotations

import logging
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from planner.config import load_cell
from planner.errors import PlanningError
from planner.job import job_from_dict
from planner.plan import plan_job
from streamer.api.errors import JobFailedError
from streamer.api.model import JobState
from tests.api.conftest import Served, free_port
from tests.api.fakes import timed_job
from tests.cli.conftest import ROOT, cli_env, flat, pvt
from tests.cli.test_tables import gantry

Serve = Callable[..., Served]
DEMO = (ROOT / "configs" / "demo.toml").read_text(encoding="utf-8")
MOVE = ROOT / "configs" / "jobs" / "move.toml"


def config(tmp_path: Path, text: str, name: str = "cell.toml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_a_duplicate_node_id_names_both_axes(tmp_path: Path) -> None:
    bad = config(tmp_path, DEMO.replace("node_id = 2", "node_id = 1", 1))
    out = pvt("plan", str(MOVE), "--config", str(bad))
    assert out.returncode == 2
    assert "duplicate axis node_id 1: axis[0] 'j1' and axis[1] 'j2' both have it" in flat(out.stderr)


def test_a_misspelt_key_is_unknown_with_the_key_it_meant(tmp_path: Path) -> None:
    bad = config(tmp_path, DEMO.replace("counts_per_unit = 65189.86      # 8192", "count_per_unit = 65189.86 #", 1))
    out = pvt("plan", str(MOVE), "--config", str(bad))
    assert out.returncode == 2
    said = flat(out.stderr)
    assert "CONFIG at axis[0].count_per_unit" in said
    assert "unknown key 'count_per_unit' (did you mean 'counts_per_unit'?) in axis[0] ('j1')" in said
    assert "missing" not in said
    drive = config(tmp_path, DEMO.replace("heartbeat_ms = 100", "heartbeat = 100", 1), "drive.toml")
    assert "unknown key 'heartbeat' (did you mean 'heartbeat_ms'?) in [drive]" in flat(
        pvt("plan", str(MOVE), "--config", str(drive)).stderr)


def test_position_limits_beyond_int32_counts_are_refused_at_load(tmp_path: Path) -> None:
    bad = config(tmp_path, DEMO.replace("position_max = 3.0", "position_max = 40000.0", 1))
    out = pvt("plan", str(MOVE), "--config", str(bad))
    assert out.returncode == 2
    said = flat(out.stderr)
    assert "LIMITS at axis[0].position_max" in said and "axis 'j1'" in said
    assert "2607594400 counts" in said and "int32" in said


def test_a_relative_moves_error_shows_what_was_written(tmp_path: Path) -> None:
    job = config(tmp_path, 'kind = "move"\naxes = ["x"]\ntarget = [500.0]\nmode = "relative"\nstart = [900.0]\n',
                 "rel.toml")
    out = pvt("plan", str(job), "--config", str(gantry(tmp_path)))
    assert out.returncode == 2
    assert ("target[0] of axis 'x' is a relative move of +500 from the start 900: it would end at 1400, outside "
            "the software position limits [0, 1200]") in flat(out.stderr)
    # planned from where the axes stand (the job service's way): the same words, "the current position"
    cell = load_cell(gantry(tmp_path))
    with pytest.raises(PlanningError) as info:
        plan_job(job_from_dict({"kind": "move", "axes": ["x"], "target": [500.0], "mode": "relative"}, cell),
                 cell, start=[900.0])
    assert "relative move of +500 from the current position 900: it would end at 1400" in info.value.message


def test_demo_on_another_cell_without_a_job_says_the_default_job_was_used(tmp_path: Path) -> None:
    out = pvt("demo", "--fast", "--config", str(gantry(tmp_path)), "--out", str(tmp_path / "out"))
    assert out.returncode == 2
    said = flat(out.stdout)
    assert "no --job given, so the default demo job configs/jobs/demo-path.toml was used" in said
    assert "does not fit cell 'gantry' (2 axes: x [mm], y [mm])" in said
    assert "axes lists 6 axes but cell 'gantry' has 2" in said and "--job FILE" in said
    assert not (tmp_path / "out").exists()


def test_demo_refuses_fast_with_external_drives(tmp_path: Path) -> None:
    out = pvt("demo", "--fast", "--external-drives", "--out", str(tmp_path / "out"))
    assert out.returncode == 2
    assert "--fast and --external-drives do not go together" in flat(out.stdout)
    assert not (tmp_path / "out").exists()


def test_the_service_logs_a_line_per_job(serve: Serve, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="streamer.api.service")
    served = serve(fail_code="DRIVE_FAULT")
    with served.client() as client:
        with pytest.raises(JobFailedError):  # the failure is what is logged
            client.submit(timed_job(0.1), job_id="log-failed").wait(timeout=10)
        client.reset()
        client.submit(timed_job(0.1), job_id="log-done").wait(timeout=10)
        queued = client.submit(timed_job(5.0), job_id="log-long")
        client.submit(timed_job(0.1), job_id="log-queued").cancel()
        queued.cancel()
        queued.wait(timeout=10)
    lines = [r.getMessage() for r in caplog.records if r.name == "streamer.api.service"]
    for expected in ("job log-failed accepted: timed job, planned 0.100 s, 3 points", "job log-failed started",
                     "job log-failed failed DRIVE_FAULT: node 3 raised DRIVE_FAULT", "job log-done done",
                     "job log-queued cancelled: cancelled while queued", "job log-long cancelling at",
                     "job log-long cancelled", "queue of cell 'demo' held: job log-long was cancelled"):
        assert any(line.startswith(expected) for line in lines), (expected, lines)


def test_pvt_serve_logs_jobs_and_keeps_its_state_in_the_data_directory(tmp_path: Path) -> None:
    cell_dir = tmp_path / "cells"
    cell_dir.mkdir()
    cell = config(cell_dir, DEMO, "demo.toml")
    data = tmp_path / "data"
    port = free_port()
    server = subprocess.Popen(
        [sys.executable, "-m", "streamer.cli", "serve", "--config", str(cell), "--listen", f"tcp/127.0.0.1:{port}",
         "--backend", "tests.api.fakes:open_fake_backend", "--store", str(data)],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env=cli_env(XDG_STATE_HOME=str(tmp_path / "state")))
    try:
        assert server.stdout is not None
        ready = server.stdout.readline()
        assert "ready" in ready and str(data / "demo.jobs.sqlite") in ready
        from streamer.api.client import MotionClient

        with MotionClient(connect=f"tcp/127.0.0.1:{port}", cell="demo") as client:
            client.wait_for_service(timeout=10)
            assert client.submit(timed_job(0.1), job_id="logged").wait(timeout=10).state == JobState.DONE
            assert client.service_status()["store"] == str(data / "demo.jobs.sqlite")
        server.send_signal(signal.SIGTERM)
        _, err = server.communicate(timeout=30)
    finally:
        if server.poll() is None:
            server.kill()
            server.wait(timeout=10)
    for line in ("job logged accepted: timed job", "job logged started", "job logged done"):
        assert line in err, err
    assert (data / "demo.jobs.sqlite").exists()
    assert sorted(p.name for p in cell_dir.iterdir()) == ["demo.toml"]  # nothing beside the config
    assert not (tmp_path / "state").exists()  # --store, not the default
    listed = pvt("jobs", "--config", str(cell), "--store", str(data), "--json")
    assert listed.returncode == 0 and '"logged"' in listed.stdout
