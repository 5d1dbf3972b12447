"""configs/drives/epos-ipm.eds and the EPOS IPM drive profile."""

from __future__ import annotations

from pathlib import Path

import canopen
import pytest
from bus_testkit import VDrive, make_axis

from bus import cob
from bus.families import EPOS_IPM
from bus.profile import PdoEntry, PdoLayout
from bus.sim import od as odm
from bus.sim.eds import EDS_PATH, render_eds
from planner.config import DriveSettings

ROOT = Path(__file__).resolve().parents[2]


def test_committed_eds_is_the_rendering_of_the_object_table() -> None:
    assert EDS_PATH == ROOT / "configs" / "drives" / "epos-ipm.eds"
    assert EDS_PATH.read_text(encoding="utf-8") == render_eds(), "run: python -m bus.sim.eds"
    assert EPOS_IPM.eds_path == str(EDS_PATH)


@pytest.mark.parametrize("kind", ["local", "remote"])
def test_eds_loads_in_canopen(kind: str) -> None:
    od = canopen.objectdictionary.import_od(str(EDS_PATH), 7)
    node = canopen.LocalNode(7, od) if kind == "local" else canopen.RemoteNode(7, od)
    assert len(node.tpdo.map) == 4 and len(node.rpdo.map) == 4
    assert od[0x1800][1].default == 0x187 and od[0x1400][1].default == 0x207  # $NODEID
    assert od[0x1014].default == 0x87


REQUIRED = [
    (0x1005, 0), (0x1006, 0), (0x1017, 0), (0x6040, 0), (0x6041, 0), (0x6060, 0), (0x6061, 0), (0x6062, 0),
    (0x6064, 0), (0x6065, 0), (0x606C, 0), (0x607D, 1), (0x607D, 2), (0x607F, 0), (0x6081, 0), (0x6083, 0),
    (0x6084, 0), (0x60C0, 0), (0x60C2, 1), (0x60C2, 2), (0x60C5, 0), (0x20C1, 0), (0x20C4, 1), (0x20C4, 2),
    (0x20C4, 3), *[(0x60C4, s) for s in range(1, 7)], *[(0x1018, s) for s in range(1, 5)],
    *[(b + n, 1) for b in (0x1400, 0x1800) for n in range(4)],
    *[(b + n, s) for b in (0x1600, 0x1A00) for n in range(4) for s in range(0, 9)],
]


def test_issue_objects_and_seed_4_3_6_values() -> None:
    od = canopen.objectdictionary.import_od(str(EDS_PATH), 1)
    for index, sub in REQUIRED:
        entry = od[index]
        obj = entry if isinstance(entry, canopen.objectdictionary.ODVariable) else entry[sub]
        assert obj.index == index and obj.subindex == sub, (hex(index), sub)
    seed = {  # (index, sub): (default, low, high, pdo mappable, access)
        (0x20C4, 2): (4, 0, 63, False, "rw"),
        (0x20C4, 3): (60, 1, 64, False, "rw"),
        (0x60C0, 0): (-1, -1, -1, False, "rw"),
        (0x60C2, 1): (1, 1, 1, False, "rw"),
        (0x60C2, 2): (-3, -3, -3, False, "rw"),
        (0x60C4, 1): (64, None, None, False, "ro"),
        (0x60C4, 3): (0, 0, 0, False, "rw"),
        (0x60C4, 4): (0, 0, 64, False, "rw"),
        (0x60C4, 5): (8, 8, 8, False, "wo"),
        (0x60C4, 6): (0, 0, 1, False, "wo"),
    }
    for (index, sub), (default, low, high, pdo, access) in seed.items():
        s = odm.EPOS_TABLE.objects[(index, sub)]
        got = (s.default, s.low, s.high, s.pdo, s.access)
        assert got == (default, low, high, pdo, access), (hex(index), sub)
    for key in ((0x20C1, 0), (0x20C4, 1), (0x60C4, 2), (0x6041, 0), (0x6040, 0), (0x6062, 0), (0x6064, 0)):
        assert odm.EPOS_TABLE.objects[key].pdo
    assert odm.EPOS_TABLE.objects[(0x20C1, 0)].access == "wo" and odm.EPOS_TABLE.objects[(0x20C1, 0)].dtype.bits == 64


def test_profile_pdo_layout_is_the_cob_contract() -> None:
    layouts = {(p.direction, p.number): p for p in EPOS_IPM.pdo_layouts(make_axis(3), None)}
    assert sorted(layouts) == [("rx", 1), ("rx", 2), ("tx", 1), ("tx", 2)]
    rx1, rx2 = layouts[("rx", 1)], layouts[("rx", 2)]
    tx1, tx2 = layouts[("tx", 1)], layouts[("tx", 2)]
    assert (rx1.cob_id(3), rx1.transmission_type, rx1.size_bytes) == (cob.rpdo1_id(3), 1, 2)
    assert (rx2.cob_id(3), rx2.transmission_type, rx2.size_bytes) == (cob.rpdo2_id(3), 255, 8)
    assert [e.word for e in tx1.entries] == [0x60410010, 0x60C40220]
    assert [e.word for e in tx2.entries] == [0x60640020, 0x60620020]
    assert tx1.cob_id(3) == cob.tpdo1_id(3) and tx2.cob_id(3) == cob.tpdo2_id(3)
    assert EPOS_IPM.record_cob_id(3) == cob.rpdo2_id(3) and EPOS_IPM.controlword_cob_id(3) == cob.rpdo1_id(3)
    assert EPOS_IPM.fifo_depth == 64 and EPOS_IPM.kind == "fifo"
    assert PdoEntry.from_word(0x20C10040) == PdoEntry(0x20C1, 0, 64)
    with pytest.raises(ValueError):
        PdoLayout("tx", 1, 0x180, 1, (PdoEntry(0x6064, 0, 32),) * 3)
    with pytest.raises(KeyError):
        EPOS_IPM.obj("no such object")


def test_configuration_is_accepted_and_in_range() -> None:
    axis = make_axis(2)
    writes = EPOS_IPM.configuration(axis, DriveSettings(underflow_warning=6, overflow_warning=50), 4)
    values = {(w.index, w.sub): w.value for w in writes}
    assert values[(0x6060, 0)] == 7 and values[(0x60C0, 0)] == -1
    assert values[(0x20C4, 2)] == 6 and values[(0x20C4, 3)] == 50 and values[(0x1006, 0)] == 4000
    for w in writes:
        odm.check_value(odm.EPOS_TABLE.objects[(w.index, w.sub)], w.value)
    # the mapping is only written while the PDO is invalid (CiA 301 order)
    order = [(w.index, w.sub, w.value) for w in writes]
    first_map = next(i for i, (ix, s, _) in enumerate(order) if ix == 0x1A00)
    disable = next(i for i, (ix, s, v) in enumerate(order) if (ix, s) == (0x1800, 1) and v & 0x80000000)
    assert disable < first_map
    # the simulated drive accepts every write (the SDO path is tested in test_bus_network.py)
    d = VDrive(axis, sync_period_ms=4)
    assert d.model.sdo_read(0x1A00, 0) == 2 and d.model.sdo_read(0x1601, 1) == 0x20C10040
    assert d.model.sdo_read(0x1402, 1) & 0x80000000 and d.model.sdo_read(0x1803, 1) & 0x80000000
