"""`pvt serve`: run the job service of one cell (bus + motion runtime + Zenoh API + job journal).

    pvt serve --config configs/demo.toml --sim
    pvt serve --config cell.toml --bus socketcan:can0 --bitrate 500000 --listen tcp/127.0.0.1:7447

Zenoh from the cell's `[zenoh]` (peer, tcp/127.0.0.1:7447, multicast scouting always off) unless
overridden; `[security]` turns on TLS, logins and roles (docs/security.md). State (journal, lock,
recordings) goes into `--store DIR`, default $XDG_STATE_HOME/pvt, never beside the config. SIGINT/SIGTERM
stop cleanly (queued jobs fail SERVICE_STOPPED, the running one is cancelled).
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from planner.config import default_config_path, load_cell
from planner.errors import PlanningError


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser(
        "serve",
        help="serve one cell's job API over Zenoh",
        description="Serve one cell: motion runtime on its CAN bus, job API over Zenoh, job journal "
        "in SQLite.",
    )
    _arguments(p)
    p.set_defaults(func=run)
    return p


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=Path, default=None, help="cell config (TOML); default configs/demo.toml")
    p.add_argument("--sim", action="store_true", help="simulated drives on an in-process virtual bus")
    p.add_argument(
        "--bus",
        metavar="INTERFACE:CHANNEL",
        default=None,
        help="python-can interface and channel, e.g. socketcan:can0 (default: the config's [bus])",
    )
    p.add_argument("--bitrate", type=int, default=None, help="CAN bitrate (default: the config's)")
    p.add_argument(
        "--mode", choices=("peer", "client", "router"), default=None, help="Zenoh mode (default: config)"
    )
    p.add_argument(
        "--listen",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help="Zenoh listen endpoint, repeatable (default: config, tcp/127.0.0.1:7447)",
    )
    p.add_argument(
        "--connect",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help="Zenoh endpoint to connect to (a router), repeatable",
    )
    p.add_argument("--store", type=Path, default=None, metavar="DIR",
                   help="data directory for the journal and recordings (default: $XDG_STATE_HOME/pvt or "
                        "~/.local/state/pvt); a path ending in .sqlite/.db names the journal file itself")
    p.add_argument("--queue", type=int, default=16, help="queued jobs before BUSY (default 16)")
    p.add_argument("--recordings", type=Path, default=None, metavar="DIR",
                   help="where each job's MCAP recording goes (default: beside the journal, "
                        "<journal stem>.recordings/)")
    p.add_argument("--keep-recordings", type=int, default=200, metavar="N",
                   help="keep the newest N recordings (default 200)")
    p.add_argument("--recordings-max-mb", type=int, default=1024, metavar="MB",
                   help="and at most MB megabytes of them (default 1024)")
    p.add_argument("--no-record", action="store_true", help="do not record jobs")
    p.add_argument("--telemetry-hz", type=float, default=None, help="telemetry rate (default: config, 20 Hz)")
    p.add_argument(
        "--backend",
        default=None,
        metavar="MODULE:FUNCTION",
        help="advanced: the motion backend factory to use instead of the built-in runtime",
    )
    p.add_argument("--log-level", default="INFO", help="logging level (default INFO)")
    from streamer.cli.live_options import add_live_option

    add_live_option(p)


def run(args: argparse.Namespace, *, stop: threading.Event | None = None) -> int:
    """Run until SIGINT/SIGTERM (or until `stop` is set, for embedding)."""
    from streamer.api.store import journal_path

    logging.basicConfig(
        level=getattr(logging, str(args.log_level).upper(), logging.INFO),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    # canopen logs every SDO transfer at INFO: keep the service's own log readable
    logging.getLogger("canopen").setLevel(max(logging.WARNING, logging.getLogger().level))
    config_path = args.config or default_config_path()
    try:
        cell = load_cell(config_path)
    except PlanningError as exc:
        print(f"pvt serve: {exc.code}: {exc.message}", file=sys.stderr)
        return 2
    try:
        bus = cell.bus.with_spec(args.bus, args.bitrate) if args.bus or args.bitrate else None
    except PlanningError as exc:
        print(f"pvt serve: {exc.code}: {exc.message}", file=sys.stderr)
        return 2
    interface, channel = (bus.interface, bus.channel) if bus is not None else (None, None)
    store_path = journal_path(cell.name, args.store)
    stop = stop or threading.Event()
    previous: dict[signal.Signals, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, lambda *_: stop.set())
    try:
        return _serve(args, cell, Path(config_path), store_path, interface, channel, stop)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _serve(
    args: argparse.Namespace,
    cell: Any,
    config_path: Path,
    store_path: Path,
    interface: str | None,
    channel: str | None,
    stop: threading.Event,
) -> int:
    import zenoh

    from streamer.api.backend import DEFAULT_BACKEND, BackendUnavailable, load_backend
    from streamer.api.security import SecurityError
    from streamer.api.service import JobService, ServiceOptions
    from streamer.api.store import JobStore, ServiceLock, StoreError
    from streamer.api.zenoh_config import service_config
    from streamer.recording.files import RecordingRetention
    from streamer.recording.model import RecordingError

    try:  # before the bus and the journal: a security mistake must not start anything
        conf = service_config(
            cell.zenoh,
            mode=args.mode,
            listen=args.listen,
            connect=args.connect,
            security=cell.security,
            base=Path(cell.source or config_path).parent,
        )
    except SecurityError as exc:
        print(f"pvt serve: {exc}", file=sys.stderr)
        return 2
    lock = ServiceLock(store_path)
    try:
        lock.acquire()
        store = JobStore(store_path)
    except StoreError as exc:
        print(f"pvt serve: {exc}", file=sys.stderr)
        return 2
    backend = None
    session: Any = None
    service = None
    live: Any = None
    try:
        try:
            backend = load_backend(
                args.backend or DEFAULT_BACKEND,
                cell,
                sim=args.sim,
                interface=interface,
                channel=channel,
                bitrate=args.bitrate,
            )
        except BackendUnavailable as exc:
            print(f"pvt serve: motion backend unavailable: {exc}", file=sys.stderr)
            return 2
        try:
            session = zenoh.open(conf)
        except zenoh.ZError as exc:
            print(f"pvt serve: cannot open the Zenoh session: {exc}", file=sys.stderr)
            return 2
        try:
            retention = RecordingRetention(max_count=args.keep_recordings,
                                           max_bytes=args.recordings_max_mb * 1024 * 1024)
        except RecordingError as exc:
            print(f"pvt serve: {exc.code}: {exc.message}", file=sys.stderr)
            return 2
        options = ServiceOptions(queue_limit=args.queue, telemetry_hz=args.telemetry_hz,
                                 record_jobs=not args.no_record, recordings=retention,
                                 recordings_dir=str(args.recordings) if args.recordings else None)
        from planner.plan import warm_up  # here: every command's parser imports this module

        warm_up()  # the planner's kernels loaded (compiled on a machine's first run) before the first job
        service = JobService(session, backend, store, options).start()
        if getattr(args, "live", None) is not None:
            live = _start_live(backend, cell, args.live)
        listen = args.listen or list(cell.zenoh.listen)
        print(
            f"pvt serve: cell {cell.name!r} ready on {', '.join(listen) or '(no listen endpoint)'}; "
            f"journal {store_path}"
            + ("; TLS and access control on" if cell.security.enabled else ""),
            flush=True,
        )
        while not stop.wait(0.5):
            pass
        print("pvt serve: stopping", flush=True)
        return 0
    finally:
        if live is not None:
            live.stop(linger_s=0.0)
        if service is not None:
            service.close()
        if session is not None:
            session.close()
        if backend is not None:
            backend.close()
        store.close()
        lock.release()


def _start_live(backend: Any, cell: Any, port: int) -> Any:
    """The live channels of the service's jobs (streamer/live/publisher.py): the running job from the runtime's
    `live` (a backend without one publishes telemetry only), the telemetry the Zenoh API serves, between jobs
    too."""
    from streamer.live.publisher import LiveJob, LivePublisher

    runtime = getattr(backend, "runtime", None)

    def source() -> LiveJob | None:
        running = getattr(runtime, "live", None)
        return None if running is None else LiveJob(*running, cell.sync_period_ms)

    publisher = LivePublisher([(a.name, a.node_id) for a in cell.axes], source=source, telemetry=backend.telemetry,
                              port=port).start()
    print(f"pvt serve: live channels on {publisher.url} (docs/recording.md#live-channels)", flush=True)
    return publisher


def main(argv: Sequence[str] | None = None) -> int:
    """Standalone entry (`python -m streamer.cli.serve ...`), same options as `pvt serve`."""
    parser = argparse.ArgumentParser(prog="pvt serve", description="Serve one cell's job API over Zenoh.")
    _arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
