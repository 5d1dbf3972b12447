"""`pvt stop`: stop all; the running job stops on its jerk-limited stop and the queue holds until `pvt resume`.

    pvt stop --connect tcp/127.0.0.1:7447 --cell demo             # waits until the axes stand still
    pvt stop --emergency --cell demo

`--emergency`: a stop at each axis' emergency deceleration, or the quick stop on every drive when none is
possible in time; the job fails EMERGENCY_STOP. Exit 0 stopped and held, 2 refused, 5 no service.
"""

from __future__ import annotations

import argparse
from typing import Any

from streamer.cli import connect


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        "stop",
        help="stop all and hold the queue (--emergency: at the emergency deceleration)",
        description="Stop all: the running job stops on its jerk-limited stop trajectory and the queue holds "
        "until `pvt resume`. --emergency: the running job stops at each axis' emergency deceleration; quick stop "
        "(0x000B) on every drive when that cannot be planned in time or nothing runs.",
    )
    p.add_argument("--emergency", action="store_true",
                   help="emergency stop: the running job stops at the emergency deceleration (quick stop on every "
                   "drive when that cannot be planned); resume re-enables them")
    p.add_argument("--no-wait", action="store_true", help="return at once, not when the stopped job has ended")
    connect.add_arguments(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from streamer.api.errors import MotionError

    err = Console(stderr=True)
    out = Console()
    client = connect.client_or_status(args, "stop")
    if isinstance(client, int):
        return client
    with client:
        try:
            reply = client.stop(emergency=args.emergency)
        except MotionError as exc:
            err.print(f"pvt stop: {exc}", highlight=False, markup=False)
            return connect.EXIT_NO_SERVICE if exc.code in connect.UNREACHED else connect.EXIT_REJECTED
        kind = "EMERGENCY STOP" if args.emergency else "stop"
        job_id = reply.get("job_id")
        out.print(f"{kind} of cell {args.cell}: {reply.get('message', '')}"
                  + (f" (job {job_id})" if job_id else ""), highlight=False, markup=False)
        queued = reply.get("queued_jobs") or []
        out.print(f"queue held ({len(queued)} queued): `pvt resume` starts the next job"
                  + (" (it re-enables the drives first)" if args.emergency else ""), highlight=False, markup=False)
        if job_id and not args.no_wait:
            try:
                job = client.job(str(job_id))
                for _ in job.events():  # until the stopped job has ended: the axes stand still
                    pass
                final = job.status()
            except MotionError as exc:
                err.print(f"pvt stop: {exc}", highlight=False, markup=False)
                return connect.EXIT_NO_SERVICE if exc.code in connect.UNREACHED else connect.EXIT_REJECTED
            error = final.error or {}
            out.print(f"job {job_id}: {final.state.value} at {100.0 * final.progress:.1f}% of its plan"
                      + (f" ({error.get('code')})" if error else ""), highlight=False, markup=False)
    return connect.EXIT_OK
