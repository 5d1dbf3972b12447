"""python-can's virtual bus as the product opens it: every receiver gets the frames in one order (bus/virtual_can.py).

The failure this guards against: the master's SYNC task and its record sender sent at once, the simulated
drive got the record before the SYNC and the master the SYNC before the record; the master then found a
record too many in the drive's FIFO (CI, tests/reliability/test_s09_bus_off.py, PROTOCOL "arrived twice").
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Iterator

import can
import pytest
from bus_testkit import unique_channel

import bus.network  # noqa: F401  (registers the ordered virtual interface)
from bus.virtual_can import OrderedVirtualBus

FRAMES_PER_SENDER = 3000


@pytest.fixture
def fast_thread_switches() -> Iterator[None]:
    """Switch threads every microsecond, so that concurrent sends interleave as they do under load."""
    before = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        yield
    finally:
        sys.setswitchinterval(before)


def test_the_virtual_interface_name_builds_the_ordered_bus() -> None:
    bus = can.Bus(interface="virtual", channel=unique_channel("ordered-name"))
    try:
        assert isinstance(bus, OrderedVirtualBus)
    finally:
        bus.shutdown()


def test_every_receiver_sees_concurrent_senders_in_one_order(fast_thread_switches: None) -> None:
    channel = unique_channel("ordered")
    senders = [can.Bus(interface="virtual", channel=channel) for _ in range(2)]
    receivers = [can.Bus(interface="virtual", channel=channel) for _ in range(3)]

    def send_all(sender_index: int) -> None:
        bus = senders[sender_index]
        for i in range(FRAMES_PER_SENDER):
            bus.send(can.Message(arbitration_id=0x100 + sender_index, data=i.to_bytes(2, "little"),
                                 is_extended_id=False))

    try:
        threads = [threading.Thread(target=send_all, args=(k,)) for k in range(len(senders))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        seen = []
        for bus in receivers:
            frames = []
            while (m := bus.recv(0)) is not None:
                frames.append((m.arbitration_id, bytes(m.data)))
            seen.append(frames)
        assert len(seen[0]) == len(senders) * FRAMES_PER_SENDER
        for k, frames in enumerate(seen[1:], start=1):
            first_difference = next((i for i, (a, b) in enumerate(zip(seen[0], frames, strict=False)) if a != b), None)
            assert frames == seen[0], f"receiver {k} differs from receiver 0 at frame {first_difference}"
    finally:
        for bus in senders + receivers:
            bus.shutdown()
