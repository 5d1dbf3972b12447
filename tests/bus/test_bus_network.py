"""The master-side adapter against the simulated cell on a python-can virtual bus."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import can
import pytest
from bus_testkit import make_axis, make_cell, ramp_records, unique_channel, wait_until

from bus import cob, codec
from bus.errors import BUS_OPEN, CALLBACK, CLOSED, NO_RESPONSE, SDO_ABORT, SEND_FAILED, VERIFY, BusError
from bus.events import (
    AdapterError,
    Bootup,
    BufferStatus,
    BusLoad,
    Emcy,
    Event,
    HeartbeatLost,
    PositionFeedback,
    Sync,
)
from bus.families import EPOS_IPM, EposProfile
from bus.network import MasterAdapter, open_bus
from bus.profile import SdoWrite
from bus.sim.node import SimulatedCell
from planner.config import AxisConfig, BusConfig, CellConfig, DriveSettings
from planner.encoding import record
from planner.errors import PlanningError

SETTINGS = DriveSettings(heartbeat_ms=20, heartbeat_timeout_ms=300)


@dataclass
class Recorder:
    events: list[Event] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __call__(self, event: Event) -> None:
        with self.lock:
            self.events.append(event)

    def of(self, kind: type) -> list[Any]:
        with self.lock:
            return [e for e in self.events if isinstance(e, kind)]

    def last_status(self, node: int) -> BufferStatus | None:
        found = [e for e in self.of(BufferStatus) if e.node == node]
        return found[-1] if found else None


class _Tap(can.Listener):  # type: ignore[misc]
    def __init__(self) -> None:
        self.frames: list[can.Message] = []

    def on_message_received(self, msg: can.Message) -> None:
        self.frames.append(msg)


@pytest.fixture
def cell() -> CellConfig:
    return make_cell(2, sync_period_ms=10, channel=unique_channel("net"), settings=SETTINGS)


@pytest.fixture
def sim(cell: CellConfig) -> Iterator[SimulatedCell]:
    # The SYNC producer is a Python thread on a shared machine: a 15 ms gap (1.5 periods) happens
    # under load and would fault the drives with 0x8780. SYNC loss itself is tested in
    # test_sim_model.py (exact, virtual time) and test_sim_faithfulness.py.
    with SimulatedCell(cell, sync_gap_factor=5.0) as s:
        yield s


def test_configure_enable_and_stream_a_synchronous_start(cell: CellConfig, sim: SimulatedCell) -> None:
    rec = Recorder()
    tap = _Tap()
    with MasterAdapter(None, cell) as m:
        m.on_event(rec)
        m.add_listener(tap)
        m.configure_drives()
        for node in (1, 2):
            assert m.read(node, 0x6060) == 7 and m.read(node, 0x60C0) == -1
            assert m.read(node, 0x1A00, 2) == 0x60C40220 and m.read(node, 0x1401, 2) == 255
        m.enable_drives()
        assert all(sim.model(n).state == codec.Cia402State.OPERATION_ENABLED for n in (1, 2))
        m.start_sync()
        assert wait_until(lambda: all(rec.last_status(n) is not None for n in (1, 2)), 1.0)
        records = {1: ramp_records(20_000, cruise_rpm=600, seg_ms=20),
                   2: ramp_records(-10_000, cruise_rpm=300, seg_ms=20)}
        for node, recs in records.items():
            for r in recs[:6]:
                m.send(cob.rpdo2_id(node), record.pack(r))
            del recs[:6]
        for node in records:  # synchronous RPDO1: both start on the next SYNC
            m.send(cob.rpdo1_id(node), cob.pack_controlword(0x001F))

        fed_at: dict[int, int | None] = {1: None, 2: None}
        seen_active: set[int] = set()

        def feed() -> bool:
            """Streamer-like: per TPDO1 (one per SYNC), top the FIFO up to 16 with what it reports."""
            done = True
            for node, recs in records.items():
                status = rec.last_status(node)
                assert status is not None
                if status.buffer_status & codec.BS_IP_ACTIVE:
                    seen_active.add(node)
                if status.sync_count != fed_at[node]:
                    fed_at[node] = status.sync_count
                    for _ in range(max(0, 16 - (64 - status.free_size))):
                        if recs:
                            m.send(cob.rpdo2_id(node), record.pack(recs.pop(0)))
                ended = node in seen_active and not status.buffer_status & codec.BS_IP_ACTIVE
                done = done and not recs and ended
            return done

        assert wait_until(feed, 8.0, poll_s=0.005), (rec.of(Emcy), [sim.model(n).fault_log for n in (1, 2)])
        m.stop_sync()
        m.check()
    assert not rec.of(Emcy), rec.of(Emcy)
    assert sim.model(1).position_demand == 20_000 and sim.model(2).position_demand == -10_000
    # events: SYNC counts are consecutive, every TPDO says which SYNC it answers
    syncs = rec.of(Sync)
    assert [s.count for s in syncs] == list(range(len(syncs)))
    last = None
    for ev in rec.events:
        if isinstance(ev, Sync):
            last = ev.count
        elif isinstance(ev, BufferStatus | PositionFeedback):
            assert ev.sync_count == last
    first_active = {n: next(e.sync_count for e in rec.of(BufferStatus)
                            if e.node == n and e.buffer_status & codec.BS_IP_ACTIVE) for n in (1, 2)}
    assert first_active[1] == first_active[2]  # the synchronous start
    assert not rec.of(Emcy) and not rec.of(AdapterError) and not rec.of(HeartbeatLost)
    assert tap.frames and {f.arbitration_id for f in tap.frames} >= {0x80, 0x181, 0x182, 0x301, 0x302}
    loads = rec.of(BusLoad)
    assert loads and all(0.0 < b.load < 1.0 for b in loads)


def test_emcy_and_error_reset_events(cell: CellConfig, sim: SimulatedCell) -> None:
    rec = Recorder()
    with MasterAdapter(None, cell) as m:
        m.on_event(rec)
        m.configure_drives()
        m.enable_drives()
        m.send(cob.rpdo2_id(1), record.pack((10, 0, 10)))
        m.send(cob.rpdo1_id(1), cob.pack_controlword(0x001F))
        m.start_sync()
        assert wait_until(lambda: rec.of(Emcy), 1.0)
        (e,) = rec.of(Emcy)
        assert e.node == 1 and e.code == 0x8782
        assert codec.decode_buffer_status(int.from_bytes(e.data[0:2], "little")).underflow_error
        m.enable_drives()  # fault reset inside
        assert wait_until(lambda: len(rec.of(Emcy)) == 2, 1.0)
        assert rec.of(Emcy)[1].code == 0x0000
        assert sim.model(1).state == codec.Cia402State.OPERATION_ENABLED
        m.write(2, 0x6040, 0, 0x000B)  # quick stop
        assert sim.model(2).state != codec.Cia402State.OPERATION_ENABLED
        m.enable_drives()
        assert sim.model(2).state == codec.Cia402State.OPERATION_ENABLED and sim.model(2).buffer_enabled


def test_bootup_and_heartbeat_lost(cell: CellConfig, sim: SimulatedCell) -> None:
    rec = Recorder()
    with MasterAdapter(None, cell) as m:
        m.on_event(rec)
        m.configure_drives()
        assert wait_until(lambda: sim.model(2).nmt_state == codec.NmtState.OPERATIONAL, 1.0)
        m.nmt(codec.NmtCommand.RESET_NODE, 1)
        assert wait_until(lambda: rec.of(Bootup), 1.0)
        assert rec.of(Bootup)[0].node == 1
        # after the reset node 1 no longer produces heartbeats (0x1017 back to 0)
        assert wait_until(lambda: rec.of(HeartbeatLost), 1.0)
        assert [h.node for h in rec.of(HeartbeatLost)] == [1]
        sim.stop()
        assert wait_until(lambda: len(rec.of(HeartbeatLost)) == 2, 1.0)
        assert rec.of(HeartbeatLost)[1].node == 2


def test_a_drive_that_does_not_answer_is_named(cell: CellConfig, sim: SimulatedCell) -> None:
    ghost = replace(cell, axes=(*cell.axes, make_axis(9)))
    with MasterAdapter(None, ghost, sdo_timeout_s=0.05, sdo_attempts=1) as m, pytest.raises(BusError) as e:
        m.configure_drives()
    assert e.value.code == NO_RESPONSE and e.value.node == 9 and e.value.obj == (0x1000, 0)
    assert "node 9" in str(e.value) and "0x1000:00" in str(e.value)


def test_a_refused_write_is_named(cell: CellConfig, sim: SimulatedCell) -> None:
    profile = replace(EPOS_IPM, ip_mode=1)  # profile position: this drive answers "not supported"
    with MasterAdapter(None, cell, profile=profile) as m, pytest.raises(BusError) as e:
        m.configure_drives()
    assert e.value.code == SDO_ABORT and e.value.node == 1 and e.value.obj == (0x6060, 0)
    assert e.value.detail["abort_code"] == 0x06090030
    assert "0x6060:00" in str(e.value) and "node 1" in str(e.value)


class _WrongReadBack(EposProfile):
    def configuration(
        self, axis: AxisConfig, settings: DriveSettings, sync_period_ms: int, **kw: Any
    ) -> tuple[SdoWrite, ...]:
        # 0x60C4:04 accepts writes that have no effect (seed 000 4.3.6.5), so it reads back the fill
        extra = SdoWrite(0x60C4, 4, 5, "buffer position")
        return (*super().configuration(axis, settings, sync_period_ms, **kw), extra)


def test_a_wrong_read_back_is_named(cell: CellConfig, sim: SimulatedCell) -> None:
    profile = _WrongReadBack(**{f: getattr(EPOS_IPM, f) for f in EPOS_IPM.__dataclass_fields__})
    with MasterAdapter(None, cell, profile=profile) as m, pytest.raises(BusError) as e:
        m.configure_drive(cell.axes[0])
    assert e.value.code == VERIFY and e.value.obj == (0x60C4, 4) and e.value.detail == {"wrote": 5, "read": 0}


def test_malformed_frame_becomes_adapter_error(cell: CellConfig, sim: SimulatedCell) -> None:
    rec = Recorder()
    with MasterAdapter(None, cell) as m, can.Bus(interface="virtual", channel=cell.bus.channel) as other:
        m.on_event(rec)
        other.send(can.Message(arbitration_id=cob.tpdo1_id(2), data=b"\x01\x02\x03", is_extended_id=False))
        assert wait_until(lambda: rec.of(AdapterError), 1.0)
        (err,) = rec.of(AdapterError)
        assert err.where == "decode 0x182" and "TPDO1" in err.reason
        # a node that is not ours: ignored, even malformed
        other.send(can.Message(arbitration_id=cob.tpdo1_id(77), data=b"\x01", is_extended_id=False))
        other.send(can.Message(arbitration_id=cob.tpdo2_id(2), data=bytes(8), is_extended_id=False))
        assert wait_until(lambda: rec.of(PositionFeedback), 1.0)
        assert len(rec.of(AdapterError)) == 1


def test_callback_exception_is_kept_and_raised(cell: CellConfig, sim: SimulatedCell) -> None:
    def boom(event: Event) -> None:
        raise RuntimeError("subscriber broke")

    m = MasterAdapter(None, cell)
    m.on_event(boom)
    m.start_sync()
    assert wait_until(lambda: bool(m.failures), 1.0)
    with pytest.raises(BusError) as e:
        m.send(cob.rpdo1_id(1), b"\x06\x00")
    assert e.value.code == CALLBACK and "subscriber broke" in str(e.value)
    with pytest.raises(BusError):
        m.close()
    with pytest.raises(BusError) as e:
        m.send(cob.rpdo1_id(1), b"\x06\x00")
    assert e.value.code == CLOSED


class _FailingBus(can.BusABC):  # type: ignore[misc]
    """A bus that refuses every frame (bus-off)."""

    def __init__(self, channel: str, **kwargs: Any):
        self._inner = can.Bus(interface="virtual", channel=channel, receive_own_messages=True)
        super().__init__(channel=channel, **kwargs)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        raise can.CanOperationError("bus-off")

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self._inner.recv(timeout), False

    def shutdown(self) -> None:
        self._inner.shutdown()
        super().shutdown()


def test_send_failure_raises_send_failed(cell: CellConfig) -> None:
    bus = _FailingBus(cell.bus.channel)
    try:
        with MasterAdapter(None, cell, bus=bus) as m:
            with pytest.raises(BusError) as e:
                m.send(cob.rpdo2_id(1), bytes(8))
            assert e.value.code == SEND_FAILED and "0x301" in str(e.value)
    finally:
        bus.shutdown()


def test_missing_sync_echo_is_reported(cell: CellConfig) -> None:
    rec = Recorder()
    bus = can.Bus(interface="virtual", channel=cell.bus.channel, receive_own_messages=False)
    try:
        with MasterAdapter(None, cell, bus=bus) as m:
            m.on_event(rec)
            m.start_sync(0.01)
            assert wait_until(lambda: rec.of(AdapterError), 1.0)
            assert rec.of(AdapterError)[0].where == "sync" and not rec.of(Sync)
    finally:
        bus.shutdown()


def test_open_bus_errors() -> None:
    with pytest.raises(PlanningError, match="udp_multicast"):
        BusConfig("udp_multicast", "239.0.0.1", 1_000_000)  # refused before any bus can be opened
    with pytest.raises(BusError) as e:
        open_bus(BusConfig("no-such-interface", "x", 1_000_000))
    assert e.value.code == BUS_OPEN and "no-such-interface" in str(e.value)
