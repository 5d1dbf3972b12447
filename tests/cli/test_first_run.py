"""A machine's first run (issue 23 item 7): the planner's kernels compile once, with progress shown, and the
demo's child processes (the simulated drives, bus/sim/process.py; the cycle engine, bus/engine.py) never
compile any: they import no numba at all, so they neither compile nor load kernels whatever the cache holds."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[2]


def test_warm_up_reports_each_step_then_done() -> None:
    from planner.plan import _WARM_JOBS, warm_up

    seen: list[tuple[int, int, str]] = []
    warm_up(lambda done, total, what: seen.append((done, total, what)))
    total = len(_WARM_JOBS) + 1
    assert [s[:2] for s in seen] == [(k, total) for k in range(total + 1)]
    assert seen[0][2] == f"{_WARM_JOBS[0]['kind']} job, {len(_WARM_JOBS[0]['axes'])} axes"
    assert seen[-1][2] == "done"


def test_the_demo_says_it_is_planning_before_it_plans(monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """The planning line is printed before demo.prepare runs (where a first run compiles the kernels)."""
    from planner.errors import PlanningError
    from streamer import demo
    from streamer.cli import demo as cli_demo

    printed_before: list[str] = []

    def prepare(*_a: Any, **_k: Any) -> Any:
        printed_before.append(capsys.readouterr().out)
        raise PlanningError("SCHEMA", "stop here", path="job")

    monkeypatch.setattr(demo, "prepare", prepare)
    args = argparse.Namespace(config=None, job=None, axes=None, sync_ms=None, fast=True, out=Path("unused"),
                              bus=None, bitrate=None, external_drives=False, quiet=True)
    assert cli_demo.run(args) == 2
    assert "planning the job" in " ".join(printed_before[0].split())


_CHILD_IMPORTS = """
import importlib, json, pkgutil, sys
import bus
names = [m.name for m in pkgutil.walk_packages(bus.__path__, "bus.")]
for name in names:
    importlib.import_module(name)
print(json.dumps({"modules": names, "numba": sorted(k for k in sys.modules if k.split(".")[0] in ("numba", "llvmlite")),
                  "kernels": sorted(k for k in sys.modules if k in ("planner.jit", "planner.plan"))}))
"""


def test_the_demos_child_processes_import_no_kernel() -> None:
    """Every module of bus/ (which holds both children's entry points, `python -m bus.sim.process` and
    `python -m bus.engine`) imports without numba or planner.jit: a child process compiles nothing."""
    out = subprocess.run([sys.executable, "-c", _CHILD_IMPORTS], cwd=ROOT, capture_output=True, text=True,
                         timeout=300, check=True)
    seen = json.loads(out.stdout.strip().splitlines()[-1])
    assert {"bus.sim.process", "bus.engine"} <= set(seen["modules"])
    assert seen["numba"] == []
    assert seen["kernels"] == []


_COMPILE = """
import json
from planner.jit import compiling, kernel

def twice(x):
    return 2.0 * x

k = kernel(twice)
seen = []
with compiling(seen.append):
    k(1.0)
    k(2.0)  # compiled already: no event
    k(3)  # another signature: compiled again
k(4 + 0j)  # outside the block: not reported
print(json.dumps(seen))
"""


def test_compiling_reports_each_kernel_as_it_is_compiled(tmp_path: Path) -> None:
    """The first run's progress (`python -m planner.jit`, `make test`) comes from numba's compile events: one per
    compiled signature of a planner kernel, none for a call that compiles nothing, none outside the block."""
    import os

    script = tmp_path / "first_compile.py"  # numba caches only functions defined in a file
    script.write_text(_COMPILE)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"), "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, str(script)], cwd=ROOT, capture_output=True, text=True, timeout=300,
                         check=True, env=env)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == ["__main__.twice", "__main__.twice"]


@pytest.mark.virtual
def test_a_first_make_demo_plans_with_the_kernels_interpreted(tmp_path: Path) -> None:
    """A machine's first `make demo` runs `pvt demo` with NUMBA_DISABLE_JIT=1 (the Makefile's demo target) so that
    motion shows without waiting a minute for the kernels: the demo's job plans and streams that way, every
    guarantee met, and the demo says it plans interpreted."""
    import os

    make = (ROOT / "Makefile").read_text()
    assert "NUMBA_DISABLE_JIT=1 $(VENV)/bin/pvt demo" in make and "-j3 $(KERNELS) lint chromium" in make
    env = {**os.environ, "NUMBA_DISABLE_JIT": "1"}
    out = subprocess.run([sys.executable, "-m", "streamer.cli", "demo", "--fast", "--quiet", "--out", str(tmp_path)],
                         cwd=ROOT, capture_output=True, text=True, timeout=600, env=env)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "kernels interpreted" in " ".join(out.stdout.split())
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["result"] == "done"
