"""`pvt watch`: a cell's live telemetry in the terminal (rich Live): every drive's state, position,
velocity and FIFO fill, the running job and its progress, the hold, refreshed as samples arrive.

    pvt watch --connect tcp/127.0.0.1:7447 --cell demo            # until Ctrl-C
    pvt watch --cell demo --count 5                                 # five samples, then exit

An observer's read (the `pvt/<cell>/telemetry` subscription, docs/api.md section 9). Into a pipe (not a
terminal) it prints one table per sample instead of redrawing. Exit status 0 (Ctrl-C, --count, --duration),
5 when no service is up or no telemetry arrives within --connect-timeout.
"""

from __future__ import annotations

import argparse
import queue
import time
from typing import Any

from streamer.cli import connect
from streamer.cli.status import clock, drives_table


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        "watch",
        help="live telemetry of a cell in the terminal",
        description="Watch a cell's telemetry live: drive states, positions, velocities, FIFO fill, the running "
        "job and the hold.",
    )
    p.add_argument("--count", type=int, default=None, metavar="N", help="stop after N samples")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--refresh-hz", type=float, default=4.0, metavar="HZ",
                   help="redraws per second in a terminal (default 4)")
    connect.add_arguments(p)
    p.set_defaults(func=run)
    return p


def view(sample: dict[str, Any], width: int) -> Any:
    """One telemetry sample as a renderable: a headline and the drives table."""
    from rich.console import Group
    from rich.text import Text

    job = sample.get("job_id")
    progress = sample.get("progress")
    job_text = "no job" if not job else (
        f"job {job} {sample.get('job_state') or ''}"
        + (f" {100.0 * float(progress):.1f}%" if isinstance(progress, int | float) else ""))
    ready = "ready" if sample.get("ready") else f"NOT READY ({sample.get('reason') or 'faulted'})"
    held = "; queue HELD" if sample.get("held") else ""
    head = Text(f"cell {sample.get('cell')} {clock(sample.get('t'))} #{sample.get('seq')}: {ready}{held}; {job_text}")
    return Group(head, drives_table({"drives": sample.get("axes") or []}, width))


def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.live import Live

    from streamer.api import keys
    from streamer.api.payload import unpack

    err = Console(stderr=True)
    client = connect.client_or_status(args, "watch")
    if isinstance(client, int):
        return client
    out = Console()
    samples: queue.Queue[bytes] = queue.Queue()
    with client:
        sub: Any = client.session.declare_subscriber(keys.telemetry(client.cell),
                                                     lambda s: samples.put(s.payload.to_bytes()))
        seen = 0
        deadline = None if args.duration is None else time.monotonic() + args.duration
        live = Live(console=out, refresh_per_second=max(0.5, args.refresh_hz), transient=False,
                    auto_refresh=True) if out.is_terminal else None
        try:
            if live is not None:
                live.start()
            while args.count is None or seen < args.count:
                wait = args.connect_timeout
                if deadline is not None:
                    wait = min(wait, deadline - time.monotonic())
                    if wait <= 0:
                        break
                try:
                    raw = samples.get(timeout=wait)
                except queue.Empty:
                    if deadline is not None and time.monotonic() >= deadline:
                        break
                    err.print(f"pvt watch: no telemetry from cell {client.cell!r} within "
                              f"{args.connect_timeout:g} s", highlight=False, markup=False)
                    return connect.EXIT_NO_SERVICE
                while not samples.empty():  # draw the newest: never fall behind a fast publisher
                    raw = samples.get_nowait()
                msg = unpack(raw)
                if not isinstance(msg, dict):
                    continue
                seen += 1
                if live is not None:
                    live.update(view(msg, out.width))
                else:
                    out.print(view(msg, out.width), highlight=False, markup=False)
        except KeyboardInterrupt:
            pass
        finally:
            if live is not None:
                live.stop()
            sub.undeclare()
    return connect.EXIT_OK
