"""Fixtures for the planner tests."""

from __future__ import annotations

import pytest
from planner_checks import CONFIGS

from planner.config import CellConfig, load_cell


@pytest.fixture(scope="session")
def cell() -> CellConfig:
    return load_cell(CONFIGS / "demo.toml")


@pytest.fixture(scope="session")
def cell8(cell: CellConfig) -> CellConfig:
    return cell.with_axes(8)
