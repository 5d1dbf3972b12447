"""The `pvt` command: one entry point, one module per subcommand (this package).

Each subcommand module defines `add_parser(subparsers)` (which sets `func` on its parser) and is
imported only when the command line is built, so `pvt plan` does not pay for Zenoh or canopen.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

# (module, one-line help) in the order `pvt --help` lists them
SUBCOMMANDS: tuple[str, ...] = (
    "streamer.cli.demo",
    "streamer.cli.plan",
    "streamer.cli.serve",
    "streamer.cli.submit",
    "streamer.cli.status",
    "streamer.cli.watch",
    "streamer.cli.view",
    "streamer.cli.jog",
    "streamer.cli.cancel",
    "streamer.cli.stop",
    "streamer.cli.halt",
    "streamer.cli.hold",
    "streamer.cli.resume",
    "streamer.cli.jobs",
    "streamer.cli.sim",
    "streamer.cli.probe",
    "streamer.cli.certs",
    "streamer.cli.record",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pvt",
        description="Time-optimal trajectory planner and PVT streaming service for CANopen servo drives.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in SUBCOMMANDS:
        importlib.import_module(name).add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    result: int = args.func(args)
    return result


if __name__ == "__main__":
    sys.exit(main())
