"""`pvt cancel JOB`: cancel one job. A queued job ends `cancelled` at once; the running one stops on its
jerk-limited stop trajectory (state `cancelling`, then `cancelled`) and the queue holds until `pvt resume`.

    pvt cancel demo-path-1a2b3c4d --connect tcp/127.0.0.1:7447 --cell demo [--wait]

Exit status: 0 the cancel was accepted (or one was already under way), 1 the job had already ended
(nothing to cancel), 2 no such job or bad options, 5 no service; with --wait the job's end: 3 cancelled,
0 done (its end was already queued), 1 failed.
"""

from __future__ import annotations

import argparse
from typing import Any

from streamer.cli import connect


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        "cancel",
        help="cancel a job (the running one stops, and the queue holds until resume)",
        description="Cancel a queued or running job. The running job stops on its jerk-limited stop trajectory "
        "and the queue holds until `pvt resume`.",
    )
    p.add_argument("job_id", metavar="JOB", help="the job's id")
    p.add_argument("--wait", action="store_true", help="wait until the job has ended")
    connect.add_arguments(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from streamer.api.errors import JobFailedError, MotionError
    from streamer.api.model import JobState

    err = Console(stderr=True)
    out = Console()
    client = connect.client_or_status(args, "cancel")
    if isinstance(client, int):
        return client
    with client:
        try:
            job = client.job(args.job_id)
            status = job.cancel()
        except MotionError as exc:
            err.print(f"pvt cancel: {exc}", highlight=False, markup=False)
            return connect.EXIT_NO_SERVICE if exc.code in connect.UNREACHED else connect.EXIT_REJECTED
        raw = status.raw
        requested = bool(raw.get("cancel_requested"))
        out.print(f"job {args.job_id}: {status.state.value}; {raw.get('message') or ''}", highlight=False, markup=False)
        if not requested and status.final:
            return connect.EXIT_FAILED
        if not args.wait:
            return connect.EXIT_OK
        try:
            final = job.wait()
        except JobFailedError as exc:
            out.print(f"job {args.job_id}: failed {exc}", highlight=False, markup=False)
            return connect.EXIT_FAILED
        except MotionError as exc:
            err.print(f"pvt cancel: {exc}", highlight=False, markup=False)
            return connect.EXIT_NO_SERVICE if exc.code in connect.UNREACHED else connect.EXIT_REJECTED
        out.print(f"job {args.job_id}: {final.state.value} at {100.0 * final.progress:.1f}% of its plan",
                  highlight=False, markup=False)
        if final.state == JobState.DONE:
            return connect.EXIT_OK
        return connect.EXIT_CANCELLED if final.state == JobState.CANCELLED else connect.EXIT_FAILED
