"""`pvt plan` on every example job in configs/jobs/ (examples are tests), and its outputs."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
from planner_checks import CONFIGS

from streamer.cli import main

JOBS = sorted((CONFIGS / "jobs").iterdir())
DEMO = str(CONFIGS / "demo.toml")


@pytest.mark.parametrize("job", JOBS, ids=[j.name for j in JOBS])
def test_every_example_job(job: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["plan", str(job), "--config", DEMO, "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["points"] >= 2 and summary["duration_s"] > 0
    assert summary["points_per_second"] == pytest.approx(summary["points"] / summary["duration_s"])
    for axis in summary["axes"]:
        assert axis["max_deviation_counts"] <= summary["tolerance_counts"]
        assert axis["acceleration_excess_share"] <= 0.05


def test_table_csv_and_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out, png = tmp_path / "pvt.csv", tmp_path / "pvt.png"
    job = CONFIGS / "jobs" / "demo-path.toml"
    assert main(["plan", str(job), "--config", DEMO, "--out", str(out), "--plot", str(png)]) == 0
    text = capsys.readouterr().out
    assert "points per axis" in text and "j6" in text and "max dev" in text
    rows = list(csv.DictReader(out.open()))
    assert list(rows[0]) == ["axis", "node_id", "index", "time_s", "dt_ms", "position_counts", "velocity_rpm"]
    firsts = [r for r in rows if r["index"] == "0"]
    assert [r["axis"] for r in firsts] == ["j1", "j2", "j3", "j4", "j5", "j6"]
    assert all(r["dt_ms"] == "0" and r["time_s"] == "0.000" for r in firsts)
    j1 = [r for r in rows if r["axis"] == "j1"]
    assert all(1 <= int(r["dt_ms"]) <= 255 for r in j1[1:])
    assert j1[-1]["velocity_rpm"] == "0"
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"


def test_default_config(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["plan", str(CONFIGS / "jobs" / "move.toml"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["cell"] == "demo"


def test_rejected_job(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"kind": "path", "axes": ["j1", "j3"], "waypoints": [[0, 0], [0, "x"]]}))
    assert main(["plan", str(bad), "--config", DEMO]) == 2
    assert "TYPE at waypoints[1][1]" in capsys.readouterr().err
    assert main(["plan", str(bad), "--config", DEMO, "--json"]) == 2
    err = json.loads(capsys.readouterr().out)["error"]
    assert err["code"] == "TYPE" and err["path"] == "waypoints[1][1]" and "'j3'" in err["message"]
