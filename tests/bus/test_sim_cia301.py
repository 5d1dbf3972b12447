"""CiA 301 behaviours a stock canopen master configures and expects (issue 11 section 1), driven in real
time by canopen's own RemoteNode against the simulated drive: event-driven TPDOs with an event timer
(0x18xx:05, sent periodically even unchanged) and an inhibit time (0x18xx:03, never two within it: exactly,
in the model's own time, in test_sim_model.py), and
store / restore parameters 0x1010:01 / 0x1011:01 with the signatures of seed 000 6.12 ("save"
0x65766173, "load" 0x64616F6C); a wrong signature is refused (SDO abort 0x08000020)."""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Iterator

import can
import canopen
import pytest
from bus_testkit import make_cell, remote_network, unique_channel, wait_until
from canopen.sdo.exceptions import SdoAbortedError

from bus import cob
from bus.sim.eds import EDS_PATH
from bus.sim.node import SimulatedCell

SAVE, LOAD = 0x65766173, 0x64616F6C


class Stamps(can.Listener):
    """Arrival times of one COB-ID."""

    def __init__(self, cob_id: int):
        self.cob_id = cob_id
        self.times: list[float] = []
        self.lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        if msg.arbitration_id == self.cob_id:
            with self.lock:
                self.times.append(msg.timestamp)


@pytest.fixture
def drive() -> Iterator[tuple[SimulatedCell, canopen.Network, canopen.RemoteNode]]:
    channel = unique_channel("cia301")
    sim = SimulatedCell(make_cell(1, channel=channel)).start()
    try:
        with remote_network(channel) as net:
            yield sim, net, net.add_node(1, str(EDS_PATH))
    finally:
        sim.stop()


def map_tpdo3_statusword(node: canopen.RemoteNode, *, inhibit_100us: int, event_timer_ms: int) -> None:
    """TPDO3 = statusword 0x6041, event driven (type 255), through canopen's own PDO API."""
    node.tpdo.read()
    pdo = node.tpdo[3]
    pdo.clear()
    pdo.add_variable(0x6041)
    pdo.trans_type = 255
    pdo.inhibit_time = inhibit_100us
    pdo.event_timer = event_timer_ms
    pdo.enabled = True
    pdo.save()


def test_event_timer_sends_an_unchanged_tpdo_periodically(drive) -> None:
    _sim, net, node = drive
    map_tpdo3_statusword(node, inhibit_100us=0, event_timer_ms=50)
    stamps = Stamps(cob.TPDO1_BASE + 0x200 + 1)  # TPDO3 of node 1: 0x381
    net.notifier.add_listener(stamps)
    node.nmt.state = "OPERATIONAL"
    time.sleep(0.6)
    with stamps.lock:
        times = list(stamps.times)
    assert len(times) >= 9, times  # the statusword does not change: only the timer sends it
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert min(gaps) > 0.040 and sorted(gaps)[len(gaps) // 2] == pytest.approx(0.050, abs=0.010), gaps


def test_inhibit_time_spaces_a_changing_tpdo(drive) -> None:
    _sim, net, node = drive
    map_tpdo3_statusword(node, inhibit_100us=1000, event_timer_ms=0)  # 100 ms between two
    stamps = Stamps(0x381)
    net.notifier.add_listener(stamps)
    node.nmt.state = "OPERATIONAL"
    assert wait_until(lambda: len(stamps.times) >= 1, 1.0)
    # change the statusword every ~10 ms for 0.6 s: shutdown / disable voltage back and forth
    t_end = time.monotonic() + 0.6
    flip = False
    while time.monotonic() < t_end:
        node.sdo[0x6040].raw = 0x0006 if flip else 0x0000
        flip = not flip
        time.sleep(0.01)
    time.sleep(0.15)  # the change made inside the last inhibit time goes out when it ends
    with stamps.lock:
        times = list(stamps.times)
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert len(times) >= 5, times
    assert len(times) <= 9  # without the inhibit: ~60 changes
    # the stamps are when the simulated node's thread got the frame onto the bus: a host stall of that thread
    # shows as one short gap after a late frame (a run here: 86 ms, then 100 ms each). The model keeps the
    # inhibit time exactly in its own time (test_sim_model.py::test_inhibit_time_spaces_a_changing_event_tpdo_exactly)
    assert sorted(gaps)[len(gaps) // 2] == pytest.approx(0.100, abs=0.005) and min(gaps) > 0.060, gaps


def test_store_and_restore_parameters_with_signatures(drive) -> None:
    _sim, _net, node = drive
    assert node.sdo[0x1010][1].raw & 1 and node.sdo[0x1011][1].raw & 1  # saves / restores on command
    node.sdo[0x1017].raw = 250
    node.sdo[0x6065].raw = 12345
    with pytest.raises(SdoAbortedError) as e:
        node.sdo[0x1010][1].raw = 0x12345678
    assert e.value.code == 0x08000020
    node.sdo[0x1010][1].raw = SAVE
    node.sdo[0x6065].raw = 999  # not saved
    node.nmt.send_command(0x81)  # reset node: stored values come back, unsaved ones do not
    assert wait_until(lambda: _read(node, 0x6065) == 12345, 2.0)
    assert node.sdo[0x1017].raw == 250
    with pytest.raises(SdoAbortedError):
        node.sdo[0x1011][1].raw = SAVE  # "save" is not the restore signature
    node.sdo[0x1011][1].raw = LOAD
    assert node.sdo[0x6065].raw == 12345  # restore takes effect at the next reset (CiA 301)
    node.nmt.send_command(0x81)
    assert wait_until(lambda: _read(node, 0x6065) == 2000, 2.0)  # the default again
    assert node.sdo[0x1017].raw == 0


def _read(node: canopen.RemoteNode, index: int) -> int | None:
    try:
        return int(node.sdo[index].raw)
    except (SdoAbortedError, canopen.SdoCommunicationError):
        return None


def test_event_timer_written_on_a_running_tpdo_takes_effect(drive) -> None:
    """Issue 23 item 4: a stock master sets 0x1801:05 on TPDO2 while it runs (event driven, valid, NMT
    operational), as CiA 301 allows for the event timer; the drive must send it every 50 ms from then on."""
    _sim, net, node = drive
    node.sdo[0x1801][2].raw = 255  # TPDO2 (0x6064, 0x6062 by default) event driven
    stamps = Stamps(cob.TPDO2_BASE + 1)
    net.notifier.add_listener(stamps)
    node.nmt.state = "OPERATIONAL"
    assert wait_until(lambda: len(stamps.times) >= 1, 1.0)  # its first transmission; nothing changes after
    node.sdo[0x1801][5].raw = 50
    assert node.sdo[0x1801][5].raw == 50
    with stamps.lock:
        before = len(stamps.times)
    time.sleep(0.5)
    with stamps.lock:
        times = stamps.times[before:]
    assert len(times) >= 8, times  # CiA 301: one every 50 ms at standstill (10 in 0.5 s)
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert sorted(gaps)[len(gaps) // 2] == pytest.approx(0.050, abs=0.010), gaps


def test_a_drives_frames_leave_under_the_lock_that_made_them(
        drive: tuple[SimulatedCell, canopen.Network, canopen.RemoteNode]) -> None:
    """The model's lock is held until what it produced is sent, by every thread that produces (the bus's, the
    timer's, the SDO server's): sent after the lock, a drive's answers to two SYNCs once crossed on the wire
    (the timer thread released the first, the bus thread made the second and sent it first), and the master
    rightly took that for records executed out of order (bench_realtime --only epos, all readings at once)."""
    sim, net, node = drive
    assert sim._network is not None
    real = sim._network.send_message
    sends: list[tuple[int, str, bool]] = []

    def send(cob_id: int, data: bytes) -> None:
        sends.append((cob_id, threading.current_thread().name, sim._lock._is_owned()))  # type: ignore[attr-defined]
        real(cob_id, data)

    sim._network.send_message = send  # type: ignore[method-assign]
    node.sdo[0x1017].raw = 20  # an SDO answer; then heartbeats from the timer thread
    net.nmt.send_command(0x01)  # start: the NMT from the bus's thread
    net.send_message(0x080, b"")  # a SYNC
    assert wait_until(lambda: sum(1 for c, _, _ in sends if c == 0x701) >= 3, timeout_s=2.0)
    node.sdo[0x1017].raw = 0
    assert len({name for _, name, _ in sends}) >= 2  # more than one thread sent
    assert all(owned for _, _, owned in sends), sends


def test_a_sync_answer_held_for_the_latency_leaves_at_its_time_not_at_the_timers_next_wake() -> None:
    """The TPDO-latency reading (docs/drive-model.md): a SYNC's answers go out within the drawn latency (up to 9 ms
    here). The timer thread slept on to its previous deadline (the SYNC watchdog's, or 50 ms), so with SYNCs
    40 ms apart (the probe's latency experiment) answers left 6-41 ms after their SYNC, and the probe reported a
    latency of 41 ms for a drive of 9. Judged on the wire: every answer before the next SYNC, most within the
    latency and a machine's scheduling margin."""
    from dataclasses import replace

    from planner.readings import SimDriveOptions

    channel = unique_channel("latency")
    base = make_cell(1, channel=channel)
    cell = replace(base, axes=tuple(replace(a, sim=SimDriveOptions(tpdo_latency_ms=9.0)) for a in base.axes))
    sim = SimulatedCell(cell).start()
    try:
        with remote_network(channel) as net:
            answers = Stamps(0x181)
            net.notifier.add_listener(answers)
            node = net.add_node(1, str(EDS_PATH))
            node.tpdo.read()
            node.tpdo[1].trans_type = 1  # synchronous: an answer to every SYNC
            node.tpdo[1].enabled = True
            node.tpdo[1].save()
            net.nmt.send_command(0x01)  # operational
            syncs = []  # the virtual bus does not echo a sender's own frames: the time just before it is sent
            for _ in range(12):
                syncs.append(time.time())
                net.send_message(cob.SYNC_COB_ID, b"")
                time.sleep(0.040)
            assert wait_until(lambda: len(answers.times) >= 12, timeout_s=2.0), answers.times
    finally:
        sim.stop()
    late = [a - s for s, a in zip(syncs, answers.times, strict=False)]
    assert all(0.0 <= x < 0.040 for x in late), late  # each before the next SYNC
    assert sorted(late)[len(late) // 2] < 0.015, late  # the median within 9 ms and a scheduling margin
