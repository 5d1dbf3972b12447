"""Stream a fixed corpus of jobs in virtual time and record or compare everything the streamer did: the
regression check for work on the streamer (or on what it uses) that must not change its behaviour.

    .venv/bin/python tools/stream_corpus.py record /tmp/before.json.gz   # on the commit before the change
    .venv/bin/python tools/stream_corpus.py compare /tmp/before.json.gz  # after it: "0 of N cases differ"

The corpus: every example job of configs/jobs/ on every cell of configs/ it fits (`load_job` accepts it),
run as `pvt demo --fast` runs it (streamer/demo.py: the plan from the job's start, the simulated drives
standing there, the stop planner, velocity streams extended chunk by chunk), plus change / cancel /
emergency-stop / velocity cases fed at fixed times as tests/streamer drives them. Virtual time, no
threads, no random numbers: two runs of the same code give the same records.

A case's records, in order: `W` every frame on the wire (start time, COB-ID, data), `E` every event fed to
the core, `S` every frame the core returned, `C` every job state change, then `R` the core's report and the
demo report built from the trace (streamer/report.py). Floats are written with `repr` (to the bit), objects
without a value of their own (planners, callbacks) by their type name, wall-clock durations (`planning_s`)
left out. The corpus file keeps, per case, the records' SHA-256 and the records themselves (gzip JSON), so
`compare` can say at which record two runs first part.
"""

from __future__ import annotations

import argparse
import dataclasses
import enum
import gzip
import hashlib
import json
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bus.events import Cancel  # noqa: E402
from bus.sim.virtual import VirtualCell  # noqa: E402
from planner.config import CellConfig, load_cell  # noqa: E402
from planner.errors import PlanningError  # noqa: E402
from planner.job import job_from_dict, load_job  # noqa: E402
from planner.plan import plan_job, warm_up  # noqa: E402
from planner.trajectory import PvtTrajectory  # noqa: E402
from streamer import demo  # noqa: E402
from streamer.core.attribution import FeedbackLog  # noqa: E402
from streamer.core.coordinator import Coordinator, Reaction  # noqa: E402
from streamer.core.plan_source import Change, EmergencyStop  # noqa: E402
from streamer.report import build_report  # noqa: E402
from streamer.runtime.extension import VelocityChangePlanner  # noqa: E402
from streamer.runtime.virtual import VirtualRuntime  # noqa: E402
from streamer.splice_planners import ChangePlanner, make_emergency_planner, make_stop_planner  # noqa: E402

CELLS = ("demo.toml", "mixed.toml", "xtrapuls.toml")
WALL_CLOCK_FIELDS = frozenset({"planning_s", "wall_s", "cpu_s"})
# three axes of each cell, as tests/streamer uses them
CASE_AXES = {"demo.toml": ["j1", "j2", "j3"], "mixed.toml": ["j1", "j3", "j4"], "xtrapuls.toml": ["j1", "j2", "j3"]}


def fmt(value: Any) -> str:
    """`value` as text that is equal for equal values (floats to the bit) and never shows a memory address."""
    if value is None or isinstance(value, (bool, int, str)):
        return repr(value)
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, enum.Enum):
        return f"{type(value).__name__}.{value.name}"
    if isinstance(value, (bytes, bytearray, memoryview)):
        return bytes(value).hex()
    if isinstance(value, np.ndarray):
        digest = hashlib.sha256(np.ascontiguousarray(value).tobytes()).hexdigest()[:16]
        return f"array{value.shape}{value.dtype}:{digest}"
    if isinstance(value, np.generic):
        return repr(value.item())
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        inner = ", ".join(f"{f.name}={fmt(getattr(value, f.name))}" for f in dataclasses.fields(value)
                          if f.name not in WALL_CLOCK_FIELDS)
        return f"{type(value).__name__}({inner})"
    if isinstance(value, tuple) and hasattr(value, "_fields"):  # a NamedTuple
        inner = ", ".join(f"{k}={fmt(getattr(value, k))}" for k in value._fields)
        return f"{type(value).__name__}({inner})"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(fmt(v) for v in value) + "]"
    if isinstance(value, FeedbackLog):  # its samples, not how it keeps them (in memory or spilled)
        cols = ", ".join(f"{k}=[{', '.join(str(x) for x in getattr(value, k))}]" for k in ("sync", "demand", "actual"))
        return f"FeedbackLog({cols}, last_active_sync={value.last_active_sync!r})"
    if isinstance(value, (set, frozenset)):
        return "{" + ", ".join(sorted(fmt(v) for v in value)) + "}"
    if isinstance(value, Mapping):
        return "{" + ", ".join(f"{fmt(k)}: {fmt(v)}" for k, v in value.items() if k not in WALL_CLOCK_FIELDS) + "}"
    return f"<{type(value).__name__}>"


class RecordingRuntime(VirtualRuntime):
    """The virtual-time runtime, unchanged, with every event the core is fed and every reaction recorded."""

    def __init__(self, cell: CellConfig, records: list[str], **kw: Any):
        self.records = records

        def log(t: float, cob_id: int, data: bytes) -> None:
            records.append(f"W {t!r} {cob_id:03X} {bytes(data).hex()}")

        super().__init__(cell, log=log, **kw)

    def _apply(self, core: Coordinator, ev: Any, t: float) -> None:
        if "handle" not in vars(core):  # the first event of this core: record what it is fed and returns
            handle = core.handle
            records = self.records

            def recorded(e: Any, **kw: Any) -> Reaction:
                records.append(f"E {fmt(e)}" + (f" {fmt(kw)}" if kw else ""))
                reaction = handle(e, **kw)
                records.extend(f"S {s.cob_id:03X} {bytes(s.data).hex()}" for s in reaction.sends)
                records.extend(f"C {fmt(c)}" for c in reaction.changes)
                return reaction

            core.handle = recorded  # type: ignore[method-assign,assignment]
        super()._apply(core, ev, t)


Feed = Callable[[CellConfig, PvtTrajectory, float], object]


def run_case(cell: CellConfig, traj: PvtTrajectory, events: Sequence[tuple[int, Feed]] = (),
             extend: bool = True) -> list[str]:
    """Stream `traj` as `pvt demo --fast` does, feeding `events` ((ms after the start SYNC, make event)) at
    the first SYNC at or after their time; the records of the run."""
    records: list[str] = []
    vcell = VirtualCell(cell, initial_positions=demo.start_positions(cell, traj))
    rt = RecordingRuntime(cell, records, vcell=vcell)
    pending = sorted(events, key=lambda x: x[0])

    def feed(core: Coordinator, sync: int, t: float) -> list[object]:
        s = core.start_sync
        out: list[object] = []
        while pending and s is not None and (sync - s) * cell.sync_period_ms >= pending[0][0]:
            out.append(pending.pop(0)[1](cell, traj, t))
        return out

    from planner.motion.travel import extend_velocity

    kept = demo.KeptChunks(extend_velocity)
    result = rt.run(traj, stop_planner=make_stop_planner(cell, traj), feed=feed, extender=kept)
    # the stream as one trajectory, as `pvt demo` reports it; a changed stream's pieces are no chunks of it
    whole = demo.whole_stream(traj, kept.chunks, result.coordinator) if not events else traj
    core = result.coordinator
    core_report = core.report()
    records.append(f"R core {fmt(core_report)}")
    records.append(f"R settled {result.settled} syncs {result.first_sync}..{result.last_sync}")
    try:
        report: Any = build_report(whole, core_report, result.trace, sync_period_ms=cell.sync_period_ms,
                              first_sync=result.first_sync, last_sync=result.last_sync,
                              readings=rt.settings.readings, time_stamp=cell.time_stamp,
                              setpoints={n: core.setpoints(n) for n in whole.node_ids})
    except Exception as e:  # what the report says of this run is a record like any other
        report = f"{type(e).__name__}: {e}"
    records.append(f"R report {fmt(report)}")
    return records


def _cancel(cell: CellConfig, traj: PvtTrajectory, t: float) -> object:
    return Cancel(t)


def _emergency(cell: CellConfig, traj: PvtTrajectory, t: float) -> object:
    return EmergencyStop(t, make_emergency_planner(cell, traj))


def _emergency_quick(cell: CellConfig, traj: PvtTrajectory, t: float) -> object:
    return EmergencyStop(t)  # no planner: the drives' quick stop


def _change_to(target: Sequence[float], mode: str = "aborting") -> Feed:
    def make(cell: CellConfig, traj: PvtTrajectory, t: float) -> object:
        return Change(t, ChangePlanner(cell, traj, dict(zip(traj.axis_names, target, strict=True))), mode=mode,
                      tag="B")
    return make


def _change_velocity(velocity: Sequence[float]) -> Feed:
    def make(cell: CellConfig, traj: PvtTrajectory, t: float) -> object:
        job = job_from_dict({"kind": "move", "axes": list(traj.axis_names), "mode": "velocity",
                             "velocity": list(velocity)}, cell)
        return Change(t, VelocityChangePlanner(cell, job, tuple(traj.node_ids)), tag="V")
    return make


def cases(only: str | None = None) -> Iterator[tuple[str, Callable[[], list[str]]]]:
    """(name, run) of every case of the corpus, in a fixed order; `only`: the names that contain it."""
    out: list[tuple[str, Callable[[], list[str]]]] = []
    for config in CELLS:
        cell_path = ROOT / "configs" / config
        for job_path in sorted((ROOT / "configs" / "jobs").iterdir()):
            name = f"{config.removesuffix('.toml')}/{job_path.name}"

            def example(cell_path: Path = cell_path, job_path: Path = job_path) -> list[str]:
                try:
                    cell, _job, traj = demo.prepare(cell_path, job_path)
                except PlanningError as e:  # the job fits the cell's axes but is refused: that is a record too
                    return [f"X refused {e.code} {e.message}"]
                return run_case(cell, traj)

            if (only is None or only in name) and _fits(cell_path, job_path):
                out.append((name, example))
        axes = CASE_AXES[config]

        def move_case(events: Sequence[tuple[int, Feed]], cell_path: Path = cell_path, axes: list[str] = axes,
                      target: Sequence[float] = (1.5, -1.0, 1.2),
                      start: Sequence[float] = (0.0, 0.0, 0.0)) -> Callable[[], list[str]]:
            def run() -> list[str]:
                cell = load_cell(cell_path)
                job = job_from_dict({"kind": "move", "axes": axes, "target": list(target)}, cell)
                return run_case(cell, plan_job(job, cell, start=list(start)), events)
            return run

        def velocity_case(events: Sequence[tuple[int, Feed]], cell_path: Path = cell_path,
                          axes: list[str] = axes) -> Callable[[], list[str]]:
            def run() -> list[str]:
                cell = load_cell(cell_path)
                job = job_from_dict({"kind": "move", "axes": axes, "mode": "velocity",
                                     "velocity": [0.1, -0.08, 0.09]}, cell)
                return run_case(cell, plan_job(job, cell, start=[0.0] * len(axes)), events)
            return run

        prefix = config.removesuffix(".toml")
        specials: list[tuple[str, Callable[[], list[str]]]] = [
            ("change-aborting", move_case([(400, _change_to((-0.5, 0.6, -0.8)))])),
            ("change-buffered", move_case([(300, _change_to((0.2, 0.3, -0.4), mode="buffered"))])),
            ("cancel", move_case([(600, _cancel)])),
            ("emergency-stop", move_case([(500, _emergency)])),
            ("velocity-stop", velocity_case([(1500, _cancel)])),
            ("velocity-change-target", velocity_case([(1200, _change_to((0.3, -0.2, 0.25)))])),
            ("velocity-change-velocity", velocity_case([(1000, _change_velocity((-0.05, 0.06, 0.02))),
                                                       (2500, _cancel)])),
        ]
        if config == "demo.toml":
            specials.append(("emergency-quick-stop", move_case([(500, _emergency_quick)])))
        out += [(f"{prefix}/{n}", f) for n, f in specials if only is None or only in f"{prefix}/{n}"]
    yield from out


def _fits(cell_path: Path, job_path: Path) -> bool:
    try:
        load_job(job_path, load_cell(cell_path))
    except PlanningError:
        return False
    return True


def record_all(only: str | None = None) -> dict[str, Any]:
    corpus: dict[str, Any] = {}
    for name, run in cases(only):
        records = run()
        digest = hashlib.sha256("\n".join(records).encode()).hexdigest()
        corpus[name] = {"digest": digest, "records": records}
    return corpus


def differences(before: dict[str, Any], after: dict[str, Any]) -> list[str]:
    """One line per case that differs: where the records first part."""
    out = []
    for name in sorted(set(before) | set(after)):
        old, new = before.get(name), after.get(name)
        if old is None or new is None:
            out.append(f"{name}: only in the {'new run' if old is None else 'saved corpus'}")
            continue
        if old["digest"] == new["digest"]:
            continue
        a, b = old["records"], new["records"]
        i = next((k for k, (x, y) in enumerate(zip(a, b, strict=False)) if x != y), min(len(a), len(b)))
        was = a[i][:300] if i < len(a) else "(end)"
        now = b[i][:300] if i < len(b) else "(end)"
        out.append(f"{name}: record {i} of {len(a)} -> {len(b)}\n    was: {was}\n    now: {now}")
    return out


def save(corpus: dict[str, Any], path: Path) -> None:
    path.write_bytes(gzip.compress(json.dumps(corpus).encode(), compresslevel=6, mtime=0))


def load(path: Path) -> dict[str, Any]:
    data: dict[str, Any] = json.loads(gzip.decompress(path.read_bytes()))
    return data


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    parser.add_argument("action", choices=("record", "compare"))
    parser.add_argument("file", type=Path, nargs="?", default=ROOT / "tools" / "stream_corpus.json.gz")
    parser.add_argument("--only", help="the cases whose name contains this (e.g. demo/ or cancel)")
    args = parser.parse_args(argv)
    warm_up()
    t0 = time.perf_counter()
    corpus = record_all(args.only)
    n_records = sum(len(c["records"]) for c in corpus.values())
    print(f"{len(corpus)} cases streamed ({n_records} records) in {time.perf_counter() - t0:.1f} s")
    if args.action == "record":
        save(corpus, args.file)
        return 0
    before = load(args.file)
    if args.only is not None:
        before = {k: v for k, v in before.items() if args.only in k}
    diff = differences(before, corpus)
    for line in diff:
        print("differs:", line)
    print(f"{len(diff)} of {len(corpus)} cases differ")
    return 1 if diff else 0


if __name__ == "__main__":
    sys.exit(main())
