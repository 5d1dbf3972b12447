"""`pvt hold`: hold a cell's queue: the running job goes on to its end, no further job starts until
`pvt resume`. (A cancel of the running job and `pvt stop` hold the queue too.)

    pvt hold --connect tcp/127.0.0.1:7447 --cell demo

Exit status: 0 held, 2 refused or bad options, 5 no service.
"""

from __future__ import annotations

import argparse
from typing import Any

from streamer.cli import connect


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        "hold",
        help="hold the queue (the running job finishes, no next job starts until resume)",
        description="Hold a cell's queue: the running job goes on, no further job starts until `pvt resume`.",
    )
    connect.add_arguments(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    reply = connect.request(args, "hold", lambda client: client.hold())
    if isinstance(reply, int):
        return reply
    running = reply.get("running_job")
    Console().print(f"queue of cell {args.cell} held ({len(reply.get('queued_jobs') or [])} queued)"
                    + (f"; job {running} runs on to its end" if running else "")
                    + ": `pvt resume` starts the next job", highlight=False, markup=False)
    return connect.EXIT_OK
