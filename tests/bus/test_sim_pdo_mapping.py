"""A PDO mapping written by a master (stock canopen RemoteNode PDO API) takes effect in the simulated
drive: its TPDOs change layout, RPDOs on new COB-IDs reach the model (the LocalNode adapter re-reads
canopen's maps, which canopen applies only after rpdo.read()/tpdo.read())."""

from __future__ import annotations

import struct

import canopen
import pytest
from bus_testkit import make_cell, remote_network, unique_channel, wait_until

from bus.codec import Cia402State as S
from bus.sim.eds import EDS_PATH
from bus.sim.node import SimulatedCell
from planner.encoding import record


def test_master_written_mapping_takes_effect() -> None:
    channel = unique_channel("pdo-map")
    with SimulatedCell(make_cell(1, channel=channel)) as sim, remote_network(channel) as net:
        node = net.add_node(1, str(EDS_PATH))
        node.tpdo.read()
        node.rpdo.read()
        # TPDO1: position actual, statusword; synchronous (type 1)
        tp = node.tpdo[1]
        tp.clear()
        tp.add_variable(0x6064)
        tp.add_variable(0x6041)
        tp.trans_type = 1
        tp.enabled = True
        tp.save()
        # RPDO1: controlword, asynchronous (applied on reception)
        rp = node.rpdo[1]
        rp.clear()
        rp.add_variable(0x6040)
        rp.trans_type = 255
        rp.enabled = True
        rp.save()
        # RPDO3 (factory: controlword) becomes the PVT record, on its predefined COB-ID 0x401
        rec = node.rpdo[3]
        rec.clear()
        rec.add_variable(0x20C1)
        rec.trans_type = 255
        rec.enabled = True
        rec.save()
        assert node.sdo[0x1A00][1].raw == 0x60640020 and node.sdo[0x1602][1].raw == 0x20C10040
        node.nmt.state = "OPERATIONAL"
        net.sync.start(0.01)

        assert tp.wait_for_reception(timeout=1.0) is not None
        assert len(tp.data) == 6
        position, statusword = struct.unpack("<iH", bytes(tp.data))
        assert statusword & 0x4F == 0x40 and position == 0  # switch on disabled, at 0

        rp["Controlword"].raw = 0x0006
        rp.transmit()
        assert wait_until(lambda: sim.model(1).state == S.READY_TO_SWITCH_ON, 1.0)

        node.sdo[0x60C4][6].raw = 1
        rec["Interpolation data record"].raw = int.from_bytes(record.pack((1234, -56, 78)), "little")
        rec.transmit()
        assert wait_until(lambda: sim.model(1).fifo_fill == 1, 1.0)
        assert sim.model(1).fifo_records == ((1234, -56, 78),)
        assert sim.model(1).pdo_config_version > 1


def test_mapping_the_master_may_not_write_is_refused() -> None:
    channel = unique_channel("pdo-refused")
    with SimulatedCell(make_cell(1, channel=channel)), remote_network(channel) as net:
        node = net.add_node(1, str(EDS_PATH))
        with pytest.raises(canopen.SdoAbortedError) as e:
            node.sdo[0x1A00][0].raw = 0  # TPDO1 still valid
        assert e.value.code == 0x06040043
        node.sdo[0x1800][1].raw = 0x80000181
        node.sdo[0x1A00][0].raw = 0
        with pytest.raises(canopen.SdoAbortedError) as e:
            node.sdo[0x1A00][1].raw = 0x10000020  # device type: not mappable
        assert e.value.code == 0x06040041
        with pytest.raises(canopen.SdoAbortedError) as e:
            node.sdo[0x6041].raw = 1
        assert e.value.code == 0x06010002
