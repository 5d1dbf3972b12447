"""`pvt demo --external-drives`: the master measures the drives on the bus, not a simulation of its own
(issue 23 item 2), with the drives in a process of their own on an ipc bus, as a user runs them with
`pvt sim`; and the cycle engine starts every axis on one SYNC."""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import pytest

from bus.sim.process import drives_process
from planner.config import BusConfig
from planner.readings import SimDriveOptions
from streamer import demo
from streamer.cli import main as pvt
from streamer.cli.demo import guarantees

pytestmark = pytest.mark.realtime


def test_the_demo_plans_for_the_rounding_of_the_drives_on_the_bus(tmp_path: Path) -> None:
    """Drives that truncate their position demand (a reading the manuals permit), run elsewhere: the demo
    plans for how they round, as measured on the bus. Before, it planned for its own in-process simulation
    (rounding to nearest) and missed the tolerance by a count on every axis."""
    channel = f"ext-{os.getpid()}"
    base, _job, traj = demo.prepare(axes=3)
    truncating = dataclasses.replace(base, bus=BusConfig("ipc", channel, base.bus.bitrate), axes=tuple(
        dataclasses.replace(a, sim=SimDriveOptions(rounding="toward_zero")) for a in base.axes))
    with drives_process(truncating):
        status = pvt(["demo", "--external-drives", "--bus", f"ipc:{channel}", "--axes", "3", "--quiet", "--no-plot",
                      "--out", str(tmp_path)])
    report = json.loads((tmp_path / "report.json").read_text())
    assert guarantees(report, traj.tolerance_counts) == [], report["message"]
    assert status == 0
    assert len({a["start_sync"] for a in report["axes"]}) == 1
