"""Shared fixtures. Hypothesis profiles: `ci` (default: 60 examples per property, derandomized, so a run
fails or passes the same way on every machine and a red CI is reproducible), `explore` (random examples,
500 per property: `HYPOTHESIS_PROFILE=explore .venv/bin/python -m pytest tests/planner`; what it finds
becomes a pinned case in tests/planner/data/hard_cases.toml)."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

from planner.config import CellConfig, load_cell

# The one timing margin of the real-time tests. This shared 2-core VM holds even a SCHED_FIFO 99 task up for
# 5-50 ms at times (benchmarks/bench_realtime.py's platform floor), so the cycle engine's SYNC then goes out
# that late; a drive that follows the manual (a SYNC half a period late is lost: EMCY 0x8780) faults the job
# for the machine's stall, not the master's. The simulated drives of the real-time tests (bus/sim/process.py,
# which every `pvt` the tests start inherits, and DRIVES_SYNC_GAP_FACTOR there, which the tests that simulate
# drives in their own process pass) let SYNCs come up to 6 periods apart. The benchmarks keep the manual's 1.5
# and count what this machine does to it.
# The isolated tests' in-process drives had 3 periods of their own (streamer/demo.py): with a CPU hog beside
# them, test_s09_bus_off failed 1 of 6 runs on EMCY 0x8780, and CI once failed test_s10_malformed's garbage test.
# 4 periods were not always enough: a fresh-clone CI run here failed test_family_demo_real_time[mixed] on an
# XtrapulsPac's EMCY 0x8780 (its SYNC jitter limit, (factor - 1) periods, was 30 ms); 6 lets a SYNC be 50 ms
# late, the worst stall measured here.
# The same stalls hold the simulated drives' process up (measured: answers up to 3 SYNCs late at 10 ms):
# the master's TPDO timeout waits at least REALTIME_HOST_STALL_MS (streamer/runtime/realtime.py).
REALTIME_SYNC_GAP_FACTOR = 6.0
REALTIME_HOST_STALL_MS = 100
os.environ.setdefault("PVT_SIM_SYNC_GAP_FACTOR", str(REALTIME_SYNC_GAP_FACTOR))
os.environ.setdefault("PVT_HOST_STALL_MS", str(REALTIME_HOST_STALL_MS))

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"

settings.register_profile(
    "ci", max_examples=60, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)
settings.register_profile(
    "explore", max_examples=500, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


# the folders whose tests run in virtual time only (no service, no wall-clock waits) unless marked otherwise:
# `make test` runs them on every core at once with the unmarked wall-clock tests (services, clients, CLI with
# generous waits), and the ones marked realtime, wallclock or isolated alone after them
VIRTUAL_TIME_FOLDERS = ("planner", "streamer", "reliability")
WALL_CLOCK_MARKS = ("realtime", "isolated", "wallclock", "vcan")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        rel = Path(str(item.fspath)).resolve().relative_to(ROOT / "tests")
        if rel.parts[0] in VIRTUAL_TIME_FOLDERS and not any(item.get_closest_marker(m) for m in WALL_CLOCK_MARKS):
            item.add_marker(pytest.mark.virtual)


@pytest.fixture(scope="session")
def demo_cell() -> CellConfig:
    return load_cell(CONFIGS / "demo.toml")


@pytest.fixture(autouse=True, scope="session")
def _private_state_dir(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Journals and recordings default to the user's state directory ($XDG_STATE_HOME/pvt): the tests (and
    every `pvt` they start as a subprocess, which inherits the environment) use a private one."""
    import os

    os.environ["XDG_STATE_HOME"] = str(tmp_path_factory.mktemp("xdg-state"))


# threads of a running bus: a master's SYNC producer and monitor, a python-can notifier, a simulated cell's
# timers. One a test leaves running keeps its SYNC, drives and CPU load alive through every later test of the
# process (a leaked real-time backend once made later in-process drives fall silent: TPDO_TIMEOUT)
_BUS_THREAD_PREFIXES = ("Cyclic send task", "Notifier for bus", "pvt-master", "sim-cell")
_LEAK_GRACE_S = 2.0


# processes of a real-time run: the cycle engine (bus/engine.py) and simulated drives (bus/sim/process.py)
_BUS_PROCESS_MODULES = ("bus.engine", "bus.sim.process")


def _bus_threads() -> set[threading.Thread]:
    return {t for t in threading.enumerate() if t.is_alive() and t.name.startswith(_BUS_THREAD_PREFIXES)}


def _bus_processes() -> set[int]:
    """This process' children that are a cycle engine or simulated drives, still running."""
    out: set[int] = set()
    for task in Path(f"/proc/{os.getpid()}/task").glob("*/children"):
        for pid in task.read_text().split():
            try:
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
                state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
            except OSError:
                continue
            if state != "Z" and any(m.encode() in cmd for m in _BUS_PROCESS_MODULES):
                out.add(int(pid))
    return out


@pytest.fixture(autouse=True)
def _no_leaked_bus_threads() -> Iterator[None]:
    """Every test stops the buses, masters, cycle engines and simulated drives it started (checked after its
    teardown)."""
    before, before_procs = _bus_threads(), _bus_processes()
    yield
    deadline = time.monotonic() + _LEAK_GRACE_S
    while ((left := _bus_threads() - before) or _bus_processes() - before_procs) and time.monotonic() < deadline:
        time.sleep(0.05)
    if left:
        names = sorted(t.name for t in left)
        pytest.fail(f"the test left bus threads running: {names}", pytrace=False)
    if procs := _bus_processes() - before_procs:
        pytest.fail(f"the test left cycle engines or drive processes running: pids {sorted(procs)}", pytrace=False)
