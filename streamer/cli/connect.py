"""What the client-side subcommands share (not a subcommand): connection options, finding the cell's service
(naming the cells that are up when `--cell` is wrong), and the exit codes (docs/api.md section 13):

    0  done (or: accepted, answered)        3  the job was cancelled
    1  the job failed                       4  --timeout: still queued or running (not cancelled)
    2  rejected (never accepted) or usage   5  no service, or the service went away: fate unknown
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

from streamer.cli import tls_options

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_REJECTED = 2
EXIT_CANCELLED = 3
EXIT_TIMEOUT = 4
EXIT_NO_SERVICE = 5
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"

# client-side codes that say nothing about the job itself: the service was not reached or went away
UNREACHED = frozenset({"NO_SERVICE", "SERVICE_GONE", "TIMEOUT"})


def add_arguments(p: argparse.ArgumentParser, *, connect_timeout: float = 10.0) -> None:
    """--connect, --cell, --connect-timeout and the security options."""
    p.add_argument("--connect", default=None, action="append", metavar="ENDPOINT",
                   help=f"Zenoh endpoint of the service or a router, repeatable (default {DEFAULT_ENDPOINT})")
    p.add_argument("--cell", default="demo", help="cell name (default demo)")
    p.add_argument("--connect-timeout", type=float, default=connect_timeout, metavar="S",
                   help=f"seconds to find the service and for each of its answers (default {connect_timeout:g})")
    tls_options.add_arguments(p)


def endpoints(args: argparse.Namespace) -> list[str]:
    return list(getattr(args, "connect", None) or [DEFAULT_ENDPOINT])


class Unreachable(Exception):
    """The service could not be used; `status` is the exit code, the message says why (and what is up)."""

    def __init__(self, message: str, status: int = EXIT_NO_SERVICE):
        super().__init__(message)
        self.status = status


def open_client(args: argparse.Namespace, timeout: float | None = None) -> Any:
    """A connected `MotionClient` whose cell's service is up; raises Unreachable (with the cells that are up
    when the cell name is wrong) or Unreachable(EXIT_REJECTED) for a bad cell name or security option."""
    from planner.errors import PlanningError
    from streamer.api.client import MotionClient
    from streamer.api.errors import MotionError
    from streamer.api.security import SecurityError

    wait = args.connect_timeout if timeout is None else timeout
    try:
        client = MotionClient(connect=endpoints(args), cell=args.cell, timeout=wait,
                              security=tls_options.client_security(args))
    except (PlanningError, SecurityError) as exc:  # a cell name against the rule of names, a missing file
        raise Unreachable(f"{getattr(exc, 'code', 'ERROR')}: {getattr(exc, 'message', exc)}", EXIT_REJECTED) from None
    except MotionError as exc:
        raise Unreachable(str(exc)) from None
    except Exception as exc:
        raise Unreachable(f"cannot open the Zenoh session: {exc}") from None
    try:
        find_service(client, wait)
    except BaseException:
        client.close()
        raise
    return client


def find_service(client: Any, timeout: float) -> None:
    """Wait for the cell's liveliness token; else Unreachable naming the cells whose services are up."""
    from streamer.api.errors import MotionError

    try:
        client.wait_for_service(timeout=timeout)
        return
    except MotionError as err:
        try:
            up = [c for c in client.cells(timeout=1.0) if c != client.cell]
        except Exception:
            up = []
        where = ", ".join([client.connect] if isinstance(client.connect, str) else list(client.connect))
        if up:
            raise Unreachable(
                f"no job service for cell {client.cell!r} at {where}; cells up there: {', '.join(up)} "
                "(--cell NAME)"
            ) from None
        raise Unreachable(f"{err.message}; no cell is up there (is `pvt serve` running?)") from None


def client_or_status(args: argparse.Namespace, verb: str) -> Any:
    """`open_client(args)`, or, when the service cannot be reached, its exit status (an int) after
    `pvt VERB: reason` on stderr."""
    from rich.console import Console

    try:
        return open_client(args)
    except Unreachable as exc:
        Console(stderr=True).print(f"pvt {verb}: {exc}", highlight=False, markup=False)
        return exc.status


def request(args: argparse.Namespace, verb: str, call: Callable[[Any], dict[str, Any]]) -> dict[str, Any] | int:
    """One request to the cell's service: `call(client)`'s reply, or, when the service cannot be reached or
    refuses, the exit status after `pvt VERB: reason` on stderr (no service 5, refused 2)."""
    from rich.console import Console

    from streamer.api.errors import MotionError

    err = Console(stderr=True)
    client = client_or_status(args, verb)
    if isinstance(client, int):
        return client
    with client:
        try:
            reply: dict[str, Any] = call(client)
            return reply
        except MotionError as exc:
            err.print(f"pvt {verb}: {exc}", highlight=False, markup=False)
            return EXIT_NO_SERVICE if exc.code in UNREACHED else EXIT_REJECTED
