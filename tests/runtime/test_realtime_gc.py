"""The real-time runtime keeps the garbage collector off what the process held before a job while it streams
(streamer/runtime/realtime.py, `quiet_gc`): a full collection of a service's heap stops every thread for
40-80 ms, several SYNC periods (it made in-process drives miss SYNCs and TPDOs in the API tests)."""

from __future__ import annotations

import dataclasses
import gc
import uuid
from pathlib import Path

import pytest

from planner.config import load_cell
from planner.job import job_from_dict
from planner.plan import plan_job
from streamer.demo import run_realtime
from streamer.runtime.realtime import quiet_gc
from tests.conftest import CONFIGS


def test_quiet_gc_freezes_the_heap_and_the_last_of_overlapping_holders_thaws_it() -> None:
    """The frozen count is judged by bounds, not equality: another test's thread still running in this pytest
    worker may free frozen objects meanwhile (seen in CI: 328237 against 328239)."""
    assert gc.get_freeze_count() == 0
    kept = [[i] for i in range(1000)]  # tracked objects that exist before the hold
    outer = quiet_gc()
    outer.__enter__()
    frozen = gc.get_freeze_count()
    assert frozen >= len(kept)
    later = [[i] for i in range(1000)]  # made after the freeze: a second freeze would take them too
    with quiet_gc():  # a second job in the same process: neither frozen again nor thawed
        assert len(kept) <= gc.get_freeze_count() <= frozen
    assert len(kept) <= gc.get_freeze_count() <= frozen  # the first one still streams
    outer.__exit__(None, None, None)
    assert gc.get_freeze_count() == 0
    assert len(later) == len(kept)


@pytest.mark.isolated  # real time with the drives in this process
def test_the_heap_is_frozen_on_the_streaming_thread_while_a_job_runs_and_thawed_after(tmp_path: Path) -> None:
    cell = load_cell(CONFIGS / "demo.toml").with_axes(1)
    cell = dataclasses.replace(cell, bus=dataclasses.replace(cell.bus, channel=f"gc-{uuid.uuid4().hex[:12]}"))
    traj = plan_job(job_from_dict({"kind": "move", "axes": ["j1"], "target": [0.05]}, cell), cell)
    frozen: list[int] = []

    def look(core: object) -> None:  # once: the count walks the frozen heap (ms in a big test process)
        if not frozen:
            frozen.append(gc.get_freeze_count())

    report, _trace = run_realtime(cell, traj, tmp_path, on_change=look, plot=False)
    assert report["result"] == "done", report
    assert frozen and frozen[0] > 0
    assert gc.get_freeze_count() == 0
