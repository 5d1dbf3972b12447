"""The interactive report: one self-contained HTML file of time series per panel, with event markers.

Theory of operation. `render_report(title, series, events, options)` takes named time series (each on a
panel's left or right y-scale), levels and event markers and returns one HTML document with plotly.js
inlined (no network at view time); the job report (`job_report_html`) and `pvt record` call it. After
EPOS Studio's data recorder (seed 004): shared-time zoom, cursor read-out of all curves or the nearest,
two y-scales per panel, linear or sample-and-hold display (`hold=True` series always held), a legend that
hides and shows curves. A None value leaves a gap.
"""

from __future__ import annotations

import html
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

LINEAR = "linear"
HOLD = "hold"
_SHAPE = {LINEAR: "linear", HOLD: "hv"}

# event kind -> marker colour (anything else: grey)
EVENT_COLOURS = {
    "start": "#2ca02c",
    "state": "#7f7f7f",
    "fault": "#d62728",
    "emcy": "#d62728",
    "cancel": "#ff7f0e",
    "heartbeat_lost": "#d62728",
    "bootup": "#d62728",
    "send_failed": "#d62728",
    "adapter_error": "#d62728",
    "trigger": "#2ca02c",
}


class ReportError(ValueError):
    def __init__(self, code: str, message: str, path: str = ""):
        super().__init__(message)
        self.code = code
        self.message = message
        self.path = path


@dataclass(frozen=True)
class Series:
    """One curve: `y[k]` at time `t[k]` (s), on panel `panel`, against its `side` y-scale."""

    name: str
    panel: str
    t: Sequence[float]
    y: Sequence[float | None]
    side: str = "left"  # "left" | "right"
    unit: str = ""
    hold: bool = False  # always sample-and-hold (a counter), whatever the display mode
    color: str | None = None
    dash: str | None = None  # plotly dash style: "dash", "dot", ...
    group: str = ""  # legend group (e.g. the axis): clicking the group title toggles all its curves

    def __post_init__(self) -> None:
        if not self.name:
            raise ReportError("REPORT", "series name must not be empty", "series.name")
        if self.side not in ("left", "right"):
            raise ReportError("REPORT", f"side of series '{self.name}' must be 'left' or 'right', got {self.side!r}",
                              "series.side")
        if len(self.t) != len(self.y):
            raise ReportError("REPORT", f"series '{self.name}' has {len(self.t)} times but {len(self.y)} values",
                              "series.y")
        for k, t in enumerate(self.t):
            if not math.isfinite(t):
                raise ReportError("REPORT", f"t[{k}] of series '{self.name}' is {t}", "series.t")


@dataclass(frozen=True)
class Level:
    """A horizontal line across a panel (a watermark), against the panel's `side` y-scale."""

    name: str
    panel: str
    y: float
    side: str = "left"
    color: str = "#d62728"

    def __post_init__(self) -> None:
        if self.side not in ("left", "right"):
            raise ReportError("REPORT", f"side of level '{self.name}' must be 'left' or 'right', got {self.side!r}",
                              "levels.side")


@dataclass(frozen=True)
class Marker:
    """An event at time `t`: a vertical line through every panel, its `label` shown on hover."""

    t: float
    label: str
    kind: str = "event"
    short: str = ""  # text drawn at the top of the line (default: the kind)


@dataclass(frozen=True)
class PanelSpec:
    """Axis titles of one panel (optional: panels without a spec get their series' units)."""

    name: str
    left_title: str = ""
    right_title: str = ""
    left_range: tuple[float, float] | None = None  # fixed left scale (e.g. a FIFO's 0..64); None: auto


@dataclass(frozen=True)
class ReportOptions:
    display: str = LINEAR  # the initial display mode: "linear" or "hold"
    subtitle: str = ""
    panel_height_px: int = 260
    levels: tuple[Level, ...] = ()
    panels: tuple[PanelSpec, ...] = ()
    time_title: str = "time [s]"
    width_px: int | None = None  # None: the page's width

    def __post_init__(self) -> None:
        if self.display not in _SHAPE:
            raise ReportError("REPORT", f"display must be 'linear' or 'hold', got {self.display!r}", "display")
        if not 80 <= self.panel_height_px <= 2000:
            raise ReportError("REPORT", f"panel_height_px must be 80..2000, got {self.panel_height_px}",
                              "panel_height_px")


@dataclass(frozen=True)
class Figure:
    """The plotly figure and what the page must show (for tests: the number of curves drawn)."""

    figure: Any
    panels: tuple[str, ...]
    switchable: tuple[int, ...]  # trace indices that follow the display mode
    series_traces: int  # traces drawn for series and levels (markers are annotations + shapes)
    meta: dict[str, Any] = field(default_factory=dict)


def _panels(series: Sequence[Series], options: ReportOptions) -> list[str]:
    out: list[str] = []
    for p in [*(s.panel for s in series), *(lv.panel for lv in options.levels)]:
        if p not in out:
            out.append(p)
    return out


def build_figure(title: str, series: Sequence[Series], events: Sequence[Marker],
                 options: ReportOptions | None = None) -> Figure:
    """The plotly figure of the report (`render_report` turns it into the page)."""
    import numpy as np
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    opts = options or ReportOptions()
    panels = _panels(series, opts)
    if not panels:
        raise ReportError("REPORT", "nothing to plot: no series and no levels", "series")
    specs = {p.name: p for p in opts.panels}
    rows = len(panels)
    fig = make_subplots(rows=rows, cols=1, shared_xaxes=True, vertical_spacing=min(0.06, 0.5 / rows),
                        specs=[[{"secondary_y": True}] for _ in panels], subplot_titles=panels)
    row_of = {p: i + 1 for i, p in enumerate(panels)}
    units: dict[tuple[str, str], str] = {}
    switchable: list[int] = []
    shape = _SHAPE[opts.display]
    t_all = [t for s in series for t in s.t[:1]] + [t for s in series for t in s.t[-1:]]
    t_lo, t_hi = (min(t_all), max(t_all)) if t_all else (0.0, 1.0)
    for s in series:
        y = np.array([math.nan if v is None else float(v) for v in s.y], dtype=float)
        line: dict[str, Any] = {"shape": "hv" if s.hold else shape, "width": 1.4}
        if s.color:
            line["color"] = s.color
        if s.dash:
            line["dash"] = s.dash
        unit = f" {s.unit}" if s.unit else ""
        fig.add_trace(
            go.Scatter(x=np.asarray(s.t, dtype=float), y=y, name=s.name, mode="lines", line=line,
                       legendgroup=s.group or s.panel, legendgrouptitle_text=s.group or None,
                       hovertemplate=f"%{{y:.6g}}{unit}<extra>{html.escape(s.name)}</extra>"),
            row=row_of[s.panel], col=1, secondary_y=(s.side == "right"))
        if not s.hold:
            switchable.append(len(fig.data) - 1)
        if s.unit:
            units.setdefault((s.panel, s.side), s.unit)
    for lv in opts.levels:
        fig.add_trace(
            go.Scatter(x=[t_lo, t_hi], y=[lv.y, lv.y], name=lv.name, mode="lines",
                       line={"color": lv.color, "dash": "dash", "width": 1}, legendgroup=lv.panel,
                       hovertemplate=f"{lv.y:g}<extra>{html.escape(lv.name)}</extra>"),
            row=row_of[lv.panel], col=1, secondary_y=(lv.side == "right"))
    n_traces = len(fig.data)
    for m in events:
        colour = EVENT_COLOURS.get(m.kind, "#7f7f7f")
        fig.add_shape(type="line", x0=m.t, x1=m.t, xref="x", yref="paper", y0=0, y1=1,
                      line={"color": colour, "width": 1, "dash": "dot"})
        fig.add_annotation(x=m.t, xref="x", y=1.0, yref="paper", yanchor="bottom", showarrow=False,
                           text=html.escape(m.short or m.kind), font={"size": 9, "color": colour},
                           hovertext=html.escape(m.label), textangle=-60)
    for p in panels:
        spec = specs.get(p)
        left = (spec.left_title if spec and spec.left_title else units.get((p, "left"), ""))
        right = (spec.right_title if spec and spec.right_title else units.get((p, "right"), ""))
        fig.update_yaxes(title_text=left, row=row_of[p], col=1, secondary_y=False)
        if spec is not None and spec.left_range is not None:
            fig.update_yaxes(range=list(spec.left_range), row=row_of[p], col=1, secondary_y=False)
        fig.update_yaxes(title_text=right, row=row_of[p], col=1, secondary_y=True, showgrid=False)
    fig.update_xaxes(showspikes=True, spikemode="across", spikesnap="cursor", spikethickness=1,
                     spikedash="dot", spikecolor="#555")
    fig.update_xaxes(title_text=opts.time_title, row=rows, col=1)
    indices = list(switchable)
    cursor = [
        {"label": "Cursor: all curves", "method": "relayout", "args": [{"hovermode": "x unified"}]},
        {"label": "nearest curve", "method": "relayout", "args": [{"hovermode": "closest"}]},
        {"label": "off", "method": "relayout", "args": [{"hovermode": False}]},
    ]
    display = [
        {"label": "Linear", "method": "restyle", "args": [{"line.shape": "linear"}, indices]},
        {"label": "Sample & hold", "method": "restyle", "args": [{"line.shape": "hv"}, indices]},
    ]
    title_text = html.escape(title) + (f"<br><sup>{html.escape(opts.subtitle)}</sup>" if opts.subtitle else "")
    fig.update_layout(
        title={"text": title_text, "x": 0.01, "y": 1.0 - 40 / (opts.panel_height_px * rows + 200), "yanchor": "top"},
        height=opts.panel_height_px * rows + 200,
        width=opts.width_px,
        hovermode="x unified",
        dragmode="zoom",
        margin={"t": 150, "l": 70, "r": 70, "b": 50},
        legend={"groupclick": "toggleitem", "tracegroupgap": 8},
        updatemenus=[
            {"type": "buttons", "direction": "right", "buttons": display, "active": 0 if shape == "linear" else 1,
             "x": 0.0, "xanchor": "left", "y": 1.0, "yanchor": "bottom", "pad": {"b": 60},
             "showactive": True},
            {"type": "buttons", "direction": "right", "buttons": cursor, "active": 0, "x": 0.45,
             "xanchor": "left", "y": 1.0, "yanchor": "bottom", "pad": {"b": 60}, "showactive": True},
        ],
        template="plotly_white",
    )
    meta = {"title": title, "panels": panels, "traces": n_traces, "markers": len(events),
            "switchable": len(indices), "display": opts.display}
    return Figure(fig, tuple(panels), tuple(indices), n_traces, meta)


def figure_to_html(fig: Figure) -> str:
    """One HTML document with plotly.js inlined (nothing is fetched when it is viewed)."""
    page: str = fig.figure.to_html(
        full_html=True, include_plotlyjs=True, include_mathjax=False, div_id="pvt-report",
        config={"displaylogo": False, "scrollZoom": True, "responsive": True,
                "toImageButtonOptions": {"format": "png", "filename": "pvt-report"}},
    )
    meta = json.dumps(fig.meta).replace("</", "<\\/")
    tag = f'<script type="application/json" id="pvt-report-meta">{meta}</script>\n'
    title = f"<title>{html.escape(str(fig.meta.get('title', 'pvt report')))}</title>"
    page = page.replace("<head>", f"<head>{title}", 1)
    return page.replace("</body>", tag + "</body>", 1)


def render_report(title: str, series: Sequence[Series], events: Sequence[Marker],
                  options: ReportOptions | None = None) -> str:
    """The self-contained interactive HTML page of `series` with `events` as markers."""
    return figure_to_html(build_figure(title, series, events, options))
