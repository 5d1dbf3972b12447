"""The README cannot rot: every `pvt` command line in it parses with the real CLI, every file it names
exists, and its Python client snippet runs against a live service (on a free loopback port)."""

from __future__ import annotations

import re
import shlex
from collections.abc import Callable
from pathlib import Path

import pytest

from streamer.cli import build_parser
from tests.api.conftest import Served

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text(encoding="utf-8")


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", README, flags=re.S)


def _pvt_commands() -> list[list[str]]:
    commands = []
    for block in _blocks("sh"):
        for line in block.splitlines():
            line = line.split("#", 1)[0].strip()
            for prefix in (".venv/bin/pvt ", "pvt "):
                if line.startswith(prefix):
                    commands.append(shlex.split(line[len(prefix):]))
    for cell in re.findall(r"\| `pvt ([^`]+)` \|", README):  # the commands table
        commands.append([w for w in shlex.split(cell.replace("[", "").replace("]", "").replace("...", ""))
                         if w != "|"])
    return commands


def test_readme_has_the_two_quick_start_commands() -> None:
    quick = _blocks("sh")[0]
    assert [line.split("#")[0].strip() for line in quick.strip().splitlines()] == ["make demo", "make test"]
    makefile = (ROOT / "Makefile").read_text()
    assert "\ndemo:" in makefile and "\ntest:" in makefile and "pvt demo" in makefile
    assert "make test" in (ROOT / ".ci" / "run").read_text()


@pytest.mark.parametrize("argv", _pvt_commands(), ids=lambda a: " ".join(a)[:60])
def test_every_pvt_command_in_the_readme_parses(argv: list[str]) -> None:
    placeholders = {"JOB": "configs/jobs/demo-path.toml", "CELL": "configs/demo.toml", "IF:CH": "virtual:x",
                    "N": "1", "PORT": "8765"}
    argv = [placeholders.get(a, a) for a in argv]
    args = build_parser().parse_args(argv)  # argparse exits (SystemExit) on an unknown option
    assert callable(args.func)


def test_every_file_the_readme_names_exists() -> None:
    names = set(re.findall(r"(?<![\w/.-])((?:configs|docs|examples|tools|benchmarks)/[\w./-]+\.\w+)", README))
    assert names
    missing = sorted(n for n in names if not (ROOT / n).exists())
    assert not missing, missing


def test_the_readme_client_snippet_runs(serve: Callable[..., Served]) -> None:
    served = serve()
    (snippet,) = _blocks("python")
    code = snippet.replace("tcp/127.0.0.1:7447", served.endpoint)
    exec(compile(code, "README.md", "exec"), {})
