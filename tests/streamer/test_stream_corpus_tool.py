"""tools/stream_corpus.py, the regression check for streamer work that must not change what the streamer
does: the same code streams the same cases to the same records, and a run that parts is reported at the
record where it parts."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]


def _tool() -> Any:
    spec = importlib.util.spec_from_file_location("stream_corpus", ROOT / "tools" / "stream_corpus.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_same_cases_stream_the_same_records_twice_and_a_run_that_parts_is_reported(tmp_path: Path) -> None:
    tool = _tool()
    before = tool.record_all("demo/cancel")
    assert list(before) == ["demo/cancel"]
    records = before["demo/cancel"]["records"]
    kinds = {r[0] for r in records}
    assert kinds == {"W", "E", "S", "C", "R"}, kinds  # frames on the wire, events, sends, state changes, report
    assert any(r.startswith("E Cancel(") for r in records)
    assert not any(" at 0x" in r for r in records)  # no memory address: equal runs give equal text
    path = tmp_path / "corpus.json.gz"
    tool.save(before, path)
    after = tool.record_all("demo/cancel")
    assert tool.differences(tool.load(path), after) == []
    # the same move cancelled 100 ms later: reported at the first record that differs, the Cancel fed later
    cell = tool.load_cell(ROOT / "configs" / "demo.toml")
    job = tool.job_from_dict({"kind": "move", "axes": ["j1", "j2", "j3"], "target": [1.5, -1.0, 1.2]}, cell)
    later = tool.run_case(cell, tool.plan_job(job, cell, start=[0.0, 0.0, 0.0]), [(700, tool._cancel)])
    moved = {"demo/cancel": {"digest": "other", "records": later}}
    (line,) = tool.differences(before, moved)
    first = int(line.split("record ")[1].split(" ")[0])
    assert records[:first] == later[:first] and 0 < first < len(records)
    assert "E Cancel(" in line.split("was: ")[1].split("\n")[0] or "E Cancel(" in line.split("now: ")[1]
