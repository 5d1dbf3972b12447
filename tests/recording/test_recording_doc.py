"""docs/recording.md matches the code: its schema blocks are the schemas the files carry, its command
lines parse, its retention defaults are the code's."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest

from streamer.cli import build_parser
from streamer.recording.files import DEFAULT_MAX_BYTES, DEFAULT_MAX_COUNT, RecordingRetention
from streamer.recording.mcap_io import SCHEMAS
from streamer.runtime.trace import DEFAULT_MAX_FRAMES

DOC = (Path(__file__).resolve().parents[2] / "docs" / "recording.md").read_text(encoding="utf-8")


def test_the_documented_schemas_are_the_stored_ones() -> None:
    blocks = dict(re.findall(r"```json (pvt\.\w+)\n(.*?)```", DOC, flags=re.S))
    assert set(blocks) == set(SCHEMAS)
    for title, text in blocks.items():
        assert json.loads(text) == SCHEMAS[title], title


def test_every_documented_channel_field_is_in_a_schema() -> None:
    for field, _index in re.findall(r"`(\w+)` \((0x[0-9A-F]{4})", DOC):
        assert field in SCHEMAS["pvt.AxisSample"]["properties"], field


@pytest.mark.parametrize("line", [ln for block in re.findall(r"```sh\n(.*?)```", DOC, flags=re.S)
                                  for ln in block.splitlines() if ln.strip()])
def test_documented_commands_parse(line: str) -> None:
    argv = shlex.split(line.split("#", 1)[0].strip())
    assert argv[0] == ".venv/bin/pvt"
    args = build_parser().parse_args([a.replace("JOB_ID", "job-1") for a in argv[1:]])
    assert callable(args.func)


def test_documented_defaults() -> None:
    r = RecordingRetention()
    assert (r.max_count, r.max_bytes) == (DEFAULT_MAX_COUNT, DEFAULT_MAX_BYTES) == (200, 1 << 30)
    assert "**200 files**" in DOC and "**1 GiB**" in DOC and "1,000,000" in DOC and DEFAULT_MAX_FRAMES == 1_000_000
    assert "--keep-recordings N" in DOC and "--recordings-max-mb MB" in DOC
    args = build_parser().parse_args(["serve"])
    assert args.keep_recordings == DEFAULT_MAX_COUNT and args.recordings_max_mb * 1024 * 1024 == DEFAULT_MAX_BYTES
