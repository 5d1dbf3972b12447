"""From `pvt certs init` to a secured `pvt serve`, then `pvt submit` / `pvt jobs --connect` as operator and
observer: the printed [security] section works as it is, with paths relative to the cell config."""

from __future__ import annotations

import argparse
import json
import re
import threading
from pathlib import Path

import pytest

from streamer.cli import build_parser
from streamer.cli import certs as cli_certs
from streamer.cli import jobs as cli_jobs
from streamer.cli import serve as cli_serve
from streamer.cli import submit as cli_submit
from tests.api.conftest import free_port
from tests.api.fakes import timed_job

ROOT = Path(__file__).resolve().parents[2]


def run_cli(module: object, argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="pvt")
    sub = parser.add_subparsers()
    module.add_parser(sub)  # type: ignore[attr-defined]
    args = parser.parse_args(argv)
    result: int = args.func(args)
    return result


def secured_cell(tmp_path: Path, capsys: pytest.CaptureFixture[str], endpoint: str) -> Path:
    """configs/demo.toml with the [security] section `pvt certs init` prints, paths made relative."""
    assert run_cli(cli_certs, ["certs", "init", str(tmp_path / "certs")]) == 0
    printed = capsys.readouterr().out
    section = printed[printed.index("[security]") :].replace(f"{tmp_path}/", "")
    assert 'ca = "certs/ca.pem"' in section
    demo = (ROOT / "configs" / "demo.toml").read_text(encoding="utf-8")
    demo = re.sub(r'listen = \["tcp/127\.0\.0\.1:7447"\]', f'listen = ["{endpoint}"]', demo)
    config = tmp_path / "cell.toml"
    config.write_text(demo + "\n" + section + "\n", encoding="utf-8")
    return config


def test_certs_init_serve_submit_and_list_as_operator_and_observer(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    endpoint = f"tls/127.0.0.1:{free_port()}"
    config = secured_cell(tmp_path, capsys, endpoint)
    stop = threading.Event()
    args = build_parser().parse_args(
        ["serve", "--config", str(config), "--store", str(tmp_path / "jobs.db"),
         "--backend", "tests.api.fakes:open_fake_backend"]
    )
    result: list[int] = []
    server = threading.Thread(target=lambda: result.append(cli_serve.run(args, stop=stop)), daemon=True)
    server.start()
    try:
        job = tmp_path / "job.json"
        job.write_text(json.dumps(timed_job(0.1, axes=["j1"])), encoding="utf-8")
        certs = tmp_path / "certs"

        def as_(who: str) -> list[str]:
            return ["--ca", str(certs / "ca.pem"), "--cert", str(certs / f"{who}.pem"),
                    "--key", str(certs / f"{who}.key")]

        common = ["--connect", endpoint, "--cell", "demo", "--timeout", "10"]
        assert run_cli(cli_submit, ["submit", str(job), *common, "--wait", "--job-id", "op-1", *as_("operator")]) == 0
        assert "TLS and access control on" in capsys.readouterr().out  # the service's ready line
        assert run_cli(cli_submit, ["submit", str(job), *common, "--job-id", "ob-1", *as_("observer")]) == 2
        assert "PERMISSION_DENIED" in capsys.readouterr().err
        assert run_cli(cli_jobs, ["jobs", *common, "--json", *as_("observer")]) == 0
        listed = json.loads(capsys.readouterr().out)
        assert [j["job_id"] for j in listed] == ["op-1"] and listed[0]["state"] == "done"
        assert run_cli(cli_jobs, ["jobs", *common, "--events", "op-1", "--json", *as_("observer")]) == 0
        assert json.loads(capsys.readouterr().out)[-1]["type"] == "done"
        assert run_cli(cli_jobs, ["jobs", *common, *as_("observer")]) == 0
        assert "op-1" in capsys.readouterr().out
        assert run_cli(cli_jobs, ["jobs", *common, "--events", "nope", *as_("observer")]) == 1
        # no client certificate: the link is refused, the command says it cannot reach the service (exit 5)
        assert run_cli(cli_submit, ["submit", str(job), *common, "--ca", str(certs / "ca.pem")]) == 5
        assert run_cli(cli_submit, ["submit", str(job), *common[:2], "--ca", str(certs / "missing.pem")]) == 2
        assert "SECURITY_FILE" in capsys.readouterr().err
    finally:
        stop.set()
        server.join(timeout=30)
    assert result == [0]


def test_serve_refuses_a_secured_cell_with_a_plain_endpoint(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = secured_cell(tmp_path, capsys, "tcp/127.0.0.1:1")
    code = run_cli(cli_serve, ["serve", "--config", str(config), "--store", str(tmp_path / "s.db")])
    err = capsys.readouterr().err
    assert code == 2 and "SECURITY_CONFIG" in err and "tcp/127.0.0.1:1" in err
    assert not (tmp_path / "s.db").exists()  # nothing was started


def test_certs_init_refuses_to_overwrite_and_bad_identities(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert run_cli(cli_certs, ["certs", "init", str(tmp_path), "--identity", "robot=pvt-robot"]) == 0
    out = capsys.readouterr().out
    assert (tmp_path / "robot.pem").exists() and '"cn:pvt-robot"' in out
    assert run_cli(cli_certs, ["certs", "init", str(tmp_path)]) == 2
    assert "CERT_EXISTS" in capsys.readouterr().err
    assert run_cli(cli_certs, ["certs", "init", str(tmp_path), "--force", "--identity", "robot"]) == 2
    assert run_cli(cli_certs, ["certs", "init", str(tmp_path), "--force"]) == 0
