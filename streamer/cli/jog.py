"""`pvt jog AXIS +|-`: move one axis at a constant velocity while the command runs, then stop it.

    pvt jog j1 + --connect tcp/127.0.0.1:7447 --cell demo        # until Ctrl-C
    pvt jog j2 - --speed 0.05 --for 2 --cell demo

An endless velocity move on one axis of an idle cell, then a halt (the queue is not held: a jog is not an
abort); it brakes by itself before the position limit. Exit 0 jogged and stopped, 1 failed, 2 refused or
bad options, 5 no service.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import threading
import time
from collections.abc import Iterator
from typing import Any

from streamer.cli import connect

DEFAULT_SPEED_SHARE = 0.1  # of the axis' velocity limit, when no --speed is given
POLL_S = 0.1


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        "jog",
        help="move one axis at a constant velocity while the command runs (Ctrl-C or --for), then stop",
        description="Jog: a velocity move of one axis of an idle cell until Ctrl-C or --for seconds, then a "
        "halt (jerk-limited stop; the queue is not held). The axis brakes by itself before its position limit.",
    )
    p.add_argument("axis", help="the axis to move (its name in the cell)")
    p.add_argument("direction", choices=["+", "-"], help="+ positive, - negative direction")
    p.add_argument("--speed", type=float, default=None, metavar="V",
                   help="velocity in the axis' unit per second (default: 10%% of its velocity limit)")
    p.add_argument("--for", dest="for_s", type=float, default=None, metavar="S",
                   help="stop after S seconds of motion (default: when the command is interrupted, Ctrl-C)")
    connect.add_arguments(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from streamer.api.errors import MotionError

    err = Console(stderr=True)
    out = Console()

    def say(text: str, *, to: Any = out) -> None:
        to.print(text, highlight=False, markup=False)

    if args.speed is not None and not args.speed > 0.0:
        say(f"pvt jog: --speed must be a positive number of units per second, got {args.speed:g}", to=err)
        return connect.EXIT_REJECTED
    if args.for_s is not None and not args.for_s > 0.0:
        say(f"pvt jog: --for must be a positive number of seconds, got {args.for_s:g}", to=err)
        return connect.EXIT_REJECTED
    client = connect.client_or_status(args, "jog")
    if isinstance(client, int):
        return client
    with client:
        try:
            status = client.service_status()
            refused = _refusal(args, status)
            if refused:
                say(f"pvt jog: {refused}", to=err)
                return connect.EXIT_REJECTED
            unit = (status.get("units") or {}).get(args.axis, "")
            limit = (status.get("velocity_limits") or {}).get(args.axis)
            speed = args.speed if args.speed is not None else DEFAULT_SPEED_SHARE * float(limit or 0.0)
            if not speed > 0.0:
                say(f"pvt jog: the service does not give axis {args.axis!r}'s velocity limit: give --speed", to=err)
                return connect.EXIT_REJECTED
            velocity = speed if args.direction == "+" else -speed
            job = client.submit({"kind": "move", "axes": [args.axis], "mode": "velocity", "velocity": [velocity]})
        except MotionError as exc:
            say(f"pvt jog: {exc}", to=err)
            return connect.EXIT_NO_SERVICE if exc.code in connect.UNREACHED else connect.EXIT_REJECTED
        say(f"jogging {args.axis} at {velocity:+g} {unit}/s (job {job.job_id}); "
            + (f"stops after {args.for_s:g} s" if args.for_s is not None else "Ctrl-C stops it"))
        try:
            return _jog(client, job, args, unit, say, err)
        except MotionError as exc:
            say(f"pvt jog: {exc}", to=err)
            return connect.EXIT_NO_SERVICE if exc.code in connect.UNREACHED else connect.EXIT_FAILED


def _refusal(args: argparse.Namespace, status: dict[str, Any]) -> str:
    axes = [str(a) for a in status.get("axes") or []]
    if args.axis not in axes:
        return f"cell {args.cell!r} has no axis {args.axis!r} (its axes: {', '.join(axes)})"
    if not status.get("ready", True):
        return f"cell {args.cell!r} is not ready: {status.get('reason') or 'faulted'} (`pvt resume --reset`)"
    busy = status.get("running_job")
    queued = status.get("queued_jobs") or []
    if busy or queued:
        return (f"cell {args.cell!r} is busy (running {busy or 'nothing'}, {len(queued)} queued): a jog moves an "
                "idle cell (`pvt stop` first)")
    return ""


@contextlib.contextmanager
def _interrupt_flag() -> Iterator[threading.Event]:
    """An event set by Ctrl-C (SIGINT) while in the block, instead of a KeyboardInterrupt. A KeyboardInterrupt
    raised while the main thread waits inside the Zenoh binding (a status query) could be lost there, and the
    jog would then run on to its software limit; a flag is seen at the next poll whatever the binding does with
    the signal. Outside the main thread (no signal handler can be set there) the flag is never set and
    KeyboardInterrupt keeps its meaning."""
    flag = threading.Event()
    try:
        previous = signal.signal(signal.SIGINT, lambda _sig, _frame: flag.set())
    except ValueError:  # not the main thread
        yield flag
        return
    try:
        yield flag
    finally:
        signal.signal(signal.SIGINT, previous)


def _jog(client: Any, job: Any, args: argparse.Namespace, unit: str, say: Any, err: Any) -> int:
    """Wait while the jog runs (Ctrl-C or --for ends it), then halt it and wait until it has ended."""
    started: float | None = None
    interrupted = False
    try:
        with _interrupt_flag() as ctrl_c:
            while not ctrl_c.is_set():
                st = job.status()
                if ctrl_c.is_set():
                    break
                if st.final:  # ended by itself: the position limit, a fault, or someone else's stop
                    return _ended(job, st, args, unit, say, err)
                if st.state.value == "running" and started is None:
                    started = time.monotonic()
                if args.for_s is not None and started is not None and time.monotonic() - started >= args.for_s:
                    break
                ctrl_c.wait(POLL_S)
            interrupted = ctrl_c.is_set()
    except KeyboardInterrupt:
        interrupted = True
    # stop it: a halt when it is the running job (the queue is not held), else a cancel of this job
    for _ in range(2):
        try:
            if client.service_status().get("running_job") == job.job_id:
                client.halt()
            else:
                job.cancel()
            break
        except KeyboardInterrupt:  # a second Ctrl-C while asking: ask again, a jog must stop
            continue
    final = job.wait(timeout=60.0)
    if interrupted:
        say("interrupted: stopped")
    return _ended(job, final, args, unit, say, err)


def _ended(job: Any, st: Any, args: argparse.Namespace, unit: str, say: Any, err: Any) -> int:
    state = st.state.value
    here = _position(job, args.axis)
    where = f" at {here:.6g} {unit}" if here is not None else ""
    if state in ("cancelled", "aborted"):
        say(f"{args.axis} stopped{where}")
        return connect.EXIT_OK
    if state == "done":  # a velocity move ends by itself only at the position limit
        say(f"{args.axis} stopped at its software position limit{where}")
        return connect.EXIT_OK
    error = st.error or {}
    say(f"pvt jog: job {job.job_id} {state}: {error.get('code', '')} {error.get('message', '')}".rstrip(), to=err)
    return connect.EXIT_FAILED


def _position(job: Any, axis: str) -> float | None:
    try:
        for d in job.client.service_status().get("drives") or []:
            if d.get("name") == axis:
                x = d.get("position_demand", d.get("position"))
                return None if x is None else float(x)
    except Exception:  # only for the message: the jog itself has ended
        return None
    return None
