"""The Foxglove layout of a cell's channels (configs/foxglove-layout.json is the demo cell's).

One layout serves a recording and a live cell (same channels and schemas), built with foxglove-sdk's
layout types: per axis position against the plan, following error, FIFO fill with the watermarks (emitted
by a user script, as plots draw no constant line), and the job's events.

    python -m streamer.live.layout configs/demo.toml > configs/foxglove-layout.json
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from streamer.recording.mcap_io import AXIS_TOPIC_PREFIX, EVENTS_TOPIC

WATERMARK_TOPIC = "/studio_script/fifo_watermarks"

_SCRIPT = """// The cell's FIFO watermarks as a topic, so the FIFO plots can draw them beside the fill (pvt's layout).
import {{ Input }} from "./types";

export const inputs = ["{first}"];
export const output = "{output}";

type Output = {{ underflow_watermark: number; overflow_watermark: number }};

export default function script(event: Input<"{first}">): Output {{
  return {{ underflow_watermark: {underflow}, overflow_watermark: {overflow} }};
}}
"""


def build_layout(cell: Any) -> Any:
    """The layout (a `foxglove.layouts.Layout`) of `cell` (a `planner.config.CellConfig`)."""
    import foxglove.layouts as fl

    names = [a.name for a in cell.axes]
    first = AXIS_TOPIC_PREFIX + names[0]

    def plot(title: str, series: list[tuple[str, str]], y_label: str) -> Any:
        return fl.PlotPanel(title=title, config=fl.PlotConfig(
            paths=[fl.PlotSeries(value=v, label=label, timestamp_method="receiveTime") for v, label in series],
            show_legend=True, legend_display="top", y_axis_label=y_label, is_synced=True))

    def axis_column(name: str) -> Any:
        topic = AXIS_TOPIC_PREFIX + name
        return fl.SplitContainer(direction="column", items=[
            fl.SplitItem(proportion=2, content=plot(f"{name}: position vs plan", [
                (f"{topic}.planned", "planned"), (f"{topic}.demand", "demand"), (f"{topic}.actual", "actual")],
                "counts")),
            fl.SplitItem(content=plot(f"{name}: following error", [(f"{topic}.following_error", "actual - demand")],
                                      "counts")),
            fl.SplitItem(content=plot(f"{name}: FIFO fill", [
                (f"{topic}.fifo_fill", "fill"),
                (f"{WATERMARK_TOPIC}.underflow_watermark", "underflow watermark"),
                (f"{WATERMARK_TOPIC}.overflow_watermark", "overflow watermark")], "records")),
        ])

    transitions = fl.StateTransitionsConfig(
        paths=[fl.StateTransitionsSeries(value=f"{EVENTS_TOPIC}.state", label="state"),
               fl.StateTransitionsSeries(value=f"{EVENTS_TOPIC}.kind", label="event")],
        is_synced=True, show_points=True)
    events = fl.SplitContainer(direction="column", items=[
        fl.SplitItem(proportion=2, content=fl.StateTransitionsPanel(title="job events", config=transitions)),
        fl.SplitItem(proportion=3, content=fl.RawMessagesPanel(title="last event", config=fl.RawMessagesConfig(
            topic_path=EVENTS_TOPIC))),
    ])
    axes_tabs = fl.TabContainer(tabs=[fl.TabItem(title=name, content=axis_column(name)) for name in names])
    script = _SCRIPT.format(first=first, output=WATERMARK_TOPIC, underflow=cell.drive.underflow_warning,
                            overflow=cell.drive.overflow_warning)
    return fl.Layout(
        content=fl.SplitContainer(direction="row", items=[fl.SplitItem(proportion=3, content=axes_tabs),
                                                          fl.SplitItem(proportion=1, content=events)]),
        user_scripts={"fifo_watermarks": fl.UserScript(name="FIFO watermarks", source_code=script)},
    )


def layout_json(cell: Any) -> str:
    """The layout as the JSON file Foxglove imports (indented, one trailing newline)."""
    return json.dumps(json.loads(build_layout(cell).to_json()), indent=2) + "\n"


def main(argv: list[str] | None = None) -> int:
    from planner.config import load_cell

    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m streamer.live.layout CELL.toml > layout.json", file=sys.stderr)
        return 2
    sys.stdout.write(layout_json(load_cell(Path(args[0]))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
