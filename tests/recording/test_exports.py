"""Exports: the CSV (one row per SYNC), the generic report renderer (the page `pvt record` reuses), and
`pvt jobs show` / `pvt jobs export` on a recording file."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import pytest

from streamer.cli import main as pvt
from streamer.recording.export import csv_columns, job_figure, write_csv
from streamer.recording.html import (
    Level,
    Marker,
    PanelSpec,
    ReportError,
    ReportOptions,
    Series,
    build_figure,
    render_report,
)
from streamer.recording.mcap_io import read_mcap

Demo = tuple[Path, Any, Any, dict[str, Any]]


def test_csv_has_one_row_per_sync_with_every_axis(demo_run: Demo, tmp_path: Path) -> None:
    out, _cell, traj, report = demo_run
    rec = read_mcap(out / "job.mcap")
    path = tmp_path / "job.csv"
    rows = write_csv(rec, path)
    with open(path, newline="") as f:
        table = list(csv.DictReader(f))
    assert rows == len(table) == len(rec.samples["j1"])
    assert list(table[0]) == csv_columns(rec) == ["time_s", "sync"] + [
        f"{n}.{c}" for n in traj.axis_names for c in ("planned", "actual", "demand", "following_error", "fifo_fill")]
    assert float(table[0]["time_s"]) == 0.0
    assert [int(r["sync"]) for r in table] == sorted(int(r["sync"]) for r in table)
    for i, name in enumerate(traj.axis_names):
        s = rec.samples[name]
        assert [int(r[f"{name}.actual"]) for r in table] == s.actual
        assert [int(r[f"{name}.planned"]) for r in table] == s.planned
        assert int(table[-1][f"{name}.planned"]) == int(traj.positions[i, -1])
        assert max(abs(int(r[f"{name}.following_error"])) for r in table) == \
            report["axes"][i]["max_following_error_counts"]


def test_render_report_is_generic_and_self_contained() -> None:
    t = [0.0, 0.1, 0.2, 0.3]
    series = [
        Series("2.position_demand", "node 2", t, [0, 10, None, 30], unit="counts"),
        Series("2.current_actual", "node 2", t, [1.5, 1.0, 0.5, 0.0], side="right", unit="mA"),
        Series("2.statusword", "node 2 words", t, [0x37, 0x37, 0x1037, 0x1037], hold=True),
    ]
    opts = ReportOptions(display="hold", levels=(Level("limit", "node 2", 25.0),),
                         panels=(PanelSpec("node 2 words", "raw", left_range=(0, 5000)),))
    fig = build_figure("recording", series, [Marker(0.0, "trigger: movement", "trigger", "T")], opts)
    assert fig.panels == ("node 2", "node 2 words") and fig.series_traces == 4
    data = fig.figure.data
    assert [d.line.shape for d in data[:3]] == ["hv", "hv", "hv"]  # hold display: switchable ones held too
    assert fig.switchable == (0, 1)
    assert data[1].yaxis != data[0].yaxis  # the right scale is its own y axis
    layout = fig.figure.layout
    buttons = {b.label: b for menu in layout.updatemenus for b in menu.buttons}
    assert buttons["Linear"].args == ({"line.shape": "linear"}, (0, 1))
    assert buttons["Sample & hold"].args == ({"line.shape": "hv"}, (0, 1))
    assert buttons["nearest curve"].args == ({"hovermode": "closest"},)
    assert layout.hovermode == "x unified" and layout.shapes[0].x0 == 0.0
    page = render_report("recording <test>", series, [], opts)
    assert page.lower().startswith("<!doctype html>") and "</html>" in page
    assert page.count("<meta charset") == 1 and "<title>recording &lt;test&gt;</title>" in page
    assert 'src="http' not in page and "plotly.js" in page  # the library is inside the page
    meta = json.loads(page.split('id="pvt-report-meta">', 1)[1].split("</script>", 1)[0])
    assert meta["traces"] == 4 and meta["panels"] == ["node 2", "node 2 words"]


def test_render_report_rejects_bad_series() -> None:
    with pytest.raises(ReportError, match="side of series 'x'"):
        Series("x", "p", [0.0], [1.0], side="middle")
    with pytest.raises(ReportError, match="series 'x' has 2 times but 1 values"):
        Series("x", "p", [0.0, 1.0], [1.0])
    with pytest.raises(ReportError, match=r"t\[1\] of series 'x' is nan"):
        Series("x", "p", [0.0, float("nan")], [1.0, 2.0])
    with pytest.raises(ReportError, match="display must be"):
        ReportOptions(display="smooth")
    with pytest.raises(ReportError, match="nothing to plot"):
        build_figure("empty", [], [])


def test_job_report_has_the_issue_curves(demo_run: Demo) -> None:
    rec = read_mcap(demo_run[0] / "job.mcap")
    fig = job_figure(rec)
    names = [d.name for d in fig.figure.data]
    for axis in ("j1", "j2", "j3"):
        for curve in ("planned", "actual 0x6064", "following error", "FIFO fill", "underflow watermark 4",
                      "overflow watermark 60"):
            assert any(n.startswith(f"{axis} {curve}") for n in names), (axis, curve)
    kinds = [a.hovertext for a in fig.figure.layout.annotations if a.hovertext]
    assert any("start" in k for k in kinds) and any("done" in k for k in kinds)  # events as markers
    assert len(fig.figure.layout.shapes) == len(rec.events)


def test_cli_show_and_export_a_recording_file(demo_run: Demo, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    mcap = demo_run[0] / "job.mcap"
    assert pvt(["jobs", "show", str(mcap), "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["result"] == "done" and shown["job_id"] == "demo" and [a["name"] for a in shown["axes"]] == [
        "j1", "j2", "j3"]
    assert shown["messages"]["/can/frames"] == demo_run[3]["frames"]
    assert pvt(["jobs", "show", str(mcap)]) == 0
    text = capsys.readouterr().out
    assert "start SYNC" in text and "state done" in text and "/axis/j1" in text
    dest = tmp_path / "x"
    assert pvt(["jobs", "export", str(mcap), "--csv", str(dest / "j.csv"), "--mcap", str(dest / "j.mcap"),
                "--html", str(dest / "j.html")]) == 0
    assert (dest / "j.mcap").read_bytes() == mcap.read_bytes()
    assert (dest / "j.csv").read_text().startswith("time_s,sync,j1.planned")
    assert (dest / "j.html").stat().st_size > 1_000_000  # plotly.js is inside
    capsys.readouterr()
    assert pvt(["jobs", "export", str(mcap)]) == 2  # nothing asked for
    assert "--csv PATH" in capsys.readouterr().err
    assert pvt(["jobs", "show", str(tmp_path / "missing.mcap")]) == 1
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x89MCAP0\r\n broken")
    assert pvt(["jobs", "show", str(junk)]) == 2
    assert "NOT_A_RECORDING" in capsys.readouterr().err
