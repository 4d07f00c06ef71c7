"""A non-editable install (what the Nano installer does) finds its shipped defaults without a source tree.

The package is built from a copy of the sources and installed into a fresh virtual environment
that sees the test interpreter's third-party packages but not this checkout; the commands then
run from an empty directory, so nothing can be found through the current directory.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ("robot", "drivers", "firmware_protocol", "config", "pyproject.toml", "setup.py", "README.md")


def _have_wheel_builder() -> bool:
    """setuptools 61 or newer (it reads pyproject.toml's [project]) and wheel, without the network."""
    try:
        import setuptools
        import wheel  # noqa: F401
    except ImportError:
        return False
    return int(setuptools.__version__.split(".")[0]) >= 61


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    if not _have_wheel_builder():
        pytest.skip("setuptools >= 61 and wheel are needed to build the package without network access")
    tmp = tmp_path_factory.mktemp("install")
    src = tmp / "src"
    src.mkdir()
    for name in SOURCES:
        p = ROOT / name
        if p.is_dir():
            shutil.copytree(p, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            shutil.copy2(p, src / name)
    venv = tmp / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    py = venv / "bin" / "python"
    site = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               check=True, capture_output=True, text=True).stdout.strip())
    target = tmp / "installed"
    r = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--no-index",
                        "--target", str(target), str(src)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    # The package first, then the test interpreter's third-party packages (numpy, cv2, ...).
    # Lines of a .pth are added to sys.path without running the .pth files found there, so the
    # development checkout's editable-install hook is not loaded.
    (site / "robot_test.pth").write_text(f"{target}\n{sysconfig.get_paths()['purelib']}\n")
    work = tmp / "cwd"
    work.mkdir()
    return py, target, work


def _run(installed, *args, timeout=300, **extra_env):
    py, _, work = installed
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env.update(extra_env)
    return subprocess.run([str(py), "-m", "robot.cli.main", *args], cwd=str(work), env=env, capture_output=True,
                          text=True, timeout=timeout)


def test_the_installed_package_is_the_copy_not_the_checkout(installed):
    py, target, work = installed
    r = subprocess.run([str(py), "-c", "import robot, robot_defaults; print(robot.__file__); print(robot_defaults.__file__)"],
                       cwd=str(work), capture_output=True, text=True, check=True)
    lines = r.stdout.split()
    assert all(line.startswith(str(target)) for line in lines), lines


def test_visible_and_demo_work_from_a_non_editable_install(installed):
    # On the numpy code: what this checks is what the package ships, and the installed copy's
    # kernels would compile from nothing into its own cache (two minutes of CPU on Python 3.8);
    # the kernels are compared with the numpy code by their own tests.
    r = _run(installed, "visible", "--pose", "0.5", "0.5", "3.1416", "--json", ROBOT_KERNELS="numpy")
    assert r.returncode == 0, r.stderr
    assert '"cameras"' in r.stdout
    r = _run(installed, "demo", "--json", ROBOT_KERNELS="numpy")
    assert r.returncode == 0, r.stderr
    assert '"rows"' in r.stdout


def test_kernels_status_finds_the_installed_sources(installed):
    """The ahead-of-time module is named by a hash of the installed kernel sources: every file it
    hashes is in the installed package, and the module is looked for beside it by default."""
    py, target, work = installed
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "NUMBA_CACHE_DIR",
                                                             "ROBOT_KERNEL_DIR")}
    r = subprocess.run([str(py), "-m", "robot.cli.main", "kernels", "status", "--json"], cwd=str(work),
                       env=dict(env, ROBOT_KERNELS="numpy"), capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    status = json.loads(r.stdout)
    assert status["backend"] == "numpy" and status["ahead_of_time_built"] is False
    assert status["ahead_of_time_module"].startswith(str(target / "robot" / "__pycache__" / "robot_kernels_"))
