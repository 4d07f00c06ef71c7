"""Shared test options: hardware-in-the-loop tests run only with --hil."""

from __future__ import annotations

import os
import sys
from pathlib import Path

# As on the robot (systemd unit, robotctl): OpenBLAS's worker threads spin on sched_yield between
# the small matrix products this code makes, which burned most of a core in system time through
# the suite. It must be set before numpy is first imported, which is after this point.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import pytest  # noqa: E402

try:
    from hypothesis import settings
except ImportError:  # the test extra is not installed: the property tests will say so
    settings = None

if settings is not None:
    # The suite draws the same examples on every run, so a failure reproduces and CI cannot fail
    # on an input no earlier run drew; the long fuzz run (ROBOT_FUZZ_LONG=1, scripts/bench_fuzz.py)
    # draws fresh ones, which is where new inputs are explored.
    settings.register_profile("suite", derandomize=True)
    settings.register_profile("explore", derandomize=False)
    settings.load_profile("explore" if os.environ.get("ROBOT_FUZZ_LONG") else "suite")

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


@pytest.fixture(scope="session", autouse=True)
def compiled_kernels():
    """Compile (or load) the numba kernels once, before any test: on a fresh clone the first
    compile takes seconds, and it belongs to no test (the app does the same at start-up)."""
    from robot.control import scan_kernels
    from robot.localization import fit_kernels, integrity_kernels

    for kernels in (fit_kernels, integrity_kernels, scan_kernels):
        kernels.warm_up()
    yield


@pytest.fixture(autouse=True)
def _kernel_backend_as_found(monkeypatch):
    """Every test leaves the kernels' backend as it found it. One that chose numba and kept it
    made the rest of its worker's tests run on the compiled kernels in the numpy pass (CI's
    ROBOT_KERNELS=numpy), a different set each run as xdist shares the tests out."""
    from robot.localization import fit_kernels

    fit_kernels.backend()
    for name in ("_backend", "_note", "_requested"):
        monkeypatch.setattr(fit_kernels, name, getattr(fit_kernels, name))


@pytest.fixture(scope="session")
def twin_rooms():
    """Two 3 x 4 m rooms 6 m apart, alike but for where the door of their north wall is (east end in
    one, west end in the other), and a pose in the first facing its south-west corner: from there
    both cameras see only what the two rooms share (two exact twins); facing north they differ.
    Returns (map, pose)."""
    import math

    import numpy as np

    from robot.base.geometry import newell_normal
    from robot.maps.plane_map import PlaneMap, make_plane

    def wall(pid, p0, p1, h=2.5):
        v = np.array([[p0[0], p0[1], 0.0], [p1[0], p1[1], 0.0], [p1[0], p1[1], h], [p0[0], p0[1], h]])
        inward = np.array([p0[1] - p1[1], p1[0] - p0[0], 0.0])  # left of the walk round the room
        return make_plane(pid, [(v if newell_normal(v) @ inward > 0 else v[::-1]).tolist()])

    def room(tag, x0, door):
        return [wall(f"{tag}_s", (x0, 0), (x0 + 3, 0)), wall(f"{tag}_e", (x0 + 3, 0), (x0 + 3, 4)),
                wall(f"{tag}_n1", (x0 + 3, 4), (x0 + door[1], 4)), wall(f"{tag}_n2", (x0 + door[0], 4), (x0, 4)),
                wall(f"{tag}_w", (x0, 4), (x0, 0))]

    return PlaneMap(room("a", 0.0, (2.0, 2.9)) + room("b", 6.0, (0.1, 1.0)), "twin rooms"), (1.5, 1.2, math.radians(-135.0))
