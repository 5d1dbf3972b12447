"""Simulated drives in a process of their own, as hardware is: `drives_process(cell)`.

A real-time run must not share an interpreter with its drives (each would wait for the other's GIL, and a
test would prove only that our simulation and our master agree). `drives_process` starts
`python -m bus.sim.process`, pickles the cell to its standard input, and waits for "drives on BUS". The
child runs `SimulatedCell` (bus/sim/node.py) at real-time priority where permitted until its standard
input closes, so the drives leave the bus when the parent dies, however it dies. The bus must join
processes: `ipc` (bus/ipc.py) or socketcan.
"""

from __future__ import annotations

import contextlib
import gc
import itertools
import os
import pickle
import signal
import subprocess
import sys
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, replace

from planner.config import BusConfig, CellConfig

# SCHED_FIFO: below the master's cycle engine (80), above its other threads; PVT_DRIVES_PRIORITY=0 in the
# environment: best-effort (tools/vcan-vm: an emulated CPU saturates, and a saturated CPU's real-time budget
# of 95 % then stalls every real-time task, the engine included)
DEFAULT_DRIVES_PRIORITY = 70
DRIVES_PRIORITY = int(os.environ.get("PVT_DRIVES_PRIORITY", str(DEFAULT_DRIVES_PRIORITY))) or None
# how late a SYNC may come before the drives report it lost (EMCY 0x8780), in periods: 1.5 is the manual's
# (seed 003: a jitter of half a period); PVT_SIM_SYNC_GAP_FACTOR in the environment widens it where the
# machine itself holds the master's cycle engine up (the test suite: tests/conftest.py says why)
DRIVES_SYNC_GAP_FACTOR = float(os.environ.get("PVT_SIM_SYNC_GAP_FACTOR", "1.5"))
DRIVES_PER_PROCESS = 6
READY_PREFIX = "drives on "


@dataclass(frozen=True)
class DrivesRequest:
    """What the child runs: the cell's simulated drives on the cell's bus."""

    cell: CellConfig
    positions: Mapping[int, float]
    sync_gap_factor: float = DRIVES_SYNC_GAP_FACTOR
    priority: int | None = DRIVES_PRIORITY


_private_buses = itertools.count()


def joining_bus(cell: CellConfig) -> CellConfig:
    """The cell on a bus that joins processes: python-can's `virtual` bus stays inside one process, so a
    real-time run on it (the embedded default) gets a private `ipc` bus (bus/ipc.py) of its own instead."""
    if cell.bus.interface != "virtual":
        return cell
    channel = f"pvt-{os.getpid()}-{next(_private_buses)}"
    return replace(cell, bus=BusConfig(interface="ipc", channel=channel, bitrate=cell.bus.bitrate))


@contextlib.contextmanager
def drives_process(cell: CellConfig, *, positions: Mapping[int, float] | None = None,
                   sync_gap_factor: float = DRIVES_SYNC_GAP_FACTOR, priority: int | None = DRIVES_PRIORITY,
                   start_timeout_s: float = 60.0) -> Iterator[list[subprocess.Popen[bytes]]]:
    """The cell's simulated drives on its bus in child processes of at most DRIVES_PER_PROCESS drives each (as
    hardware, each drive answers on its own: one interpreter for 24 drives answers the last ones late), from
    their power-on (`positions` in counts by node id, default 0) until the block ends. Raises RuntimeError
    with a child's output if its drives do not come up."""
    axes = cell.axes
    with contextlib.ExitStack() as stack:
        procs = [stack.enter_context(_drives_process(replace(cell, axes=axes[k:k + DRIVES_PER_PROCESS]),
                                                     positions, sync_gap_factor, priority, start_timeout_s))
                 for k in range(0, len(axes), DRIVES_PER_PROCESS)]
        yield procs


@contextlib.contextmanager
def _drives_process(cell: CellConfig, positions: Mapping[int, float] | None, sync_gap_factor: float,
                    priority: int | None, start_timeout_s: float) -> Iterator[subprocess.Popen[bytes]]:
    proc = subprocess.Popen([sys.executable, "-m", "bus.sim.process"], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        assert proc.stdin is not None and proc.stdout is not None
        pickle.dump(DrivesRequest(cell, dict(positions or {}), sync_gap_factor, priority), proc.stdin)
        proc.stdin.flush()
        lines: list[str] = []
        while True:
            line = proc.stdout.readline().decode(errors="replace")
            lines.append(line)
            if not line or line.startswith(READY_PREFIX):
                break
        if not line.startswith(READY_PREFIX):
            proc.wait(start_timeout_s)
            raise RuntimeError(f"the drive process did not start: {''.join(lines).strip()}")
        yield proc
    finally:
        if proc.stdin is not None:
            with contextlib.suppress(OSError):
                proc.stdin.close()  # the child's signal to leave the bus
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()


def main() -> int:
    """The child: read the request, run the drives until standard input closes."""
    from bus.engine import request_realtime
    from bus.sim.node import SimulatedCell

    request: DrivesRequest = pickle.load(sys.stdin.buffer)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # the parent stops us by closing the pipe
    status = request_realtime(request.priority, lock_memory=False)  # before any thread: they inherit it
    cell = request.cell
    sim = SimulatedCell(cell, initial_positions=request.positions, sync_gap_factor=request.sync_gap_factor)
    sim.start()
    # what the drives are made of (canopen's object dictionaries, the models) stays out of every collection: a
    # full one walked it at the drives' real-time priority for 14-25 ms while they streamed (0.2-0.3 ms after)
    gc.collect()
    gc.freeze()
    try:
        print(f"{READY_PREFIX}{cell.bus.interface}:{cell.bus.channel}: {len(cell.axes)} drives of cell "
              f"{cell.name!r} ({status.message}; {gc.get_freeze_count()} objects kept out of the garbage "
              "collector)", flush=True)
        while sys.stdin.buffer.read(4096):
            pass
    finally:
        sim.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
