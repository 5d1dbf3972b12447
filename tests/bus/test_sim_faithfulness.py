"""The stock canopen RemoteNode (not the product's master code) drives the simulated drive in real time
through the typical IPM commanding sequence (seed 001 p. 18 / seed 000 table 4-39):

    modes of operation 0x6060 = 7; controlword 0x0006, 0x000F; buffer clear 0x60C4:06 = 0 then
    enable = 1; at least 2 PVT records to 0x20C1; controlword 0x001F; while 0x20C4:01 bit 0
    (underflow warning) is set, write records (until bit 1, overflow warning)

and checks what section 3 of the issue asks of the drive: the time-0 end, underflow EMCY and fault,
fault reset, overflow error, velocity error abort, halt, following error, SYNC loss. Everything goes
over SDO, EMCY and SYNC exactly as an external CANopen master would do it.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import canopen
import pytest
from bus_testkit import make_cell, ramp_records, remote_network, unique_channel, wait_until

from bus import codec
from bus.codec import Cia402State as S
from bus.sim.eds import EDS_PATH
from bus.sim.node import SimulatedCell
from planner.encoding import record

SEG_MS = 50  # long segments: the SDO-fed FIFO has slack on a loaded machine


@dataclass
class Rig:
    sim: SimulatedCell
    net: canopen.Network
    node: canopen.RemoteNode

    def state(self) -> S:
        return codec.state_from_statusword(self.node.sdo[0x6041].raw)

    def buffer_status(self) -> codec.BufferStatusWord:
        return codec.decode_buffer_status(self.node.sdo[0x20C4][1].raw)

    def write_record(self, r: tuple[int, int, int]) -> None:
        self.node.sdo[0x20C1].raw = int.from_bytes(record.pack(r), "little")

    def seed_start(self, records: list[tuple[int, int, int]], prime: int = 3) -> list[tuple[int, int, int]]:
        """Seed 000 table 4-39 up to controlword 0x001F; returns the records still to feed."""
        sdo = self.node.sdo
        sdo[0x6060].raw = 7
        sdo[0x6040].raw = 0x0006
        sdo[0x6040].raw = 0x000F
        assert self.state() == S.OPERATION_ENABLED
        sdo[0x60C4][6].raw = 0  # clear
        sdo[0x60C4][6].raw = 1  # enable
        for r in records[:prime]:
            self.write_record(r)
        sdo[0x6040].raw = 0x001F
        return records[prime:]

    def feed_while_underflow_warning(self, pending: list[tuple[int, int, int]],
                                     timeout_s: float = 5.0) -> None:
        """Seed 001 p. 18: while the underflow warning is set, write records; stop at the overflow
        warning. Returns when ip mode is no longer active."""
        def step() -> bool:
            status = self.buffer_status()
            if status.underflow_warning:
                while pending and not self.buffer_status().overflow_warning:
                    self.write_record(pending.pop(0))
                    if len(pending) % 4 == 0:
                        break
            return not status.ip_active and not pending

        assert wait_until(step, timeout_s, poll_s=0.002)

    def emcy_codes(self) -> list[int]:
        return [e.code for e in self.node.emcy.log]

    def wait_emcy(self, code: int, timeout_s: float) -> canopen.emcy.EmcyError | None:
        """The first EMCY with `code` in the node's EMCY log (canopen's wait() misses past ones)."""
        wait_until(lambda: code in self.emcy_codes(), timeout_s)
        return next((e for e in self.node.emcy.log if e.code == code), None)


@pytest.fixture
def rig() -> Iterator[Rig]:
    channel = unique_channel("faithful")
    cell = make_cell(1, sync_period_ms=10, channel=channel)
    sim = SimulatedCell(cell)
    sim.start()
    try:
        with remote_network(channel) as net:
            node = net.add_node(1, str(EDS_PATH))
            net.sync.start(0.010)
            yield Rig(sim, net, node)
    finally:
        sim.stop()  # raises any error recorded inside the simulated drive's callbacks


def test_seed_sequence_runs_to_the_time_zero_end(rig: Rig) -> None:
    records = ramp_records(20_000, cruise_rpm=600, seg_ms=SEG_MS)
    pending = rig.seed_start(records)
    assert wait_until(lambda: rig.buffer_status().ip_active, 1.0)
    assert rig.node.sdo[0x6041].raw & codec.SW_IP_ACTIVE
    rig.feed_while_underflow_warning(pending)
    assert rig.emcy_codes() == []  # a time-0 record ends interpolation without error
    assert rig.state() == S.OPERATION_ENABLED
    assert rig.node.sdo[0x6062].raw == 20_000
    assert wait_until(lambda: rig.node.sdo[0x6041].raw & codec.SW_TARGET_REACHED, 2.0)
    assert abs(rig.node.sdo[0x6064].raw - 20_000) <= 100
    assert rig.node.sdo[0x60C4][2].raw == 64 and rig.node.sdo[0x60C4][4].raw == 0


def test_underflow_emcy_fault_and_fault_reset(rig: Rig) -> None:
    rig.seed_start(ramp_records(20_000, cruise_rpm=600, seg_ms=SEG_MS), prime=3)  # nothing more is fed
    emcy = rig.wait_emcy(0x8782, 3.0)
    assert emcy is not None, rig.emcy_codes()
    status = codec.decode_buffer_status(int.from_bytes(emcy.data[0:2], "little"))
    assert status.underflow_error and not status.overflow_error and not status.ip_active
    assert emcy.register & codec.ER_GENERIC
    assert wait_until(lambda: rig.state() == S.FAULT, 2.0)
    assert rig.buffer_status().underflow_error
    assert rig.node.sdo[0x603F].raw == 0x8782
    # fault reset: rising edge of bit 7
    rig.node.sdo[0x6040].raw = 0x0080
    assert rig.wait_emcy(0x0000, 1.0) is not None
    assert rig.state() == S.SWITCH_ON_DISABLED
    assert not rig.buffer_status().any_error and rig.node.sdo[0x603F].raw == 0
    rig.node.sdo[0x6040].raw = 0x0006
    rig.node.sdo[0x6040].raw = 0x000F
    assert rig.state() == S.OPERATION_ENABLED  # re-enabled after the reset


def test_activation_with_one_record_is_refused_with_underflow(rig: Rig) -> None:
    rig.seed_start(ramp_records(20_000, seg_ms=SEG_MS), prime=1)
    assert rig.wait_emcy(0x8782, 1.0) is not None
    assert rig.state() == S.FAULT


def test_overflow_error(rig: Rig) -> None:
    sdo = rig.node.sdo
    sdo[0x6060].raw = 7
    sdo[0x60C4][6].raw = 0
    sdo[0x60C4][6].raw = 1
    for k in range(64):
        rig.write_record((k, 0, 10))
    assert sdo[0x60C4][2].raw == 0 and rig.buffer_status().overflow_warning
    assert rig.emcy_codes() == []
    rig.write_record((64, 0, 10))
    emcy = rig.wait_emcy(0x8782, 1.0)
    assert emcy is not None
    assert codec.decode_buffer_status(int.from_bytes(emcy.data[0:2], "little")).overflow_error
    assert rig.buffer_status().overflow_error and rig.state() == S.FAULT


def test_velocity_error_aborts_the_trajectory(rig: Rig) -> None:
    rig.node.sdo[0x607F].raw = 300  # max profile velocity, rpm
    pending = rig.seed_start(ramp_records(20_000, cruise_rpm=600, seg_ms=SEG_MS), prime=4)
    emcy = rig.wait_emcy(0xFF10, 3.0)
    assert emcy is not None, rig.emcy_codes()
    assert codec.decode_buffer_status(int.from_bytes(emcy.data[0:2], "little")).velocity_error
    assert wait_until(lambda: rig.state() == S.FAULT, 2.0)
    assert not rig.buffer_status().ip_active and pending


def test_halt_decelerates_and_reports_target_reached(rig: Rig) -> None:
    rig.node.sdo[0x6084].raw = 5000  # profile deceleration, rpm/s
    records = ramp_records(100_000, cruise_rpm=1200, seg_ms=SEG_MS)
    rig.seed_start(records, prime=6)
    assert wait_until(lambda: abs(rig.node.sdo[0x606C].raw) > 300, 2.0)
    rig.node.sdo[0x6040].raw = 0x011F  # halt
    assert wait_until(lambda: rig.node.sdo[0x6041].raw & codec.SW_TARGET_REACHED, 2.0)
    sw = rig.node.sdo[0x6041].raw
    assert not sw & codec.SW_IP_ACTIVE and rig.state() == S.OPERATION_ENABLED
    demand = rig.node.sdo[0x6062].raw
    assert 0 < demand < 100_000
    assert wait_until(lambda: rig.node.sdo[0x6062].raw == demand, 0.1)
    assert rig.emcy_codes() == []


def test_following_error(rig: Rig) -> None:
    rig.node.sdo[0x6065].raw = 30  # following error window, counts
    rig.seed_start(ramp_records(50_000, cruise_rpm=1200, seg_ms=SEG_MS), prime=6)
    emcy = rig.wait_emcy(0x8611, 3.0)
    assert emcy is not None, rig.emcy_codes()
    assert wait_until(lambda: rig.state() == S.FAULT, 2.0)


def test_sync_loss_while_ip_active(rig: Rig) -> None:
    rig.node.sdo[0x1006].raw = 10_000  # the communication cycle period the SYNC monitor checks
    rig.seed_start(ramp_records(50_000, cruise_rpm=600, seg_ms=SEG_MS), prime=6)
    assert wait_until(lambda: rig.buffer_status().ip_active, 1.0)
    rig.net.sync.stop()
    emcy = rig.wait_emcy(0x8780, 1.0)
    assert emcy is not None, rig.emcy_codes()
    assert wait_until(lambda: rig.state() in (S.FAULT, S.FAULT_REACTION_ACTIVE), 1.0)
