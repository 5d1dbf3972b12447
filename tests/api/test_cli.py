"""`pvt submit`, `pvt jobs`, `pvt serve` options, and the example client script (examples are tests)."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from streamer.cli import jobs as cli_jobs
from streamer.cli import serve as cli_serve
from streamer.cli import submit as cli_submit
from tests.api.conftest import Served
from tests.api.fakes import timed_job

ROOT = Path(__file__).resolve().parents[2]


def run_cli(module: object, argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="pvt")
    sub = parser.add_subparsers()
    module.add_parser(sub)  # type: ignore[attr-defined]
    args = parser.parse_args(argv)
    result: int = args.func(args)
    return result


@pytest.fixture
def job_file(tmp_path: Path) -> Path:
    path = tmp_path / "job.json"
    path.write_text(json.dumps(timed_job(0.2, axes=["j1", "j2"])), encoding="utf-8")
    return path


def test_submit_wait_shows_progress_and_exits_0(
    serve: Callable[..., Served], job_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    served = serve()
    code = run_cli(
        cli_submit,
        [
            "submit",
            str(job_file),
            "--connect",
            served.endpoint,
            "--cell",
            "demo",
            "--wait",
            "--job-id",
            "cli-1",
            "--json",
        ],
    )
    assert code == 0
    out = capsys.readouterr()
    assert json.loads(out.out)["state"] == "done"
    assert "100.0%" in out.err
    rec = served.store.get("cli-1")
    assert rec is not None and rec.state.value == "done"


def test_submit_without_wait_toml_and_put(
    serve: Callable[..., Served], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    served = serve()
    toml_job = tmp_path / "job.toml"
    toml_job.write_text('kind = "timed"\naxes = ["j1"]\ntimes = [0.0, 0.1]\npositions = [[0.0], [0.1]]\n')
    assert run_cli(cli_submit, ["submit", str(toml_job), "--connect", served.endpoint, "--json"]) == 0
    reply = json.loads(capsys.readouterr().out)
    assert reply["state"] == "queued" and reply["points"] == 3
    assert (
        run_cli(
            cli_submit,
            ["submit", str(toml_job), "--connect", served.endpoint, "--put", "--wait", "--job-id", "by-put"],
        )
        == 0
    )
    assert served.store.get("by-put") is not None


def test_submit_rejections_and_failures_exit_codes(serve: Callable[..., Served], tmp_path: Path) -> None:
    served = serve(fail_code="BUFFER_UNDERFLOW")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"kind": "path", "axes": ["j1"], "waypoints": [["x"]]}))
    assert run_cli(cli_submit, ["submit", str(bad), "--connect", served.endpoint]) == 2
    good = tmp_path / "good.json"
    good.write_text(json.dumps(timed_job(0.2)))
    assert run_cli(cli_submit, ["submit", str(good), "--connect", served.endpoint, "--wait"]) == 1  # failed
    assert run_cli(cli_submit, ["submit", str(tmp_path / "missing.json"), "--connect", served.endpoint]) == 2
    assert (  # no service for that cell: 5 (not 2: nothing was rejected)
        run_cli(
            cli_submit,
            ["submit", str(good), "--connect", served.endpoint, "--cell", "nocell", "--connect-timeout", "0.3"],
        )
        == 5
    )


def test_jobs_lists_the_journal(
    serve: Callable[..., Served], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    served = serve()
    with served.client() as client:
        for i in range(3):
            client.submit(timed_job(0.02), job_id=f"listed-{i}").wait(timeout=5)
    capsys.readouterr()
    store = str(served.store.path)
    assert run_cli(cli_jobs, ["jobs", "--store", store, "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)
    assert [j["job_id"] for j in listed] == ["listed-2", "listed-1", "listed-0"]
    assert run_cli(cli_jobs, ["jobs", "--store", store]) == 0
    table = capsys.readouterr().out
    assert "listed-1" in table and "done" in table
    assert run_cli(cli_jobs, ["jobs", "--store", store, "--events", "listed-0"]) == 0
    assert "accepted" in capsys.readouterr().out
    assert run_cli(cli_jobs, ["jobs", "--store", store, "--events", "listed-0", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)[0]["type"] == "accepted"
    assert run_cli(cli_jobs, ["jobs", "--store", store, "--state", "failed", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == []
    assert run_cli(cli_jobs, ["jobs", "--store", store, "--state", "bogus"]) == 2
    assert run_cli(cli_jobs, ["jobs", "--store", store, "--events", "nope"]) == 1
    assert run_cli(cli_jobs, ["jobs", "--store", str(tmp_path / "none.db")]) == 0
    assert not (tmp_path / "none.db").exists()


def test_serve_rejects_bad_options(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = ROOT / "configs" / "demo.toml"
    for bad_bus in ("nochannel", "udp_multicast:239.0.0.1"):
        code = run_cli(
            cli_serve,
            ["serve", "--config", str(config), "--bus", bad_bus, "--store", str(tmp_path / "s.db")],
        )
        assert code == 2 and "CONFIG" in capsys.readouterr().err
    assert run_cli(cli_serve, ["serve", "--config", str(tmp_path / "missing.toml")]) == 2
    code = run_cli(
        cli_serve,
        [
            "serve",
            "--config",
            str(config),
            "--store",
            str(tmp_path / "s.db"),
            "--backend",
            "no.such.module:factory",
            "--listen",
            "tcp/127.0.0.1:1",
        ],
    )
    assert code == 2 and "backend unavailable" in capsys.readouterr().err


def test_example_script_runs_against_a_service(serve: Callable[..., Served]) -> None:
    served = serve()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run(
        [
            sys.executable,
            str(ROOT / "examples" / "submit_job.py"),
            "--connect",
            served.endpoint,
            "--cell",
            "demo",
            "--timeout",
            "20",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    assert "final state: done" in out.stdout and "#1 accepted" in out.stdout


def test_submitting_a_job_file_twice_runs_it_twice(serve: Callable[..., Served]) -> None:
    served = serve()
    job = ROOT / "configs" / "jobs" / "move.toml"
    for _ in range(2):
        assert run_cli(cli_submit, ["submit", str(job), "--connect", served.endpoint, "--wait"]) == 0
    ids = [r.job_id for r in served.store.list_jobs()]
    assert len(ids) == 2 and ids[0] != ids[1] and all(i.startswith("demo-move-") for i in ids)
    # with --job-id the id is exact and a resubmit is idempotent
    for _ in range(2):
        assert (
            run_cli(cli_submit, ["submit", str(job), "--connect", served.endpoint, "--job-id", "exact"]) == 0
        )
    assert served.store.count() == 3
