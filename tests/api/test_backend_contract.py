"""The backend contract declared (issue 24): `MotionBackend` is a base class whose required methods are
abstract and whose optional capabilities have defaults, so the service calls every method as declared and
probes nothing (no `inspect.signature`, no `getattr` on the backend)."""

from __future__ import annotations

import ast
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pytest

from planner.config import CellConfig
from streamer.api import errors as E
from streamer.api.backend import CancelToken, Emit, MotionBackend, Planned, check_backend
from streamer.api.errors import MotionError
from streamer.runtime.bus_backend import RuntimeBackend
from tests.api.fakes import FakeBackend

ROOT = Path(__file__).resolve().parents[2]


class Minimal(MotionBackend):
    """Only the required methods: every optional capability is the base class' default."""

    def __init__(self, cell: CellConfig) -> None:
        self.cell = cell

    def validate(self, body: Mapping[str, Any]) -> Any:
        return dict(body)

    def plan(self, job: Any, start: Mapping[str, float] | None, *,
             last_target: Mapping[str, float | None] | None = None,
             last_direction: Mapping[str, int] | None = None, lead_ms: int | None = None) -> Planned:
        return Planned(job=job, trajectory=None, duration_s=0.0, points=1)

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


def test_the_optional_capabilities_have_their_documented_defaults(demo_cell: CellConfig) -> None:
    backend = Minimal(demo_cell)
    check_backend(backend)
    assert not backend.can_change and not backend.can_emergency_stop
    assert backend.current_positions() is None and backend.take_recording() is None
    with pytest.raises(MotionError) as e:
        backend.change({}, "aborting", lambda kind, fields: None, last_target={}, last_direction={})
    assert e.value.code == E.COMMAND_REJECTED and e.value.path == "buffer"
    with pytest.raises(NotImplementedError):
        backend.emergency_stop()


def test_a_backend_that_misses_a_required_method_or_the_base_class_is_refused(demo_cell: CellConfig) -> None:
    class NoPlan(MotionBackend):
        cell = demo_cell

    with pytest.raises(TypeError, match="plan"):
        NoPlan()  # type: ignore[abstract]

    class Lookalike:  # every method, but not a MotionBackend
        cell = demo_cell
        validate = plan = execute = telemetry = ready = reset = close = staticmethod(lambda *a, **k: None)

    with pytest.raises(TypeError, match="MotionBackend"):
        check_backend(Lookalike())


def test_the_fake_the_benchmark_and_the_runtime_backends_declare_what_they_have() -> None:
    from benchmarks.bench_api import _Backend

    assert issubclass(FakeBackend, MotionBackend) and issubclass(_Backend, MotionBackend)
    assert FakeBackend.can_emergency_stop and not FakeBackend.can_change
    assert issubclass(RuntimeBackend, MotionBackend) and RuntimeBackend.can_change and RuntimeBackend.can_emergency_stop


# the job service and the parts it is put together from (service.py's docstring names them)
SERVICE_MODULES = ("service", "service_state", "intake", "cell_queue", "control_verbs", "journal", "progress",
                   "telemetry", "handlers")


@pytest.mark.parametrize("module", SERVICE_MODULES)
def test_the_service_never_probes_its_backend(module: str) -> None:
    tree = ast.parse((ROOT / "streamer" / "api" / f"{module}.py").read_text(encoding="utf-8"))
    probes = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            names = [a.name for a in node.names] + ([node.module] if isinstance(node, ast.ImportFrom) else [])
            if "inspect" in names:
                probes.append(f"line {node.lineno}: imports inspect")
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
              and node.func.id in ("getattr", "hasattr") and node.args
              and "backend" in ast.unparse(node.args[0])):
            probes.append(f"line {node.lineno}: {ast.unparse(node)}")
    assert not probes, probes
