"""Shared fixtures. Hypothesis profiles: `ci` (default, bounded so `make test` stays fast)."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

from planner.config import CellConfig, load_cell

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"

settings.register_profile(
    "ci", max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile("ci")


@pytest.fixture(scope="session")
def demo_cell() -> CellConfig:
    return load_cell(CONFIGS / "demo.toml")


@pytest.fixture(autouse=True, scope="session")
def _private_state_dir(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Journals and recordings default to the user's state directory ($XDG_STATE_HOME/pvt): the tests (and
    every `pvt` they start as a subprocess, which inherits the environment) use a private one."""
    import os

    os.environ["XDG_STATE_HOME"] = str(tmp_path_factory.mktemp("xdg-state"))
