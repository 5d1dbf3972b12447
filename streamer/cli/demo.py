"""`pvt demo`: plan the default 6-axis path and stream it to simulated drives.

Real time at the cell's SYNC period: the simulated drives in a process of their own on a private ipc bus (or
the cell's bus, --bus), the cycle engine in another, a live progress bar of every FIFO; --fast runs the same
core and drives in virtual time, in one process. Writes report.json, motion.png (not with --no-plot), bus.log
(candump -L) and job.mcap to --out (default demo-out/). Exit 0 done with every guarantee met, 1 failed or a
guarantee missed, 2 rejected. --axes N runs the job on N axes. A velocity job runs until its chunk that brakes
before the position limits; a home job is refused (`pvt serve --sim` runs it).
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

from rich.markup import escape


def add_parser(sub: Any) -> None:
    p = sub.add_parser("demo", help="run the default job end to end on simulated drives",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", type=Path, default=None, help="cell config TOML (default: configs/demo.toml)")
    p.add_argument("--job", type=Path, default=None, help="job file (default: configs/jobs/demo-path.toml)")
    p.add_argument("--axes", type=int, default=None, help="number of axes (the job's axes are repeated)")
    p.add_argument("--sync-ms", type=int, default=None, help="SYNC period in ms (default: the config's)")
    p.add_argument("--fast", action="store_true", help="virtual time: as fast as possible, same core and drives")
    p.add_argument("--out", type=Path, default=Path("demo-out"), help="output folder (default: demo-out)")
    p.add_argument("--bus", default=None, help="INTERFACE:CHANNEL, e.g. socketcan:vcan0 (default: the config's)")
    p.add_argument("--bitrate", type=int, default=None, help="CAN bitrate (default: the config's)")
    p.add_argument("--external-drives", action="store_true",
                   help="do not start simulated drives here (they run elsewhere, e.g. `pvt sim`)")
    p.add_argument("--quiet", action="store_true", help="no live display")
    p.add_argument("--no-plot", dest="plot", action="store_false",
                   help="write no motion.png (headless runs: drawing it costs about 3 s of CPU)")
    from streamer.cli.live_options import add_live_option

    add_live_option(p)
    p.add_argument("--live-wait", type=float, default=30.0, metavar="S",
                   help="with --fast --live: wait up to S seconds for a client to subscribe to every axis before "
                        "the job runs (virtual time is over in a blink), default 30")
    p.set_defaults(func=run)


def guarantees(report: dict[str, Any], tolerance_counts: int) -> list[str]:
    """What `pvt demo` promises; an empty list means every promise was kept."""
    problems: list[str] = []
    axes = report["axes"]
    if report["result"] != "done":
        problems.append(f"result is {report['result']!r}: {report.get('message', '')}")
    starts = {a["start_sync"] for a in axes}
    if len(starts) != 1 or None in starts:
        problems.append(f"axes started on different SYNCs: {sorted(map(str, starts))}")
    for a in axes:
        n = a["name"]
        if a["max_deviation_counts"] > tolerance_counts:
            problems.append(f"axis {n}: deviation {a['max_deviation_counts']} counts > tolerance {tolerance_counts}")
        if a.get("unexplained_counts", 0) > 0:
            problems.append(f"axis {n}: demand off the plan by {a['unexplained_counts']} counts more than its "
                            f"clock's stated error explains")
        if a["final_position_error_counts"] != 0:
            problems.append(f"axis {n}: final position error {a['final_position_error_counts']} counts")
        if a["errors"]:
            problems.append(f"axis {n}: errors {a['errors']}")
    return problems


PLANNING_LINE = ("pvt demo: planning the job (the first run on a machine compiles the planner's kernels first, "
                 "once, then they load from the cache in about a second)")
INTERPRETED_LINE = ("pvt demo: planning the job with the planner's kernels interpreted (NUMBA_DISABLE_JIT=1: a "
                    "machine's first `make demo`, which compiles them after the demo; a few seconds)")


def planning_line() -> str:
    """What the demo says before it plans: with the kernels compiled (or compiling first), or interpreted."""
    return INTERPRETED_LINE if os.environ.get("NUMBA_DISABLE_JIT", "0") not in ("", "0") else PLANNING_LINE


def job_kind(path: Path) -> str | None:
    """The `kind` of a job file (TOML for .toml, else JSON, as planner.job.load_job reads it), or None when
    the file cannot be read as one (the demo's own validation then says why)."""
    import json
    import tomllib

    try:
        text = path.read_text(encoding="utf-8")
        data = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except (OSError, UnicodeDecodeError, ValueError, RecursionError):
        return None
    kind = data.get("kind") if isinstance(data, dict) else None
    return kind if isinstance(kind, str) else None


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from planner.errors import PlanningError
    from streamer import demo

    console = Console(stderr=False)
    if args.fast and args.external_drives:
        console.print("[red]error:[/red] --fast and --external-drives do not go together: --fast runs the "
                      "simulated drives here, in virtual time; drives in another process (`pvt sim`) run in real "
                      "time on a bus. Drop one of them.", highlight=False)
        return 2
    if args.job is not None and job_kind(args.job) == "home":
        console.print(f"[red]error SCHEMA at kind:[/red] {escape(str(args.job))} is a home job: `pvt demo` streams a "
                      "planned motion, and a home job plans none (the drives search their home positions in homing "
                      "mode). `pvt plan JOB` shows what it will do; run it through the job service: `pvt serve --sim` "
                      "and `pvt submit JOB --wait` (docs/api.md).", highlight=False)
        return 2
    # shown before planning: a machine's first plan compiles the planner's kernels (planner/jit.py), which
    # takes minutes on a loaded machine, and nothing else would be shown meanwhile
    console.print(planning_line(), highlight=False)
    try:
        # virtual time measures its own simulated drives; in real time the drives on the bus are measured
        # (demo.run_realtime), and the job is planned again when they round otherwise
        cell, job, traj = demo.prepare(args.config, args.job, axes=args.axes, sync_ms=args.sync_ms,
                                       bus=args.bus, bitrate=args.bitrate, commissioned=args.fast)
    except PlanningError as e:
        console.print(f"[red]error {e.code}[/red]" + escape((f" at {e.path}" if e.path else "") + f": {e.message}"),
                      highlight=False)
        return 2
    bus = "a private ipc bus" if cell.bus.interface == "virtual" else f"{cell.bus.interface}:{cell.bus.channel}"
    where = "the drives elsewhere" if args.external_drives else "the drives in a process of their own"
    mode = "virtual time" if args.fast else f"real time on {bus}, {where}"
    console.print(
        f"[bold]pvt demo[/bold]: {traj.n_axes} axes, {traj.duration_s:.2f} s, {traj.n_points} points/axis, "
        f"SYNC {cell.sync_period_ms} ms, {mode}"
        + (" (the first chunk of an endless velocity move: it goes on until it brakes before the position "
           "limits)" if traj.open_ended else "")
    )
    display = _Display(console, traj, cell, enabled=not args.quiet)
    from streamer.live.publisher import LiveJob

    live = _start_live(console, args, cell)
    try:
        with display:
            if args.fast:
                on_start = None
                if live is not None:
                    publisher, slot = live
                    if not publisher.wait_subscribed(args.live_wait):
                        console.print(f"pvt demo: no client subscribed within {args.live_wait:g} s; running anyway",
                                      highlight=False)

                    wall0 = time.time()  # virtual time starts at 0 (run_fast's recording counts from here too)

                    def on_start(plan: Any, core: Any, trace: Any) -> None:
                        slot[0] = LiveJob(plan, core, trace, cell.sync_period_ms, epoch_s=wall0)

                report, _ = demo.run_fast(cell, traj, args.out, on_sync=display.on_sync, on_start=on_start,
                                          plot=args.plot)
            else:
                on_runtime = None
                if live is not None:
                    publisher, slot = live

                    def on_runtime(rt: Any) -> None:
                        slot[1] = rt

                # the drives in a process of their own (`pvt sim`; elsewhere with --external-drives), the
                # cycle engine in another (bus/engine.py)
                report, _ = demo.run_realtime(cell, traj, args.out, external_drives=args.external_drives,
                                              job=job, on_change=display.on_change, on_engine=display.on_engine,
                                              on_runtime=on_runtime, plot=args.plot)
    except Exception as e:  # bus errors, timeouts: say what and where, do not dump a traceback on users
        from bus.errors import BusError

        if isinstance(e, BusError | TimeoutError | RuntimeError):
            console.print(f"[red]demo failed:[/red] {escape(str(e))}")
            return 1
        raise
    finally:
        if live is not None:
            live[0].stop()
    _summary(console, report, args.out, plot=args.plot)
    problems = guarantees(report, job.tolerance_counts)
    for p in problems:
        console.print(f"[red]guarantee missed:[/red] {escape(p)}")
    return 0 if not problems else 1


def _start_live(console: Any, args: argparse.Namespace, cell: Any) -> tuple[Any, list[Any]] | None:
    """With --live: the publisher and its slot ([a LiveJob handed over in virtual time, the real-time
    runtime whose `live` is the running job])."""
    if args.live is None:
        return None
    from streamer.live.publisher import LiveJob, LivePublisher

    slot: list[Any] = [None, None]

    def source() -> Any:
        if slot[1] is not None:
            running = slot[1].live
            return None if running is None else LiveJob(*running, cell.sync_period_ms)
        return slot[0]

    publisher = LivePublisher([(a.name, a.node_id) for a in cell.axes], source=source, port=args.live).start()
    console.print(f"pvt demo: live channels on {publisher.url} (Foxglove: open connection, Foxglove WebSocket; "
                  "layout configs/foxglove-layout.json)", highlight=False, markup=False)
    return publisher, slot


class _Display:
    """A rich progress bar with per-axis FIFO fill, refreshed from the core's counters (read only)."""

    def __init__(self, console: Any, traj: Any, cell: Any, *, enabled: bool):
        self.console = console
        self.traj = traj
        self.cell = cell
        self.enabled = enabled and console.is_terminal
        self._live: Any = None
        self._lock = threading.Lock()
        self._progress = 0.0
        self._fills: dict[int, int | None] = {}
        self._state = "configuring"

    def __enter__(self) -> _Display:
        if self.enabled:
            from rich.live import Live

            # Live renders `self` (its __rich__) on every refresh, so the display follows the counters
            self._live = Live(self, console=self.console, refresh_per_second=8, transient=False)
            self._live.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._live is not None:
            self._live.__exit__(None, None, None)

    def on_change(self, core: Any) -> None:
        # called on the streaming thread for every event: copy three numbers, nothing else
        self._progress = core.progress
        self._fills = core.fifo_fills()
        self._state = core.state.value  # rich's Live redraws from its own thread (refresh_per_second)

    def on_sync(self, core: Any, n: int) -> None:
        self.on_change(core)

    def on_engine(self, adapter: Any) -> None:
        """Say once how the cycle engine runs (real-time priority, or best-effort and why)."""
        status = adapter.engine.realtime if adapter.engine is not None else None
        if status is not None:
            colour = "green" if status.fifo else "yellow"
            self.console.print(f"[{colour}]cycle engine:[/{colour}] {escape(status.message)}", highlight=False)

    def __rich__(self) -> Any:
        return self._render()

    def _render(self) -> Any:
        from rich.progress_bar import ProgressBar
        from rich.table import Table

        t = Table.grid(padding=(0, 1))
        t.add_row(f"[bold]{self._state:>11}[/bold]", ProgressBar(total=1.0, completed=self._progress, width=40),
                  f"{100 * self._progress:5.1f}%")
        for name, node in zip(self.traj.axis_names, self.traj.node_ids, strict=True):
            fill = self._fills.get(node)
            f = 0 if fill is None else fill
            t.add_row(f"{name:>11}", ProgressBar(total=64, completed=f, width=40),
                      f"FIFO {'-' if fill is None else fill:>2}/64")
        return t


def _summary(console: Any, report: dict[str, Any], out: Path, *, plot: bool = True) -> None:
    from rich.text import Text

    from streamer.cli.tables import Col, fit_table

    axes = report["axes"]
    starts = {a["start_sync"] for a in axes}
    common = f", start SYNC {next(iter(starts))} (all axes)" if len(starts) == 1 else ""
    title = (f"{report['result'].upper()}: {report['duration_s']:.2f} s, {report['syncs']} SYNCs, "
             f"{report['frames']} frames, peak bus load {100 * report['bus_load_peak']:.1f}%{common}")
    columns = [
        Col("axis"), Col("node", justify="right", drop=3),
        Col("start SYNC", justify="right", drop=0 if not common else 5), Col("end SYNC", justify="right", drop=2),
        Col("points", justify="right"), Col("FIFO min/max", justify="right"),
        Col("deviation [counts]", justify="right"), Col("following error [counts]", justify="right"),
        Col("final error [counts]", justify="right"), Col("underflow warnings", justify="right", drop=1),
    ]
    rows = [[a["name"], str(a["node_id"]), str(a["start_sync"]), str(a["end_sync"]), str(a["points_sent"]),
             f"{a['min_fifo']}/{a['max_fifo']}", str(a["max_deviation_counts"]),
             str(a["max_following_error_counts"]), str(a["final_position_error_counts"]),
             str(a["underflow_warnings"])] for a in axes]
    console.print(Text(title))
    console.print(fit_table(columns, rows, console.width, more=f"{out / 'report.json'}"), highlight=False)
    for f in report["faults"]:
        console.print(f"[red]fault[/red] {escape(str(f))}", highlight=False)
    names = ("report.json", "motion.png", "bus.log", "job.mcap") if plot else ("report.json", "bus.log", "job.mcap")
    console.print("wrote " + ", ".join(str(out / name) for name in names), highlight=False, markup=False)


def main() -> None:  # pragma: no cover - convenience for `python -m streamer.cli.demo`
    from streamer.cli import main as cli_main

    sys.exit(cli_main(["demo", *sys.argv[1:]]))
