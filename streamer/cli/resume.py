"""`pvt resume`: release a held queue; the next queued job starts.

    pvt resume --connect tcp/127.0.0.1:7447 --cell demo [--reset]

After `pvt stop --emergency` it re-enables the drives first; `--reset` also clears a drive fault. A queued
job must still start where the axes stand (a move is re-planned). Exit 0 resumed, 2 refused, 5 no service.
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
