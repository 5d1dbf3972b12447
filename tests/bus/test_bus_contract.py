"""The python-can bus contract the project relies on (tests/vcan/test_socketcan_bus_contract.py, where it runs on
SocketCAN's vcan0) over the buses the project runs on without SocketCAN: python-can's `virtual` (one process, the
tests and `--fast`), our `ipc` (processes on one machine, bus/ipc.py) and the fault-injecting bus with no rule
(bus/faults.py `FaultyBus`, wrapping `virtual` as the reliability tests do). The same test functions, another
`open_bus`. Not here: the SYNC period from `send_periodic`, which on SocketCAN is the kernel's broadcast manager
(tests/bus/test_engine.py times the cycle engine's SYNC on the ipc bus)."""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from typing import Any

import can
import pytest

import bus.ipc  # noqa: F401  (registers the "ipc" interface)
from bus.faults import FaultModel, FaultyBus
from tests.vcan.test_socketcan_bus_contract import (  # noqa: F401  (collected here too)
    test_burst_arrives_complete_and_in_order,
    test_filters_can_be_replaced_on_an_open_handle,
    test_filters_pass_exactly_what_they_name,
    test_frame_kinds_survive_the_bus,
    test_frame_sent_on_one_handle_reaches_the_other_unchanged,
    test_full_fifo_fill_reaches_a_handle_that_reads_in_a_thread,
    test_handle_does_not_receive_its_own_frames_unless_asked,
    test_recv_honours_its_timeout_on_a_quiet_bus,
)

BUSES = ("virtual", "ipc", "faulty")
_channels = itertools.count()


@pytest.fixture(params=BUSES)
def bus_kind(request: pytest.FixtureRequest) -> str:
    return str(request.param)


@pytest.fixture
def vcan_channel(bus_kind: str, worker_id: str) -> str:
    """A channel of its own per test (and per xdist worker): no frame of another test reaches it."""
    return f"contract-{worker_id}-{next(_channels)}"


@pytest.fixture
def open_bus(bus_kind: str, vcan_channel: str) -> Iterator[Callable[..., can.BusABC]]:
    """`open_bus(**kwargs)` opens a handle of the bus under test on the test's channel; all are shut down at
    teardown."""
    buses: list[can.BusABC] = []

    def _open(**kwargs: Any) -> can.BusABC:
        if bus_kind == "faulty":
            filters = kwargs.pop("can_filters", None)
            bus: can.BusABC = FaultyBus(can.Bus(interface="virtual", channel=vcan_channel, **kwargs), FaultModel(),
                                        can_filters=filters)
        else:
            bus = can.Bus(interface=bus_kind, channel=vcan_channel, **kwargs)
        buses.append(bus)
        return bus

    yield _open
    for b in buses:
        b.shutdown()
