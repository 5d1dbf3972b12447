"""Job API latency: submit -> accepted reply, and the planner's share of it.

In one run, on loopback, with a Zenoh client and a job service in the same process:

1. planning alone: `job_from_dict` + `plan_job` on the default job (what the service must do before it
   may answer), repeated, p50/p99;
2. submit -> accepted: `MotionClient.submit` of the same job (fresh job_id each time) against a job
   service whose backend plans with the real planner and whose execute() returns at once (no motion:
   the measurement is the API path: Zenoh query, strict decoding, validation, planning, SQLite
   journal with full sync, reply);
3. API overhead alone: the same with a trivial planner (a fixed 1-point plan).

Target: submit->accepted p50 <= 3 x planning p50.

Run: python -m benchmarks.bench_api [--n 50] [--job configs/jobs/<job>.toml]
"""

from __future__ import annotations

import argparse
import importlib
import socket
import statistics
import tempfile
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import zenoh

from planner.config import CellConfig, load_cell
from streamer.api.backend import CancelToken, Emit, MotionBackend, Planned, planned_from_trajectory
from streamer.api.client import MotionClient, load_job_file
from streamer.api.service import JobService
from streamer.api.store import JobStore
from streamer.api.zenoh_config import build_config

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_JOBS = ("configs/jobs/demo-path.toml",)

# The 6-axis path of the demo when no job file is found: 10 waypoints inside every axis' limits.
FALLBACK_JOB: dict[str, Any] = {
    "kind": "path",
    "axes": ["j1", "j2", "j3", "j4", "j5", "j6"],
    "waypoints": [
        [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        [0.3, -0.2, 0.4, 0.5, -0.3, 0.6],
        [0.8, -0.5, 0.9, 1.0, -0.6, 1.2],
        [1.2, -0.3, 1.4, 0.6, -0.2, 1.8],
        [1.0, 0.2, 1.0, 0.0, 0.4, 1.2],
        [0.5, 0.6, 0.3, -0.6, 0.8, 0.4],
        [-0.2, 0.8, -0.4, -1.0, 0.5, -0.4],
        [-0.8, 0.4, -1.0, -0.5, 0.0, -1.0],
        [-0.5, 0.1, -0.5, 0.0, -0.2, -0.5],
        [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    ],
}


class _Backend(MotionBackend):
    """Plans with `plan_fn`; execute() reports done at once (this benchmark measures the API path)."""

    def __init__(
        self,
        cell: CellConfig,
        validate: Callable[[Mapping[str, Any]], Any],
        plan: Callable[[Any], Planned],
    ):
        self.cell = cell
        self._validate = validate
        self._plan = plan

    def validate(self, body: Mapping[str, Any]) -> Any:
        return self._validate(body)

    def plan(self, job: Any, start: Mapping[str, float] | None = None, *,
             last_target: Mapping[str, float | None] | None = None,
             last_direction: Mapping[str, int] | None = None, lead_ms: int | None = None) -> Planned:
        return self._plan(job)  # every benchmark job starts from home (execute does not move)

    def execute(self, planned: Planned, emit: Emit, cancel: CancelToken) -> Mapping[str, Any]:
        return {"result": "done"}

    def telemetry(self) -> Sequence[Mapping[str, Any]]:
        return []

    def ready(self) -> tuple[bool, str]:
        return True, ""

    def reset(self) -> tuple[bool, str]:
        return True, ""

    def close(self) -> None:
        pass


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def _pct(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]


def measure_submit(cell: CellConfig, backend: _Backend, job: Mapping[str, Any], n: int) -> list[float]:
    """Seconds from submit() to the accepted reply, n times (after 3 warm-up submits)."""
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    session: Any = zenoh.open(build_config(listen=[endpoint]))
    with tempfile.TemporaryDirectory() as tmp:
        store = JobStore(Path(tmp) / "bench.jobs.sqlite")  # synchronous=FULL, as in production
        service = JobService(session, backend, store).start()
        try:
            with MotionClient(connect=endpoint, cell=cell.name, timeout=60) as client:
                client.wait_for_service(timeout=10)
                out = []
                for i in range(n + 3):
                    t0 = time.perf_counter()
                    handle = client.submit(job, job_id=uuid.uuid4().hex)
                    dt = time.perf_counter() - t0
                    handle.close()
                    if i >= 3:
                        out.append(dt)
                    while service.queue_length:  # keep the queue from filling up (BUSY)
                        time.sleep(0.001)
                return out
        finally:
            service.close()
            store.close()
            session.close()


def find_job(path: str | None) -> tuple[str, dict[str, Any]]:
    if path:
        return path, load_job_file(path)
    for rel in DEFAULT_JOBS:
        if (ROOT / rel).exists():
            return rel, load_job_file(ROOT / rel)
    return "built-in 6-axis 10-waypoint path", dict(FALLBACK_JOB)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Job API latency benchmark")
    parser.add_argument("--n", type=int, default=50, help="submits per measurement (default 50)")
    parser.add_argument("--job", default=None, help="job file (default: the demo's default job)")
    parser.add_argument("--config", default=str(ROOT / "configs" / "demo.toml"))
    args = parser.parse_args(argv)
    cell = load_cell(args.config)
    label, job = find_job(args.job)
    job.pop("job_id", None)

    rows: list[tuple[str, str]] = []
    trivial = _Backend(
        cell, lambda body: dict(body), lambda j: Planned(job=j, trajectory=None, duration_s=0.0, points=1)
    )
    overhead = measure_submit(cell, trivial, job, args.n)
    rows.append(
        (
            "API overhead only (trivial planner): submit->accepted p50 / p99",
            f"{1e3 * _pct(overhead, 0.5):.2f} ms / {1e3 * _pct(overhead, 0.99):.2f} ms",
        )
    )
    try:
        job_from_dict: Callable[[Mapping[str, Any], CellConfig], Any] = importlib.import_module(
            "planner.job"
        ).job_from_dict
        plan_job: Callable[[Any, CellConfig], Any] = importlib.import_module("planner.plan").plan_job
    except ImportError as exc:
        print(f"planner.job / planner.plan_job not available ({exc}): only the API overhead is measured")
        _print(label, args.n, rows)
        return 0

    def validate(body: Mapping[str, Any]) -> Any:
        return job_from_dict(body, cell)

    def plan(j: Any) -> Planned:
        t0 = time.perf_counter()
        traj = plan_job(j, cell)
        return planned_from_trajectory(j, traj, time.perf_counter() - t0)

    planning = []
    for i in range(args.n + 3):
        t0 = time.perf_counter()
        plan(validate(job))
        if i >= 3:
            planning.append(time.perf_counter() - t0)
    real = measure_submit(cell, _Backend(cell, validate, plan), job, args.n)
    p50_plan, p50_submit = _pct(planning, 0.5), _pct(real, 0.5)
    rows.append(
        (
            "planning alone (job_from_dict + plan_job) p50 / p99",
            f"{1e3 * p50_plan:.2f} ms / {1e3 * _pct(planning, 0.99):.2f} ms",
        )
    )
    rows.append(
        (
            "submit->accepted (real planner) p50 / p99",
            f"{1e3 * p50_submit:.2f} ms / {1e3 * _pct(real, 0.99):.2f} ms",
        )
    )
    rows.append(("submit p50 / planning p50 (target <= 3)", f"{p50_submit / p50_plan:.2f}"))
    rows.append(("planner's share of submit p50", f"{100 * p50_plan / p50_submit:.0f} %"))
    rows.append(
        ("mean submit - mean planning", f"{1e3 * (statistics.mean(real) - statistics.mean(planning)):.2f} ms")
    )
    _print(label, args.n, rows)
    return 0


def _print(label: str, n: int, rows: list[tuple[str, str]]) -> None:
    print(f"Job API latency ({label}, n={n}, loopback, SQLite synchronous=FULL)")
    width = max(len(r[0]) for r in rows)
    for name, value in rows:
        print(f"  {name:<{width}}  {value}")


if __name__ == "__main__":
    raise SystemExit(main())
