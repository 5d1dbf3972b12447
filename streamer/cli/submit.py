"""`pvt submit`: send a job file to a cell's job service; with --wait, follow it with a progress bar.

    pvt submit configs/jobs/pick.toml --connect tcp/127.0.0.1:7447 --cell demo --wait
    pvt submit JOB --connect tls/127.0.0.1:7447 --ca ca.pem --cert operator.pem --key operator.key

Exit status: 0 accepted (or, with --wait, done); 1 the job failed or was cancelled; 2 rejected, no
service, or bad usage. Ctrl-C while waiting cancels the job (its jerk-limited stop) and waits for it.
"""

from __future__ import annotations

import argparse
import json
import re
import uuid
from pathlib import Path
from typing import Any

from streamer.cli import tls_options


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        "submit",
        help="submit a job file to a cell's job service",
        description="Submit a job (TOML or JSON job file) to a cell's job service over Zenoh.",
    )
    p.add_argument("job", type=Path, help="job file (TOML or JSON, the planner's job format)")
    p.add_argument(
        "--connect",
        default=None,
        action="append",
        metavar="ENDPOINT",
        help="Zenoh endpoint of the service or a router (default tcp/127.0.0.1:7447)",
    )
    p.add_argument("--cell", default="demo", help="cell name (default demo)")
    p.add_argument(
        "--job-id",
        default=None,
        help="exact job id; resubmitting one is idempotent (default: the file's job_id plus a unique suffix)",
    )
    p.add_argument("--wait", action="store_true", help="follow the job to its end with a progress bar")
    p.add_argument("--put", action="store_true", help="submit by put (fire and forget) instead of a query")
    p.add_argument("--timeout", type=float, default=30.0, help="seconds to wait for the service (default 30)")
    p.add_argument("--json", action="store_true", help="print the reply / final status as JSON")
    tls_options.add_arguments(p)
    p.set_defaults(func=run)
    return p


def run_id(file_job_id: object) -> str:
    """A new job id for one run of a job file: the file's `job_id` (a name) plus a unique suffix, so
    submitting the same file twice runs it twice; --job-id gives an exact (idempotent) id instead."""
    suffix = uuid.uuid4().hex[:8]
    if not isinstance(file_job_id, str) or not file_job_id:
        return uuid.uuid4().hex
    name = re.sub(r"[^A-Za-z0-9_.\-]", "-", file_job_id)[: 64 - len(suffix) - 1]
    return f"{name}-{suffix}"


def _endpoints(args: argparse.Namespace) -> list[str]:
    return list(args.connect or ["tcp/127.0.0.1:7447"])


def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from streamer.api.client import MotionClient, load_job_file
    from streamer.api.errors import JobFailedError, MotionError
    from streamer.api.model import JobState

    console = Console(stderr=True)
    out = Console()
    try:
        body = load_job_file(args.job)
    except MotionError as err:
        console.print(f"[red]pvt submit: {err}[/red]")
        return 2
    job_id = args.job_id or run_id(body.pop("job_id", None))
    try:
        client = MotionClient(
            connect=_endpoints(args),
            cell=args.cell,
            timeout=args.timeout,
            security=tls_options.client_security(args),
        )
    except Exception as exc:
        console.print(f"[red]pvt submit: cannot open the Zenoh session: {exc}[/red]")
        return 2
    with client:
        try:
            client.wait_for_service(timeout=args.timeout)
            job = (
                client.submit_put(body, job_id=job_id)
                if args.put
                else client.submit(body, job_id=job_id, timeout=args.timeout)
            )
        except MotionError as err:
            console.print(f"[red]rejected: {err}[/red]")
            if args.json:
                out.print_json(json.dumps({"error": err.to_dict()}))
            return 2
        if not args.put:
            acc = job.accepted
            if args.json and not args.wait:
                out.print_json(json.dumps(acc))
            else:
                console.print(
                    f"job [bold]{job.job_id}[/bold] {acc.get('state')}"
                    f"{' (existing)' if acc.get('existing') else ''}: planned "
                    f"{acc.get('planned_duration_s', 0.0):.3f} s, {acc.get('points')} points"
                )
        else:
            console.print(f"job [bold]{job.job_id}[/bold] submitted by put")
        if not args.wait:
            return 0
        duration = job.planned_duration_s or 0.0
        try:
            with Progress(
                TextColumn("[bold]{task.fields[state]:>9}"),
                BarColumn(),
                TextColumn("{task.percentage:>5.1f}%"),
                TimeElapsedColumn(),
                console=console,
                transient=False,
            ) as bar:
                task = bar.add_task("job", total=1.0, state="queued")
                try:
                    for ev in job.events(timeout=max(args.timeout, 2 * duration + 10.0)):
                        progress = ev.progress
                        bar.update(
                            task,
                            state=ev.type,
                            completed=progress
                            if progress is not None
                            else (1.0 if ev.type == "done" else None),
                        )
                except KeyboardInterrupt:
                    console.print("[yellow]cancelling...[/yellow]")
                    job.cancel()
                    for ev in job.events(timeout=max(args.timeout, 30.0)):
                        bar.update(task, state=ev.type)
            status = job.wait(timeout=args.timeout)
        except JobFailedError as err:
            console.print(f"[red]failed: {err}[/red]")
            if args.json:
                out.print_json(json.dumps(dict(err.status.raw) if err.status is not None else err.to_dict()))
            return 1
        except MotionError as err:
            console.print(
                f"[red]{'rejected' if err.code not in ('TIMEOUT', 'NO_SERVICE') else 'error'}: {err}[/red]"
            )
            return 2
        if args.json:
            out.print_json(json.dumps(dict(status.raw)))
        else:
            console.print(f"job {job.job_id}: {status.state.value}")
        return 0 if status.state == JobState.DONE else 1
