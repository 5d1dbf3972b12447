"""The interactive report opens in headless Chromium with no network and draws every curve; its
"Sample & hold" button switches the curves that follow the display mode (issue 16, must show).

Chromium is Debian's `chromium`, installed by `tools/ensure-chromium` (run by `make test`); where it
cannot be installed (not root, no apt-get) these tests skip and say so."""

from __future__ import annotations

import subprocess
from html.parser import HTMLParser
from pathlib import Path
from typing import Any

import pytest

from streamer.cli import main as pvt
from streamer.recording.export import job_figure
from streamer.recording.mcap_io import read_mcap
from tests.live.cdp import chromium

CLICK_SAMPLE_AND_HOLD = """
<script>
window.addEventListener('load', function () {
  setTimeout(function () {
    var buttons = Array.from(document.querySelectorAll('g.updatemenu-button'));
    var hold = buttons.find(function (g) { return g.textContent.indexOf('Sample & hold') >= 0; });
    if (hold) { hold.dispatchEvent(new MouseEvent('click', {bubbles: true})); }
    document.body.setAttribute('data-clicked', hold ? 'yes' : 'no');
  }, 300);
});
</script>
"""


def _dump_dom(page: Path, tmp_path: Path) -> str:
    profile = tmp_path / f"chromium-profile-{page.stem}"
    cmd = [
        chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        f"--user-data-dir={profile}",
        "--host-resolver-rules=MAP * ~NOTFOUND",  # no name resolves: the page must need no network
        "--virtual-time-budget=20000", "--dump-dom", page.resolve().as_uri(),
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


class _Traces(HTMLParser):
    """Plotly's rendered scatter traces: one `<g class="trace scatter ...">` each, its line a
    `<path class="js-line" d="M...">`."""

    def __init__(self) -> None:
        super().__init__()
        self.stack: list[bool] = []  # per open <g>: is it a scatter trace group
        self.paths: list[str] = []  # the line of each trace group ("" = the group drew no line)
        self.buttons: list[str] = []
        self._in_button = 0
        self.body: dict[str, str | None] = {}

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        cls = (a.get("class") or "").split()
        if tag == "body":
            self.body = a
        if tag == "g":
            is_trace = "trace" in cls and "scatter" in cls
            self.stack.append(is_trace)
            if is_trace:
                self.paths.append("")
            if "updatemenu-button" in cls:
                self._in_button = len(self.stack)
                self.buttons.append("")
        if tag == "path" and "js-line" in cls and any(self.stack) and self.paths:
            self.paths[-1] += a.get("d") or ""

    def handle_endtag(self, tag: str) -> None:
        if tag == "g" and self.stack:
            if self._in_button == len(self.stack):
                self._in_button = 0
            self.stack.pop()

    def handle_data(self, data: str) -> None:
        if self._in_button and self.buttons:
            self.buttons[-1] += data


def _parse(dom: str) -> _Traces:
    p = _Traces()
    p.feed(dom)
    return p


def _has_diagonals(d: str) -> bool:
    return "L" in d


@pytest.fixture(scope="module")
def exported(demo_run: tuple[Path, Any, Any, dict[str, Any]], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`pvt jobs export demo-out/job.mcap --html ...`: the report of the demo job."""
    out = demo_run[0]
    page = tmp_path_factory.mktemp("html") / "job.html"
    assert pvt(["jobs", "export", str(out / "job.mcap"), "--html", str(page)]) == 0
    return page


def test_every_curve_renders_with_no_network(exported: Path, demo_run: tuple[Path, Any, Any, dict[str, Any]],
                                            tmp_path: Path) -> None:
    text = exported.read_text(encoding="utf-8")
    assert 'src="http' not in text and "src='http" not in text  # plotly.js is inlined, nothing is fetched
    fig = job_figure(read_mcap(demo_run[0] / "job.mcap"))
    expected = fig.series_traces
    assert expected == 3 * 4 + 3 + 3 * 2  # per axis planned/actual/demand/following error, FIFO, 2 watermarks
    parsed = _parse(_dump_dom(exported, tmp_path))
    assert len(parsed.paths) == expected, f"{len(parsed.paths)} of {expected} curves rendered"
    assert all(d.startswith("M") for d in parsed.paths), "a curve rendered without a line"
    labels = " ".join(parsed.buttons)
    for label in ("Linear", "Sample & hold", "Cursor: all curves", "nearest curve", "off"):
        assert label in labels
    # linear display: every curve that follows the mode has straight segments; the FIFO fills are held
    assert sum(_has_diagonals(d) for d in parsed.paths) == len(fig.switchable) + 3 * 2


def test_sample_and_hold_button_switches_the_curves(exported: Path, demo_run: tuple[Path, Any, Any, dict[str, Any]],
                                                    tmp_path: Path) -> None:
    page = tmp_path / "clicked.html"
    page.write_text(exported.read_text(encoding="utf-8").replace("</body>", CLICK_SAMPLE_AND_HOLD + "</body>", 1),
                    encoding="utf-8")
    fig = job_figure(read_mcap(demo_run[0] / "job.mcap"))
    parsed = _parse(_dump_dom(page, tmp_path))
    assert parsed.body.get("data-clicked") == "yes"
    assert len(parsed.paths) == fig.series_traces
    # held: only the watermarks (two-point horizontal lines) still have a plain line segment
    assert sum(_has_diagonals(d) for d in parsed.paths) == 3 * 2
    assert sum(("H" in d or "V" in d) for d in parsed.paths) >= len(fig.switchable) + 3
