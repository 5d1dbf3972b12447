"""docs/security.md cannot rot: its tables are the code's, its config loads, its commands parse and its
Python example runs against a secured service."""

from __future__ import annotations

import contextlib
import io
import re
import shlex
import tomllib
from collections.abc import Callable
from pathlib import Path

from planner.config import cell_from_dict
from streamer.api import security as sec
from streamer.api.certs import CertSet
from streamer.cli import build_parser
from tests.api.conftest import Served, secure_settings

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "security.md"
TEXT = DOC.read_text(encoding="utf-8")


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", TEXT, flags=re.S)


def test_the_key_table_is_key_access() -> None:
    rows = re.findall(r"^\| `pvt/<cell>/([^`]+)` \| (\w+) \| (\w+) \| (.+?) \|$", TEXT, re.M)
    assert rows == [(r.pattern, r.op.value, r.role, r.what) for r in sec.KEY_ACCESS]


def test_the_message_table_is_the_rule_builders() -> None:
    rows = re.findall(r"^\| (query|put|subscribe|liveliness) \| (.+?) \| (.+?) \|$", TEXT, re.M)
    documented = {op: (re.findall(r"`(\w+)`", i), re.findall(r"`(\w+)`", e)) for op, i, e in rows}
    assert documented == {op.value: (list(i), list(e)) for op, (i, e) in sec.MESSAGES.items()}


def test_the_config_example_loads_and_the_warning_is_quoted() -> None:
    (example,) = _blocks("toml")
    demo = tomllib.loads((ROOT / "configs" / "demo.toml").read_text(encoding="utf-8"))
    extra = tomllib.loads(example)
    cell = cell_from_dict({**demo, "zenoh": {**demo["zenoh"], **extra["zenoh"]}, "security": extra["security"]})
    assert cell.security.enabled and cell.zenoh.listen == ("tls/127.0.0.1:7447",)
    (warning,) = sec.exposure_warnings(["tcp/0.0.0.0:7447"], [], tls=False, access_control=False)
    assert warning[:60] in TEXT


def test_every_pvt_command_in_the_doc_parses() -> None:
    commands = []
    for block in _blocks("sh"):
        for line in block.splitlines():
            line = line.split("#", 1)[0].strip()
            if line.startswith(".venv/bin/pvt "):
                commands.append(shlex.split(line[len(".venv/bin/pvt "):]))
    assert len(commands) == 4
    for argv in commands:
        assert callable(build_parser().parse_args(argv).func)


def test_the_python_example_runs(serve: Callable[..., Served], certs: CertSet) -> None:
    served = serve(security=secure_settings(certs))
    (code,) = _blocks("python")
    code = code.replace("certs/", f"{certs.directory}/").replace("tls/127.0.0.1:7447", served.endpoint)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, str(DOC), "exec"), {"__name__": "security_example"})
    lines = out.getvalue().splitlines()
    assert lines[0] == "JobState.DONE" and lines[-1] == "PERMISSION_DENIED"
    assert served.store.count() == 1
