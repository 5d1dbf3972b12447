"""configs/foxglove-layout.json: what streamer/live/layout.py builds for the demo cell, and every message path
in it names a channel the recording and the live view have and a field of that channel's schema."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from planner.config import load_cell
from streamer.live.layout import WATERMARK_TOPIC, layout_json
from streamer.recording.mcap_io import AXIS_SAMPLE_SCHEMA, JOB_EVENT_SCHEMA

ROOT = Path(__file__).resolve().parents[2]


def _paths(node: Any) -> list[str]:
    out: list[str] = []
    if isinstance(node, dict):
        for k, v in node.items():
            if k in ("value", "topicPath") and isinstance(v, str):
                out.append(v)
            else:
                out += _paths(v)
    elif isinstance(node, list):
        for v in node:
            out += _paths(v)
    return out


def test_the_shipped_layout_is_the_demo_cells() -> None:
    cell = load_cell(ROOT / "configs" / "demo.toml")
    shipped = (ROOT / "configs" / "foxglove-layout.json").read_text(encoding="utf-8")
    assert shipped == layout_json(cell), "regenerate: python -m streamer.live.layout configs/demo.toml"


def test_every_path_of_the_layout_is_a_recorded_field() -> None:
    cell = load_cell(ROOT / "configs" / "demo.toml")
    layout = json.loads(layout_json(cell))
    paths = _paths(layout["content"])
    axes = {a.name for a in cell.axes}
    plotted: dict[str, set[str]] = {}
    for p in paths:
        m = re.fullmatch(r"(/[\w/]+?)(?:\.(\w+))?", p)
        assert m, p
        topic, field = m.group(1), m.group(2)
        if topic.startswith("/axis/"):
            assert topic[len("/axis/"):] in axes, p
            assert field in AXIS_SAMPLE_SCHEMA["properties"], p
            plotted.setdefault(topic, set()).add(field)
        elif topic == "/job/events":
            assert field is None or field in JOB_EVENT_SCHEMA["properties"], p
        else:
            assert topic == WATERMARK_TOPIC and field in ("underflow_watermark", "overflow_watermark"), p
    # every axis: position against the plan, following error, FIFO fill
    assert set(plotted) == {f"/axis/{a}" for a in axes}
    assert all(f >= {"planned", "actual", "demand", "following_error", "fifo_fill"} for f in plotted.values())
    script = layout["userScripts"]["fifo_watermarks"]["sourceCode"]
    assert f"underflow_watermark: {cell.drive.underflow_warning}" in script
    assert f"overflow_watermark: {cell.drive.overflow_warning}" in script
