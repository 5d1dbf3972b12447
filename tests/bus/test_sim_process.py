"""The simulated drives' process (bus/sim/process.py): what it says when its drives are up."""

from __future__ import annotations

import dataclasses
import os
import pickle
import re
import subprocess
import sys
from pathlib import Path

from bus.sim.process import READY_PREFIX, DrivesRequest
from planner.config import BusConfig, load_cell

ROOT = Path(__file__).resolve().parents[2]


def test_the_drives_keep_what_they_are_made_of_out_of_the_garbage_collector(tmp_path: Path) -> None:
    """A full collection walked the drives' object dictionaries and models at their real-time priority for
    14-25 ms while they streamed, SYNCs they did not answer: the process freezes them once its drives are
    up, and says how many objects that keeps out."""
    base = load_cell(ROOT / "configs" / "xtrapuls.toml").with_axes(1)
    cell = dataclasses.replace(base, bus=BusConfig("ipc", f"gc-{os.getpid()}", base.bus.bitrate))
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path)}  # a private ipc registry
    proc = subprocess.Popen([sys.executable, "-m", "bus.sim.process"], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=ROOT, env=env)
    assert proc.stdin is not None and proc.stdout is not None
    try:
        pickle.dump(DrivesRequest(cell, {}, priority=None), proc.stdin)
        proc.stdin.flush()
        lines = []
        while not lines or (lines[-1] and not lines[-1].startswith(READY_PREFIX)):
            lines.append(proc.stdout.readline().decode(errors="replace"))
    finally:
        proc.stdin.close()  # the child's signal to leave the bus
        proc.wait(timeout=20)
    ready = lines[-1]
    assert ready.startswith(READY_PREFIX), "".join(lines)
    frozen = re.search(r"(\d+) objects kept out of the garbage collector", ready)
    assert frozen is not None, ready
    assert int(frozen.group(1)) > 10_000  # canopen's dictionary and the model, not a handful
