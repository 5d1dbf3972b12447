"""`pvt submit`: send a job file to a cell's job service; with --wait, follow it with a progress bar.

    pvt submit configs/jobs/pick.toml --connect tcp/127.0.0.1:7447 --cell demo --wait
    pvt submit MOVE --buffer aborting           # a new target for the running move, without stopping

Each run is a new job `<job_id>-<8 hex digits>`; `--job-id` gives the exact id (resubmitting it is
idempotent). `--lead-ms` sets the job's lead. Exit status (streamer/cli/connect.py): 0 accepted (with
--wait: done), 1 failed, 2 rejected or bad usage, 3 cancelled or aborted, 4 --timeout ran out while the
job was queued or running (it goes on), 5 no service or it went away. Ctrl-C while waiting cancels the job.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from rich.markup import escape

from streamer.cli import connect
from streamer.cli.connect import (
    EXIT_CANCELLED,
    EXIT_FAILED,
    EXIT_NO_SERVICE,
    EXIT_OK,
    EXIT_REJECTED,
    EXIT_TIMEOUT,
    UNREACHED,
)


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        "submit",
        help="submit a job file to a cell's job service",
        description="Submit a job (TOML or JSON job file) to a cell's job service over Zenoh. Exit status: "
        "0 done (without --wait: accepted), 1 failed, 2 rejected, 3 cancelled, 4 --timeout while still "
        "queued or running, 5 no service or it went away.",
    )
    p.add_argument("job", type=Path, help="job file (TOML or JSON, the planner's job format)")
    p.add_argument(
        "--job-id",
        default=None,
        help="exact job id; resubmitting one is idempotent (default: the file's job_id plus a unique suffix)",
    )
    p.add_argument("--wait", action="store_true", help="follow the job to its end with a progress bar")
    p.add_argument("--timeout", type=float, default=None, metavar="S",
                   help="with --wait: stop waiting after S seconds, exit 4 (the job goes on); default: wait "
                        "while it is queued or running")
    p.add_argument("--buffer", choices=("queued", "aborting", "buffered"), default=None,
                   help="aborting: replace the running move without stopping; default queued (after the others)")
    p.add_argument("--lead-ms", type=int, default=None, metavar="MS",
                   help="this job's lead time (motion queued ahead; a change or stop acts after it)")
    p.add_argument("--put", action="store_true", help="submit by put (fire and forget) instead of a query")
    p.add_argument("--json", action="store_true", help="print the reply / final status as JSON")
    connect.add_arguments(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from streamer.api.client import load_job_file, run_job_id
    from streamer.api.errors import MotionError

    console = Console(stderr=True)
    out = Console()
    try:
        body = load_job_file(args.job)
        name = body.pop("job_id", None)
        job_id = args.job_id or run_job_id(name)
        if args.buffer is not None:
            body["buffer"] = args.buffer
        if args.lead_ms is not None:
            body["lead_ms"] = args.lead_ms
    except MotionError as err:
        console.print(f"[red]rejected:[/red] {escape(str(err))}", highlight=False)
        return EXIT_REJECTED
    try:
        client = connect.open_client(args)
    except connect.Unreachable as exc:
        console.print(f"[red]pvt submit:[/red] {escape(str(exc))}", highlight=False)
        return exc.status
    with client:
        try:
            job = (
                client.submit_put(body, job_id=job_id)
                if args.put
                else client.submit(body, job_id=job_id, timeout=args.connect_timeout)
            )
        except MotionError as err:
            if err.code in UNREACHED:
                console.print(f"[red]no answer:[/red] {escape(str(err))}; the job may have been accepted: "
                              f"`pvt jobs --connect ... --cell {args.cell}` shows it, or submit again with "
                              f"--job-id {job_id} (idempotent) to find out", highlight=False)
                return EXIT_NO_SERVICE
            console.print(f"[red]rejected:[/red] {escape(str(err))}", highlight=False)
            if args.json:
                out.print_json(json.dumps({"error": err.to_dict()}))
            return EXIT_REJECTED
        if not args.put:
            acc = job.accepted
            if args.json and not args.wait:
                out.print_json(json.dumps(acc))
            else:
                console.print(
                    f"job [bold]{escape(job.job_id)}[/bold] {acc.get('state')}"
                    f"{' (existing)' if acc.get('existing') else ''}: "
                    + ("a home job (nothing planned: the drives search their home positions)"
                       if acc.get("kind") == "home" else
                       f"planned {acc.get('planned_duration_s', 0.0):.3f} s, {acc.get('points')} points")
                    + (", the queue is held: it starts after `pvt resume`" if acc.get("held") else ""),
                    highlight=False,
                )
        else:
            console.print(f"job [bold]{escape(job.job_id)}[/bold] submitted by put", highlight=False)
        if not args.wait:
            return EXIT_OK
        return _follow(job, args, console, out)


def _follow(job: Any, args: argparse.Namespace, console: Any, out: Any) -> int:
    """Follow the job's events to its end with a progress bar; the exit status of its outcome."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from streamer.api.errors import JobFailedError, MotionError
    from streamer.api.model import JobState

    try:
        with Progress(
            TextColumn("[bold]{task.fields[state]:>10}"),
            BarColumn(),
            TextColumn("{task.percentage:>5.1f}%"),
            TimeElapsedColumn(),
            console=console,
            transient=False,
        ) as bar:
            task = bar.add_task("job", total=1.0, state="queued")
            try:
                for ev in job.events(total_timeout=args.timeout):
                    progress = ev.progress
                    bar.update(
                        task,
                        state=ev.type,
                        completed=progress if progress is not None else (1.0 if ev.type == "done" else None),
                    )
            except KeyboardInterrupt:
                console.print("[yellow]cancelling...[/yellow]")
                job.cancel()
                for ev in job.events(timeout=max(args.connect_timeout, 30.0)):
                    bar.update(task, state=ev.type, completed=ev.progress)
        status = job.wait(timeout=args.connect_timeout)
    except JobFailedError as err:
        console.print(f"[red]failed:[/red] {escape(str(err))}", highlight=False)
        if args.json:
            out.print_json(json.dumps(dict(err.status.raw) if err.status is not None else err.to_dict()))
        return EXIT_FAILED
    except MotionError as err:
        if err.code == "TIMEOUT" and args.timeout is not None:
            console.print(f"[yellow]still waiting:[/yellow] {escape(err.message)}; not cancelled: follow it with "
                          f"`pvt status --cell {args.cell}`, stop it with `pvt cancel {job.job_id}`", highlight=False)
            return EXIT_TIMEOUT
        if err.code in UNREACHED:
            console.print(f"[red]service gone:[/red] {escape(str(err))}", highlight=False)
            return EXIT_NO_SERVICE
        console.print(f"[red]rejected:[/red] {escape(str(err))}", highlight=False)  # e.g. a put the service refused
        return EXIT_REJECTED
    if args.json:
        out.print_json(json.dumps(dict(status.raw)))
    else:
        console.print(escape(f"job {job.job_id}: {status.state.value}"), highlight=False)
    if status.state == JobState.DONE:
        return EXIT_OK
    # a job replaced by a change (aborted) did not reach its own end, as a cancelled one
    return EXIT_CANCELLED if status.state in (JobState.CANCELLED, JobState.ABORTED) else EXIT_FAILED
