"""The failure context a real-time demo test prints (tests/runtime/wire_context.py): the SYNCs around the one
the failure names, by count, and the named node's TPDOs between them, decoded."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import can
import pytest
from wire_context import explain_failure


@pytest.mark.virtual
def test_the_wire_around_the_named_sync(tmp_path: Path) -> None:
    frames = []
    times = {}
    for k in range(10, 20):
        t = 100.0 + 0.01 * k
        times[k] = t
        frames.append(can.Message(timestamp=t, arbitration_id=0x80, is_extended_id=False, data=b""))
        frames.append(can.Message(timestamp=t + 0.004, arbitration_id=0x281, is_extended_id=False,
                                  data=(-1000 * k).to_bytes(4, "little", signed=True) + bytes(4)))
        frames.append(can.Message(timestamp=t + 0.005, arbitration_id=0x282, is_extended_id=False, data=bytes(8)))
    with can.Logger(str(tmp_path / "bus.log")) as log:
        for f in frames:
            log.on_message_received(f)
    report = {"message": "node 1: position demand -14000 at SYNC 15 is 739 counts from the plan's -15000"}
    text = explain_failure(report, tmp_path, SimpleNamespace(sync_times=times), before=2, after=1)
    lines = text.splitlines()
    assert lines[0] == report["message"]
    assert [ln.split()[-1] for ln in lines[2:] if "SYNC" in ln] == ["13", "14", "15", "16"]
    assert sum("TPDO2" in ln for ln in lines) == 4 and "(int32: -15000 0)" in text
    assert text.count("TPDO") == 4  # node 2's frames are left out
    assert explain_failure({"message": "no node named"}, tmp_path, SimpleNamespace(sync_times=times)) == "no node named"
