"""Submit a motion job to a cell's job service and follow it to its end.

    pvt serve --config configs/demo.toml --sim        # in another terminal
    python examples/submit_job.py --connect tcp/127.0.0.1:7447 --cell demo

Shows the client API: wait for the service, submit (the answer comes after planning), iterate the
job's events in order, get the final status, and handle errors by their code.
"""

from __future__ import annotations

import argparse
import sys

from streamer.api.client import MotionClient
from streamer.api.errors import JobFailedError, MotionError

# A jerk-limited point-to-point move of two joints (radians), all axes arriving together.
JOB = {"kind": "move", "axes": ["j1", "j2"], "target": [0.3, -0.2], "mode": "absolute"}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--connect", default="tcp/127.0.0.1:7447", help="Zenoh endpoint of the service")
    parser.add_argument("--cell", default="demo", help="cell name")
    parser.add_argument("--timeout", type=float, default=60.0, help="seconds to wait for the job")
    args = parser.parse_args(argv)

    with MotionClient(connect=args.connect, cell=args.cell) as client:
        try:
            client.wait_for_service(timeout=10)
            job = client.submit(JOB)
        except MotionError as err:  # rejected (err.code: SCHEMA, INFEASIBLE, BUSY, ...) or no service
            print(f"rejected: {err.code} {err.path} {err.message}")
            return 2
        print(f"job {job.job_id}: planned {job.planned_duration_s:.3f} s, {job.points} points")
        for event in job.events(timeout=args.timeout):
            progress = f" {100 * event.progress:5.1f}%" if event.progress is not None else ""
            print(f"  #{event.seq} {event.type}{progress}")
        try:
            status = job.wait(timeout=args.timeout)
        except JobFailedError as err:
            print(f"failed: {err.code} (node {err.detail.get('node')}): {err.message}")
            return 1
        print(f"final state: {status.state.value}")
        return 0 if status.state.value == "done" else 1


if __name__ == "__main__":
    sys.exit(main())
