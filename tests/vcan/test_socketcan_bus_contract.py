"""The python-can bus contract the project relies on, checked on a real SocketCAN interface (vcan0).

What the streamer and the simulated drives assume of any bus (the virtual bus gives the same in one
process): a frame sent on one handle reaches every other handle on the channel, unchanged and in order;
a handle does not see its own frames unless asked; acceptance filters pass exactly what they name
(11-bit and 29-bit apart); `recv` honours its timeout; and `send_periodic` keeps the SYNC period. On
socketcan, `send_periodic` is the kernel's broadcast manager (BCM), so the SYNC period is measured
from the kernel's receive timestamps: its mean must be within 1 % of the period, and the p99 jitter is
reported in pytest's closing summary.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import can
import pytest
from can.interfaces.socketcan import CyclicSendTask

from bus.cob import SYNC_COB_ID, rpdo2_id, tpdo1_id, tpdo2_id

pytestmark = pytest.mark.vcan

OpenBus = Callable[..., can.BusABC]
RECV_TIMEOUT_S = 2.0  # generous: TCG guests are slow, and a missing frame still fails fast enough


def recv_all(bus: can.BusABC, count: int, timeout_s: float = RECV_TIMEOUT_S) -> list[can.Message]:
    frames: list[can.Message] = []
    while len(frames) < count:
        msg = bus.recv(timeout=timeout_s)
        if msg is None:
            break
        frames.append(msg)
    return frames


def drain(bus: can.BusABC, quiet_s: float = 0.1) -> list[can.Message]:
    """Everything still arriving until the bus has been quiet for `quiet_s`."""
    frames: list[can.Message] = []
    while (msg := bus.recv(timeout=quiet_s)) is not None:
        frames.append(msg)
    return frames


def test_frame_sent_on_one_handle_reaches_the_other_unchanged(open_bus: OpenBus, vcan_channel: str) -> None:
    master, drive = open_bus(), open_bus()
    sent = can.Message(arbitration_id=0x201, data=bytes(range(8)), is_extended_id=False)
    before = time.time()
    master.send(sent)

    got = drive.recv(timeout=RECV_TIMEOUT_S)

    assert got is not None
    assert got.arbitration_id == 0x201
    assert not got.is_extended_id
    assert not got.is_remote_frame
    assert got.dlc == 8
    assert bytes(got.data) == bytes(range(8))
    assert got.channel == vcan_channel
    assert before - 1.0 < got.timestamp < time.time() + 1.0  # kernel wall-clock receive timestamp


@pytest.mark.parametrize(
    "sent",
    [
        can.Message(arbitration_id=SYNC_COB_ID, data=b"", is_extended_id=False),  # SYNC without counter
        can.Message(arbitration_id=0x7FF, data=b"\x05", is_extended_id=False),
        can.Message(arbitration_id=0x1ABCDEF, data=b"\x01\x02\x03", is_extended_id=True),
        can.Message(arbitration_id=0x701, is_remote_frame=True, dlc=1, is_extended_id=False),
    ],
    ids=["empty", "max-11-bit", "29-bit", "remote"],
)
def test_frame_kinds_survive_the_bus(open_bus: OpenBus, sent: can.Message) -> None:
    master, drive = open_bus(), open_bus()
    master.send(sent)

    got = drive.recv(timeout=RECV_TIMEOUT_S)

    assert got is not None
    assert got.equals(sent, timestamp_delta=None, check_channel=False, check_direction=False)


def send_records(bus: can.BusABC, count: int) -> list[int]:
    """`count` 8-byte RPDO2 frames for nodes 1..6 in turn, numbered in their data; returns their ids."""
    ids = [rpdo2_id(1 + i % 6) for i in range(count)]
    for i, cob_id in enumerate(ids):
        bus.send(can.Message(arbitration_id=cob_id, data=i.to_bytes(8, "little"), is_extended_id=False))
    return ids


def test_burst_arrives_complete_and_in_order(open_bus: OpenBus) -> None:
    # Nobody reads while the burst is sent, so it must fit the receiving socket's buffer: with the
    # default net.core.rmem_default (212992) a socket keeps 278 such frames, and drops the rest
    # silently. 200 is more than one SYNC period of the demo cell's traffic.
    master, drive = open_bus(), open_bus()
    ids = send_records(master, 200)

    frames = recv_all(drive, len(ids))

    assert [int.from_bytes(f.data, "little") for f in frames] == list(range(len(ids)))
    assert [f.arbitration_id for f in frames] == ids


def test_full_fifo_fill_reaches_a_handle_that_reads_in_a_thread(open_bus: OpenBus) -> None:
    # The streamer's worst burst: 64 records for each of 6 axes, back to back, more than a socket
    # keeps unread. A reader thread (python-can's Notifier, as canopen's Network uses) keeps up.
    master, drive = open_bus(), open_bus()
    reader = can.BufferedReader()
    notifier = can.Notifier(drive, [reader], timeout=0.05)
    try:
        ids = send_records(master, 6 * 64)
        frames: list[can.Message] = []
        while len(frames) < len(ids) and (msg := reader.get_message(timeout=RECV_TIMEOUT_S)) is not None:
            frames.append(msg)
    finally:
        notifier.stop()

    assert [int.from_bytes(f.data, "little") for f in frames] == list(range(len(ids)))
    assert [f.arbitration_id for f in frames] == ids


def test_handle_does_not_receive_its_own_frames_unless_asked(open_bus: OpenBus) -> None:
    plain, own, other = open_bus(), open_bus(receive_own_messages=True), open_bus()
    plain.send(can.Message(arbitration_id=tpdo1_id(1), data=b"\x01", is_extended_id=False))
    own.send(can.Message(arbitration_id=tpdo1_id(2), data=b"\x02", is_extended_id=False))

    assert [m.arbitration_id for m in drain(plain)] == [tpdo1_id(2)]
    assert [m.arbitration_id for m in drain(own)] == [tpdo1_id(1), tpdo1_id(2)]
    assert [m.arbitration_id for m in drain(other)] == [tpdo1_id(1), tpdo1_id(2)]


def test_filters_pass_exactly_what_they_name(open_bus: OpenBus) -> None:
    sender = open_bus()
    sync_only = open_bus(can_filters=[{"can_id": SYNC_COB_ID, "can_mask": 0x7FF, "extended": False}])
    tpdo1_any_node = open_bus(can_filters=[{"can_id": 0x180, "can_mask": 0x780, "extended": False}])
    frames = [
        can.Message(arbitration_id=SYNC_COB_ID, data=b"", is_extended_id=False),
        can.Message(arbitration_id=SYNC_COB_ID, data=b"", is_extended_id=True),  # same number, 29-bit
        can.Message(arbitration_id=tpdo1_id(1), data=b"\x01", is_extended_id=False),
        can.Message(arbitration_id=tpdo1_id(6), data=b"\x06", is_extended_id=False),
        can.Message(arbitration_id=tpdo2_id(1), data=b"\x07", is_extended_id=False),
    ]
    for frame in frames:
        sender.send(frame)

    assert [(m.arbitration_id, m.is_extended_id) for m in drain(sync_only)] == [(SYNC_COB_ID, False)]
    assert [m.arbitration_id for m in drain(tpdo1_any_node)] == [tpdo1_id(1), tpdo1_id(6)]


def test_filters_can_be_replaced_on_an_open_handle(open_bus: OpenBus) -> None:
    sender, receiver = open_bus(), open_bus(can_filters=[{"can_id": tpdo1_id(1), "can_mask": 0x7FF}])
    sender.send(can.Message(arbitration_id=tpdo1_id(2), data=b"", is_extended_id=False))
    assert drain(receiver) == []

    receiver.set_filters([{"can_id": tpdo1_id(2), "can_mask": 0x7FF}])
    sender.send(can.Message(arbitration_id=tpdo1_id(1), data=b"", is_extended_id=False))
    sender.send(can.Message(arbitration_id=tpdo1_id(2), data=b"", is_extended_id=False))
    assert [m.arbitration_id for m in drain(receiver)] == [tpdo1_id(2)]

    receiver.set_filters(None)  # back to everything
    sender.send(can.Message(arbitration_id=tpdo1_id(1), data=b"", is_extended_id=False))
    assert [m.arbitration_id for m in drain(receiver)] == [tpdo1_id(1)]


def test_recv_honours_its_timeout_on_a_quiet_bus(open_bus: OpenBus) -> None:
    quiet = open_bus()
    start = time.monotonic()
    assert quiet.recv(timeout=0.05) is None
    assert 0.04 < time.monotonic() - start < 1.0


@pytest.mark.parametrize("period_ms", [10])
def test_sync_from_send_periodic_keeps_its_period(
    open_bus: OpenBus, sync_report: Callable[[str, list[float], float], Any], period_ms: int
) -> None:
    period_s = period_ms / 1000
    producer = open_bus()
    consumer = open_bus(can_filters=[{"can_id": SYNC_COB_ID, "can_mask": 0x7FF, "extended": False}])
    sync = can.Message(arbitration_id=SYNC_COB_ID, data=b"", is_extended_id=False)
    task = producer.send_periodic(sync, period_s)
    assert isinstance(task, CyclicSendTask), "on socketcan the SYNC must come from the kernel's BCM"

    wanted = 301  # 3 s of SYNC: 300 intervals
    stamps = [m.timestamp for m in recv_all(consumer, wanted)]
    task.stop()
    drain(consumer, quiet_s=3 * period_s)  # whatever was in flight when we stopped
    after_stop = drain(consumer, quiet_s=5 * period_s)

    assert len(stamps) == wanted, f"only {len(stamps)} of {wanted} SYNCs arrived"
    stats = sync_report(f"BCM send_periodic {period_ms} ms on {producer.channel_info}", stamps, period_s)
    assert stats.mean_error < 0.01, stats.describe()
    assert after_stop == [], "SYNC kept coming after the task was stopped"
