"""`pvt halt`: stop the running job with the normal deceleration (its jerk-limited stop trajectory), without
holding the queue: the next queued job starts from where the axes came to rest. (`pvt stop` also holds the
queue until `pvt resume`; `pvt stop --emergency` is the fastest stop the cell has.)

    pvt halt --connect tcp/127.0.0.1:7447 --cell demo

Exit status: 0 halted (or nothing was moving), 2 refused or bad options, 5 no service.
"""

from __future__ import annotations

import argparse
from typing import Any

from streamer.cli import connect


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        "halt",
        help="stop the running job (normal deceleration); the queue goes on",
        description="Halt: the running job stops on its jerk-limited stop trajectory and ends cancelled; the queue "
        "is not held (the next job starts). `pvt stop` holds the queue too.",
    )
    connect.add_arguments(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    reply = connect.request(args, "halt", lambda client: client.halt())
    if isinstance(reply, int):
        return reply
    job = reply.get("job_id")
    Console().print(f"cell {args.cell}: " + (f"job {job}: {reply.get('message')}" if job else "nothing was moving"),
                    highlight=False, markup=False)
    return connect.EXIT_OK
