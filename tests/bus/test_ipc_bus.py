"""The `ipc` python-can interface (bus/ipc.py): buses of any process of this user on one channel are one
CAN bus, over UDP on 127.0.0.1.

Each test gets a private registry (XDG_RUNTIME_DIR in tmp_path, inherited by the subprocesses it starts)
and a fresh channel name; every bus it opens is shut down at teardown.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import select
import signal
import subprocess
import sys
import textwrap
import threading
import time
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import can
import canopen
import pytest
from canopen.objectdictionary import ODVariable
from canopen.objectdictionary.datatypes import UNSIGNED32, VISIBLE_STRING

import bus.ipc
from bus.errors import CONFIG
from bus.events import BufferStatus, Event
from bus.ipc import IpcBus, IpcChannelError
from planner.config import BusConfig, CellConfig

ROOT = Path(__file__).resolve().parents[2]
RECV_TIMEOUT_S = 2.0
OpenBus = Callable[..., IpcBus]


@pytest.fixture
def registry(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    runtime = tmp_path / "run"
    runtime.mkdir(mode=0o700)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(runtime))
    return runtime / "pvt-ipc"


@pytest.fixture
def channel(registry: Path, request: pytest.FixtureRequest) -> str:
    return f"t-{os.getpid()}-{abs(hash(request.node.nodeid)) % 10**8}"


@pytest.fixture
def open_bus(channel: str) -> Iterator[OpenBus]:
    opened: list[can.BusABC] = []

    def _open(**kwargs: Any) -> IpcBus:
        b = can.Bus(interface="ipc", channel=kwargs.pop("channel", channel), **kwargs)
        opened.append(b)
        assert isinstance(b, IpcBus)
        return b

    yield _open
    for b in opened:
        b.shutdown()


def entries(directory: Path) -> set[str]:
    return {p.name for p in directory.iterdir()}


def run_python(code: str, **kwargs: Any) -> subprocess.Popen[str]:
    """`python -c code` from the worktree root (its packages first), with this test's environment."""
    return subprocess.Popen([sys.executable, "-c", textwrap.dedent(code)], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, **kwargs)


def msg(arbitration_id: int, data: bytes = b"", **kw: Any) -> can.Message:
    kw.setdefault("is_extended_id", False)
    return can.Message(arbitration_id=arbitration_id, data=data, **kw)


# --- frames between buses ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "sent",
    [
        msg(0x201, bytes(range(8))),
        msg(0x080),  # SYNC without counter: no data
        msg(0x7FF, b"\x05"),
        msg(0x1ABCDEF, b"\x01\x02\x03", is_extended_id=True),
        msg(0x701, is_remote_frame=True, dlc=1),
        msg(0x1FFFFFFF, is_remote_frame=True, dlc=8, is_extended_id=True),
        msg(0x123, bytes(range(64)), is_fd=True, bitrate_switch=True),
    ],
    ids=["8-bytes", "empty", "max-11-bit", "29-bit", "remote", "remote-29-bit", "fd"],
)
def test_a_frame_sent_on_one_bus_reaches_the_other_intact(open_bus: OpenBus, channel: str,
                                                          sent: can.Message) -> None:
    master, drive = open_bus(), open_bus()
    master.send(sent)

    got = drive.recv(timeout=RECV_TIMEOUT_S)

    assert got is not None
    assert (got.arbitration_id, got.is_extended_id, got.is_remote_frame, got.dlc, bytes(got.data)) == (
        sent.arbitration_id, sent.is_extended_id, sent.is_remote_frame, sent.dlc, bytes(sent.data))
    assert (got.is_fd, got.bitrate_switch, got.is_error_frame) == (sent.is_fd, sent.bitrate_switch, False)
    assert got.channel == channel
    assert got.is_rx
    assert drive.recv(timeout=0.05) is None  # exactly one copy


def test_a_frame_fans_out_to_every_other_bus_on_the_channel(open_bus: OpenBus) -> None:
    sender, *receivers = open_bus(), open_bus(), open_bus(), open_bus()
    elsewhere = open_bus(channel="another-channel")
    sender.send(msg(0x181, b"\x11\x22"))

    for r in receivers:
        got = r.recv(timeout=RECV_TIMEOUT_S)
        assert got is not None and got.arbitration_id == 0x181 and bytes(got.data) == b"\x11\x22"
    assert elsewhere.recv(timeout=0.05) is None
    assert sender.recv(timeout=0.05) is None  # not its own frame: receive_own_messages is off
    assert sorted(sender.peers) == sorted(r.port for r in receivers)


def test_a_frame_from_another_process_arrives_and_the_reply_goes_back(open_bus: OpenBus, channel: str) -> None:
    here = open_bus()
    proc = run_python(f"""
        import can, bus.ipc
        with can.Bus(interface="ipc", channel={channel!r}) as b:
            b.send(can.Message(arbitration_id=0x581, data=b"ping", is_extended_id=False))
            reply = b.recv(timeout=10)
            print(reply.arbitration_id, bytes(reply.data).decode(), reply.is_rx, reply.channel)
    """)
    try:
        got = here.recv(timeout=15)  # the child's python start-up included
        assert got is not None and got.arbitration_id == 0x581 and bytes(got.data) == b"ping"
        here.send(msg(0x601, b"pong"))
        out, err = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert out.split() == [str(0x601), "pong", "True", channel]


def test_the_receive_stamp_is_the_senders_not_the_readers(open_bus: OpenBus) -> None:
    sender, receiver = open_bus(), open_bus()
    before = time.time()
    sender.send(msg(0x080))
    after = time.time()
    time.sleep(0.05)  # a receiving thread that did not get to run for 50 ms

    got = receiver.recv(timeout=RECV_TIMEOUT_S)
    read_at = time.time()

    assert got is not None
    assert before <= got.timestamp <= after  # the send time (within the time send took, microseconds)
    assert read_at - got.timestamp >= 0.049


def test_the_sent_message_carries_the_stamp_every_receiver_sees(open_bus: OpenBus) -> None:
    """The cycle engine notes its SYNC's time on the wire from `msg.timestamp` after `send`: a time taken when
    `send` returned can be later than the stamp the drives saw, when the sender was preempted in its
    datagrams to the peers (bus/engine.py `_send`)."""
    sender, receiver = open_bus(), open_bus()
    m = msg(0x080)
    sender.send(m)
    got = receiver.recv(timeout=RECV_TIMEOUT_S)
    assert got is not None and m.timestamp == got.timestamp


def test_receive_own_messages_delivers_own_frames_in_send_order_with_the_wire_stamp(open_bus: OpenBus) -> None:
    echoing, peer = open_bus(receive_own_messages=True), open_bus()
    for i in range(5):
        echoing.send(msg(0x200 + i, bytes([i])))

    own = [echoing.recv(timeout=RECV_TIMEOUT_S) for _ in range(5)]
    seen = [peer.recv(timeout=RECV_TIMEOUT_S) for _ in range(5)]

    assert all(m is not None for m in own + seen)
    assert [m.arbitration_id for m in own if m] == [0x200 + i for i in range(5)]
    assert all(not m.is_rx for m in own if m)
    assert [m.timestamp for m in own if m] == [m.timestamp for m in seen if m]  # the same stamp
    assert echoing.recv(timeout=0.05) is None


class _InstantReplySocket:
    """The socket of a bus whose peer answers a frame the moment it is sent to it (before the sender's
    thread runs on: a preempted sender)."""

    def __init__(self, real: Any, peer: IpcBus):
        self._real, self._peer = real, peer

    def sendto(self, data: bytes, address: Any) -> int:
        sent: int = self._real.sendto(data, address)
        if address[1] == self._peer.port:
            question = self._peer.recv(timeout=RECV_TIMEOUT_S)
            assert question is not None
            self._peer.send(msg(question.arbitration_id + 0x100, b"answer"))
        return sent

    def __getattr__(self, name: str) -> Any:
        return getattr(self._real, name)


def test_an_answer_never_arrives_before_the_echo_of_the_frame_it_answers(open_bus: OpenBus,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    master, drive = open_bus(receive_own_messages=True), open_bus()
    master.send(msg(0x700))  # learns its peer
    assert master.recv(timeout=RECV_TIMEOUT_S) is not None and drive.recv(timeout=RECV_TIMEOUT_S) is not None
    monkeypatch.setattr(master, "_sock", _InstantReplySocket(master._sock, drive))

    master.send(msg(0x080))  # SYNC; the drive answers at once

    got = [master.recv(timeout=RECV_TIMEOUT_S), master.recv(timeout=RECV_TIMEOUT_S)]
    assert [(m.arbitration_id, m.is_rx) for m in got if m] == [(0x080, False), (0x180, True)]


def test_without_receive_own_messages_own_frames_do_not_come_back(open_bus: OpenBus) -> None:
    quiet, peer = open_bus(receive_own_messages=False), open_bus()
    quiet.send(msg(0x123, b"x"))

    assert peer.recv(timeout=RECV_TIMEOUT_S) is not None
    assert quiet.recv(timeout=0.1) is None


def test_select_on_fileno_wakes_when_a_frame_arrives(open_bus: OpenBus) -> None:
    sender, receiver = open_bus(), open_bus()
    assert select.select([receiver.fileno()], [], [], 0)[0] == []

    threading.Timer(0.05, sender.send, args=(msg(0x181, b"\x01"),)).start()
    started = time.monotonic()
    readable = select.select([receiver.fileno()], [], [], RECV_TIMEOUT_S)[0]

    assert readable == [receiver.fileno()]
    assert time.monotonic() - started < RECV_TIMEOUT_S
    got = receiver.recv(timeout=0)
    assert got is not None and got.arbitration_id == 0x181


def test_recv_honours_its_timeout(open_bus: OpenBus) -> None:
    receiver = open_bus()
    started = time.monotonic()
    assert receiver.recv(timeout=0.1) is None
    assert 0.09 <= time.monotonic() - started < 1.0


def test_a_notifier_hands_frames_to_its_listeners(open_bus: OpenBus) -> None:
    sender, receiver = open_bus(), open_bus()
    reader = can.BufferedReader()
    notifier = can.Notifier(receiver, [reader], timeout=0.05)
    try:
        for i in range(3):
            sender.send(msg(0x300 + i, bytes([i])))
        got = [reader.get_message(RECV_TIMEOUT_S) for _ in range(3)]
    finally:
        notifier.stop()
    assert [m.arbitration_id if m else None for m in got] == [0x300, 0x301, 0x302]


def test_acceptance_filters_pass_what_they_name(open_bus: OpenBus) -> None:
    sender = open_bus()
    receiver = open_bus(can_filters=[{"can_id": 0x180, "can_mask": 0x780, "extended": False}])
    for cob_id in (0x181, 0x281, 0x182):
        sender.send(msg(cob_id))

    got = [receiver.recv(timeout=0.2) for _ in range(3)]

    assert [m.arbitration_id if m else None for m in got] == [0x181, 0x182, None]


# --- peers that leave ---------------------------------------------------------------------------------


def test_shutdown_removes_the_registry_entry_and_senders_stop_sending_there(open_bus: OpenBus,
                                                                             channel: str) -> None:
    sender, leaving, staying = open_bus(), open_bus(), open_bus()
    directory = bus.ipc.channel_directory(channel)
    assert entries(directory) == {f"{os.getpid()}-{b.port}" for b in (sender, leaving, staying)}
    sender.send(msg(0x100))
    assert leaving.port in sender.peers

    leaving.shutdown()
    assert f"{os.getpid()}-{leaving.port}" not in entries(directory)
    time.sleep(2 * bus.ipc.RESCAN_CHECK_S)
    sender.send(msg(0x101))

    assert leaving.port not in sender.peers
    assert sender.stats.peers_dropped == 0  # it left properly: nothing stale to clean up
    assert [m.arbitration_id for m in (staying.recv(RECV_TIMEOUT_S), staying.recv(RECV_TIMEOUT_S)) if m] == [
        0x100, 0x101]


def test_the_last_bus_to_leave_removes_the_channel_directory(open_bus: OpenBus, channel: str) -> None:
    first, second = open_bus(), open_bus()
    directory = bus.ipc.channel_directory(channel)
    first.shutdown()
    assert directory.is_dir()  # the second one is still there

    second.shutdown()

    assert not directory.exists()
    again, peer = open_bus(), open_bus()  # the channel comes back with its next bus
    again.send(msg(0x100))
    got = peer.recv(timeout=RECV_TIMEOUT_S)
    assert got is not None and got.arbitration_id == 0x100


def test_a_bus_opening_while_the_last_one_removes_the_directory_registers_all_the_same(
        open_bus: OpenBus, channel: str, monkeypatch: pytest.MonkeyPatch) -> None:
    make_dir = bus.ipc._make_private_dir
    calls: list[Path] = []

    def make_then_lose_it_once(path: Path) -> None:
        make_dir(path)
        calls.append(path)
        if len(calls) == 1:
            path.rmdir()  # the channel's last bus left between our mkdir and our entry

    with monkeypatch.context() as patched:
        patched.setattr(bus.ipc, "_make_private_dir", make_then_lose_it_once)
        joining = open_bus()

    assert len(calls) == 2
    assert f"{os.getpid()}-{joining.port}" in entries(bus.ipc.channel_directory(channel))
    open_bus().send(msg(0x100))
    got = joining.recv(timeout=RECV_TIMEOUT_S)
    assert got is not None and got.arbitration_id == 0x100


def test_a_killed_peer_causes_no_error_and_its_stale_entry_is_removed(open_bus: OpenBus, channel: str) -> None:
    sender, staying = open_bus(), open_bus()
    directory = bus.ipc.channel_directory(channel)
    proc = run_python(f"""
        import os, sys, can, bus.ipc
        b = can.Bus(interface="ipc", channel={channel!r})
        print(b.port, flush=True)
        sys.stdin.read()
    """, stdin=subprocess.PIPE)
    assert proc.stdout is not None
    port = int(proc.stdout.readline())
    stale = f"{proc.pid}-{port}"
    assert stale in entries(directory)
    sender.send(msg(0x100))
    assert port in sender.peers

    proc.send_signal(signal.SIGKILL)  # no shutdown: its entry stays, and nothing is bound to its port
    proc.communicate()
    assert stale in entries(directory)
    for i in range(1, 4):
        sender.send(msg(0x100 + i))  # no error; the refusal tells the sender

    assert stale not in entries(directory)
    assert port not in sender.peers
    assert sender.stats.peers_dropped == 1
    got = [staying.recv(RECV_TIMEOUT_S) for _ in range(4)]
    assert [m.arbitration_id for m in got if m] == [0x100, 0x101, 0x102, 0x103]


def test_the_entry_of_a_dead_pid_is_removed_when_the_directory_is_read(open_bus: OpenBus, channel: str) -> None:
    sender, staying = open_bus(), open_bus()
    directory = bus.ipc.channel_directory(channel)
    ended = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                           text=True, check=True)
    dead = f"{int(ended.stdout)}-9"  # a pid that has exited
    (directory / dead).touch()  # the directory's mtime changes: the sender reads it again

    time.sleep(2 * bus.ipc.RESCAN_CHECK_S)
    sender.send(msg(0x100))

    assert dead not in entries(directory)
    assert sender.peers == [staying.port]
    assert sender.stats.peers_dropped == 1
    got = staying.recv(RECV_TIMEOUT_S)
    assert got is not None and got.arbitration_id == 0x100


def test_a_bus_opened_later_is_found_by_a_sender_already_running(open_bus: OpenBus) -> None:
    sender = open_bus()
    sender.send(msg(0x100))  # nobody there yet
    late = open_bus()
    time.sleep(2 * bus.ipc.RESCAN_CHECK_S)
    sender.send(msg(0x101))

    got = late.recv(timeout=RECV_TIMEOUT_S)
    assert got is not None and got.arbitration_id == 0x101


def test_a_peer_registered_in_the_clock_tick_of_the_last_listing_is_still_found(open_bus: OpenBus,
                                                                                 channel: str) -> None:
    sender = open_bus()  # its first listing is as fresh as the directory's mtime (its own entry)
    directory = bus.ipc.channel_directory(channel)
    listed_at = directory.stat().st_mtime_ns
    peer = open_bus()
    os.utime(directory, ns=(listed_at, listed_at))  # a coarse clock: the new entry left the mtime as it was

    time.sleep(2 * bus.ipc.RESCAN_CHECK_S)
    sender.send(msg(0x100))

    got = peer.recv(timeout=RECV_TIMEOUT_S)
    assert got is not None and got.arbitration_id == 0x100


# --- order and loss -------------------------------------------------------------------------------


def test_per_sender_order_is_kept_over_10000_frames_from_another_process(open_bus: OpenBus, channel: str) -> None:
    receiver = open_bus()
    count = 10_000
    proc = run_python(f"""
        import can, bus.ipc
        with can.Bus(interface="ipc", channel={channel!r}) as b:
            for i in range({count}):
                b.send(can.Message(arbitration_id=0x200 + i % 16, data=i.to_bytes(4, "little"),
                                   is_extended_id=False))
            print(b.stats.sent, b.stats.tx_dropped)
    """)
    try:
        indices: list[int] = []
        stamps: list[float] = []
        while not indices or indices[-1] < count - 1:
            if (m := receiver.recv(timeout=15 if not indices else 2.0)) is None:
                break
            indices.append(int.from_bytes(m.data, "little"))
            stamps.append(m.timestamp)
        out, err = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert out.split() == [str(count), "0"]
    assert indices, "nothing arrived"
    assert all(a < b for a, b in itertools.pairwise(indices))  # strictly in send order
    assert stamps == sorted(stamps)
    # whatever did not arrive (a receive buffer smaller than the burst) is counted, nothing else
    assert receiver.stats.rx_late == 0
    assert receiver.stats.rx_lost == (indices[-1] - indices[0] + 1) - len(indices)


def test_a_full_receive_buffer_loses_frames_counted_and_warned_once_never_blocking_the_sender(
        open_bus: OpenBus, caplog: pytest.LogCaptureFixture) -> None:
    sender, sleeper = open_bus(), open_bus()
    count = max(20_000, sleeper.rcvbuf_bytes // 256)  # far more than the receive buffer holds (~800 B a frame)
    frame = msg(0x481, bytes(8))
    started = time.monotonic()
    for _ in range(count):
        sender.send(frame)
    send_s = time.monotonic() - started

    with caplog.at_level(logging.WARNING, logger="bus.ipc"):
        drained = []
        while (m := sleeper.recv(timeout=0.2)) is not None:
            drained.append(m)
        sender.send(msg(0x482, b"last"))  # the gap before it shows how many never arrived
        last = sleeper.recv(timeout=RECV_TIMEOUT_S)

    assert sender.stats.sent == count + 1 and sender.stats.tx_dropped == 0
    assert 0 < len(drained) < count
    assert last is not None and last.arbitration_id == 0x482
    assert sleeper.stats.rx_lost == count - len(drained)
    assert sleeper.dropped == sleeper.stats.rx_lost
    assert len(caplog.records) == 1 and "stats.rx_lost" in caplog.records[0].message
    assert send_s < 60  # not a performance bound: the sends returned without waiting for the reader


class _RefusingSocket:
    """A socket whose sends the kernel refuses with EAGAIN (the sender's own buffer full)."""

    def __init__(self, real: Any):
        self._real = real

    def sendto(self, data: bytes, address: Any) -> int:
        raise BlockingIOError(11, "Resource temporarily unavailable")

    def __getattr__(self, name: str) -> Any:
        return getattr(self._real, name)


def test_a_send_the_kernel_cannot_take_is_dropped_for_that_peer_counted_and_warned_once(
        open_bus: OpenBus, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    sender, a, b = open_bus(), open_bus(), open_bus()
    sender.send(msg(0x100))  # learns its peers
    monkeypatch.setattr(sender, "_sock", _RefusingSocket(sender._sock))
    with caplog.at_level(logging.WARNING, logger="bus.ipc"):
        for _ in range(3):
            sender.send(msg(0x101))  # never raises, never blocks

    assert sender.stats.tx_dropped == 3 * 2  # 3 frames, 2 peers
    for peer in (a, b):
        got = peer.recv(timeout=RECV_TIMEOUT_S)
        assert got is not None and got.arbitration_id == 0x100
        assert peer.recv(timeout=0.05) is None
    assert sender.dropped == 6
    assert len(caplog.records) == 1 and "stats.tx_dropped" in caplog.records[0].message


def test_datagrams_that_are_not_frames_are_ignored_and_counted(open_bus: OpenBus) -> None:
    import socket

    receiver = open_bus()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as stray:
        stray.sendto(b"hello", ("127.0.0.1", receiver.port))
        stray.sendto(b"XXXX" + bytes(40), ("127.0.0.1", receiver.port))
    sender = open_bus()
    sender.send(msg(0x100))

    got = receiver.recv(timeout=RECV_TIMEOUT_S)

    assert got is not None and got.arbitration_id == 0x100
    assert receiver.stats.malformed == 2


def test_a_frame_older_than_one_delivered_from_its_sender_is_dropped_and_counted(open_bus: OpenBus) -> None:
    import socket

    receiver = open_bus()

    def frame(seq: int, cob_id: int) -> bytes:
        return bus.ipc.HEADER.pack(bus.ipc.MAGIC, bus.ipc.VERSION, 0, 1, 0, 0xABCD, seq, cob_id, time.time()) + b"x"

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:  # one sender: one port, one id
        for seq, cob_id in ((7, 0x101), (9, 0x103), (8, 0x102), (10, 0x104)):
            sender.sendto(frame(seq, cob_id), ("127.0.0.1", receiver.port))
        got = [receiver.recv(timeout=RECV_TIMEOUT_S) for _ in range(3)]

    assert [m.arbitration_id for m in got if m] == [0x101, 0x103, 0x104]  # 0x102 came late: not delivered
    assert receiver.stats.rx_late == 1
    assert receiver.stats.rx_lost == 1  # the gap 7 -> 9 (its frame then came too late to fill it)


# --- CANopen over it ------------------------------------------------------------------------------


def test_a_canopen_sdo_upload_works_between_a_local_and_a_remote_node(open_bus: OpenBus) -> None:
    def dictionary() -> canopen.ObjectDictionary:
        od = canopen.ObjectDictionary()
        number = ODVariable("number", 0x2000, 0)
        number.data_type, number.access_type, number.default = UNSIGNED32, "rw", 0xCAFE1234
        text = ODVariable("text", 0x2001, 0)  # longer than 4 bytes: a segmented transfer
        text.data_type, text.access_type, text.default = VISIBLE_STRING, "ro", "simulated drive over ipc"
        od.add_object(number)
        od.add_object(text)
        return od

    drive_net, master_net = canopen.Network(open_bus()), canopen.Network(open_bus())
    drive_net.NOTIFIER_CYCLE = master_net.NOTIFIER_CYCLE = 0.05
    local = canopen.LocalNode(5, dictionary())
    remote = canopen.RemoteNode(5, dictionary())
    drive_net.add_node(local)
    master_net.add_node(remote)
    drive_net.connect()
    master_net.connect()
    try:
        remote.sdo.RESPONSE_TIMEOUT = 2.0
        assert remote.sdo[0x2000].raw == 0xCAFE1234
        assert remote.sdo[0x2001].raw == "simulated drive over ipc"
        remote.sdo[0x2000].raw = 42
        assert local.sdo[0x2000].raw == 42
    finally:
        master_net.disconnect()
        drive_net.disconnect()


def test_the_channels_in_use_are_detected(open_bus: OpenBus, channel: str) -> None:
    open_bus()
    assert {"interface": "ipc", "channel": channel} in can.detect_available_configs(interfaces=["ipc"])


def test_the_benchmark_measures_both_buses(registry: Path) -> None:
    from benchmarks import bench_ipc

    virtual = bench_ipc.run("virtual", "burst", 200)
    ipc = bench_ipc.run("ipc", "paced", 20)
    assert virtual["received"] == 200 and virtual["lost"] == 0
    assert ipc["received"] == 20 and ipc["lost"] == 0
    assert 0 < ipc["p50_ms"] <= ipc["p99_ms"] and virtual["frames_per_s"] > 0


# --- configuration ----------------------------------------------------------------------------------


@pytest.mark.parametrize("bad", ["a/b", "", "..", ".hidden", "x" * 65, "sp ace", None, 3])
def test_a_bad_channel_name_is_refused_with_a_clear_error(registry: Path, bad: object) -> None:
    with pytest.raises(IpcChannelError) as err:
        can.Bus(interface="ipc", channel=bad)
    assert err.value.code == CONFIG
    assert err.value.detail == {"field": "channel", "value": repr(bad)}
    assert "ipc channel" in str(err.value) and repr(bad) in str(err.value)
    assert not registry.exists() or not any(registry.iterdir())


def test_the_channel_directory_is_under_xdg_runtime_dir_or_dev_shm(monkeypatch: pytest.MonkeyPatch,
                                                                   tmp_path: Path) -> None:
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    assert bus.ipc.channel_directory("pvt0") == tmp_path / "pvt-ipc" / "pvt0"
    monkeypatch.delenv("XDG_RUNTIME_DIR")
    assert bus.ipc.channel_directory("pvt0") == Path(f"/dev/shm/pvt-ipc-{os.getuid()}/pvt0")


def test_bitrate_is_kept_and_unknown_keyword_arguments_are_ignored(open_bus: OpenBus) -> None:
    b = open_bus(bitrate=500_000, fd=False, app_name="pvt", receive_own_messages=True)
    assert b.bitrate == 500_000 and b.receive_own_messages


def test_the_interface_is_declared_as_a_python_can_entry_point_and_registered_on_import() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert project["project"]["entry-points"]["can.interface"] == {"ipc": "bus.ipc:IpcBus"}
    import can.interfaces
    import can.util

    assert can.interfaces.BACKENDS["ipc"] == ("bus.ipc", "IpcBus")
    assert "ipc" in can.util.VALID_INTERFACES and "ipc" in can.VALID_INTERFACES


def test_a_cell_accepts_the_ipc_interface_and_still_refuses_udp_multicast() -> None:
    from planner.errors import PlanningError

    assert BusConfig().with_spec("ipc:pvt0") == BusConfig("ipc", "pvt0", 1_000_000)
    with pytest.raises(PlanningError):
        BusConfig("udp_multicast", "224.0.0.1")


# --- the product across two processes ---------------------------------------------------------------


def test_pvt_sim_on_ipc_answers_a_master_in_this_process(registry: Path, channel: str,
                                                         demo_cell: CellConfig) -> None:
    from bus.network import MasterAdapter

    cell = replace(demo_cell.with_axes(2), bus=BusConfig("ipc", channel, demo_cell.bus.bitrate))
    cmd = [sys.executable, "-m", "streamer.cli", "sim", "--config", str(ROOT / "configs" / "demo.toml"),
           "--bus", f"ipc:{channel}", "--axes", "2", "--sync-gap-factor", "5", "--stop-on-stdin-eof"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    statuses: list[BufferStatus] = []

    def on_event(event: Event) -> None:
        if isinstance(event, BufferStatus):
            statuses.append(event)

    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()
        assert "2 drives" in first and f"ipc:{channel}" in first, first
        with MasterAdapter(None, cell) as master:
            master.on_event(on_event)
            master.configure_drives()
            master.enable_drives()
            master.start_sync()
            deadline = time.monotonic() + 5.0
            while {s.node for s in statuses} != {1, 2} and time.monotonic() < deadline:
                time.sleep(0.01)
        assert {s.node for s in statuses} == {1, 2}  # TPDO1 of both drives, answering our SYNCs
    finally:
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(signal.SIGTERM)
        try:
            out, _ = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
    assert proc.returncode == 0, out
    assert "pvt sim: stopped" in out
