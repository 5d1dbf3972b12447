"""`pvt view`: a page of the cell, live, served on 127.0.0.1 (streamer/view/server.py).

    pvt view --cell demo [--port 8080] [--role observer] [--config configs/demo.toml]

Connects like `pvt watch` (the page reads and acts with this identity) and serves one self-contained page:
positions, following errors, FIFO fills, states, progress, queue and events; for an operator the stop,
emergency stop, hold and resume buttons. The printed URL carries a random token. Runs until Ctrl-C.
"""

from __future__ import annotations

import argparse
import contextlib
import secrets
import threading
from pathlib import Path
from typing import Any

from streamer.cli import connect


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        "view", help="a live page of a cell, with stop/hold/resume for an operator",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--port", type=int, default=8080, help="HTTP port on 127.0.0.1 (default 8080; 0: any free one)")
    p.add_argument("--role", choices=("operator", "observer"), default="operator",
                   help="operator: the page has the stop, emergency stop, hold and resume buttons (the service "
                        "still refuses them to an identity without the operator role); observer: no buttons")
    p.add_argument("--config", type=Path, default=None,
                   help="the cell's config, for its FIFO watermarks (default: configs/demo.toml's)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop serving after S seconds")
    p.add_argument("--no-token", action="store_true",
                   help="serve the page without its token (any local process may then read and, on an operator "
                        "page, press its buttons)")
    connect.add_arguments(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace, *, stop: threading.Event | None = None) -> int:
    from planner.config import default_config_path, load_cell
    from planner.errors import PlanningError
    from streamer.view.server import ViewServer

    try:
        cell = load_cell(args.config or default_config_path())
    except PlanningError as e:
        print(f"pvt view: {e.code}: {e.message}")
        return connect.EXIT_REJECTED
    client = connect.client_or_status(args, "view")
    if isinstance(client, int):
        return client
    stop = stop or threading.Event()
    token = None if args.no_token else secrets.token_urlsafe(18)
    with client, ViewServer(client, role=args.role, port=args.port, token=token,
                            watermarks=(cell.drive.underflow_warning, cell.drive.overflow_warning)) as server:
        print(f"pvt view: cell {client.cell!r} ({args.role} page): open {server.entry_url} ; Ctrl-C stops",
              flush=True)
        with contextlib.suppress(KeyboardInterrupt):
            stop.wait(args.duration)
    return connect.EXIT_OK
