"""PVT_HOST_STALL_MS (streamer/runtime/realtime.py): a machine that may hold the master and the drives' process
up that long gets a TPDO timeout and, in cells with drives fed one set point per SYNC, a lead of the core that
cover it; without it the cell's own figures hold."""

from __future__ import annotations

import pytest

from planner.config import load_cell
from streamer.core.settings import StreamerSettings
from streamer.runtime import realtime
from tests.conftest import CONFIGS


def test_the_tpdo_timeout_covers_the_stated_stall() -> None:
    base = StreamerSettings(counts_per_rev={1: 4096}, sync_period_ms=10, tpdo_timeout_syncs=3)
    assert realtime.with_host_stall(base, 0).tpdo_timeout_syncs == 3
    assert realtime.with_host_stall(base, 100).tpdo_timeout_syncs == 10
    assert realtime.with_host_stall(base, 15).tpdo_timeout_syncs == 3  # never shorter than the cell's
    assert realtime.with_host_stall(base, 5000).tpdo_timeout_syncs == 100
    assert realtime.with_host_stall(base, 0).repair_syncs == base.repair_syncs
    assert realtime.with_host_stall(base, 100).repair_syncs == 10  # the FIFOs topped up through it


def test_the_cyclic_lead_covers_the_stated_stall(monkeypatch: pytest.MonkeyPatch) -> None:
    cyclic, fifo = load_cell(CONFIGS / "xtrapuls.toml"), load_cell(CONFIGS / "demo.toml")
    monkeypatch.setattr(realtime, "HOST_STALL_MS", 0.0)
    assert realtime.default_ahead_ms(cyclic) == realtime.CYCLIC_AHEAD_MS
    assert realtime.default_ahead_ms(fifo) == realtime.FIFO_AHEAD_MS
    monkeypatch.setattr(realtime, "HOST_STALL_MS", 120.0)
    assert realtime.default_ahead_ms(cyclic) == 120.0
    assert realtime.default_ahead_ms(fifo) == realtime.FIFO_AHEAD_MS  # a FIFO rides out a late record
