"""`pvt status`: one look at a cell: its service, whether the queue is held, the drives and where they
stand, the running job and the queue.

    pvt status --connect tcp/127.0.0.1:7447 --cell demo [--json]

An observer's read (`get pvt/<cell>/service`, docs/api.md section 8). Exit status 0, or 5 when no service
for the cell is up (the cells that are up are named), 2 for bad options.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import time
from typing import Any

from streamer.cli import connect
from streamer.cli.tables import Col, fit_table, number


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        "status",
        help="a cell's service, drives, positions, running job and queue",
        description="Show a cell's job service: ready or not, whether the queue is held, every drive's state "
        "and position, the running job and the queue.",
    )
    p.add_argument("--json", action="store_true", help="the service's status as JSON")
    connect.add_arguments(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from streamer.api.errors import MotionError

    err = Console(stderr=True)
    client = connect.client_or_status(args, "status")
    if isinstance(client, int):
        return client
    with client:
        try:
            status = client.service_status()
        except MotionError as exc:
            err.print(f"pvt status: {exc}", highlight=False, markup=False)
            return connect.EXIT_NO_SERVICE if exc.code in connect.UNREACHED else connect.EXIT_REJECTED
    if args.json:
        print(json.dumps(status, indent=2))
        return connect.EXIT_OK
    out = Console()
    for renderable in render(status, out.width):
        out.print(renderable, highlight=False, markup=False)
    return connect.EXIT_OK


def clock(t: Any) -> str:
    """HH:MM:SS today, else the date too."""
    if not isinstance(t, int | float):
        return "-"
    when = dt.datetime.fromtimestamp(float(t))
    return when.strftime("%H:%M:%S" if when.date() == dt.date.today() else "%Y-%m-%d %H:%M:%S")


def _since(t: Any) -> str:
    if not isinstance(t, int | float):
        return "-"
    s = max(0, int(time.time() - float(t)))
    return f"{s // 3600} h {s % 3600 // 60} min" if s >= 3600 else f"{s // 60} min {s % 60} s"


def headline(status: dict[str, Any]) -> list[str]:
    """The lines above the tables: readiness, the hold, the running job."""
    cell = status.get("cell", "?")
    lines = []
    ready = "ready" if status.get("ready") else f"NOT READY ({status.get('reason') or 'faulted'})"
    lines.append(f"cell {cell}: {ready}; up since {clock(status.get('started_t'))} "
                 f"({_since(status.get('started_t'))})")
    if status.get("held"):
        lines.append(f"queue HELD since {clock(status.get('hold_t'))}: {status.get('hold_reason') or 'held'}; "
                     "`pvt resume` starts the next job")
    running = status.get("running")
    if isinstance(running, dict):
        duration = running.get("planned_duration_s")
        share = f"{100.0 * float(running.get('progress') or 0.0):.1f}%"
        # a home job has no planned duration: its progress is the share of its axes that ended homing
        of = " of its axes homed" if running.get("kind") == "home" else f" of {number(duration)} s"
        lines.append(f"running: job {running.get('job_id')} ({running.get('kind')}), {running.get('state')}, "
                     f"{share}{of}")
    else:
        lines.append("running: no job")
    return lines


def drives_table(status: dict[str, Any], width: int) -> Any:
    drives = [d for d in status.get("drives") or [] if isinstance(d, dict)]
    units = {str(d.get("unit") or "") for d in drives}
    same = units.pop() if len(units) == 1 else None
    unit = f" [{same}]" if same else ""
    columns = [
        Col("axis"), Col("node", justify="right", drop=2), Col("state"),
        Col(f"position{unit}", justify="right"), Col(f"velocity{unit[:-1] + '/s]' if unit else ''}", justify="right"),
        Col("FIFO", justify="right", drop=1),
    ]
    if same is None:
        columns.insert(3, Col("unit"))
    # `referenced` (a home job attained on the axis: docs/api.md) when the runtime reports it
    homing = any("referenced" in d for d in drives)
    if homing:
        columns.append(Col("homed"))
    rows = []
    for d in drives:
        row = [str(d.get("name")), number(d.get("node_id")), str(d.get("state") or "-"),
               number(d.get("position"), 6), number(d.get("velocity"), 4), number(d.get("fifo_fill"))]
        if same is None:
            row.insert(3, str(d.get("unit") or "-"))
        if homing:
            ref = d.get("referenced")
            row.append("yes" if ref is True else "no" if ref is False else "-")
        rows.append(row)
    return fit_table(columns, rows, width, title="drives")


def queue_table(status: dict[str, Any], width: int) -> Any:
    queue = [q for q in status.get("queue") or [] if isinstance(q, dict)]
    rows = [[str(i), str(q.get("job_id")), str(q.get("kind")), number(q.get("planned_duration_s"))]
            for i, q in enumerate(queue, start=1)]
    title = f"queue: {len(queue)} of {status.get('queue_limit', '?')}" + (" (held)" if status.get("held") else "")
    return fit_table([Col("#", justify="right"), Col("job_id"), Col("kind"), Col("planned [s]", justify="right")],
                     rows, width, title=title)


def render(status: dict[str, Any], width: int) -> list[Any]:
    from rich.text import Text

    parts: list[Any] = [Text(line) for line in headline(status)]
    parts.append(drives_table(status, width))
    parts.append(queue_table(status, width))
    return parts
