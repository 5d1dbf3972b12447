"""`pvt jobs`: list the jobs journalled by a cell's job service, and show or export one job's recording.

    pvt jobs --config configs/demo.toml [--state failed] [--json] [--events JOB_ID]
    pvt jobs show JOB_ID [--config CELL | --store PATH] [--json]
    pvt jobs export JOB_ID [--csv PATH] [--html PATH] [--mcap PATH]

Reads the SQLite journal directly (works while the service is down or running: WAL), or with --connect
asks a running service (an observer's read). The journal is `<data dir>/<cell>.jobs.sqlite` (`--store`,
else $XDG_STATE_HOME/pvt); recordings are beside it, or an .mcap path. Tables fit the terminal (cli/tables.py).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import shutil
import sys
from pathlib import Path
from typing import Any

from rich.markup import escape

from streamer.cli import tls_options
from streamer.cli.tables import Col, fit_table, number

STORE_HELP = ("data directory of the journal (default: the state dir, $XDG_STATE_HOME/pvt or ~/.local/state/pvt), "
              "or the journal file itself (.sqlite/.db)")
# one line per job whatever its error: id, kind, state and planned duration always, the error cut to the line
# (the whole of it in `pvt jobs show ID`), the rest while it fits
JOB_COLUMNS = [
    Col("#", justify="right", drop=1), Col("job_id"), Col("kind"), Col("state"), Col("via", drop=4),
    Col("planned [s]", justify="right"), Col("points", justify="right", drop=3), Col("submitted", drop=2),
    Col("error", cut=True, whole="`pvt jobs show ID` has the whole text"),
]
EVENT_COLUMNS = [Col("seq", justify="right"), Col("time", drop=1), Col("type"), Col("state", drop=2),
                 Col("details", text=True)]


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        "jobs",
        help="list the jobs in a cell's job journal",
        description="List the jobs journalled by `pvt serve` (every accepted job, its state and result).",
    )
    p.add_argument("--config", type=Path, default=None, help="cell config (default configs/demo.toml)")
    p.add_argument("--store", type=Path, default=None, help=STORE_HELP)
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
    actions = p.add_subparsers(dest="jobs_action", metavar="{show,export}")
    show = actions.add_parser("show", help="summary of one job and its recording",
                              description="Summary of one job: its journal row and its recording (per axis "
                                          "numbers from the samples, events, messages per channel).")
    show.add_argument("job", metavar="ID", help="job id, or the path of a recording (.mcap)")
    _location(show)
    show.add_argument("--json", action="store_true", default=argparse.SUPPRESS, help="JSON output")
    show.set_defaults(func=run_show)
    export = actions.add_parser("export", help="export one job's recording (CSV, HTML report, MCAP)",
                                description="Export one job's recording: --csv (one row per SYNC), --html "
                                            "(the interactive report, one self-contained file), --mcap (the "
                                            "recording itself, for Foxglove or PlotJuggler).")
    export.add_argument("job", metavar="ID", help="job id, or the path of a recording (.mcap)")
    export.add_argument("--csv", type=Path, default=None, metavar="PATH", help="per-SYNC samples as CSV")
    export.add_argument("--html", type=Path, default=None, metavar="PATH", help="the interactive report")
    export.add_argument("--mcap", type=Path, default=None, metavar="PATH", help="a copy of the MCAP recording")
    _location(export)
    export.set_defaults(func=run_export)
    return p


def _location(p: argparse.ArgumentParser) -> None:
    # SUPPRESS: given before the action (`pvt jobs --store X show ID`) the value is kept
    p.add_argument("--config", type=Path, default=argparse.SUPPRESS, help="cell config (default configs/demo.toml)")
    p.add_argument("--store", type=Path, default=argparse.SUPPRESS, help=STORE_HELP)
    p.add_argument("--recordings", type=Path, default=argparse.SUPPRESS, metavar="DIR",
                   help="recordings folder (default: beside the journal, <journal stem>.recordings/)")


def _journal_path(args: argparse.Namespace) -> Path:
    """The journal of the cell of `--config` in `--store` (a data dir) or the state dir; `--store FILE`
    names the file itself (raises PlanningError for a bad config)."""
    from planner.config import default_config_path, load_cell
    from streamer.api.store import journal_path

    store = getattr(args, "store", None)
    if store is not None and journal_path("x", store) == Path(store).expanduser():
        return Path(store).expanduser()  # the journal file itself: no config needed
    cell = load_cell(getattr(args, "config", None) or default_config_path())
    return journal_path(cell.name, store)


class _Lookup(Exception):
    def __init__(self, message: str, status: int, record: Any = None):
        super().__init__(message)
        self.status = status
        self.record = record  # the journal's record when the job exists but has no recording


def _find(args: argparse.Namespace) -> tuple[Path, Any]:
    """(recording path, journal record or None) of `args.job`: a path to an .mcap file, or a job id."""
    from planner.errors import PlanningError
    from streamer.api.store import JobStore, StoreError
    from streamer.recording.files import RecordingFiles, default_recordings_dir
    from streamer.recording.model import RecordingError

    given = Path(args.job)
    if given.is_file():
        return given, None
    if given.suffix == ".mcap" and len(given.parts) > 1:  # a path, not a job id (ids have no "/")
        raise _Lookup(f"no recording {given}", 1)
    try:
        journal = _journal_path(args)
    except PlanningError as exc:
        raise _Lookup(f"{exc.code}: {exc.message}", 2) from None
    record = None
    if journal.exists():
        try:
            with JobStore(journal, readonly=True) as store:
                record = store.get(args.job)
        except StoreError as exc:
            raise _Lookup(str(exc), 2) from None
    folder = getattr(args, "recordings", None) or default_recordings_dir(journal)
    try:
        path = RecordingFiles(folder).find(args.job)
    except RecordingError as exc:
        raise _Lookup(f"{exc.code}: {exc.message}", 2) from None
    if path is None:
        if record is None:
            raise _Lookup(f"no job {args.job!r} in {journal} and no recording of it in {folder}", 1)
        why = ("it never started, so nothing was recorded" if not record.started_t
               else "retention removed it, or the job streamed nothing (or ran with recording off)")
        raise _Lookup(f"job {args.job!r} ({record.state.value}) has no recording in {folder}: {why}", 1, record)
    return path, record


def run_show(args: argparse.Namespace) -> int:
    from rich.console import Console

    from streamer.recording.export import summary
    from streamer.recording.mcap_io import read_mcap
    from streamer.recording.model import RecordingError

    err = Console(stderr=True)
    try:
        path, record = _find(args)
        rec = read_mcap(path)
    except _Lookup as exc:
        if exc.record is not None:  # the journal still has the job: its row, the error whole
            _show_journal(exc.record.to_status(), str(exc), getattr(args, "json", False))
            err.print(f"pvt jobs show: {exc}", highlight=False, markup=False)
            return exc.status  # 1: no recording (what the journal has is printed)
        err.print(f"pvt jobs show: {exc}", highlight=False, markup=False)
        return exc.status
    except RecordingError as exc:
        err.print(f"pvt jobs show: {exc.code}: {exc.message}", highlight=False, markup=False)
        return 2
    info = summary(rec)
    info["file"] = str(path)
    info["bytes"] = path.stat().st_size
    if record is not None:
        info["journal"] = {k: v for k, v in record.to_status().items() if k != "report"}
    if getattr(args, "json", False):
        print(json.dumps(info, indent=2, default=str))
        return 0
    out = Console()
    journal = info.get("journal")
    state = journal["state"] if journal else rec.result
    out.print(f"[bold]job {rec.job_id or '-'}[/bold] on cell {rec.cell or '-'}: {state}; recording {path} "
              f"({info['bytes']} bytes)")
    if journal:
        for line in _journal_lines(journal):
            out.print(line)
    out.print(f"SYNC {rec.sync_period_ms} ms, first SYNC {rec.first_sync}, start SYNC {rec.start_sync}, "
              f"{info['duration_s']:.3f} s recorded, {info['frames']} CAN frames"
              + (f" ({rec.frames_dropped} more not kept)" if rec.frames_dropped else ""))
    columns = [Col("axis"), Col("node", justify="right", drop=3), Col("samples", justify="right", drop=4),
               Col("max following error [counts]", justify="right"), Col("FIFO min/max", justify="right", drop=2),
               Col("max |demand - plan| [counts]", justify="right"), Col("final actual [counts]", justify="right",
                                                                          drop=1),
               Col("final plan [counts]", justify="right", drop=1)]
    rows = [[a["name"], str(a["node_id"]), str(a["samples"]), _opt(a["max_following_error_counts"]),
             f"{_opt(a['fifo_min'])}/{_opt(a['fifo_max'])}", _opt(a["max_demand_vs_plan_counts"]),
             _opt(a["final_actual_counts"]), _opt(a["final_planned_counts"])] for a in info["axes"]]
    out.print(fit_table(columns, rows, out.width, title="axes (from the recorded samples)"), highlight=False)
    rows = [[f"{e['t']:.3f}", _opt(e["sync"]), e["label"]] for e in info["events"]]
    out.print(fit_table([Col("t [s]", justify="right"), Col("SYNC", justify="right"), Col("event", text=True)],
                        rows, out.width, title="events"), highlight=False)
    out.print("messages: " + ", ".join(f"{topic} {n}" for topic, n in info["messages"].items()), markup=False)
    return 0


def _journal_lines(journal: dict[str, Any]) -> list[str]:
    """The journal's part of `pvt jobs show`: kind and times, the error whole (markup escaped)."""
    lines = [f"kind {journal.get('kind')}, submitted {_time(journal.get('submitted_t'))}, started "
             f"{_time(journal.get('started_t'))}, finished {_time(journal.get('finished_t'))}"]
    e = journal.get("error")
    if isinstance(e, dict):
        lines.append(f"[red]error {escape(str(e.get('code')))}[/red]: " + escape(str(e.get("message", ""))))
    return lines


def _show_journal(journal: dict[str, Any], why: str, as_json: bool) -> None:
    """`pvt jobs show` of a job without a recording (it never started, or retention removed it): what the
    journal has."""
    from rich.console import Console

    journal = {k: v for k, v in journal.items() if k != "report"}
    if as_json:
        print(json.dumps({"journal": journal, "recording": None, "why": why}, indent=2, default=str))
        return
    out = Console()
    out.print(f"[bold]job {escape(str(journal.get('job_id')))}[/bold] on cell {escape(str(journal.get('cell')))}: "
              f"{journal.get('state')}")
    for line in _journal_lines(journal):
        out.print(line)


def run_export(args: argparse.Namespace) -> int:
    from rich.console import Console

    from streamer.recording.export import write_csv, write_html
    from streamer.recording.mcap_io import read_mcap
    from streamer.recording.model import RecordingError

    err = Console(stderr=True)
    if args.csv is None and args.html is None and args.mcap is None:
        err.print("pvt jobs export: say what to write: --csv PATH, --html PATH and/or --mcap PATH")
        return 2
    try:
        path, _record = _find(args)
        rec = read_mcap(path)
    except _Lookup as exc:
        err.print(f"pvt jobs export: {exc}", highlight=False, markup=False)
        return exc.status
    except RecordingError as exc:
        err.print(f"pvt jobs export: {exc.code}: {exc.message}", highlight=False, markup=False)
        return 2
    out = Console()
    try:
        if args.mcap is not None:
            args.mcap.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(path, args.mcap)
            out.print(f"wrote {args.mcap} (MCAP, {args.mcap.stat().st_size} bytes)")
        if args.csv is not None:
            args.csv.parent.mkdir(parents=True, exist_ok=True)
            rows = write_csv(rec, args.csv)
            out.print(f"wrote {args.csv} ({rows} rows, one per SYNC)")
        if args.html is not None:
            args.html.parent.mkdir(parents=True, exist_ok=True)
            fig = write_html(rec, args.html)
            out.print(f"wrote {args.html} (interactive report, {fig.series_traces} curves, "
                      f"{args.html.stat().st_size} bytes)")
    except OSError as exc:
        err.print(f"pvt jobs export: cannot write: {exc}", highlight=False, markup=False)
        return 2
    return 0


def _opt(v: Any) -> str:
    return "-" if v is None else str(v)


def _time(t: float | None) -> str:
    """HH:MM:SS today, else the date too."""
    if t is None:
        return "-"
    when = dt.datetime.fromtimestamp(t)
    return when.strftime("%H:%M:%S" if when.date() == dt.date.today() else "%Y-%m-%d %H:%M:%S")


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    if args.connect:
        return _run_remote(args)

    from planner.errors import PlanningError
    from streamer.api.model import JobState
    from streamer.api.store import JobStore, StoreError

    err = Console(stderr=True)
    out = Console()
    try:
        path = _journal_path(args)
    except PlanningError as exc:
        err.print(f"pvt jobs: {exc.code}: {exc.message}", highlight=False, markup=False)
        return 2
    states = None
    if args.state:
        try:
            states = [JobState(s.strip()) for s in args.state.split(",") if s.strip()]
        except ValueError:
            err.print(f"pvt jobs: --state takes {', '.join(s.value for s in JobState)}", highlight=False, markup=False)
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
        err.print(f"pvt jobs: {exc}", highlight=False, markup=False)
        return 2
    with store:
        if args.events:
            events = store.events(args.events)
            if not events and store.get(args.events) is None:
                err.print(f"pvt jobs: no job {args.events!r} in {path}", highlight=False, markup=False)
                return 1
            if args.json:
                print(
                    json.dumps(
                        [e.to_wire(store.get(args.events).cell) for e in events],  # type: ignore[union-attr]
                        indent=2,
                    )
                )
                return 0
            rows = [[str(e.seq), _time(e.t), e.type.value, e.state.value,
                     _details({k: v for k, v in e.data.items() if k != "report"})] for e in events]
            out.print(fit_table(EVENT_COLUMNS, rows, out.width, title=f"events of {args.events}"), highlight=False)
            return 0
        records = store.list_jobs(states=states, limit=args.limit or None)
        if args.json:
            print(json.dumps([r.to_status() for r in records], indent=2))
            return 0
        rows = [_job_row(r.to_status()) for r in records]
        out.print(fit_table(JOB_COLUMNS, rows, out.width, title=f"jobs in {path} ({store.count()} total)"),
                  highlight=False)
    return 0


def _job_row(st: dict[str, Any]) -> list[str]:
    """One job's row of the jobs table (from its status map): whole values, the error's full message."""
    error = st.get("error")
    planned = st.get("planned_duration_s")
    return [
        str(st.get("number", "")),
        str(st.get("job_id", "")),
        str(st.get("kind", "")),
        str(st.get("state", "")),
        str(st.get("via", "")),
        f"{planned:.3f}" if isinstance(planned, int | float) else "-",
        number(st.get("points")),
        _time(st.get("submitted_t")),
        f"{error.get('code')}: {error.get('message', '')}" if isinstance(error, dict) else "",
    ]


def _details(data: dict[str, Any]) -> str:
    """An event's own fields, as `key=value` words (the table wraps them; nothing is cut)."""
    skip = ("job_id", "cell", "seq", "t", "type", "state", "report")
    parts = []
    for k, v in data.items():
        if k in skip:
            continue
        if isinstance(v, float):
            parts.append(f"{k}={number(v)}")
        elif isinstance(v, dict | list):
            parts.append(f"{k}={json.dumps(v, separators=(',', ':'))}")
        else:
            parts.append(f"{k}={v}")
    return " ".join(parts)


def _run_remote(args: argparse.Namespace) -> int:
    """The same listing from a running service's job API (`pvt/<cell>/jobs`, `.../events`)."""
    from rich.console import Console

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
        err.print(f"pvt jobs: cannot open the Zenoh session: {exc}", highlight=False, markup=False)
        return 2
    with client:
        try:
            from streamer.cli.connect import Unreachable, find_service

            find_service(client, args.timeout)
        except Unreachable as exc:
            err.print(f"pvt jobs: {exc}", highlight=False, markup=False)
            return exc.status
        try:
            if args.events:
                events = [dict(e.data) for e in client.job(args.events).history()]
                if not events:
                    client.job(args.events).status()  # NOT_FOUND for an unknown job
            else:
                statuses = [dict(st.raw) for st in client.jobs(state=states, limit=args.limit or 10_000)]
        except MotionError as exc:
            err.print(f"pvt jobs: {exc}", highlight=False, markup=False)
            return 1 if exc.code == "NOT_FOUND" else 2
    if args.events:
        if args.json:
            print(json.dumps(events, indent=2))
            return 0
        rows = [[str(e["seq"]), _time(e["t"]), str(e["type"]), str(e["state"]), _details(e)] for e in events]
        out.print(fit_table(EVENT_COLUMNS, rows, out.width, title=f"events of {args.events} (cell {args.cell})"),
                  highlight=False)
        return 0
    if args.json:
        print(json.dumps(statuses, indent=2))
        return 0
    out.print(fit_table(JOB_COLUMNS, [_job_row(st) for st in statuses], out.width,
                        title=f"jobs of cell {args.cell} at {', '.join(args.connect)}"), highlight=False)
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
