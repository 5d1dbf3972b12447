"""`pvt record`: read the drives' own data recorders (seed 004), optionally around a job.

    pvt record --config CELL --node N --var NAME|0xIIII:SS (--period-ms T | --total-ms T)
               --trigger movement|error|input|end|continuous|force [--job JOB] [--fast] [--out DIR]

Configures and arms each recorder over SDO, optionally runs JOB, uploads and decodes, and writes
recording.csv, .png and .html (trigger at t = 0) to DIR. --fast runs in virtual time. Exit 0 all read,
1 a node did not trigger or the job failed, 2 bad input.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any, ClassVar

DEFAULT_OUT = Path("record-out")
FILES = ("recording.csv", "recording.png", "recording.html")


def add_parser(sub: Any) -> None:
    p = sub.add_parser("record", help="read the drives' own data recorders (optionally around a job)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", type=Path, default=None, help="cell config TOML (default: configs/demo.toml)")
    p.add_argument("--node", type=int, action="append", required=True, help="node id to record (repeat)")
    p.add_argument("--var", action="append", required=True, metavar="NAME|0xIIII:SS",
                   help="variable to record (repeat, at most 4)")
    period = p.add_mutually_exclusive_group(required=True)
    period.add_argument("--period-ms", type=float, default=None, help="sampling period (n x 0.1 ms)")
    period.add_argument("--total-ms", type=float, default=None,
                        help="time the buffer must span (the shortest period that does)")
    p.add_argument("--trigger", required=True, choices=("movement", "error", "input", "end", "continuous", "force"))
    p.add_argument("--preceding-ms", type=float, default=0.0, help="time kept before the trigger (default 0)")
    p.add_argument("--job", type=Path, default=None, help="job file to run while recording")
    p.add_argument("--fast", action="store_true", help="simulated drives in virtual time")
    p.add_argument("--bus", default=None, help="INTERFACE:CHANNEL (default: the config's)")
    p.add_argument("--bitrate", type=int, default=None, help="CAN bitrate (default: the config's)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output folder (default: record-out)")
    p.add_argument("--timeout", type=float, default=None,
                   help="seconds to wait for the triggers (default: the buffer's span + the job + 10 s)")
    p.add_argument("--upload", choices=("auto", "block", "segmented"), default="auto",
                   help="SDO upload of the buffer: block where the drive has it (auto), or forced")
    p.add_argument("--quiet", action="store_true", help="no live display")
    p.set_defaults(func=run)


# ------------------------------------------------------------------------------------------------------------
# sessions: the same steps in virtual time and in real time


class _FastSession:
    """The cell's simulated drives and the runtime in virtual time (VirtualCell + VirtualRuntime)."""

    mode = "virtual time"

    def __init__(self, cell: Any, traj: Any, nodes: Sequence[int], upload: str):
        from bus.sim.virtual import VirtualCell
        from streamer.recording.recorder_client import ModelSdo, Recorder
        from streamer.runtime.virtual import VirtualRuntime

        positions = _start_positions(traj)
        self.cell = cell
        self.vcell = VirtualCell(cell, initial_positions=positions)
        self.rt = VirtualRuntime(cell, vcell=self.vcell)
        rt = self.rt
        self.recorders = {n: Recorder(ModelSdo(self.vcell.model(n), clock=lambda: rt.now,
                                               emit=lambda frames: rt.drive_frames(frames, rt.now)), direct=True)
                          for n in nodes}
        self.clock_s = 0.0

    def prepare(self) -> None:
        self.rt.ensure_readings()  # the standstill probe moves ip mode: before the recorders are armed

    def idle(self, seconds: float) -> None:
        if seconds > 0:
            self.rt.idle(seconds)

    def run_job(self, traj: Any, on_change: Callable[[Any], None]) -> tuple[str, str]:
        from streamer.splice_planners import make_stop_planner

        result = self.rt.run(traj, stop_planner=make_stop_planner(self.cell, traj),
                             on_sync=lambda core, n: on_change(core))
        outcome = result.coordinator.outcome
        return (outcome.result.value, outcome.message) if outcome is not None else ("unknown", "")

    def now(self) -> float:
        return self.rt.now

    def close(self) -> None:
        pass


class _RealtimeSession:
    """The cell's bus in real time: MasterAdapter with its cycle engine + RealtimeRuntime (+ the simulated drives
    in a process of their own, on a private ipc bus, when the cell's bus is python-can's virtual one)."""

    def __init__(self, cell: Any, traj: Any, nodes: Sequence[int], upload: str):
        from streamer.demo import realtime_cell
        from streamer.recording.recorder_client import CanopenSdo, Recorder
        from streamer.runtime.realtime import RealtimeRuntime

        self.cell = cell
        simulated = cell.bus.interface == "virtual"
        where = "the simulated drives in a process of their own" if simulated else "the drives on the bus"
        self.mode = f"real time on {cell.bus.interface}:{cell.bus.channel}, {where}"
        self._stack = ExitStack()
        self.rt: Any = None
        try:
            self.adapter = self._stack.enter_context(realtime_cell(cell, traj, external_drives=not simulated))
            self.rt = RealtimeRuntime(self.adapter.cell, self.adapter)
        except BaseException:
            self.close()
            raise
        block = {"auto": None, "block": True, "segmented": False}[upload]
        self.recorders = {n: Recorder(CanopenSdo(self.adapter.remote[n]), block=block) for n in nodes}

    def prepare(self) -> None:
        self.rt.ensure_readings()  # the standstill probe moves ip mode: before the recorders are armed
        if not self.adapter.sync_running:
            self.adapter.start_sync()  # SYNC-locked drives tick (and sample) only while SYNC runs

    def idle(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)

    def run_job(self, traj: Any, on_change: Callable[[Any], None]) -> tuple[str, str]:
        from streamer.splice_planners import make_stop_planner

        result = self.rt.run(traj, stop_planner=make_stop_planner(self.cell, traj), on_change=on_change)
        outcome = result.coordinator.outcome
        return (outcome.result.value, outcome.message) if outcome is not None else ("unknown", "")

    def now(self) -> float:
        return time.monotonic()

    def close(self) -> None:
        if self.rt is not None:
            self.rt.close()
        self._stack.close()


def _start_positions(traj: Any) -> dict[int, float] | None:
    if traj is None:
        return None
    return {int(n): float(traj.positions[i, 0]) for i, n in enumerate(traj.node_ids)}


@contextmanager
def _session(cell: Any, traj: Any, nodes: Sequence[int], *, fast: bool, upload: str) -> Iterator[Any]:
    s: Any = _FastSession(cell, traj, nodes, upload) if fast else _RealtimeSession(cell, traj, nodes, upload)
    try:
        yield s
    finally:
        s.close()


# ------------------------------------------------------------------------------------------------------------
# the command


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from planner.config import default_config_path, load_cell
    from planner.errors import PlanningError
    from streamer.recording.drive import DriveRecordingError, RecordRequest, parse_variable, recorded_axes

    console = Console()
    try:
        variables = tuple(parse_variable(v, path="--var") for v in args.var)
        request = RecordRequest(variables, trigger=args.trigger, period_ms=args.period_ms, total_ms=args.total_ms,
                                preceding_ms=args.preceding_ms)
        cell = load_cell(args.config or default_config_path())
        if args.bus is not None or args.bitrate is not None:
            cell = replace(cell, bus=cell.bus.with_spec(args.bus, args.bitrate))
        nodes = list(dict.fromkeys(args.node))
        known = {a.node_id: a.name for a in cell.axes}
        unknown = [n for n in nodes if n not in known]
        if unknown:
            raise PlanningError("CONFIG", f"--node {unknown[0]} is not a node of cell {cell.name!r} (nodes "
                                f"{sorted(known)})", path="node")
        axes = {a.node_id: a for a in cell.axes}
        recorded_axes([axes[n] for n in nodes], [axes[n].name for n in nodes], path="--node")
        traj = None
        if args.job is not None:
            from planner.job import load_job
            from planner.plan import plan_job

            job = load_job(args.job, cell)
            traj = plan_job(job, cell)
            moving = {int(n) for n in traj.node_ids}
            idle_nodes = [n for n in nodes if n not in moving]
            if args.trigger == "movement" and idle_nodes:
                raise PlanningError("CONFIG", f"--node {idle_nodes[0]} is not an axis of the job {args.job} (axes "
                                    f"{list(traj.axis_names)}): its movement trigger would never fire", path="node")
    except (DriveRecordingError, PlanningError) as e:
        print(f"pvt record: {e.code}" + (f" at {e.path}" if e.path else "") + f": {e.message}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"pvt record: {e}", file=sys.stderr)
        return 2
    return _record(console, cell, nodes, {n: known[n] for n in nodes}, request, traj, args)


def _record(console: Any, cell: Any, nodes: list[int], names: dict[int, str], request: Any, traj: Any,
            args: argparse.Namespace) -> int:
    from bus.errors import BusError
    from streamer.recording.drive import DriveRecording, DriveRecordingError
    from streamer.recording.recorder_client import RecorderGroup

    d = request.describe()
    mode = "virtual time" if args.fast else f"real time on {cell.bus.interface}:{cell.bus.channel}"
    console.print(f"[bold]pvt record[/bold]: nodes {nodes}, {', '.join(d['variables'])}; period {d['period_ms']} ms "
                  f"x {d['samples']} samples = {d['span_ms']} ms, {d['preceding_samples']} before the trigger; "
                  f"trigger {request.trigger}; {mode}" + (f"; job {args.job}" if args.job else ""))
    display = _Display(console, nodes, enabled=not args.quiet)
    problems: list[str] = []
    try:
        with _session(cell, traj, nodes, fast=args.fast, upload=args.upload) as s, display:
            display.phase("probing the drives" if not args.fast else "preparing")
            s.prepare()
            group = RecorderGroup(s.recorders, request, idle=s.idle, now=s.now, on_status=display.status)
            display.phase("arming")
            group.start()
            if traj is not None:
                display.phase("running the job")
                job_result, message = s.run_job(traj, display.on_job)
                if job_result != "done":
                    problems.append(f"the job ended {job_result}: {message}")
            timeout = args.timeout if args.timeout is not None else request.span_s + 10.0
            display.phase("waiting for the recorders")
            recordings = group.finish(timeout)
            for n in group.not_triggered:
                problems.append(f"node {n}: no {request.trigger} trigger within {timeout:g} s; stopped and read "
                                "as it was")
            uploads = {n: r.last_upload for n, r in s.recorders.items()}
            upload_s = {n: r.last_upload_s for n, r in s.recorders.items()}
    except (DriveRecordingError, BusError) as e:
        console.print(f"[red]pvt record: {getattr(e, 'code', 'ERROR')}: {e}[/red]")
        return 1
    except TimeoutError as e:
        console.print(f"[red]pvt record: {e}[/red]")
        return 1
    rec = DriveRecording(request, recordings, names=names, upload=uploads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from streamer.recording.drive import write_csv, write_html, write_png

    rows = write_csv(rec, out / "recording.csv")
    write_png(rec, out / "recording.png")
    write_html(rec, out / "recording.html", title=f"pvt record: cell {cell.name}, nodes {nodes}")
    _summary(console, rec, upload_s)
    console.print(f"wrote {rows} samples per variable to {', '.join(str(out / f) for f in FILES)}")
    for p in problems:
        console.print(f"[red]{p}[/red]")
    return 1 if problems else 0


def _summary(console: Any, rec: Any, upload_s: dict[int, float]) -> None:
    from rich.table import Table

    t = Table(title="recorded")
    for col in ("node", "samples", "triggered", "trigger sample", "upload", *(v.name for v in rec.request.variables)):
        t.add_column(col, justify="right")
    for n, r in sorted(rec.nodes.items()):
        ranges = []
        for v in r.variables:
            s = r.values[v.name]
            ranges.append(f"{min(s)}..{max(s)}")
        up = rec.upload.get(n, "")
        t.add_row(str(n), str(r.samples), "yes" if r.triggered else "no",
                  "-" if r.trigger_index is None else str(r.trigger_index),
                  f"{up} {1000 * upload_s.get(n, 0.0):.1f} ms" if up != "direct" else "direct", *ranges)
    console.print(t)


class _Display:
    """A live line: the phase, the job's progress while it runs, each node's recorder status."""

    _NAMES: ClassVar[dict[int, str]] = {0: "stopped", 1: "waiting", 2: "stopped (triggered)", 3: "triggered"}

    def __init__(self, console: Any, nodes: Sequence[int], *, enabled: bool):
        self.console = console
        self.enabled = enabled and console.is_terminal
        self._phase = ""
        self._progress: float | None = None
        self._status: dict[int, int | None] = dict.fromkeys(nodes)
        self._live: Any = None

    def __enter__(self) -> _Display:
        if self.enabled:
            from rich.live import Live

            self._live = Live(self, console=self.console, refresh_per_second=8, transient=True)
            self._live.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._live is not None:
            self._live.__exit__(None, None, None)

    def phase(self, text: str) -> None:
        self._phase = text
        if not self.enabled:
            self.console.print(f"  {text}", style="dim")

    def on_job(self, core: Any) -> None:
        self._progress = core.progress

    def status(self, node: int, status: int) -> None:
        self._status[node] = status

    def __rich__(self) -> Any:
        from rich.progress_bar import ProgressBar
        from rich.table import Table

        t = Table.grid(padding=(0, 1))
        t.add_row(f"[bold]{self._phase}[/bold]")
        if self._progress is not None:
            t.add_row(ProgressBar(total=1.0, completed=self._progress, width=40), f"job {100 * self._progress:5.1f}%")
        for n, s in self._status.items():
            t.add_row(f"node {n}: recorder {'-' if s is None else self._NAMES.get(s & 3, hex(s))}")
        return t
