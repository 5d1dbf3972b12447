"""`pvt sim`: run a cell's simulated drives on a CAN bus in real time.

    pvt sim --config configs/demo.toml [--bus socketcan:vcan0] [--stop-on-stdin-eof] [--duration S]

The drives (bus/sim, one canopen LocalNode and drive model per axis) boot, answer SDO, NMT, SYNC and
RPDOs, and send TPDOs, EMCYs and heartbeats until a signal, `--duration`, or standard input closing (a
parent's pipe: the drives leave the bus when it dies, however it dies). Across processes use the `ipc`
bus or socketcan; `virtual` reaches only this process. Threads at real-time priority where permitted.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from dataclasses import replace
from types import FrameType
from typing import Any

from bus.errors import BusError
from bus.sim.motor import PRESETS
from planner.config import default_config_path, load_cell
from planner.errors import PlanningError


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        "sim", help="run the cell's simulated drives on a CAN bus in real time",
        description=__doc__.splitlines()[0] if __doc__ else None)
    p.add_argument("--config", default=str(default_config_path()), help="cell config (TOML)")
    p.add_argument("--bus", default=None,
                   help="INTERFACE:CHANNEL, e.g. socketcan:vcan0 (default: the cell's [bus])")
    p.add_argument("--bitrate", type=int, default=None, help="bit/s (default: the cell's)")
    p.add_argument("--axes", type=int, default=None,
                   help="number of drives (the config's axes repeated, as `pvt demo --axes`)")
    p.add_argument("--sync-ms", type=int, default=None, help="SYNC period the drives expect (default: the config's)")
    p.add_argument("--motor", choices=sorted(PRESETS), default="re35",
                   help="motor/controller preset from seed 000 chapter 7 (default: re35)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    p.add_argument("--sync-gap-factor", type=float, default=1.5,
                   help="SYNC loss when no SYNC comes within this many periods (0x1006) while ip mode "
                        "is active (default 1.5)")
    p.add_argument("--stop-on-stdin-eof", action="store_true",
                   help="stop when standard input closes (a parent process holds it open: the drives leave the "
                        "bus when that process ends, even if it is killed)")
    p.add_argument("--positions", default=None, metavar="NODE=COUNTS,...",
                   help="where drives stand at power-on, in counts (default 0), e.g. 1=0,2=1500")
    p.add_argument("--rt-priority", type=int, default=70,
                   help="SCHED_FIFO priority of the drives' threads, as hardware answers on time (default 70; "
                        "0: best-effort); refused without an rtprio limit or CAP_SYS_NICE, then best-effort")
    p.set_defaults(func=run)
    return p


def parse_positions(text: str | None) -> dict[int, float]:
    """`1=0,2=1500` -> {1: 0.0, 2: 1500.0}; raises ValueError naming the bad item."""
    out: dict[int, float] = {}
    for item in (text or "").split(","):
        if not item.strip():
            continue
        node, sep, value = item.partition("=")
        try:
            if not sep:
                raise ValueError
            out[int(node)] = float(value)
        except ValueError:
            raise ValueError(f"--positions: {item!r} is not NODE=COUNTS") from None
    return out


def run(args: argparse.Namespace, stop: threading.Event | None = None) -> int:
    import bus.ipc  # noqa: F401  (registers the "ipc" interface where the installed entry points predate it)
    from bus.sim.node import SimulatedCell  # canopen only when the command runs

    try:
        cell = load_cell(args.config)
        if args.axes is not None:
            cell = cell.with_axes(args.axes)
        if args.sync_ms is not None:
            cell = replace(cell, sync_period_ms=args.sync_ms)
        bus_config = cell.bus.with_spec(args.bus, args.bitrate)
        positions = parse_positions(args.positions)
    except (PlanningError, ValueError) as e:
        print(f"pvt sim: {e}", file=sys.stderr)
        return 2
    stop = stop or threading.Event()
    previous: dict[signal.Signals, Any] = {}

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, on_signal)
    if args.stop_on_stdin_eof:
        threading.Thread(target=_stop_at_eof, args=(sys.stdin, stop), name="pvt-sim-stdin", daemon=True).start()
    if args.rt_priority:
        # before any thread starts: the drives' threads inherit it
        from bus.engine import request_realtime

        status = request_realtime(args.rt_priority, lock_memory=False)
        if not status.fifo:
            print(f"pvt sim: {status.message}", flush=True)
    try:
        sim = SimulatedCell(cell, bus_config, motor=PRESETS[args.motor], sync_gap_factor=args.sync_gap_factor,
                            initial_positions=positions)
    except ValueError as e:
        print(f"pvt sim: {e}", file=sys.stderr)
        return 2
    try:
        try:
            sim.start()
            nodes = ", ".join(f"{a.name}={a.node_id}" for a in cell.axes)
            print(f"pvt sim: cell {cell.name!r}, {len(cell.axes)} drives ({nodes}) on "
                  f"{bus_config.interface}:{bus_config.channel} @ {bus_config.bitrate} bit/s; Ctrl-C to stop",
                  flush=True)
            stop.wait(args.duration)
        finally:
            sim.stop()  # raises the first error recorded in a bus callback
    except BusError as e:
        print(f"pvt sim: {e.code}: {e}", file=sys.stderr)
        return 1
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    print("pvt sim: stopped", flush=True)
    return 0


def _stop_at_eof(stream: Any, stop: threading.Event) -> None:
    """Read `stream` to its end (whatever is written to it is ignored), then stop the drives."""
    try:
        while stream.read(4096):
            pass
    except (OSError, ValueError):
        pass  # closed under us: the same end
    stop.set()
