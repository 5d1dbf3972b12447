"""The house rules of planner/, bus/ and streamer/ (issue 24), read from the source with `ast`:

- no import cycle among their modules, counting every import (module level, inside functions, under
  TYPE_CHECKING): a cycle is two modules that can only be understood, tested and moved together;
- planner/ imports neither bus/ nor streamer/ (the planner is pure computation on a cell and a job);
- streamer/core imports no I/O, directly or through what it imports: no sockets, CAN, Zenoh, threads,
  processes, clocks or the runtimes (time is an argument of the core);
- no module over MAX_LINES lines;
- no module imports another's private names (`from x import _name`): what a module shares it names
  publicly, so a reader can tell a module's interface from its insides.
"""

from __future__ import annotations

import ast
import functools
from collections.abc import Iterable, Mapping
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("planner", "bus", "streamer")
MAX_LINES = 1000
# what streamer/core must not reach: I/O, threads, processes, clocks, and the parts of the product that do them
CORE_FORBIDDEN_EXTERNAL = frozenset({
    "socket", "can", "canopen", "zenoh", "threading", "subprocess", "multiprocessing", "asyncio", "selectors",
    "select", "ssl", "http", "urllib", "signal", "os", "time", "sched", "queue", "concurrent", "mmap", "fcntl",
    "ctypes", "sqlite3", "shutil", "tempfile", "logging",
})
CORE_FORBIDDEN_INTERNAL = ("bus.network", "bus.engine", "bus.sim", "bus.probe", "streamer.runtime", "streamer.api",
                           "streamer.cli", "streamer.recording", "streamer.demo")


def modules(root: Path = ROOT, packages: Iterable[str] = PACKAGES) -> dict[str, Path]:
    """Dotted module name -> file, for every module of `packages` (a package by its __init__.py)."""
    out: dict[str, Path] = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def imports_of(name: str, source: str, known: Mapping[str, Path]) -> tuple[set[str], set[str]]:
    """(the known modules `name` imports, the top-level names of the other modules it imports), every import
    statement of the source counted wherever it stands. `from package import module` is the module."""
    is_package = name in known and known[name].name == "__init__.py"
    internal: set[str] = set()
    external: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = name.split(".") if is_package else name.split(".")[:-1]
                parts = parts[: len(parts) - node.level + 1]
                base = ".".join([*parts, base] if base else parts)
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names]
        for target in targets:
            top = target.split(".")[0]
            if top not in PACKAGES:
                external.add(top)
                continue
            while target and target not in known:
                target = target.rpartition(".")[0]
            if target and target != name:
                internal.add(target)
    return internal, external


@functools.cache
def import_graph() -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    known = modules()
    graph: dict[str, set[str]] = {}
    external: dict[str, set[str]] = {}
    for name, path in known.items():
        graph[name], external[name] = imports_of(name, path.read_text(encoding="utf-8"), known)
    return graph, external


def cycles(graph: Mapping[str, Iterable[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work: list[tuple[str, list[str]]] = [(root, sorted(graph.get(root, ())))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, todo = work[-1]
            if todo:
                w = todo.pop(0)
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, sorted(graph.get(w, ()))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                component = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.append(w)
                    if w == v:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def reachable(graph: Mapping[str, Iterable[str]], start: Iterable[str]) -> set[str]:
    seen = set(start)
    todo = list(seen)
    while todo:
        for w in graph.get(todo.pop(), ()):
            if w not in seen:
                seen.add(w)
                todo.append(w)
    return seen


def test_the_guards_read_imports_everywhere_and_find_a_cycle() -> None:
    """The reader sees a function-level, a TYPE_CHECKING and a relative import, and the cycle finder a cycle
    through them: the guards below are not empty."""
    known = {"planner.a": Path("planner/a.py"), "planner.b": Path("planner/b.py"),
             "planner.c": Path("planner/c.py"), "planner": Path("planner/__init__.py")}
    source = ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from planner.b import X\n"
              "def f():\n    import socket\n    from . import c\n")
    internal, external = imports_of("planner.a", source, known)
    assert internal == {"planner.b", "planner.c"} and external == {"typing", "socket"}
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle_among_planner_bus_and_streamer() -> None:
    graph, _external = import_graph()
    found = cycles(graph)
    detail = [" <-> ".join(c) + ": " + "; ".join(f"{a} -> {b}" for a in c for b in sorted(graph[a]) if b in c)
              for c in found]
    assert not found, "import cycles:\n" + "\n".join(detail)


def test_the_planner_imports_neither_bus_nor_streamer() -> None:
    graph, _external = import_graph()
    bad = sorted(f"{m} -> {d}" for m, deps in graph.items() if m.split(".")[0] == "planner"
                 for d in deps if d.split(".")[0] != "planner")
    assert not bad, bad


def test_the_streamer_core_imports_no_io() -> None:
    graph, external = import_graph()
    core = [m for m in graph if m == "streamer.core" or m.startswith("streamer.core.")]
    assert "streamer.core.coordinator" in core
    reached = reachable(graph, core)
    bad_external = sorted(f"{m} imports {x}" for m in reached for x in external[m] if x in CORE_FORBIDDEN_EXTERNAL)
    bad_internal = sorted(m for m in reached if any(m == f or m.startswith(f + ".") for f in CORE_FORBIDDEN_INTERNAL))
    assert not bad_external, bad_external
    assert not bad_internal, f"streamer/core reaches {bad_internal}"


def _line_counts() -> dict[str, int]:
    return {path.relative_to(ROOT).as_posix(): len(path.read_text(encoding="utf-8").splitlines())
            for path in modules().values()}


def test_no_module_over_the_line_limit() -> None:
    """Issue 24 split the five modules that were over it (the coordinator into streamer/core's job_core, sending,
    splices, open_stream, feedback and scheduling; the simulated drive into bus/sim's layers; the job service
    into streamer/api's parts; planner/job.py and encoder.py gave fields.py and reconstruction.py). A module
    that grows over the limit is split too."""
    over = sorted(f"{p}: {n} lines" for p, n in _line_counts().items() if n > MAX_LINES)
    assert not over, f"over {MAX_LINES} lines (split them): {over}"


def private_imports(known: Mapping[str, Path]) -> list[str]:
    """`module: from other import _name` for every private name a module imports from another of `known`."""
    out = []
    for name, path in known.items():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module in known and node.module != name:
                out += [f"{name}: from {node.module} import {a.name}" for a in node.names
                        if a.name.startswith("_") and not a.name.startswith("__")]
    return sorted(out)


def test_the_private_import_check_sees_a_private_import(tmp_path: Path) -> None:
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "a.py").write_text("_x = 1\n__all__ = []\n")
    (tmp_path / "pkg" / "b.py").write_text("from pkg.a import _x, __all__\ndef f():\n    from pkg.a import _x as y\n")
    known = modules(tmp_path, ("pkg",))
    assert private_imports(known) == ["pkg.b: from pkg.a import _x", "pkg.b: from pkg.a import _x"]


def test_no_module_imports_another_s_private_names() -> None:
    bad = private_imports(modules())
    assert not bad, "private names imported across modules (name them publicly):\n" + "\n".join(bad)
