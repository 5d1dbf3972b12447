"""Fixtures of the CLI tests: the API tests' services (FakeBackend on a free loopback port) and `pvt` run
as a subprocess at 80 columns, the way a user runs it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from rich.cells import cell_len

from tests.api.conftest import serve  # noqa: F401  (the fixture)

ROOT = Path(__file__).resolve().parents[2]
WIDTH = 80


def cli_env(**extra: str) -> dict[str, str]:
    """The environment of a `pvt` subprocess: 80 columns, the source tree importable (for the fake
    backend), plain output (no colour codes to strip)."""
    env = {**os.environ, "COLUMNS": str(WIDTH), "LINES": "50", "PYTHONPATH": str(ROOT), "NO_COLOR": "1",
           "TERM": "dumb"}
    env.pop("FORCE_COLOR", None)
    env.update(extra)
    return env


def pvt(*args: str, timeout: float = 120.0, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """`pvt ARGS...` as a subprocess at 80 columns; stdout, stderr and the exit status."""
    return subprocess.run([sys.executable, "-m", "streamer.cli", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout, env=env or cli_env())


def start_pvt(*args: str, env: dict[str, str] | None = None) -> subprocess.Popen[str]:
    """`pvt ARGS...` in the background (stop it with `.kill()` / read it with `.communicate()`)."""
    return subprocess.Popen([sys.executable, "-m", "streamer.cli", *args], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env or cli_env())


def assert_fits(text: str, width: int = WIDTH) -> None:
    """Every line within `width` terminal cells, and nothing shortened with an ellipsis."""
    wide = [line for line in text.splitlines() if cell_len(line) > width]
    assert not wide, f"lines over {width} columns: {wide}"
    assert "…" not in text, f"a value was cut:\n{text}"


def words_in(text: str, phrase: str) -> bool:
    """`phrase` is in `text` whole, though a table may have wrapped it over lines (at spaces) or folded a
    long word: compared without whitespace and table borders (the other cells of its rows are one line)."""
    def bare(s: str) -> str:
        return "".join(ch for ch in s if not ch.isspace() and ch not in "│┃┆|")
    return bare(phrase) in bare(text)


def flat(text: str) -> str:
    """`text` with every run of whitespace one space: a message the terminal wrapped reads whole again."""
    return " ".join(text.split())
