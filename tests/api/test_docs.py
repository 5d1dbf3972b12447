"""docs/api.md is the contract: its raw Zenoh example runs verbatim, its tables match the code."""

from __future__ import annotations

import contextlib
import io
import json
import re
from collections.abc import Callable
from pathlib import Path

import pytest

from planner.errors import CODES as PLANNER_CODES
from streamer.api import keys
from streamer.api.errors import API_CODES
from streamer.api.payload import decode_submission, pack
from tests.api.conftest import Served
from tests.api.helpers import raw_get

DOC = Path(__file__).resolve().parents[2] / "docs" / "api.md"
TEXT = DOC.read_text(encoding="utf-8")


def raw_example() -> str:
    m = re.search(r"```python raw-zenoh-example\n(.*?)```", TEXT, re.S)
    assert m, "docs/api.md lost its raw-zenoh-example block"
    return m.group(1)


def test_raw_zenoh_example_from_the_doc_submits_and_reads_events(serve: Callable[..., Served]) -> None:
    served = serve()
    code = raw_example()
    assert "streamer" not in code and "planner" not in code  # nothing of this project
    code = code.replace('ENDPOINT = "tcp/127.0.0.1:7447"', f'ENDPOINT = "{served.endpoint}"')
    namespace: dict[str, object] = {"__name__": "raw_example"}
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, str(DOC), "exec"), namespace)
    events = namespace["events"]
    assert isinstance(events, list)
    assert [e["type"] for e in events][:4] == ["accepted", "planned", "priming", "running"]
    assert events[-1]["type"] == "done"
    assert namespace["status"]["state"] == "done"  # type: ignore[index]
    assert "final state: done" in out.getvalue()


def test_key_table_matches_keys_module() -> None:
    table = set(re.findall(r"^\| `(pvt/[^`]+)` \|", TEXT, re.M))
    cell, job = "<cell>", "<job_id>"
    expected = {
        keys.submit("CELL"),
        keys.rejected("CELL"),
        keys.jobs("CELL"),
        keys.job("CELL", "JOB"),
        keys.job_events("CELL", "JOB"),
        keys.job_cancel("CELL", "JOB"),
        keys.service("CELL"),
        keys.reset("CELL"),
        keys.stop("CELL"),
        keys.hold("CELL"),
        keys.halt("CELL"),
        keys.resume("CELL"),
        keys.telemetry("CELL"),
        keys.alive("CELL"),
    }
    expected = {k.replace("CELL", cell).replace("JOB", job) for k in expected}
    assert table == expected


def test_every_error_code_is_documented() -> None:
    documented = set(re.findall(r"^\| `([A-Z_]+)` \|", TEXT, re.M))
    in_text = set(re.findall(r"`([A-Z][A-Z_]+)`", TEXT))
    table_codes = (API_CODES | PLANNER_CODES) - {
        "CONFIG",
        "SERVICE_RESTART",
        "SERVICE_STOPPED",
        "TIMEOUT",
        "NO_SERVICE",
    }
    assert table_codes <= documented, table_codes - documented
    assert {"SERVICE_RESTART", "SERVICE_STOPPED", "TIMEOUT", "NO_SERVICE", "SERVICE_GONE"} <= in_text


def job_examples() -> list[dict[str, object]]:
    blocks = re.findall(r"```json\n(.*?)```", TEXT, re.S)
    jobs = [json.loads(b) for b in blocks]
    return [j for j in jobs if isinstance(j, dict) and "kind" in j and "axes" in j]


def test_doc_has_an_example_of_each_job_kind() -> None:
    assert sorted({str(j["kind"]) for j in job_examples()}) == ["move", "path", "pvt", "timed"]  # (a velocity move too)


@pytest.mark.parametrize("job", job_examples(), ids=lambda j: str(j["kind"]))
def test_doc_job_examples_decode(job: dict[str, object]) -> None:
    sub = decode_submission(pack(job))
    assert sub.kind == job["kind"]


def test_doc_job_examples_are_accepted_by_the_service(serve: Callable[..., Served]) -> None:
    """Through the service (the fake backend's schema mirrors the planner's; test_e2e uses the planner)."""
    from tests.api.fakes import KINDS

    served = serve()
    with served.client() as client:
        for job in job_examples():
            body = {k: v for k, v in job.items() if k != "job_id"}
            required, optional = KINDS[str(job["kind"])]
            assert not set(body) - required - optional, "the fake's schema is the planner's"
            kind, msg = raw_get(client.session, keys.submit("demo"), pack(body))
            assert kind == "ok", (job, msg)


@pytest.mark.parametrize("job", job_examples(), ids=lambda j: str(j["kind"]))
def test_doc_job_examples_are_valid_for_the_planner(job: dict[str, object], demo_cell: object) -> None:
    planner_job = pytest.importorskip("planner.job")
    import planner

    body = {k: v for k, v in job.items() if k != "job_id"}
    parsed = planner_job.job_from_dict(body, demo_cell)
    traj = planner.plan_job(parsed, demo_cell)  # type: ignore[attr-defined]
    assert traj.duration_s > 0
