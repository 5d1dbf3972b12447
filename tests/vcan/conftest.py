"""Tests on a real SocketCAN interface (vcan0 by default, `PVT_VCAN_CHANNEL` to change it).

Every test in this folder (and every test marked `vcan` elsewhere, once this folder is collected) is
skipped when the machine has no usable vcan0, which is the normal case on the development and CI
kernels. `make vcan-test` runs them where vcan0 exists: on the host when it has one, else inside
tools/vcan-vm. It sets `PVT_REQUIRE_VCAN=1`, which turns "no vcan0" into an error so that a broken VM
cannot pass by skipping everything.

Fixtures: `vcan_channel`, `open_bus` (socketcan bus handles, closed at teardown) and `sync_report`
(period statistics of received SYNC timestamps, printed in pytest's closing summary).
"""

from __future__ import annotations

import os
import socket
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

CHANNEL = os.environ.get("PVT_VCAN_CHANNEL", "vcan0")
REQUIRED = os.environ.get("PVT_REQUIRE_VCAN") == "1"
HERE = Path(__file__).resolve().parent
IFF_UP = 0x1


def vcan_unavailable_reason(channel: str) -> str | None:
    """Why `channel` cannot carry CAN frames here, or None when it can."""
    if not hasattr(socket, "AF_CAN"):
        return "this Python has no AF_CAN sockets"
    sysfs = Path("/sys/class/net") / channel
    if not sysfs.exists():
        return f"no {channel} interface (the kernel has no SocketCAN here; make vcan-test runs these in a VM)"
    if not int((sysfs / "flags").read_text(), 16) & IFF_UP:
        return f"{channel} is down (ip link set up {channel})"
    try:
        with socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW) as probe:
            probe.bind((channel,))
    except OSError as exc:
        return f"cannot bind a CAN_RAW socket to {channel}: {exc}"
    return None


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    reason = vcan_unavailable_reason(CHANNEL)
    ours = [item for item in items if HERE in item.path.parents or item.get_closest_marker("vcan")]
    if reason is None or not ours:
        return
    if REQUIRED:
        raise pytest.UsageError(f"PVT_REQUIRE_VCAN=1 but {reason}")
    for item in ours:
        item.add_marker(pytest.mark.skip(reason=reason))


@pytest.fixture
def vcan_channel() -> str:
    return CHANNEL


@pytest.fixture
def open_bus(vcan_channel: str) -> Iterator[Callable[..., can.BusABC]]:
    """`open_bus(**kwargs)` opens a socketcan bus handle on vcan0; all are shut down at teardown."""
    buses: list[can.BusABC] = []

    def _open(**kwargs: Any) -> can.BusABC:
        bus = can.Bus(interface="socketcan", channel=vcan_channel, **kwargs)
        buses.append(bus)
        return bus

    yield _open
    for bus in buses:
        bus.shutdown()


@dataclass(frozen=True)
class SyncStats:
    """Period statistics of a SYNC stream, from receive timestamps (s)."""

    label: str
    period_s: float
    count: int
    mean_period_s: float
    p99_jitter_s: float  # 99th percentile of |interval - period|
    max_jitter_s: float

    @property
    def mean_error(self) -> float:
        """Relative error of the mean period (0.01 = 1 %)."""
        return abs(self.mean_period_s - self.period_s) / self.period_s

    def describe(self) -> str:
        return (
            f"{self.label}: {self.count} SYNCs, mean period {self.mean_period_s * 1e3:.4f} ms "
            f"(configured {self.period_s * 1e3:g} ms, error {self.mean_error * 100:.3f} %), "
            f"jitter p99 {self.p99_jitter_s * 1e6:.0f} us, max {self.max_jitter_s * 1e6:.0f} us"
        )


def sync_stats(label: str, timestamps_s: list[float], period_s: float) -> SyncStats:
    stamps = np.asarray(timestamps_s, dtype=float)
    if stamps.size < 3:
        raise ValueError(f"{label}: need at least 3 SYNC timestamps, got {stamps.size}")
    intervals = np.diff(stamps)
    jitter = np.abs(intervals - period_s)
    return SyncStats(
        label=label,
        period_s=period_s,
        count=int(stamps.size),
        mean_period_s=float((stamps[-1] - stamps[0]) / (stamps.size - 1)),
        p99_jitter_s=float(np.percentile(jitter, 99)),
        max_jitter_s=float(jitter.max()),
    )


_REPORTS: list[SyncStats] = []


@pytest.fixture
def sync_report() -> Callable[[str, list[float], float], SyncStats]:
    """`sync_report(label, timestamps_s, period_s)`: statistics, also listed in the closing summary."""

    def _report(label: str, timestamps_s: list[float], period_s: float) -> SyncStats:
        stats = sync_stats(label, timestamps_s, period_s)
        _REPORTS.append(stats)
        return stats

    return _report


def pytest_terminal_summary(terminalreporter: Any) -> None:
    if _REPORTS:
        terminalreporter.section("SYNC period on SocketCAN")
        for stats in _REPORTS:
            terminalreporter.write_line(stats.describe())
