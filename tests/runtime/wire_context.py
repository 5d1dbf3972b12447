"""What a failed real-time demo test prints besides the report: the frames on the wire around the SYNC the
failure names (every SYNC with its count, the named node's TPDOs with their bytes, times from the first SYNC
shown). A real-time failure is seldom reproduced on demand; CI keeps only what the test printed."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import can

from bus.cob import SYNC_COB_ID, TPDO1_BASE, TPDO2_BASE

_NAMED = re.compile(r"node (\d+)\b.*?\bSYNC (\d+)")


def explain_failure(report: dict[str, Any], out: Path, trace: Any, before: int = 8, after: int = 2) -> str:
    """The report's message, and when it names a node and a SYNC, the wire from `before` SYNCs before that
    SYNC to `after` after it (bus.log in `out`, the SYNCs' times from the run's trace)."""
    message = str(report.get("message", report))
    found = _NAMED.search(message)
    log = out / "bus.log"
    times: dict[int, float] = dict(getattr(trace, "sync_times", {}) or {})
    if found is None or not log.exists() or not times:
        return message
    node, sync = int(found.group(1)), int(found.group(2))
    shown = [k for k in range(sync - before, sync + after + 1) if k in times]
    if not shown:
        return message
    count_at = {round(times[k], 6): k for k in shown}
    last = shown[-1]
    t0, t1 = times[shown[0]], times.get(last + 1, times[last] + 0.02) - 1e-6
    lines = [message, f"the wire around SYNC {sync} (node {node}; ms from SYNC {shown[0]}):"]
    with can.LogReader(str(log)) as reader:
        for msg in reader:
            if not t0 - 1e-6 <= msg.timestamp <= t1:
                continue
            at = f"{1000.0 * (msg.timestamp - t0):9.3f}"
            if msg.arbitration_id == SYNC_COB_ID:
                k = count_at.get(round(msg.timestamp, 6))
                lines.append(f"{at}  SYNC {k if k is not None else '?'}")
            elif msg.arbitration_id in (TPDO1_BASE + node, TPDO2_BASE + node):
                which = "TPDO1" if msg.arbitration_id == TPDO1_BASE + node else "TPDO2"
                data = bytes(msg.data)
                words = [int.from_bytes(data[i : i + 4], "little", signed=True) for i in range(0, len(data) - 3, 4)]
                lines.append(f"{at}    {which} {data.hex(' ')}  (int32: {' '.join(map(str, words))})")
    return "\n".join(lines)
