"""Shared test options: hardware-in-the-loop tests run only with --hil."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

SHARED = ROOT.parent / "shared"


def pytest_addoption(parser):
    parser.addoption("--hil", action="store_true", default=False,
                     help="run hardware-in-the-loop tests in tests/hil (needs the robot's hardware)")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--hil"):
        return
    skip = pytest.mark.skip(reason="hardware-in-the-loop test: run with --hil on the robot")
    for item in items:
        if "hil" in item.keywords or "/hil/" in str(item.fspath).replace("\\", "/"):
            item.add_marker(skip)


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return ROOT
