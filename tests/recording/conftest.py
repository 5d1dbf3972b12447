"""Fixtures of the recording tests: the demo's outputs, made once per session."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from streamer import demo


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Any, Any, dict[str, Any]]:
    """`pvt demo --fast` on 3 axes, once per session: (out dir, cell, trajectory, report)."""
    out = tmp_path_factory.mktemp("demo")
    cell, _job, traj = demo.prepare(axes=3)
    report, _trace = demo.run_fast(cell, traj, out, plot=False)
    return out, cell, traj, report
