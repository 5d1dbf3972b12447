"""`pvt jobs`: list the jobs journalled by a cell's job service (read from its SQLite journal).

    pvt jobs --config configs/demo.toml            # the journal next to the config
    pvt jobs --store /var/lib/pvt/demo.jobs.sqlite --state failed --json
    pvt jobs --config configs/demo.toml --events JOB_ID
    pvt jobs --connect tls/127.0.0.1:7447 --cell demo --ca ca.pem --cert observer.pem --key observer.key

Reads the journal directly (no Zenoh, works while the service is down, and while it runs: WAL), or,
with --connect, asks a running service over the job API (an observer's read; docs/security.md).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
from pathlib import Path
from typing import Any

from streamer.cli import tls_options


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        "jobs",
        help="list the jobs in a cell's job journal",
        description="List the jobs journalled by `pvt serve` (every accepted job, its state and result).",
    )
    p.add_argument("--config", type=Path, default=None, help="cell config (default configs/demo.toml)")
    p.add_argument("--store", type=Path, default=None, help="journal file (default: next to the config)")
    p.add_argument(
        "--state", default=None, help="only these states, comma separated (queued,running,done,...)"
    )
    p.add_argument("--limit", type=int, default=50, help="newest N jobs (default 50; 0 = all)")
    p.add_argument("--events", metavar="JOB_ID", default=None, help="print the events of one job instead")
    p.add_argument("--json", action="store_true", help="JSON output")
    p.add_argument(
        "--connect",
        default=None,
        action="append",
        metavar="ENDPOINT",
        help="ask a running service over Zenoh instead of reading the journal file",
    )
    p.add_argument("--cell", default="demo", help="with --connect: the cell name (default demo)")
    p.add_argument("--timeout", type=float, default=10.0, help="with --connect: seconds to wait (default 10)")
    tls_options.add_arguments(p)
    p.set_defaults(func=run)
    return p


def _time(t: float | None) -> str:
    if t is None:
        return "-"
    return dt.datetime.fromtimestamp(t).strftime("%Y-%m-%d %H:%M:%S")


def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    if args.connect:
        return _run_remote(args)

    from planner.config import default_config_path, load_cell
    from planner.errors import PlanningError
    from streamer.api.model import JobState
    from streamer.api.store import JobStore, StoreError, default_store_path

    err = Console(stderr=True)
    out = Console()
    path = args.store
    if path is None:
        config_path = args.config or default_config_path()
        try:
            cell = load_cell(config_path)
        except PlanningError as exc:
            err.print(f"pvt jobs: {exc.code}: {exc.message}")
            return 2
        path = default_store_path(cell.source or str(config_path), cell.name)
    states = None
    if args.state:
        try:
            states = [JobState(s.strip()) for s in args.state.split(",") if s.strip()]
        except ValueError:
            err.print(f"pvt jobs: --state takes {', '.join(s.value for s in JobState)}")
            return 2
    try:
        store = JobStore(path, readonly=True)
    except StoreError as exc:
        if not Path(path).exists():
            if args.json:
                print("[]")
            else:
                err.print(f"no jobs: journal {path} does not exist yet")
            return 0
        err.print(f"pvt jobs: {exc}")
        return 2
    with store:
        if args.events:
            events = store.events(args.events)
            if not events and store.get(args.events) is None:
                err.print(f"pvt jobs: no job {args.events!r} in {path}")
                return 1
            if args.json:
                print(
                    json.dumps(
                        [e.to_wire(store.get(args.events).cell) for e in events],  # type: ignore[union-attr]
                        indent=2,
                    )
                )
                return 0
            table = Table(title=f"events of {args.events}")
            for col in ("seq", "time", "type", "state", "details"):
                table.add_column(col)
            for e in events:
                details = {k: v for k, v in e.data.items() if k != "report"}
                table.add_row(str(e.seq), _time(e.t), e.type.value, e.state.value, json.dumps(details)[:80])
            out.print(table)
            return 0
        records = store.list_jobs(states=states, limit=args.limit or None)
        if args.json:
            print(json.dumps([r.to_status() for r in records], indent=2))
            return 0
        table = Table(title=f"jobs in {path} ({store.count()} total)")
        for col in ("#", "job_id", "kind", "state", "via", "planned s", "points", "submitted", "error"):
            table.add_column(col)
        for r in records:
            error = f"{r.error.get('code')}: {r.error.get('message', '')}"[:60] if r.error else ""
            table.add_row(
                str(r.number),
                r.job_id,
                r.kind,
                r.state.value,
                r.via,
                f"{r.planned_duration_s:.3f}" if r.planned_duration_s is not None else "-",
                str(r.points) if r.points is not None else "-",
                _time(r.submitted_t),
                error,
            )
        out.print(table)
    return 0


def _run_remote(args: argparse.Namespace) -> int:
    """The same listing from a running service's job API (`pvt/<cell>/jobs`, `.../events`)."""
    from rich.console import Console
    from rich.table import Table

    from streamer.api.client import MotionClient
    from streamer.api.errors import MotionError

    err = Console(stderr=True)
    out = Console()
    states = [s.strip() for s in args.state.split(",") if s.strip()] if args.state else None
    try:
        client = MotionClient(
            connect=args.connect, cell=args.cell, timeout=args.timeout, security=tls_options.client_security(args)
        )
    except Exception as exc:
        err.print(f"pvt jobs: cannot open the Zenoh session: {exc}")
        return 2
    with client:
        try:
            client.wait_for_service(timeout=args.timeout)
            if args.events:
                events = [dict(e.data) for e in client.job(args.events).history()]
                if not events:
                    client.job(args.events).status()  # NOT_FOUND for an unknown job
            else:
                statuses = [dict(st.raw) for st in client.jobs(state=states, limit=args.limit or 10_000)]
        except MotionError as exc:
            err.print(f"pvt jobs: {exc}")
            return 1 if exc.code == "NOT_FOUND" else 2
    if args.events:
        if args.json:
            print(json.dumps(events, indent=2))
            return 0
        table = Table(title=f"events of {args.events} (cell {args.cell})")
        for col in ("seq", "time", "type", "state", "details"):
            table.add_column(col)
        for e in events:
            details = {k: v for k, v in e.items() if k not in ("report", "job_id", "cell", "seq", "t", "type", "state")}
            table.add_row(str(e["seq"]), _time(e["t"]), e["type"], e["state"], json.dumps(details)[:80])
        out.print(table)
        return 0
    if args.json:
        print(json.dumps(statuses, indent=2))
        return 0
    table = Table(title=f"jobs of cell {args.cell} at {', '.join(args.connect)}")
    for col in ("#", "job_id", "kind", "state", "via", "planned s", "points", "submitted", "error"):
        table.add_column(col)
    for st in statuses:
        error = st.get("error") or None
        planned = st.get("planned_duration_s")
        table.add_row(
            str(st.get("number", "")),
            str(st.get("job_id", "")),
            str(st.get("kind", "")),
            str(st.get("state", "")),
            str(st.get("via", "")),
            f"{planned:.3f}" if isinstance(planned, int | float) else "-",
            str(st.get("points") if st.get("points") is not None else "-"),
            _time(st.get("submitted_t")),
            f"{error.get('code')}: {error.get('message', '')}"[:60] if isinstance(error, dict) else "",
        )
    out.print(table)
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(prog="pvt")
    sub = parser.add_subparsers()
    add_parser(sub)
    args = parser.parse_args(["jobs", *sys.argv[1:]])
    result: int = args.func(args)
    return result


if __name__ == "__main__":
    sys.exit(main())
