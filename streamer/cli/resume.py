"""`pvt resume`: release a held queue (after `pvt stop`, a cancel of the running job, or `pvt hold`): the
next queued job starts. After `pvt stop --emergency` it re-enables the drives first. `--reset` also
clears a drive fault (a cell that is not ready for another reason refuses a plain resume).

    pvt resume --connect tcp/127.0.0.1:7447 --cell demo [--reset]

Before a queued job starts, the service checks it still starts where the axes stand: a move is
re-planned from there, a path/timed/pvt job fails INFEASIBLE naming the axis and both positions (unless
it has `start = "current"`). Exit status: 0 resumed, 2 refused (NOT_READY, BUSY) or bad options, 5 no
service.
"""

from __future__ import annotations

import argparse
from typing import Any

from streamer.cli import connect


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        "resume",
        help="release a held queue (after stop, cancel or hold)",
        description="Release a cell's held queue; after an emergency stop, re-enable the drives first.",
    )
    p.add_argument("--reset", action="store_true", help="clear a drive fault (fault reset, re-enable) first")
    connect.add_arguments(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    reply = connect.request(args, "resume", lambda client: client.resume(reset=args.reset))
    if isinstance(reply, int):
        return reply
    queued = reply.get("queued_jobs") or []
    Console().print(
        f"cell {args.cell} resumed{' after a reset' if reply.get('reset') else ''}"
        f"{'' if reply.get('was_held') else ' (it was not held)'}: {len(queued)} job(s) queued"
        + (f", next {queued[0]}" if queued else ""), highlight=False, markup=False)
    return connect.EXIT_OK
